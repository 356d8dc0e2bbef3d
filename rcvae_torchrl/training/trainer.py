"""``train_ensemble``: the world model's training loop, with validation, early stopping and resume.

One Adam step trains every member (the loss sums over members); each member draws its own
windows from its own generator (from all the episodes, or with ``bootstrap`` from its own
resample of them), and nothing of one member depends on the others: its noise, gradient
clipping and early stopping are its own. Validation windows are fixed per run. Members stop
improving at different times, so the best weights are kept per member. A checkpoint (weights,
optimiser, best weights, generator states, history) is written atomically at each validation,
so ``resume=True`` continues a run killed at any point (even ``kill -9``) from its last
validation, and a finished run is not trained again. Under ``torch.distributed`` the members
are shared out over the ranks (:mod:`rcvae_torchrl.distributed`), each rank checkpoints its own
block, and the gathered ensemble equals a single process's. With ``data_parallel`` groups of
ranks share out the members instead, and the ranks of a group share every step's windows
(``DistributedDataParallel``).
"""

from __future__ import annotations

import dataclasses
import inspect
import logging
import math
import os
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch.nn.parallel import DistributedDataParallel
from torchrl.record.loggers import Logger
from torchrl.record.loggers.csv import CSVLogger
from tqdm.auto import tqdm

from rcvae_torchrl import distributed, fingerprint
from rcvae_torchrl._checks import (
    check_bool,
    check_dtype,
    check_finite,
    check_non_negative,
    check_non_negative_int,
    check_positive,
    check_positive_int,
    check_unit_interval,
)
from rcvae_torchrl.data import (
    TRAJ_KEY,
    check_episode_ids,
    check_frames_type,
    episode_spans,
    make_window_buffer,
    resample_episodes,
    sample_windows,
)
from rcvae_torchrl.io import _as_json, save_torch
from rcvae_torchrl.loggers import log_scalars
from rcvae_torchrl.models import RCVAEEnsemble, masked_mean_std
from rcvae_torchrl.objectives import RCVAELoss
from rcvae_torchrl.threads import collection_paused

from .checkpoint import CheckpointError, ensemble_payload, read_checkpoint
from .checks import ModelChecks, ModelCheckWarning, check_model
from .dynamics import MIN_HELD_OUT, STEPS, DynamicsNovelty
from .novelty import StateNovelty, check_novelty_episodes, entry_groups

log = logging.getLogger(__name__)

__all__ = [
    "TrainConfig",
    "TrainResult",
    "clip_grad_norm_per_member",
    "log_history",
    "train_ensemble",
]


@dataclass(frozen=True)
class TrainConfig:
    """Budget and hyper-parameters of :func:`train_ensemble`.

    Args:
        max_steps: optimiser steps at most.
        batch_windows: windows per member per step.
        window: window length L (steps).
        lr: Adam learning rate.
        lr_final_fraction: the learning rate follows a cosine from ``lr`` at step 0 to
            ``lr * lr_final_fraction`` at ``max_steps`` (1 keeps it constant). It is a function
            of the step alone, so a resumed run continues on the same schedule.
        grad_clip: max gradient norm of each member (over its own parameters).
        beta: KL weight.
        free_nats: per-step free nats of the KL.
        open_loop_steps: trailing transitions of each window fed with the model's own samples.
        nll_beta: β of the β-NLL weighting of the reconstruction term (see :class:`RCVAELoss`).
        val_every: steps between validations (and checkpoints).
        val_windows: fixed validation windows (shared by all members).
        patience: validations without improvement after which a member stops (its best
            weights are kept; the run ends when every member has stopped).
        seed: seeds sampling and the model's noise (one generator per member and purpose,
            seeded by the seed and the member's index). Not the initial weights: the ensemble
            drew those when it was built (``RCVAEEnsemble(..., seed=s)``, or
            ``torch.manual_seed(s)`` before building it).
        episode_start_fraction: the fraction of each member's windows that begin at the first
            step of an episode (the rest are drawn uniformly over the data). Imagination
            starts every episode there, from h_0 = 0, with nothing seen yet: a model whose
            randomness is fixed per episode (``RCVAEConfig.episode_latent_dim``) must learn
            what an episode's first steps look like, which uniform windows show rarely; so
            must any model forecast from episodes' first states when the episodes are long
            (a quarter, 0.25, is a start).
        bootstrap: each member trains on its own bootstrap resample of the training episodes
            (:func:`~rcvae_torchrl.data.resample_episodes`, drawn once per run from the seed
            and the member's index: about 63 % of the episodes, some twice), as PETS trains
            its ensemble (Chua et al. 2018), so that members differ where the data are thin.
            Off, every member draws its windows from all episodes: over a run it sees them all,
            and members differ by their initialisation and the order of their windows.
        data_parallel: under ``torch.distributed``, the number D of ranks that train each block
            of members together (data parallel, for a member whose data or model outgrows one
            rank): the ranks form groups of D consecutive ranks, the groups share out the
            members, and within a group each rank computes the loss of its
            ``batch_windows / D`` of every step's windows (the same windows a single process
            draws for the step) with its own noise, ``DistributedDataParallel`` averaging the
            group's gradients before each member's clipping and Adam step. The members' weights
            stay identical on the ranks of a group. D must divide the world size and
            ``batch_windows``. With D > 1 the results depend on D (each rank draws its own
            noise), not on the number of groups; 1 (the default) shards members only, and a
            run then equals a single process's. Without a process group it has no effect.
        compile: run the training loss (forward and backward) under ``torch.compile`` (static
            shapes; validation stays eager). The same computation up to float rounding, not
            bit for bit. It pays only for long runs: measured on the study's model (5
            members, 64 windows of 32 steps), a step took 10.2 ms compiled against 16.4 eager
            on an H100 after a 27 s compile (paid back after about 4,400 steps), and 1.23x
            faster on a CPU core after an 81 s compile (about 7,700 steps), so it is off by
            default.
    """

    max_steps: int = 3000
    batch_windows: int = 64
    window: int = 32
    lr: float = 1e-3
    lr_final_fraction: float = 1.0
    grad_clip: float = 100.0
    beta: float = 1.0
    free_nats: float = 0.0
    open_loop_steps: int = 0
    nll_beta: float = 0.0
    val_every: int = 100
    val_windows: int = 256
    patience: int = 5
    seed: int = 0
    episode_start_fraction: float = 0.0
    bootstrap: bool = False
    data_parallel: int = 1
    compile: bool = False

    def __post_init__(self) -> None:
        check_unit_interval("episode_start_fraction", self.episode_start_fraction)
        for name in ("max_steps", "batch_windows", "val_every", "val_windows", "patience"):
            check_positive_int(name, getattr(self, name))
        check_positive_int("window", self.window)
        if self.window < 2:
            raise ValueError(f"window: expected >= 2 steps, got {self.window}")
        check_positive("lr", self.lr)
        check_positive("grad_clip", self.grad_clip)
        check_unit_interval("lr_final_fraction", self.lr_final_fraction, include_zero=False)
        check_positive("beta", self.beta)
        check_non_negative("free_nats", self.free_nats)
        check_non_negative_int("open_loop_steps", self.open_loop_steps)
        if self.open_loop_steps >= self.window:
            raise ValueError(
                f"open_loop_steps: expected fewer than the window's {self.window} steps (the "
                f"first transition of a window reads a true state), got {self.open_loop_steps}"
            )
        check_unit_interval("nll_beta", self.nll_beta)
        for name in ("bootstrap", "compile"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: expected True or False, got {getattr(self, name)!r}")
        check_non_negative_int("seed", self.seed)
        if self.seed >= 2**63:  # torch's generators take seeds below 2**63
            raise ValueError(f"seed: expected an integer in [0, 2**63), got {self.seed!r}")
        parallel = self.data_parallel
        if isinstance(parallel, bool) or not isinstance(parallel, int) or parallel < 1:
            raise ValueError(f"data_parallel: expected an integer >= 1, got {parallel!r}")
        if self.batch_windows % parallel:
            raise ValueError(
                f"data_parallel: expected a divisor of batch_windows={self.batch_windows} (each "
                f"rank of a group takes an equal share of the windows), got {parallel}"
            )

    def lr_at(self, step: int) -> float:
        """The learning rate of optimiser step ``step`` (0-based): cosine decay."""
        progress = min(step / self.max_steps, 1.0)
        fraction = self.lr_final_fraction
        return self.lr * (fraction + (1 - fraction) * 0.5 * (1 + math.cos(math.pi * progress)))


@dataclass
class TrainResult:
    """What :func:`train_ensemble` returns: the best weights are loaded into ``ensemble``
    (and its self-checks, when run, into ``ensemble.checks`` and ``checks``; its check of
    novelty, when fitted, into ``ensemble.novelty`` and ``novelty``).

    Each member stops on its own (``patience`` validations without improvement):
    ``member_steps`` says when each did, ``stopped_early`` only whether all of them stopped
    before ``max_steps``.
    """

    ensemble: RCVAEEnsemble
    steps: int  #: the steps run: the last member's stop, or ``max_steps``
    best_val: torch.Tensor  #: ``[E]`` each member's best validation loss (its kept weights')
    stopped_early: bool  #: every member stopped before ``max_steps``
    history: list[dict[str, Any]] = field(default_factory=list)  #: one entry per validation
    checks: ModelChecks | None = None  #: the self-checks, when run (``checks=``)
    member_steps: torch.Tensor | None = None  #: ``[E]`` the step at which each member stopped
    #: the check of novelty against the training states, when fitted (``novelty=``)
    novelty: StateNovelty | None = None
    #: the model's one-step errors on held-out episodes, when measured (``dynamics=``)
    dynamics: DynamicsNovelty | None = None


@dataclass
class _State:
    """One shard's training state (a run of one process is one shard of all members)."""

    step: int
    best_val: torch.Tensor  # [e]
    best_weights: dict[str, torch.Tensor]
    bad_evals: torch.Tensor  # [e] validations without improvement, per member
    stop_step: torch.Tensor  # [e] the step at which the member stopped, 0 while it trains
    finished: bool = False
    stopped_early: bool = False
    history: list[dict[str, Any]] = field(default_factory=list)


def train_ensemble(
    ensemble: RCVAEEnsemble,
    train_data: TensorDictBase,
    val_data: TensorDictBase,
    config: TrainConfig = TrainConfig(),
    *,
    checkpoint_path: str | Path | None = None,
    resume: bool = False,
    logger: Logger | None = None,
    log_prefix: str = "",
    progress: bool = True,
    checks: bool | Mapping[str, Any] = True,
    novelty: bool = True,
    dynamics: bool = True,
) -> TrainResult:
    """Train ``ensemble`` on episodes (flat TensorDicts ``[frames]`` from ``collect_episodes``).

    Members are trained independently: each has its own generators (seeded by ``config.seed``
    and its index) for its windows (from all episodes, or its own bootstrap resample of them)
    and its noise, its own gradient clipping and its own early stopping (a member stops after
    ``patience`` validations without improvement; the run ends when every member has stopped).
    So a member's weights do not depend on the members it is trained with, and under
    ``torch.distributed`` (:mod:`rcvae_torchrl.distributed`) every rank trains a contiguous
    block of members, and the gathered ensemble equals the one a single process trains.

    Args:
        ensemble: the model; its normaliser is fitted on ``train_data`` if not fitted yet, and
            kept if fitted (a fine-tune on more data), with a warning where ``train_data``
            lie far from its statistics (refit it with ``ensemble.fit_normalizer`` there).
            Under ``torch.distributed`` rank 0's initial weights are used by every rank.
        train_data, val_data: whole episodes, split by episode (``split_episodes``).
        config: budget and hyper-parameters.
        checkpoint_path: where the training checkpoint goes (written at each validation);
            CSV logs go to ``<checkpoint dir>/logs`` unless ``logger`` is given. Under
            ``torch.distributed`` each rank writes its block's checkpoint beside it
            (``<stem>.members-<first>-<last><suffix>``) and rank 0 writes the gathered
            ensemble to ``checkpoint_path`` at the end.
        resume: continue from ``checkpoint_path`` (or this rank's block checkpoint) if it
            exists (a finished run returns at once); resume with the same number of ranks.
        logger: a TorchRL logger of this rank's records (default: CSV beside the checkpoint
            on rank 0, or none); :func:`~rcvae_torchrl.loggers.make_logger` makes a
            TensorBoard, W&B or MLflow one. Per-member values go to ``<name>/<member>``.
        log_prefix: put before every logged name (e.g. ``"models/stochastic/"`` when several
            trainings share one logger).
        progress: show a tqdm bar (rank 0).
        checks: run the model's self-checks on ``val_data`` after training
            (:func:`~rcvae_torchrl.training.check_model`): per state dimension, held-out
            one-step and open-loop errors against copying the previous state and against the
            data's spread, and the coverage of its spread; a warning names every dimension the
            model has not learned. A mapping runs them with these arguments of
            ``check_model`` (e.g. ``{"coverage_steps": 5}``: a system that an open-loop
            drive sends off its course within the default 20 steps, such as an inverted
            pendulum, is checked nearer).
        novelty: fit the check of how unlike its training states a state is
            (:class:`~rcvae_torchrl.training.StateNovelty`: ``train_data``'s states, the level
            from ``val_data``'s; each entry of two or more dimensions that the config's
            ``observation_names`` name, ``key[0]``, ``key[1]``, ..., also judged on its own,
            :func:`~rcvae_torchrl.training.entry_groups`) into ``ensemble.novelty``; the
            competency assessor then says which start states, and how many imagined states,
            lie beyond it.
        dynamics: measure how far the trained model's one-step predictions miss
            (:class:`~rcvae_torchrl.training.DynamicsNovelty`: their unit on ``train_data``,
            their level on ``val_data``'s episodes) into ``ensemble.dynamics``, with which
            :func:`~rcvae_torchrl.training.check_dynamics` tells whether real episodes of an
            env move as the model learned. Left ``None`` where ``val_data`` holds fewer than
            :data:`~rcvae_torchrl.training.dynamics.MIN_HELD_OUT` episodes of at least
            :data:`~rcvae_torchrl.training.dynamics.STEPS` frames, or ``train_data`` none.
    """
    if not isinstance(ensemble, RCVAEEnsemble):
        raise TypeError(f"ensemble: expected an RCVAEEnsemble, got {type(ensemble).__name__}")
    if checkpoint_path is not None and not isinstance(checkpoint_path, (str, os.PathLike)):
        raise TypeError(
            f"checkpoint_path: expected a str, a path or None, got {type(checkpoint_path).__name__}"
        )
    for name, flag in (
        ("resume", resume),
        ("progress", progress),
        ("novelty", novelty),
        ("dynamics", dynamics),
    ):
        check_bool(name, flag)
    path = Path(checkpoint_path) if checkpoint_path is not None else None
    if resume and path is None:
        raise ValueError("resume: expected a checkpoint_path to resume from, got None")
    check_args = _check_args(checks)
    if not isinstance(log_prefix, str):
        raise TypeError(f"log_prefix: expected a str, got {type(log_prefix).__name__}")
    if logger is not None and not callable(getattr(logger, "log_scalar", None)):
        raise TypeError(
            f"logger: expected a TorchRL Logger or None (make_logger makes one), got {logger!r}"
        )
    if path is not None:
        _check_checkpoint_path(path, resume)
    if not isinstance(config, TrainConfig):
        raise TypeError(f"config: expected a TrainConfig, got {type(config).__name__}")
    for name, data in (("train_data", train_data), ("val_data", val_data)):
        spans = _check_episodes(ensemble, data, name, config.window)
        if distributed.is_main():
            _warn_short_episodes(data, name, config.window, spans)
    if novelty:  # fitted after training: refused before it
        check_novelty_episodes(train_data)
    if train_data is val_data and distributed.is_main():
        warnings.warn(
            "val_data: the same episodes as train_data: validation then measures the fit, not "
            "how the model does on episodes it has not seen, and early stopping and the "
            "self-checks lose their meaning; hold episodes out with split_episodes",
            UserWarning,
            stacklevel=2,
        )
    torch.manual_seed(config.seed)
    if not ensemble.normalizer.fitted:
        ensemble.fit_normalizer(
            train_data["observation"],
            train_data["action"],
            next_observations=train_data["next", "observation"],
        )
    elif distributed.is_main() and not resume:
        _warn_stale_normalizer(ensemble, train_data)
    ensemble.load_state_dict(distributed.broadcast(_weights(ensemble)))
    data = _data_digest(train_data, val_data) if path is not None else None
    state = _finished_gathered_run(path, data) if resume else None
    if state is None:
        layout = _replicas(config)
        try:
            shard = _train_shard(
                ensemble,
                layout,
                train_data,
                val_data,
                config,
                path,
                resume,
                (logger, log_prefix),
                progress,
                data,
            )
        finally:
            if layout.group is not None:
                torch.distributed.destroy_process_group(layout.group)
        state = _gather(ensemble, shard if layout.index == 0 else None)
        if distributed.is_active() and path is not None:
            _write_gathered(path, ensemble, state, config, data)
    ensemble.load_state_dict(state.best_weights)
    result = TrainResult(
        ensemble,
        state.step,
        state.best_val,
        state.stopped_early,
        state.history,
        member_steps=state.stop_step,
    )
    if distributed.is_main():
        _warn_stuck_members(state, config)
    if checks is not False:  # True or a mapping of check_model's arguments (even empty)
        found = None
        if distributed.is_main():
            found = check_model(
                ensemble, val_data, **{"seed": config.seed, **check_args, "warn": False}
            )
            if not found.passed:
                message = found.message() + _stopped_early_hint(found, state.stop_step, config)
                warnings.warn(message, ModelCheckWarning, stacklevel=2)
        result.checks = ensemble.checks = distributed.broadcast(found)
    if novelty:
        fitted = None
        if distributed.is_main():
            groups = entry_groups(ensemble.config.observation_names)
            fitted = StateNovelty.from_episodes(
                train_data, val_data, seed=config.seed, groups=groups
            )
        result.novelty = ensemble.novelty = distributed.broadcast(fitted)
    if dynamics:
        measured = None
        enough = _long_episodes(val_data) >= MIN_HELD_OUT and _long_episodes(train_data) > 0
        if distributed.is_main() and enough:
            measured = DynamicsNovelty.fit(ensemble, train_data, val_data, seed=config.seed)
        elif distributed.is_main():
            _warn_dynamics_unmeasured(val_data)
        result.dynamics = ensemble.dynamics = distributed.broadcast(measured)
    return result


def _warn_dynamics_unmeasured(val_data: TensorDictBase) -> None:
    """Warn that ``dynamics=True`` measured nothing: too few episodes long enough (in
    ``val_data``, else in the training data)."""
    held = _long_episodes(val_data)
    short = (
        f"val_data holds {held} episodes of at least {STEPS} frames ({MIN_HELD_OUT} needed)"
        if held < MIN_HELD_OUT
        else f"train_data holds no episode of at least {STEPS} frames"
    )
    warnings.warn(
        f"dynamics: not measured, {short}: ensemble.dynamics is None, so check_dynamics has no "
        "held-out errors to rank real episodes against. Give it a reference of episodes of the "
        "env the model learned (DynamicsNovelty.fit(ensemble, train_data, episodes, steps=...), "
        "passed as check_dynamics(..., novelty=...)), or train with dynamics=False to measure "
        "none",
        UserWarning,
        stacklevel=3,
    )


def _long_episodes(data: TensorDictBase) -> int:
    """The episodes of ``data`` long enough for the dynamics check (:data:`STEPS` frames)."""
    return int((episode_spans(data)[1] >= STEPS).sum())


def _check_args(checks: object) -> dict[str, Any]:
    """``train_ensemble``'s ``checks`` as arguments of ``check_model`` (none for a bool)."""
    if isinstance(checks, bool):
        return {}
    if not isinstance(checks, Mapping):
        raise TypeError(
            f"checks: expected True, False or a mapping of check_model's arguments, got "
            f"{type(checks).__name__}"
        )
    known = set(inspect.signature(check_model).parameters) - {"ensemble", "data", "warn"}
    unknown = sorted(set(checks) - known)
    if unknown:
        raise TypeError(f"checks: unknown check_model arguments {unknown} (known: {sorted(known)})")
    return dict(checks)


#: how a resume refusal says to go on from a trained model with other data or settings
_WARM_START = (
    "a new path trains the ensemble it is given: to go on from this run's weights, on more "
    "data or for more steps, pass load_ensemble(...) of its model, and refit its normaliser "
    "where the data moved"
)

#: a fitted normaliser is stale for data whose mean lies this many of its stds from its mean,
#: or whose std is this many times its std (or this many times smaller)
_STALE_SHIFT = 1.0
_STALE_SCALE = 2.0


def _warn_stale_normalizer(ensemble: RCVAEEnsemble, train_data: TensorDictBase) -> None:
    """Warn when the ensemble's normaliser, fitted before (a model trained on other data,
    loaded to be trained on more), is far from ``train_data``'s statistics: it is kept, so the
    new states are scaled by the old ones (a point-mass trial's new half of the arena sat
    about 4 of the old stds out), with nothing said."""
    norm = ensemble.normalizer
    names = ensemble.config.observation_names
    worst = None
    for entry, key, mean, std in (
        ("observation", "observation", norm.state_mean, norm.state_std),
        ("action", "action", norm.action_mean, norm.action_std),
    ):
        m, s = masked_mean_std(train_data[key].to(mean))  # as the normaliser fits them
        shift = (m - mean).abs() / std
        scale = torch.maximum(s / std, std / s)
        for i in range(mean.shape[0]):
            score = max(float(shift[i]) / _STALE_SHIFT, float(scale[i]) / _STALE_SCALE)
            if score > 1 and (worst is None or score > worst[0]):
                label = names[i] if entry == "observation" and names else f"{entry}[{i}]"
                worst = (score, label, float(m[i]), float(s[i]), float(mean[i]), float(std[i]))
    if worst is None:
        return
    _, label, m, s, fitted_mean, fitted_std = worst
    warnings.warn(
        f"train_data: the ensemble's normaliser was fitted before, and is kept, but these data "
        f"lie elsewhere: {label} has mean {m:.3g} and std {s:.3g} here, {fitted_mean:.3g} and "
        f"{fitted_std:.3g} in the statistics; to train on new data (more episodes, a fine-tune), "
        "refit them first (ensemble.fit_normalizer(train_data['observation'], "
        "train_data['action'], next_observations=train_data['next', 'observation'])) or train a "
        "new ensemble, which fits its own",
        UserWarning,
        stacklevel=3,
    )


def _warn_short_episodes(
    data: TensorDictBase, name: str, window: int, spans: tuple[torch.Tensor, torch.Tensor]
) -> None:
    """Warn that episodes shorter than ``window`` are never drawn (a window never crosses an
    episode's end), and how many of them the env ended (``("next", "terminated")``): quick
    failures or successes whose endings the model then never sees. ``spans``: the episodes'
    first frames and lengths (``episode_spans``)."""
    first, lengths = spans
    short = lengths < window
    if not bool(short.any()):
        return
    ended = ""
    if ("next", "terminated") in data.keys(True):
        last = data.get(("next", "terminated"))[first + lengths - 1]
        terminated = last.reshape(lengths.shape[0], -1).any(-1)
        ended = (
            f"; {int((terminated & short).sum())} of them (of the {int(terminated.sum())} "
            "episodes the env terminated) end in a termination the model then never sees"
        )
    warnings.warn(
        f"{name}: {int(short.sum())} of {lengths.numel()} episodes ({int(lengths[short].sum())} "
        f"frames) are shorter than the window (TrainConfig.window = {window} steps) and are "
        f"never drawn{ended}; a shorter window, or episodes that last at least as long, let "
        "the model learn from them",
        UserWarning,
        stacklevel=3,
    )


def _warn_stuck_members(state: _State, config: TrainConfig) -> None:
    """Warn about members that kept their first validation's weights: their validation loss
    never improved after it in ``patience`` validations (a run too short for that says
    nothing)."""
    if len(state.history) < 2:
        return
    first = torch.tensor(state.history[0]["val_loss_member"], dtype=state.best_val.dtype)
    long_enough = (state.stop_step < config.max_steps) | (len(state.history) > config.patience)
    stuck = ((state.best_val == first) & long_enough).nonzero()
    if stuck.numel() == 0:
        return
    members = stuck.flatten().tolist()
    warnings.warn(
        f"train_ensemble: member(s) {members} kept the weights of their first validation "
        f"(step {int(state.history[0]['step'])}, validation loss "
        f"{', '.join(f'{float(first[m]):.3g}' for m in members)}; the ensemble's best "
        f"{float(state.best_val.min()):.3g}): their validation loss never improved after it, "
        f"so they are barely trained (stopped at step(s) "
        f"{[int(state.stop_step[m]) for m in members]}, patience={config.patience}); the "
        "ensemble's spread and forecasts inherit them. Look at the validation loss "
        "(log_history), lower the learning rate or raise patience",
        UserWarning,
        stacklevel=3,
    )


def _stopped_early_hint(found: ModelChecks, stop_step: torch.Tensor, config: TrainConfig) -> str:
    """Where members that have not learned a dimension stopped before ``max_steps``, say so:
    early stopping (``patience``) may have ended them before they learned it."""
    early = stop_step < config.max_steps
    if not found.unlearned or not bool(early.any()):
        return ""
    steps = stop_step[early]
    return (
        f"; {int(early.sum())} of {stop_step.numel()} members stopped early, after "
        f"{int(steps.min())}–{int(steps.max())} of max_steps={config.max_steps} steps "
        f"(patience={config.patience} validations without improvement): training longer (a "
        "larger patience, more steps or more data) may teach them"
    )


def _check_episodes(
    ensemble: RCVAEEnsemble, data: object, name: str, window: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Require flat episodes ``[frames]`` that ``ensemble`` can learn from, all of them checked
    before any is used: episode ids (:data:`TRAJ_KEY`) and an episode of at least ``window``
    steps, ``"observation"`` ``[frames, S]``, ``"action"`` ``[frames, A]`` and
    ``("next", "observation")`` ``[frames, S]`` in the model's dtype, every entry finite (a NaN
    that no sampled window happens to hold would otherwise pass, and a NaN in the normaliser's
    statistics spoils every prediction). Errors name ``name`` and the entry. Returns the
    episodes' spans (``episode_spans``)."""
    check_frames_type(data, name)
    if data.batch_dims != 1 or data.batch_size[0] == 0:
        raise ValueError(
            f"{name}: expected a flat TensorDict of episodes [frames] with at least one frame, "
            f"got batch {tuple(data.batch_size)}"
        )
    cfg = ensemble.config
    for key, size, axis in (
        ("observation", cfg.obs_dim, "S"),
        ("action", cfg.action_dim, "A"),
        (("next", "observation"), cfg.obs_dim, "S"),
    ):
        label = f"{name}[{key!r}]"
        x = data.get(key, None)
        if x is None:
            keys = sorted(map(str, data.keys(True, True)))
            raise ValueError(f"{name}: expected an entry {key!r}, got the entries {keys}")
        if x.dim() != 2 or x.shape[-1] != size:  # the TensorDict's batch is [frames] already
            raise ValueError(
                f"{label}: expected shape [frames, {axis}={size}], got {tuple(x.shape)}"
            )
        check_dtype(label, x, ensemble.dtype)
        check_finite(label, x)
    if TRAJ_KEY not in data.keys(True):
        raise ValueError(
            f"{name}: expected episode ids under {TRAJ_KEY} (collect_episodes writes them), got "
            f"the entries {sorted(map(str, data.keys(True, True)))}"
        )
    check_episode_ids(data, name)
    spans = episode_spans(data)
    longest = int(spans[1].max())
    if longest < window:
        raise ValueError(
            f"{name}: expected an episode of at least TrainConfig.window = {window} steps, got "
            f"episodes of at most {longest}; collect longer episodes or shorten the window"
        )
    return spans


def _replicas(config: TrainConfig) -> distributed.Replicas:
    """This rank's group of ``config.data_parallel`` ranks (see :class:`TrainConfig`)."""
    world = distributed.world_size()
    if distributed.is_active() and world % config.data_parallel:
        raise ValueError(
            f"data_parallel: expected a divisor of the world size {world} (ranks per group), "
            f"got {config.data_parallel}"
        )
    return distributed.replicas(config.data_parallel)


def _train_shard(
    ensemble: RCVAEEnsemble,
    layout: distributed.Replicas,
    train_data: TensorDictBase,
    val_data: TensorDictBase,
    config: TrainConfig,
    path: Path | None,
    resume: bool,
    logging: tuple[Logger | None, str],
    progress: bool,
    data: str | None = None,
) -> _State | None:
    """Train this rank's block of members of ``ensemble`` (a copy of them), on its share of
    every step's windows; their final state (``None`` when the block is empty: more groups
    than members)."""
    members = distributed.shard(ensemble.ensemble_size, layout.block, layout.blocks)
    if len(members) == 0:
        return None
    device = next(ensemble.parameters()).device
    with torch.random.fork_rng(devices=[]):  # building the copy draws an initialisation
        local = ensemble.select_members(list(members))
    shard_path = _shard_path(path, members, ensemble.ensemble_size)
    windows_rng = _generators(config.seed, members, _WINDOWS, torch.device("cpu"))
    # replica 0 draws a single process's noise, the others their own
    noise_keys = (_NOISE,) if layout.index == 0 else (_NOISE, layout.index)
    noise_rng = _generators(config.seed, members, noise_keys, device)
    share = distributed.shard(config.batch_windows, layout.index, layout.size)
    if config.bootstrap:  # each member's own resample of the episodes, the same on every rank
        boot = _generators(config.seed, members, _BOOTSTRAP, torch.device("cpu"))
        buffer = [make_window_buffer(resample_episodes(train_data, g), config.window) for g in boot]
    else:
        buffer = make_window_buffer(train_data, config.window)
    val_windows = _fixed_windows(val_data, config).to(device)
    loss_fn = RCVAELoss(
        local,
        beta=config.beta,
        free_nats=config.free_nats,
        open_loop_steps=config.open_loop_steps,
        nll_beta=config.nll_beta,
        generator=noise_rng,
        validate=False,  # every frame was checked up front (_check_episodes)
    )
    params = list(local.parameters())
    optimizer = _adam(params, config.lr)
    trained: Callable[[TensorDictBase], TensorDictBase] = loss_fn
    if layout.group is not None:  # the group's gradients averaged in the backward pass
        trained = DistributedDataParallel(loss_fn, process_group=layout.group)
    if config.compile:  # no batched env's finalizer may change the threads while it traces
        trained = collection_paused(torch.compile(trained, dynamic=False))
    state = _new_state(local)
    if resume and shard_path is not None:
        _check_no_foreign_shards(shard_path, path)
        if shard_path.is_file():
            state = _restore(
                shard_path,
                local,
                optimizer,
                (config, data),
                members,
                windows_rng,
                noise_rng,
                layout,
            )
            _log_resumed(shard_path, state, config)
    logger, prefix = logging
    logger = logger if logger is not None else _default_logger(path)
    bar = tqdm(
        total=config.max_steps,
        initial=state.step,
        desc="train world model",
        disable=not (progress and distributed.is_main()),
        leave=False,
    )
    start_windows = round(config.episode_start_fraction * config.batch_windows)
    checked_step = state.step  # the last step whose training loss was seen finite
    while not state.finished:
        windows = sample_windows(
            buffer,
            config.batch_windows,
            config.window,
            len(members),
            windows_rng,
            start_windows=start_windows,
        )[:, share.start : share.stop]
        for group in optimizer.param_groups:
            group["lr"] = config.lr_at(state.step)
        train_loss = _train_step(
            trained, optimizer, params, _to_device(windows, device), config.grad_clip
        )
        state.step += 1
        bar.update(1)
        if state.step % config.val_every == 0 or state.step >= config.max_steps:
            if layout.group is not None:  # the group's mean: the loss of all the step's windows
                torch.distributed.all_reduce(train_loss, group=layout.group)
                train_loss /= layout.size
            train_loss = train_loss.cpu()
            _check_training_loss(train_loss, checked_step, state.step)
            checked_step = state.step
            record = _validate(loss_fn, val_windows, local, members, state, config, train_loss)
            bar.set_postfix(train=f"{record['train_loss']:.3g}", val=f"{record['val_loss']:.3g}")
            _log(logger, record, state.step, prefix)
            if shard_path is not None:
                _save(
                    shard_path,
                    local,
                    optimizer,
                    state,
                    config,
                    members,
                    windows_rng,
                    noise_rng,
                    layout,
                    data,
                )
    bar.close()
    return state


# Streams of a member's generators (with the run's seed and the member's index).
_WINDOWS, _NOISE, _VALIDATION, _BOOTSTRAP = 0, 1, 2, 3


def _generators(
    seed: int, members: range, stream: int | tuple[int, ...], device: torch.device
) -> list:
    """One generator per member, seeded by (seed, member, *stream) alone."""
    keys = stream if isinstance(stream, tuple) else (stream,)
    return [distributed.work_generator(seed, m, *keys, device=device) for m in members]


def _new_state(local: RCVAEEnsemble) -> _State:
    e = local.ensemble_size
    zeros = torch.zeros(e, dtype=torch.int64)
    return _State(0, torch.full((e,), math.inf), _weights(local), zeros, zeros.clone())


def _fixed_windows(val_data: TensorDictBase, config: TrainConfig) -> TensorDict:
    """The same validation windows for every validation of a run (own RNG stream)."""
    with torch.random.fork_rng():
        torch.manual_seed(config.seed + 1)
        buffer = make_window_buffer(val_data, config.window)
        return sample_windows(buffer, config.val_windows, config.window)


def _adam(params: list[torch.Tensor], lr: float) -> torch.optim.Adam:
    """Adam with its multi-tensor (``foreach``) update: each of its ops is one call for all
    parameter tensors, not one per tensor (torch picks it by default only on GPUs), and it
    computes the per-tensor update's numbers. Not ``fused=True`` (faster still): with the
    fused CPU kernel (torch 2.13) a member's weights come out different when it is trained
    with other members, and a sharded run no longer equals a single process's."""
    return torch.optim.Adam(params, lr=lr, foreach=True)


def _to_device(windows: TensorDict, device: torch.device) -> TensorDict:
    """The sampled windows on ``device``. To a GPU they go from page-locked memory without
    waiting (the host memory comes from torch's caching allocator, reused once the copy is
    done), so the host samples the next windows while the GPU still runs this step."""
    if device.type != "cuda":
        return windows.to(device)
    return windows.pin_memory().to(device, non_blocking=True)


def _train_step(
    loss_fn: Callable[[TensorDictBase], TensorDictBase],
    optimizer: torch.optim.Optimizer,
    params: list[torch.Tensor],
    windows: TensorDict,
    grad_clip: float,
) -> torch.Tensor:
    """One Adam step of every member; the members' training losses ``[e]`` (detached, on the
    model's device: nothing in a step reads a value back to the host, so on a GPU the host
    queues the next step while this one runs; :func:`_check_training_loss` reads them)."""
    out = loss_fn(windows)
    loss = out["loss_reconstruction"] + out["loss_kl"]
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    clip_grad_norm_per_member(params, grad_clip)
    optimizer.step()
    return out["loss_per_member"].detach()


def _check_training_loss(train_loss: torch.Tensor, checked_step: int, step: int) -> None:
    """Raise when a member's training loss is not finite. Read at each validation rather than
    at every step (a read waits for the device): a step with a non-finite loss leaves
    non-finite weights, so every later step's loss is non-finite too and the next read finds
    it; the weights kept so far (best and checkpointed) are those validated before it."""
    if not bool(torch.isfinite(train_loss).all()):
        raise FloatingPointError(
            f"training loss is not finite at step {step} ({train_loss.tolist()} per member), "
            f"from a step in {checked_step + 1}..{step} on; lower lr?"
        )


@torch.no_grad()
def clip_grad_norm_per_member(params: list[torch.Tensor], max_norm: float) -> torch.Tensor:
    """Clip each member's gradient norm (parameters stacked ``[E, ...]``) to ``max_norm``, as
    ``torch.nn.utils.clip_grad_norm_`` does for one model; returns the norms ``[E]``."""
    grads = [p.grad for p in params if p.grad is not None]
    squares = torch._foreach_mul(grads, grads)  # one call for all tensors, the same numbers
    # each member's sums along its own row ([E, P], an inner reduction): a sum over the
    # stacked tensors' axis ([P, E].sum(0)) rounds otherwise for 2 members than for 4, and a
    # rank training 2 of 4 members clipped them otherwise than one process training all 4
    norms = torch.stack([s.flatten(1).sum(1) for s in squares], dim=1).sum(1).sqrt()
    scale = (max_norm / (norms + 1e-6)).clamp(max=1.0)
    # Every gradient times its member's factor, unread: a test of the factors on the host
    # would wait for the device; a factor of 1 leaves a gradient as it is.
    torch._foreach_mul_(grads, [scale.view(-1, *([1] * (g.ndim - 1))) for g in grads])
    return norms


@torch.no_grad()
def _validate(
    loss_fn: RCVAELoss,
    windows: TensorDict,
    local: RCVAEEnsemble,
    members: range,
    state: _State,
    config: TrainConfig,
    train_loss: torch.Tensor,
) -> dict[str, Any]:
    """Per-member validation loss; keep improved members' weights; stop members that have
    not improved for ``patience`` validations (each member on its own)."""
    device = next(local.parameters()).device
    noise, loss_fn.generator = (
        loss_fn.generator,
        _generators(config.seed, members, _VALIDATION, device),
    )
    try:
        per_member = loss_fn(windows)["loss_per_member"].cpu()
    finally:
        loss_fn.generator = noise
    active = state.stop_step == 0
    improved = (per_member < state.best_val) & active
    state.best_val = torch.where(improved, per_member, state.best_val)
    if improved.any():
        for name, param in local.named_parameters():  # stacked [e, ...]: copy improved rows
            state.best_weights[name][improved] = param.detach().cpu()[improved]
    state.bad_evals = torch.where(improved, 0, state.bad_evals + active.long())
    stopping = active & ((state.bad_evals >= config.patience) | (state.step >= config.max_steps))
    state.stop_step[stopping] = state.step
    _finish(state, config)
    nan = torch.tensor(math.nan)
    record = _record(
        state.step,
        torch.where(active, train_loss, nan).tolist(),
        torch.where(active, per_member, nan).tolist(),
        state.best_val.tolist(),
        int(improved.sum()),
    )
    state.history.append(record)
    return record


def _finish(state: _State, config: TrainConfig) -> None:
    stopped = state.stop_step > 0
    state.finished = bool(stopped.all())
    state.stopped_early = state.finished and bool((state.stop_step < config.max_steps).all())


def _record(
    step: int, train: list[float], val: list[float], best: list[float], improved: int
) -> dict[str, Any]:
    """A history row: means over the members still training, and the per-member values."""

    def mean(values: list[float]) -> float:
        return float(torch.tensor(values).nanmean())

    return {
        "step": float(step),
        "train_loss": mean(train),
        "val_loss": mean(val),
        "best_val_loss": mean(best),
        "members_improved": float(improved),
        "train_loss_member": train,
        "val_loss_member": val,
        "best_val_member": best,
    }


def _weights(ensemble: RCVAEEnsemble) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu().clone() for k, v in ensemble.state_dict().items()}


def _default_logger(path: Path | None) -> Logger | None:
    if path is None or not distributed.is_main():
        return None
    return CSVLogger(exp_name=path.stem, log_dir=str(path.parent / "logs"))


def _log(logger: Logger | None, record: dict[str, Any], step: int, prefix: str) -> None:
    """The record's numbers; a per-member list as ``<name>/<member>`` (finite values only)."""
    metrics = {
        k: dict(enumerate(v)) if isinstance(v, list) else v
        for k, v in record.items()
        if k != "step"
    }
    log_scalars(logger, metrics, step, prefix=prefix)


def log_history(logger: Logger | None, history: list[dict[str, Any]], prefix: str = "") -> None:
    """Log a finished training's history (:attr:`TrainResult.history`) to ``logger``, each row
    at its step, as :func:`train_ensemble` logs it while it trains: for a training that ran
    where ``logger`` could not go (another process)."""
    for record in history:
        _log(logger, record, int(record["step"]), prefix)


# ---------------------------------------------------------------------- checkpoints
def _shard_path(path: Path | None, members: range, ensemble_size: int) -> Path | None:
    """The checkpoint of a block of members: ``path`` itself when it holds them all."""
    if path is None or len(members) == ensemble_size:
        return path
    return path.with_name(f"{path.stem}.members-{members[0]}-{members[-1]}{path.suffix}")


def _check_no_foreign_shards(shard_path: Path, path: Path) -> None:
    """Block checkpoints of another split of the members (another number of ranks or groups),
    or an unfinished run of all members at ``path`` where this rank trains a block."""
    if shard_path.is_file():
        return
    if shard_path != path and path.is_file() and not _training_payload(path)["state"]["finished"]:
        raise CheckpointError(
            f"checkpoint_path {str(path)!r}: holds an unfinished run of all members (one "
            f"process, or one data-parallel group), this rank trains the block of "
            f"{shard_path.name!r}; resume with the same number of ranks and data_parallel"
        )
    others = sorted(path.parent.glob(f"{path.stem}.members-*{path.suffix}"))
    if others:
        raise CheckpointError(
            f"checkpoint_path {str(path)!r}: expected this rank's block checkpoint "
            f"{shard_path.name!r} to resume, found {[p.name for p in others]} (written by a run "
            "with another number of ranks); resume with the same number of ranks"
        )


def _save(
    path: Path,
    local: RCVAEEnsemble,
    optimizer: torch.optim.Optimizer,
    state: _State,
    config: TrainConfig,
    members: range,
    windows_rng: list[torch.Generator],
    noise_rng: list[torch.Generator],
    layout: distributed.Replicas,
    data: str | None = None,
) -> None:
    """Write the block's checkpoint. A data-parallel group writes one, from its first rank,
    holding every rank's noise generators (the weights and optimiser are the same on all),
    so that a kill at any moment leaves the whole group one consistent state to resume."""
    noise = [g.get_state() for g in noise_rng]
    replica_rng = None
    if layout.group is not None:
        replica_rng = [None] * layout.size
        torch.distributed.all_gather_object(replica_rng, noise, group=layout.group)
    if layout.index != 0:
        return
    payload: dict[str, Any] = {
        **ensemble_payload(local),
        "training": {
            "config": dataclasses.asdict(config),
            "data": data,
            "members": [members.start, members.stop],
            "optimizer": optimizer.state_dict(),
            "rng": [g.get_state() for g in windows_rng] + noise,
            "replica_rng": replica_rng,
            "state": {**dataclasses.asdict(state)},
        },
    }
    save_torch(path, payload)


def _data_digest(train_data: TensorDictBase, val_data: TensorDictBase) -> str:
    """A digest of the values of every entry of the training and validation data: a resumed
    run must continue on the data it started with."""
    return fingerprint.digest(
        {
            name: {str(k): v for k, v in d.items(include_nested=True, leaves_only=True)}
            for name, d in (("train", train_data), ("val", val_data))
        }
    )


def _check_checkpoint_path(path: Path, resume: bool) -> None:
    """Refuse a ``checkpoint_path`` that training would write over and that is not a training
    checkpoint (a folder, a user's episodes, a model saved with ``save_ensemble``)."""
    if path.is_dir():
        raise ValueError(
            f"checkpoint_path: {str(path)!r} is a directory; expected the path of a file (e.g. "
            f"{str(path / 'model.pt')!r})"
        )
    if resume or not path.is_file():  # resuming reads it, and refuses what it cannot resume
        return
    try:
        found = "training" in read_checkpoint(path)
        reason = "it holds no training state: a model saved with save_ensemble?"
    except CheckpointError as err:
        found, reason = False, str(err)
    if not found:
        raise ValueError(
            f"checkpoint_path: {str(path)!r} exists and is not a training checkpoint ({reason}); "
            "training would overwrite it: give a new path"
        )


def _training_payload(
    path: Path, config: TrainConfig | None = None, data: str | None = None
) -> dict[str, Any]:
    training = read_checkpoint(path).get("training")
    if training is None:
        raise CheckpointError(f"checkpoint {str(path)!r}: holds no training state to resume", path)
    # a setting added since the checkpoint was written had its default value then
    saved = {**dataclasses.asdict(TrainConfig()), **training["config"]}
    given = dataclasses.asdict(config) if config is not None else saved
    _refuse_other(path, saved, given, "with another TrainConfig", "config")
    saved_data = training.get("data")  # None: written before data digests, or without a path
    if data is not None and saved_data is not None and saved_data != data:
        raise CheckpointError(
            f"checkpoint {str(path)!r}: was written by a training on other data (train_data or "
            "val_data differ from the run's that wrote it, in a value or a dtype: the same "
            "episodes cast to another precision are other data); resume with the same data or "
            f"a new path ({_WARM_START})",
            path,
        )
    return training


def _restore(
    path: Path,
    local: RCVAEEnsemble,
    optimizer: torch.optim.Optimizer,
    run: tuple[TrainConfig, str | None],
    members: range,
    windows_rng: list[torch.Generator],
    noise_rng: list[torch.Generator],
    layout: distributed.Replicas,
) -> _State:
    payload = read_checkpoint(path)
    training = _training_payload(path, *run)
    saved = training.get("members", [0, local.ensemble_size])
    if list(saved) != [members.start, members.stop]:
        raise CheckpointError(
            f"checkpoint {str(path)!r}: holds members {saved[0]}..{saved[1] - 1}, this run "
            f"trains {members.start}..{members.stop - 1} (another ensemble size, or another "
            "number of ranks); resume with the same ensemble and the same number of ranks",
            path,
        )
    _check_model_config(path, payload.get("config"), local.config)
    try:  # a finished run's too: its best weights are loaded into the caller's model
        local.load_state_dict(payload["state_dict"])
    except RuntimeError as err:
        raise CheckpointError(
            f"checkpoint {str(path)!r}: weights do not match: {err}", path
        ) from err
    if training["state"]["finished"]:
        return _State(**training["state"])
    optimizer.load_state_dict(training["optimizer"])
    states = training["rng"]
    if layout.index > 0:  # this rank of a data-parallel group: its own noise
        states = states[: len(windows_rng)] + training["replica_rng"][layout.index]
    for g, rng in zip(windows_rng + noise_rng, states, strict=True):
        g.set_state(rng)
    return _State(**training["state"])


def _check_model_config(path: Path, saved: Any, config: Any) -> None:
    """Refuse to resume into a model of another config: weights of the same shapes would load
    and come back under the new config's bounds, names or step (and other shapes would fail
    with a list of every tensor that does not fit); named by the fields that differ."""
    if isinstance(saved, dict):  # a checkpoint without its config: nothing to compare
        given = dataclasses.asdict(config)
        _refuse_other(path, saved, given, "for a model of another config", "model config")


def _refuse_other(path: Path, saved: dict, given: dict, written: str, same: str) -> None:
    """A :class:`CheckpointError` naming each field of ``saved`` (the checkpoint's config)
    that differs from ``given`` (this run's), compared as JSON (tuples and lists alike)."""
    as_read, now = _as_json(saved), _as_json(given)
    differ = [k for k in sorted(as_read.keys() | now.keys()) if as_read.get(k) != now.get(k)]
    if differ:
        changes = ", ".join(f"{k}={saved.get(k)!r} there, {given.get(k)!r} now" for k in differ)
        raise CheckpointError(
            f"checkpoint {str(path)!r}: was written {written} ({changes}); resume with the "
            f"same {same} or a new path ({_WARM_START})",
            path,
        )


def _finished_gathered_run(path: Path | None, data: str | None) -> _State | None:
    """The state of a finished run gathered from ranks, if ``path`` holds one."""
    if path is None or not distributed.is_active() or not path.is_file():
        return None
    training = _training_payload(path, data=data)
    if not training["state"]["finished"]:
        return None  # a single process's checkpoint: this rank's block check refuses it
    state = _State(**training["state"])
    if distributed.is_main():
        _log_resumed(path, state, config=None)
    return state


def _log_resumed(path: Path, state: _State, config: TrainConfig | None) -> None:
    """Say in the log (``rcvae_torchrl.training.trainer``, INFO) that training goes on from
    ``path``, or that ``path`` holds a finished run whose best weights are taken as they are."""
    if state.finished:
        log.info(
            "train world model: %s holds a finished run (%d steps): its best weights are loaded, "
            "nothing is trained",
            path,
            state.step,
        )
    else:
        log.info(
            "train world model: resuming from %s at step %d of %d",
            path,
            state.step,
            config.max_steps,
        )


# ---------------------------------------------------------------------- gathering
def _gather(ensemble: RCVAEEnsemble, shard: _State | None) -> _State:
    """Every rank's final state, joined in member order (a single process's as it is)."""
    if not distributed.is_active():
        return shard
    shards = [s for s in distributed.all_gather(shard) if s is not None]
    stacked = {name for name, _ in ensemble.named_parameters()}
    weights = {
        k: torch.cat([s.best_weights[k] for s in shards]) if k in stacked else v
        for k, v in shards[0].best_weights.items()
    }
    state = _State(
        max(s.step for s in shards),
        torch.cat([s.best_val for s in shards]),
        weights,
        torch.cat([s.bad_evals for s in shards]),
        torch.cat([s.stop_step for s in shards]),
        history=_merge_histories([s.history for s in shards]),
    )
    state.finished = True
    state.stopped_early = all(s.stopped_early for s in shards)
    return state


def _merge_histories(histories: list[list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """One row per validation step over all members; a block that had finished contributes
    NaN losses and its last best losses (as its members would in one process)."""
    steps = sorted({row["step"] for rows in histories for row in rows})
    merged = []
    for step in steps:
        train, val, best, improved = [], [], [], 0
        for rows in histories:
            row = next((r for r in rows if r["step"] == step), None)
            last = row or [r for r in rows if r["step"] < step][-1]
            n = len(last["best_val_member"])
            train += row["train_loss_member"] if row else [math.nan] * n
            val += row["val_loss_member"] if row else [math.nan] * n
            best += last["best_val_member"]
            improved += int(row["members_improved"]) if row else 0
        merged.append(_record(int(step), train, val, best, improved))
    return merged


def _write_gathered(
    path: Path, ensemble: RCVAEEnsemble, state: _State, config: TrainConfig, data: str | None
) -> None:
    """Rank 0 writes the gathered run (its best weights, no optimiser state) to ``path`` and
    removes the block checkpoints; every rank waits for it."""
    if distributed.is_main():
        ensemble.load_state_dict(state.best_weights)
        payload: dict[str, Any] = {
            **ensemble_payload(ensemble),
            "training": {
                "config": dataclasses.asdict(config),
                "data": data,
                "members": [0, ensemble.ensemble_size],
                "optimizer": None,
                "rng": None,
                "state": {**dataclasses.asdict(state)},
            },
        }
        save_torch(path, payload)
        for block in path.parent.glob(f"{path.stem}.members-*{path.suffix}"):
            block.unlink()
    distributed.barrier()

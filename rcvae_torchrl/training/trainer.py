"""``train_ensemble``: the world model's training loop, with validation, early stopping and resume.

One Adam step trains every member (the loss sums over members); each member draws its own
windows, so it sees its own resample of the data. Validation windows are fixed per run. Members
stop improving at different times, so the best weights are kept per member. A checkpoint
(weights, optimiser, best weights, RNG state, history) is written atomically at each validation,
so ``resume=True`` continues a run killed at any point (even ``kill -9``) from its last
validation, and a finished run is not trained again.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.record.loggers import Logger
from torchrl.record.loggers.csv import CSVLogger
from tqdm.auto import tqdm

from rcvae_torchrl._checks import check_non_negative, check_positive
from rcvae_torchrl.data import make_window_buffer, sample_windows
from rcvae_torchrl.io import atomic_write
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.objectives import RCVAELoss

from .checkpoint import CheckpointError, ensemble_payload, read_checkpoint
from .checks import ModelChecks, check_model

__all__ = ["TrainConfig", "TrainResult", "train_ensemble"]


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
        grad_clip: max global gradient norm.
        beta: KL weight.
        free_nats: per-step free nats of the KL.
        open_loop_steps: trailing transitions of each window fed with the model's own samples.
        nll_beta: β of the β-NLL weighting of the reconstruction term (see :class:`RCVAELoss`).
        val_every: steps between validations (and checkpoints).
        val_windows: fixed validation windows (shared by all members).
        patience: validations without improvement of any member before stopping early.
        seed: seeds sampling and the model's noise.
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

    def __post_init__(self) -> None:
        for name in ("max_steps", "batch_windows", "val_every", "val_windows", "patience"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if self.window < 2:
            raise ValueError(f"window: expected >= 2 steps, got {self.window}")
        if not (self.lr > 0 and self.grad_clip > 0):
            raise ValueError(f"lr, grad_clip: expected > 0, got {self.lr}, {self.grad_clip}")
        if not 0 < self.lr_final_fraction <= 1:
            raise ValueError(
                f"lr_final_fraction: expected a value in (0, 1], got {self.lr_final_fraction}"
            )
        check_positive("beta", self.beta)
        check_non_negative("free_nats", self.free_nats)
        open_loop = self.open_loop_steps
        if isinstance(open_loop, bool) or not isinstance(open_loop, int) or open_loop < 0:
            raise ValueError(f"open_loop_steps: expected an integer >= 0, got {open_loop!r}")
        if not 0.0 <= self.nll_beta <= 1.0:
            raise ValueError(f"nll_beta: expected a value in [0, 1], got {self.nll_beta!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed: expected an integer >= 0, got {self.seed!r}")

    def lr_at(self, step: int) -> float:
        """The learning rate of optimiser step ``step`` (0-based): cosine decay."""
        progress = min(step / self.max_steps, 1.0)
        fraction = self.lr_final_fraction
        return self.lr * (fraction + (1 - fraction) * 0.5 * (1 + math.cos(math.pi * progress)))


@dataclass
class TrainResult:
    """What :func:`train_ensemble` returns: the best weights are loaded into ``ensemble``
    (and its self-checks, when run, into ``ensemble.checks`` and ``checks``)."""

    ensemble: RCVAEEnsemble
    steps: int
    best_val: torch.Tensor  # [E] best validation loss per member
    stopped_early: bool
    history: list[dict[str, float]] = field(default_factory=list)
    checks: ModelChecks | None = None


@dataclass
class _State:
    step: int
    best_val: torch.Tensor
    best_weights: dict[str, torch.Tensor]
    bad_evals: int = 0
    finished: bool = False
    stopped_early: bool = False
    history: list[dict[str, float]] = field(default_factory=list)


def train_ensemble(
    ensemble: RCVAEEnsemble,
    train_data: TensorDictBase,
    val_data: TensorDictBase,
    config: TrainConfig = TrainConfig(),
    *,
    checkpoint_path: str | Path | None = None,
    resume: bool = False,
    logger: Logger | None = None,
    progress: bool = True,
    checks: bool = True,
) -> TrainResult:
    """Train ``ensemble`` on episodes (flat TensorDicts ``[frames]`` from ``collect_episodes``).

    Args:
        ensemble: the model; its normaliser is fitted on ``train_data`` if not fitted yet.
        train_data, val_data: whole episodes, split by episode (``split_episodes``).
        config: budget and hyper-parameters.
        checkpoint_path: where the training checkpoint goes (written at each validation);
            CSV logs go to ``<checkpoint dir>/logs`` unless ``logger`` is given.
        resume: continue from ``checkpoint_path`` if it exists (a finished run returns at once).
        logger: a TorchRL logger (default: CSV beside the checkpoint, or none).
        progress: show a tqdm bar.
        checks: run the model's self-checks on ``val_data`` after training
            (:func:`~rcvae_torchrl.training.check_model`): per state dimension, held-out
            one-step and open-loop errors against copying the previous state and against the
            data's spread; a warning names every dimension the model has not learned.
    """
    path = Path(checkpoint_path) if checkpoint_path is not None else None
    if resume and path is None:
        raise ValueError("resume: expected a checkpoint_path to resume from, got None")
    torch.manual_seed(config.seed)
    device = next(ensemble.parameters()).device
    if not ensemble.normalizer.fitted:
        ensemble.fit_normalizer(
            train_data["observation"],
            train_data["action"],
            next_observations=train_data["next", "observation"],
        )
    buffer = make_window_buffer(train_data, config.window)
    val_windows = _fixed_windows(val_data, config).to(device)
    loss_fn = RCVAELoss(
        ensemble,
        beta=config.beta,
        free_nats=config.free_nats,
        open_loop_steps=config.open_loop_steps,
        nll_beta=config.nll_beta,
    )
    optimizer = torch.optim.Adam(ensemble.parameters(), lr=config.lr)
    state = _State(0, torch.full((ensemble.ensemble_size,), math.inf), _weights(ensemble))
    if resume and path.is_file():
        state = _restore(path, ensemble, optimizer, config)
    logger = logger if logger is not None else _default_logger(path)
    bar = tqdm(
        total=config.max_steps,
        initial=state.step,
        desc="train world model",
        disable=not progress,
        leave=False,
    )
    while not state.finished:
        windows = sample_windows(
            buffer, config.batch_windows, config.window, members=ensemble.ensemble_size
        ).to(device)
        for group in optimizer.param_groups:
            group["lr"] = config.lr_at(state.step)
        train_loss = _train_step(loss_fn, optimizer, windows, config.grad_clip)
        state.step += 1
        bar.update(1)
        if state.step % config.val_every == 0 or state.step >= config.max_steps:
            record = _validate(loss_fn, val_windows, ensemble, state, config, train_loss)
            bar.set_postfix(train=f"{train_loss:.3g}", val=f"{record['val_loss']:.3g}")
            _log(logger, record, state.step)
            if path is not None:
                _save(path, ensemble, optimizer, state, config)
    bar.close()
    ensemble.load_state_dict(state.best_weights)
    result = TrainResult(ensemble, state.step, state.best_val, state.stopped_early, state.history)
    if checks:
        result.checks = ensemble.checks = check_model(ensemble, val_data, seed=config.seed)
    return result


def _fixed_windows(val_data: TensorDictBase, config: TrainConfig) -> TensorDict:
    """The same validation windows for every validation of a run (own RNG stream)."""
    with torch.random.fork_rng():
        torch.manual_seed(config.seed + 1)
        buffer = make_window_buffer(val_data, config.window)
        return sample_windows(buffer, config.val_windows, config.window)


def _train_step(
    loss_fn: RCVAELoss, optimizer: torch.optim.Optimizer, windows: TensorDict, grad_clip: float
) -> float:
    out = loss_fn(windows)
    loss = out["loss_reconstruction"] + out["loss_kl"]
    if not torch.isfinite(loss):
        raise FloatingPointError(f"training loss is not finite ({loss.item()}); lower lr?")
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(loss_fn.parameters(), grad_clip)
    optimizer.step()
    return loss.item() / loss_fn.ensemble.ensemble_size


@torch.no_grad()
def _validate(
    loss_fn: RCVAELoss,
    windows: TensorDict,
    ensemble: RCVAEEnsemble,
    state: _State,
    config: TrainConfig,
    train_loss: float,
) -> dict[str, float]:
    """Per-member validation loss; keep improved members' weights; decide early stopping."""
    with torch.random.fork_rng():
        torch.manual_seed(config.seed + 2)
        per_member = loss_fn(windows)["loss_per_member"].cpu()
    improved = per_member < state.best_val
    state.best_val = torch.where(improved, per_member, state.best_val)
    if improved.any():
        for name, param in ensemble.named_parameters():  # stacked [E, ...]: copy improved rows
            state.best_weights[name][improved] = param.detach().cpu()[improved]
    state.bad_evals = 0 if improved.any() else state.bad_evals + 1
    state.stopped_early = state.bad_evals >= config.patience
    state.finished = state.stopped_early or state.step >= config.max_steps
    record = {
        "step": float(state.step),
        "train_loss": train_loss,
        "val_loss": float(per_member.mean()),
        "best_val_loss": float(state.best_val.mean()),
        "members_improved": float(improved.sum()),
    }
    state.history.append(record)
    return record


def _weights(ensemble: RCVAEEnsemble) -> dict[str, torch.Tensor]:
    return {k: v.detach().cpu().clone() for k, v in ensemble.state_dict().items()}


def _default_logger(path: Path | None) -> Logger | None:
    if path is None:
        return None
    return CSVLogger(exp_name=path.stem, log_dir=str(path.parent / "logs"))


def _log(logger: Logger | None, record: dict[str, float], step: int) -> None:
    if logger is None:
        return
    for name, value in record.items():
        if name != "step":
            logger.log_scalar(name, value, step=step)


def _save(
    path: Path,
    ensemble: RCVAEEnsemble,
    optimizer: torch.optim.Optimizer,
    state: _State,
    config: TrainConfig,
) -> None:
    payload: dict[str, Any] = {
        **ensemble_payload(ensemble),
        "training": {
            "config": dataclasses.asdict(config),
            "optimizer": optimizer.state_dict(),
            "rng": torch.get_rng_state(),
            "state": {**dataclasses.asdict(state)},
        },
    }
    atomic_write(path, lambda f: torch.save(payload, f))


def _restore(
    path: Path, ensemble: RCVAEEnsemble, optimizer: torch.optim.Optimizer, config: TrainConfig
) -> _State:
    payload = read_checkpoint(path)
    training = payload.get("training")
    if training is None:
        raise CheckpointError(f"checkpoint {str(path)!r}: holds no training state to resume", path)
    if training["config"] != dataclasses.asdict(config):
        raise CheckpointError(
            f"checkpoint {str(path)!r}: was written with another TrainConfig "
            f"({training['config']}); resume with the same config or a new path",
            path,
        )
    try:
        ensemble.load_state_dict(payload["state_dict"])
    except RuntimeError as err:
        raise CheckpointError(
            f"checkpoint {str(path)!r}: weights do not match: {err}", path
        ) from err
    optimizer.load_state_dict(training["optimizer"])
    torch.set_rng_state(training["rng"])
    return _State(**training["state"])

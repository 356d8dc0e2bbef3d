"""The real agent from the forecast's start states: outcomes to hold a forecast against.

:func:`real_outcomes` runs a policy ``R`` times from each of ``B`` start states in the real env
(each run with its own seed, so a stochastic env or policy gives different episodes) and
gathers what a forecast predicts: success, the first success step and, optionally, a per-step
trace (e.g. a distance to the goal). :func:`score_forecast` scores a forecast against them,
start by start (:func:`~rcvae_torchrl.competency.validate_forecasts`).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType
from torchrl.modules.planners import MPCPlannerBase

from rcvae_torchrl import distributed
from rcvae_torchrl._checks import (
    check_bool,
    check_entries,
    check_finite,
    check_non_negative_int,
    check_positive_int,
    check_same_starts,
    check_tensor,
)
from rcvae_torchrl.competency import (
    CompetencyReport,
    SuccessBoundary,
    check_same_predicates,
    compare_agents,
    hold_last_state,
    time_to_success_scores,
    validate_forecasts,
)
from rcvae_torchrl.competency.intervals import mean_interval
from rcvae_torchrl.data import TRAJ_KEY, acting_record, check_same_agent, exploration_mode
from rcvae_torchrl.fingerprint import agent_digest
from rcvae_torchrl.threads import threads_kept

from .episodes import (
    ResetToState,
    _success_flags,
    check_not_cut_short,
    check_policy,
    episode_groups,
    episode_lengths,
    run_episodes,
)
from .policy import FixedRowsPolicy
from .starts import reset_by_seed, reset_to_physics, start_episodes
from .workers import episode_workers, start_worker_episodes

__all__ = ["RealOutcomes", "real_outcomes", "score_comparison", "score_forecast"]


@dataclass
class RealOutcomes:
    """Outcomes of ``R`` real episodes from each of ``B`` start states."""

    success: torch.Tensor  #: bool ``[B, R]``
    first_step: torch.Tensor  #: int64 ``[B, R]``: index of the first success, ``T`` when none
    steps: torch.Tensor  #: int64 ``[B, R]``: the episode's length
    trace: torch.Tensor | None = None  #: ``[B, R, T]`` per-step values, NaN after the episode
    #: how the policy acted (its exploration type's name, e.g. ``"random"``: see
    #: :func:`~rcvae_torchrl.data.exploration_mode`); ``None`` where not known (outcomes made
    #: of plain tensors) or where the policy acts alike in every mode (a deterministic network,
    #: a planner: :func:`~rcvae_torchrl.data.acting_record`)
    acting: str | None = None
    #: the steps each episode was run for at most (``real_outcomes``' ``max_steps``); ``None``
    #: where not known (outcomes made of plain tensors)
    max_steps: int | None = None
    #: the agent, as the digest of its policy's weights, or of a weightless module's settings
    #: (:func:`~rcvae_torchrl.fingerprint.agent_digest`); ``None`` where not known (a policy
    #: written as a function, outcomes made of plain tensors)
    agent: str | None = None
    #: what judged the episodes, where a :class:`~rcvae_torchrl.competency.SuccessBoundary`
    #: did (its :attr:`~rcvae_torchrl.competency.SuccessBoundary.predicates`); ``None`` where
    #: an env's flag or a function of one's own judged them
    predicates: str | None = None
    #: ``[B, R, T, S]`` the observation after each step (``real_outcomes``'
    #: ``keep_observations``), NaN after the episode; ``None`` where not kept
    observation: torch.Tensor | None = None
    #: ``[B, S]`` the start states' observations (``real_outcomes``' starts, or their
    #: ``"observation"``); ``None`` where not known. A forecast of other start states, or of
    #: these in another order, is not scored against them
    starts: torch.Tensor | None = None
    #: where a survival boundary judged the episodes, its time limit in steps: a success is
    #: no failure in that many steps, which tells nothing of another deadline (:meth:`within`);
    #: ``None`` otherwise
    survival_limit: int | None = None

    def __post_init__(self) -> None:
        check_tensor("success", self.success)
        if self.success.dtype != torch.bool or self.success.dim() == 0:
            raise ValueError(
                f"success: expected a bool tensor [B, R] (starts, runs), got dtype "
                f"{self.success.dtype} and shape {tuple(self.success.shape)}"
            )
        for name in ("first_step", "steps"):
            value = check_tensor(name, getattr(self, name))
            if value.shape != self.success.shape:
                raise ValueError(
                    f"{name}: expected a tensor of success's shape {tuple(self.success.shape)}, "
                    f"got {tuple(value.shape)}"
                )
        if self.max_steps is not None:
            check_positive_int("max_steps", self.max_steps)
        limit = self.survival_limit
        if limit is not None and (
            isinstance(limit, bool) or not isinstance(limit, int) or limit < 1
        ):
            raise ValueError(
                f"survival_limit: expected None or a survival boundary's time limit (an int >= "
                f"1, in steps), got {limit!r}"
            )

    def as_dict(self) -> dict[str, Any]:
        """Plain values (for ``torch.save``): the tensors (the kept observations and start
        states where known), and what is known of the agent and of the predicates that judged
        the episodes, as strings."""
        out: dict[str, Any] = {
            "success": self.success,
            "first_step": self.first_step,
            "steps": self.steps,
        }
        for name in ("trace", "observation", "starts"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        if self.max_steps is not None:
            out["max_steps"] = torch.tensor(self.max_steps)
        # always, None too: a record without it (written before it) cannot tell a survival
        # boundary's outcomes from a reach boundary's
        out["survival_limit"] = (
            None if self.survival_limit is None else torch.tensor(self.survival_limit)
        )
        for name in _KNOWN:
            if getattr(self, name) is not None:
                out[name] = getattr(self, name)
        return out

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> RealOutcomes:
        """What :meth:`as_dict` gave."""
        check_entries(
            "values", values, ("success", "first_step", "steps"), "a RealOutcomes.as_dict()"
        )
        most, lasting = values.get("max_steps"), values.get("survival_limit")
        if "survival_limit" not in values and values.get("predicates") is not None:
            warnings.warn(
                "values: a record written before RealOutcomes kept survival_limit: whether a "
                "survival boundary judged its episodes, and for how long, is not known. Read at "
                "another deadline than that boundary's, a survival's outcomes are counted "
                "wrong (a forecast of a survival boundary is refused); judge the kept episodes "
                "again (judged_by) or run them again",
                UserWarning,
                stacklevel=2,
            )
        if lasting is not None:
            lasting = _whole("values['survival_limit']", lasting)
        if most is not None:
            most = _whole("values['max_steps']", most)
        known = {}
        for name in _KNOWN:
            value = values.get(name)
            if value is not None and not isinstance(value, str):
                raise TypeError(
                    f"values[{name!r}]: expected a str (RealOutcomes.as_dict()), got "
                    f"{type(value).__name__}"
                )
            known[name] = value
        return cls(
            values["success"],
            values["first_step"],
            values["steps"],
            values.get("trace"),
            max_steps=None if most is None else int(most),
            survival_limit=None if lasting is None else int(lasting),
            observation=values.get("observation"),
            starts=values.get("starts"),
            **known,
        )

    def within(self, steps: int) -> RealOutcomes:
        """These outcomes with a success counted only within its first ``steps`` steps (a
        forecast's deadline): a later one is a failure of the task the forecast answers, and
        its ``first_step`` is ``steps`` ("not within", as a forecast's imagined times say it:
        a time-to-success score of real times past the deadline would judge another task).
        Episodes run for fewer steps (``max_steps``) are refused: one without a success by
        their end has no known outcome within the deadline (with a flag the env writes as
        ``success``, :func:`real_outcomes` cannot tell the deadline, so this is where it is
        checked). So are episodes judged by a survival boundary of another time limit
        (:attr:`survival_limit`): lasting one deadline without a failure says nothing of
        another, and a success there is never "within" a shorter one."""
        check_positive_int("steps", steps)
        if self.survival_limit is not None and self.survival_limit != steps:
            raise ValueError(
                f"steps: these outcomes were judged by a survival boundary of "
                f"{self.survival_limit} steps (a success: no failure for {self.survival_limit} "
                f"steps), which does not tell whether an episode lasted {steps}; judge the kept "
                "episodes by the forecast's boundary (outcomes.judged_by(boundary), after "
                "real_outcomes(..., keep_observations=True)), or run real_outcomes with "
                "success=boundary.success_over_time of the assessor's boundary"
            )
        if self.max_steps is not None and self.max_steps < steps:
            unknown = ~self.success & (self.steps >= self.max_steps)
            raise ValueError(
                f"steps: expected real episodes run for at least the forecast's deadline of "
                f"{steps} steps, got episodes of at most max_steps={self.max_steps}: the "
                f"{int(unknown.sum())} of {unknown.numel()} without a success by then have no "
                f"known outcome within the deadline (a success could still come, or, for a "
                f"survival boundary, the episode could last to it); run real_outcomes with "
                f"max_steps >= {steps}"
            )
        hit = self.success & (self.first_step < steps)
        first = torch.where(hit, self.first_step, torch.full_like(self.first_step, steps))
        return dataclasses.replace(self, success=hit, first_step=first)

    def judged_by(self, boundary: SuccessBoundary) -> RealOutcomes:
        """These episodes judged by another :class:`~rcvae_torchrl.competency.SuccessBoundary`
        (another radius, deadline or failure region), from their kept observations
        (``real_outcomes(..., keep_observations=True)``), as :func:`real_outcomes` judges
        them with ``success=boundary.success_over_time``: ``first_step`` the first step in
        its success region (``T`` when none), ``steps`` one past it, else the episode's
        length. The episodes do not depend on the boundary (they end at the env's own ``done``
        or after ``max_steps``), so these are the outcomes that run would have given, and
        the same warning says where the env ended an episode the boundary decided nothing
        in. The outcomes keep the boundary's ``predicates``; the trace stays as it was."""
        if not isinstance(boundary, SuccessBoundary):
            raise TypeError(f"boundary: expected a SuccessBoundary, got {type(boundary).__name__}")
        if self.observation is None:
            raise ValueError(
                "observation: these outcomes kept no observations to judge again; run "
                "real_outcomes(..., keep_observations=True)"
            )
        steps = self.observation.shape[-2]
        limit = _decided_by(boundary.success_over_time)
        if limit is not None and limit > steps:
            dt = getattr(boundary, "dt", None)
            said = "" if dt is None else f" ({limit} · dt {dt:g} {boundary.time_unit})"
            raise ValueError(
                f"boundary: expected a time limit within the kept episodes' {steps} steps, got "
                f"{limit} steps{said}; a dt other than the env's step counts its time in other "
                "steps, and episodes shorter than the limit cannot tell a survival"
            )
        held, alive = hold_last_state(self.observation)
        success = boundary.success_over_time
        won = success(held) & alive
        hit = won.any(-1)
        first = torch.where(hit, won.float().argmax(-1), steps)
        length = alive.sum(-1)
        undecided = _undecided_ends(success, held, hit, length, steps)
        if undecided is not None and bool(undecided.any()):
            _warn_undecided_ends(undecided, boundary)
        return dataclasses.replace(
            self,
            success=hit,
            first_step=first,
            steps=torch.where(hit, first + 1, length),
            predicates=boundary.predicates,
            survival_limit=_survival_limit(boundary),
        )

    def __len__(self) -> int:
        """``B``, the start states."""
        return self.success.shape[0]

    def __getitem__(self, index: Any) -> RealOutcomes:
        """The outcomes of some start states (``index`` into ``B``: a slice, indices or a bool
        mask), e.g. to score the forecasts of a subset."""
        if isinstance(index, tuple) or (isinstance(index, int) and not isinstance(index, bool)):
            raise IndexError(
                f"index: expected a slice, indices or a bool mask of the {len(self)} start "
                f"states (one start state: outcomes[i : i + 1]), got {index!r}"
            )
        pick = {k: v[index] for k, v in self.as_dict().items() if k in _PER_START}
        picked = RealOutcomes.from_dict(pick)
        kept = {name: getattr(self, name) for name in (*_KNOWN, "max_steps", "survival_limit")}
        return dataclasses.replace(picked, **kept)


#: what RealOutcomes knows of how its episodes were made and judged (strings, or None)
_KNOWN = ("acting", "agent", "predicates")
#: its entries of one row per start state
_PER_START = ("success", "first_step", "steps", "trace", "observation", "starts")


def real_outcomes(
    env: EnvBase | Callable[[], EnvBase],
    policy: Callable[[TensorDictBase], TensorDictBase],
    starts: torch.Tensor | TensorDictBase,
    *,
    runs_per_start: int,
    reset_to_state: ResetToState,
    max_steps: int,
    success: str | Callable[[torch.Tensor], torch.Tensor] = "success",
    trace: Callable[[torch.Tensor], torch.Tensor] | None = None,
    seed: int = 0,
    workers: int = 1,
    policy_rows: int | None = None,
    progress: bool = True,
    desc: str = "real episodes",
    exploration_type: ExplorationType | str | None = None,
    keep_observations: bool = False,
) -> RealOutcomes:
    """Run ``policy`` ``runs_per_start`` times from each start ``[B, ...]``.

    Run ``r`` of start ``b`` is seeded with ``seed·100_003 + b·R + r`` (the env and its noise
    transforms, :func:`~rcvae_torchrl.data.seed_env`), then put in the start state with
    ``reset_to_state``. ``success`` and ``trace`` are as in
    :func:`~rcvae_torchrl.agent.run_episodes` (a flag the env writes, or a function of the
    observations); ``trace`` maps observations ``[..., T, S] -> [..., T]``. The env's own
    time limit must not end an episode before ``max_steps`` (as there, an episode it cuts
    short without a success is refused: its outcome is unknown). An episode the env ends itself
    (``terminated``) counts as a failure; where ``success`` is a
    :class:`~rcvae_torchrl.competency.SuccessBoundary`'s ``success_over_time`` and such an end
    came before its time limit, neither in its success region nor in its failure region, a
    warning says so: imagined episodes do not end there, so the forecast judges another event
    (give the boundary the env's termination condition as its failure).

    ``env`` is a TorchRL env, or a function that makes one (called here when ``workers=1``).
    A batched env (``env.batch_size == [N]``, e.g. a vectorised simulator) runs the episodes
    ``N`` at a time with one policy call per step: each chunk is started with
    :func:`~rcvae_torchrl.agent.start_episodes` (one seed per sub-env, the seeds above, so the
    outcomes equal the one-env run's, where the env has ``set_seeds(seeds)``; a TorchRL
    ``SerialEnv``, ``ParallelEnv`` or ``BatchSizeTransform`` has none, is seeded with the
    chunk's first seed and warned about: for those, pass a function that makes one env and
    ``workers=K``) and runs ``max_steps`` steps (a sub-env that is done stays done). The last
    chunk is padded with repeats of its last episode, whose results are dropped. Where the
    starts are a TensorDict with an ``"observation"``, or a tensor of observations, the reset
    must give that observation (a reset that did not take the state is refused).

    With ``workers=K > 1``, ``env`` must be a picklable function that makes the env: the
    episodes run in ``K`` worker processes of a TorchRL ``ParallelEnv``
    (:func:`~rcvae_torchrl.agent.episode_workers`), ``K·N`` at a time for envs of
    ``batch_size`` ``[N]`` (``N = 1`` for ``[]``), each worker seeding and resetting its own
    env to its episodes' starts; ``reset_to_state`` must then be picklable too. The outcomes
    are the one-env run's, episode by episode, for a policy whose actions depend on its input
    alone (see ``policy_rows``). A policy that draws random numbers of its own (a planner's
    candidates) draws them in another order when episodes run side by side, and for other
    episodes: its outcomes are then other draws of the same chances, not the same draws (a
    pendulum's planner agent: 3 of 12 episodes against 1 of 12 in one env, 2 of 12 flipped).

    ``policy_rows``: call a stateless ``policy`` on blocks of exactly that many rows
    (:class:`~rcvae_torchrl.agent.FixedRowsPolicy`), so that an episode's float32 arithmetic,
    and with it its outcome, does not depend on how many episodes run beside it (the batch
    size, the workers, the ranks); ``None`` (default): one call on the whole batch.

    Under ``torch.distributed`` (:mod:`rcvae_torchrl.distributed`) the ``B·R`` episodes are
    shared out over the ranks in blocks, each rank with its own ``env`` (and ``workers``
    processes) and ``policy``, and the outcomes gathered on every rank: the same as one
    process's.

    ``exploration_type``: how a stochastic policy (a TorchRL ``ProbabilisticActor``) acts,
    as in :func:`~rcvae_torchrl.agent.run_episodes` (by default the caller's
    ``set_exploration_type``, else sampled); its samples are drawn from torch's global random
    stream seeded by each episode's seed (each group's first, side by side), and so are a
    planner's (its own generator and its model env's). The outcomes keep
    it (:attr:`RealOutcomes.acting`), and a forecast made with the policy acting otherwise is
    not scored against them (:func:`score_forecast`, ``OutcomeCheck.from_outcomes``).

    ``keep_observations``: keep every episode's observations, ``[B, R, max_steps, S]`` in
    :attr:`RealOutcomes.observation` (memory: ``B·R·max_steps·S`` values), e.g. to measure
    the real episodes' spread the way a report measures the imagined ones'
    (:meth:`~rcvae_torchrl.competency.CompetencyAssessor.real_spread`), or to judge them by
    another boundary (:meth:`RealOutcomes.judged_by`).
    """
    check_positive_int("runs_per_start", runs_per_start)
    check_positive_int("workers", workers)
    check_positive_int("max_steps", max_steps)
    check_non_negative_int("seed", seed)
    check_bool("keep_observations", keep_observations)
    if env is None:
        raise TypeError("env: expected a TorchRL env or a function that makes one, got None")
    check_policy(policy)
    if not isinstance(starts, (torch.Tensor, TensorDictBase)):
        raise TypeError(
            f"starts: expected start states as a tensor [B, S] or a TensorDict [B], got "
            f"{type(starts).__name__} (torch.as_tensor converts an array)"
        )
    if isinstance(starts, torch.Tensor) and starts.dim() < 2:
        raise ValueError(
            f"starts: expected start states [B, S] (or a TensorDict [B]), got shape "
            f"{tuple(starts.shape)}; one start is starts[None]"
        )
    if len(starts) == 0:
        raise ValueError("starts: expected at least one start state, got none")
    _check_steps_cover_the_boundary(success, max_steps)
    mode = exploration_mode(exploration_type)
    leaves = starts.values(True, True) if isinstance(starts, TensorDictBase) else [starts]
    for leaf in leaves:
        if isinstance(leaf, torch.Tensor):
            check_finite("starts", leaf)
    if workers > 1 and (isinstance(env, EnvBase) or not callable(env)):
        raise ValueError(
            f"env: with workers={workers}, expected a function that makes the env (each worker "
            f"process builds its own), got {type(env).__name__}"
        )
    boundary = _boundary_of(success)
    observed = starts.get("observation", None) if isinstance(starts, TensorDictBase) else starts
    made = {  # of the policy given, before any wrapper here
        "acting": acting_record(policy, mode),
        "agent": agent_digest(policy),
        "predicates": None if boundary is None else boundary.predicates,
        "survival_limit": _survival_limit(boundary),
    }
    if policy_rows is not None:
        if isinstance(policy, MPCPlannerBase):
            raise ValueError(
                f"policy_rows: expected None for a planner (its warm start would carry over "
                f"from one block of {policy_rows} rows to the next), got {policy_rows}"
            )
        policy = FixedRowsPolicy(policy, policy_rows)
    b, r = len(starts), runs_per_start
    last = seed * 100_003 + b * r - 1
    if last >= 2**32:  # an env's seed is a 32-bit integer (numpy, MuJoCo)
        raise ValueError(
            f"seed: expected episode seeds below 2**32 (seed·100_003 + episode), got seed={seed}, "
            f"whose last episode's is {last}; take seed <= {(2**32 - b * r) // 100_003}"
        )
    mine = list(distributed.shard(b * r) if distributed.is_active() else range(b * r))
    index = torch.arange(b).repeat_interleave(r)[mine]
    seeds = [seed * 100_003 + i for i in mine]
    episodes = (starts, index, seeds, max_steps, success, trace, keep_observations)
    show = progress and distributed.is_main()
    sampled = made["acting"] == ExplorationType.RANDOM.value  # draws of its own per action
    part = (
        _my_outcomes(env, workers, policy, reset_to_state, episodes, show, desc, mode, sampled)
        if mine
        else None
    )
    *flat, observation, fingerprints, undecided = _gathered(part)
    if r > 1:
        _warn_copies(fingerprints.reshape(b, r), reset_to_state, mode)
    if undecided is not None and bool(undecided.any()):
        _warn_undecided_ends(undecided, _boundary_of(success))
    shaped = (None if v is None else v.reshape(b, r, *v.shape[1:]) for v in (*flat, observation))
    *outcomes, observation = shaped
    kept_starts = None
    if isinstance(observed, torch.Tensor) and observed.dim() == 2:
        kept_starts = observed.detach().cpu()
    return RealOutcomes(
        *outcomes, max_steps=max_steps, observation=observation, starts=kept_starts, **made
    )


def _judged_for(
    report: CompetencyReport, outcomes: RealOutcomes, name: str, whose: str = "the forecast's"
) -> RealOutcomes:
    """``outcomes`` (the argument ``name``) checked to be real episodes of ``report``'s agent,
    boundary and start states, with a success counted within its deadline only."""
    _check_count(name, report.batch_size.numel(), outcomes, whose)
    check_same_agent(report, outcomes, name=name)
    check_same_predicates(report, outcomes, name=name)
    check_same_starts(name, report.start_states, outcomes.starts, "real episodes")
    return outcomes.within(report.time_limit)


def _check_count(name: str, count: int, outcomes: RealOutcomes, whose: str) -> None:
    if count != len(outcomes):
        raise ValueError(
            f"{name}: expected the real outcomes of {whose} {count} start states, got "
            f"{len(outcomes)}"
        )


def _decided_by(success: object) -> int | None:
    """The step by which a :class:`~rcvae_torchrl.competency.SuccessBoundary`'s outcome is
    decided (its time limit), where ``success`` is its method: an episode the env cuts short
    after it has a known outcome (a pendulum's ``StepCounter(50)`` with a 40-step deadline was
    refused). ``None`` otherwise."""
    boundary = _boundary_of(success)
    if boundary is None or math.isinf(boundary.time_limit):
        return None
    return int(boundary.time_limit)


def _boundary_of(success: object) -> SuccessBoundary | None:
    """The :class:`~rcvae_torchrl.competency.SuccessBoundary` whose ``success_over_time``
    ``success`` is (another of its methods judges no success: it labels nothing)."""
    boundary = getattr(success, "__self__", None)
    if getattr(success, "__func__", None) is not SuccessBoundary.success_over_time:
        return None
    return boundary if isinstance(boundary, SuccessBoundary) else None


def _whole(name: str, value: Any) -> int:
    """``value`` (a number or a one-element tensor) as an int, refused where it is not whole."""
    number = value.item() if isinstance(value, torch.Tensor) else value
    if isinstance(number, bool) or not isinstance(number, (int, float)) or number != int(number):
        raise ValueError(f"{name}: expected a whole number of steps, got {value!r}")
    return int(number)


def _undecided_ends(
    success: object,
    observation: torch.Tensor,
    hit: torch.Tensor,
    length: torch.Tensor,
    max_steps: int,
) -> torch.Tensor | None:
    """``[...]`` bool: episodes (observations ``[..., T, S]``, ``length`` steps each) that the
    env ended before ``max_steps`` and the boundary's time limit with neither its success
    (``hit``) nor its failure; ``None`` where ``success`` is not a boundary's."""
    boundary = _boundary_of(success)
    if boundary is None:
        return None
    early = ~hit & (length < min(max_steps, boundary.time_limit))
    if boundary.failure is None or not bool(early.any()):
        return early
    failed = boundary._failed_by_step(observation)
    last = (length - 1).clamp_min(0).unsqueeze(-1)
    return early & ~failed.gather(-1, last).squeeze(-1)


def _warn_undecided_ends(undecided: torch.Tensor, boundary: SuccessBoundary) -> None:
    """Warn that real episodes ended (the env's own termination) where the boundary decided
    nothing: they count as failures, and imagined episodes go on there."""
    region = "its failure" if boundary.failure is not None else "a failure region"
    warnings.warn(
        f"success: {int(undecided.sum())} of the {undecided.numel()} real episodes ended by the "
        f"env itself (terminated) before the boundary's time limit of {boundary.time_limit} "
        "steps, neither in its success region nor in its failure region. They count as "
        "failures (an ended episode cannot succeed), but a forecast's imagined episodes end "
        "only at the boundary's success or failure and go on there, counting what would "
        "follow: the forecast and these outcomes judge different events. Give the boundary the "
        f"env's termination condition as {region} (SuccessBoundary(..., failure=...), "
        "SuccessBoundary.survival(...)), so that both end at it",
        UserWarning,
        stacklevel=3,
    )


def _warn_copies(
    fingerprints: torch.Tensor, reset_to_state: ResetToState, mode: ExplorationType
) -> None:
    """Warn when every start's runs repeat one episode step for step (``fingerprints``
    ``[B, R]``, each episode's observations summed): its R runs are then R copies, not R draws
    of its chance."""
    if not bool((fingerprints == fingerprints[:, :1]).all()):
        return
    drawless = (
        ""
        if mode is ExplorationType.RANDOM
        else f"; a stochastic policy (a ProbabilisticActor) acting {mode.value!r}, as here "
        "(exploration_type, or the caller's set_exploration_type), draws no samples either"
    )
    b, r = fingerprints.shape
    replay = (
        " (as reset_by_seed does, replaying the start's seeded reset)"
        if reset_to_state is reset_by_seed
        else ""
    )
    physics = (
        ". reset_to_physics restores the start's model fields too (masses, sizes): physics "
        "the task draws per episode then repeats the start's draw in every run; leave those "
        "fields out (reset_to_physics(..., model_fields=...))"
        if reset_to_physics in (reset_to_state, getattr(reset_to_state, "func", None))
        else ""
    )
    warnings.warn(
        f"runs_per_start: each of the {b} starts' {r} runs repeated one episode, step for step: "
        f"they are {r} copies of one outcome, not {r} draws of the start's chance. A "
        "deterministic env does this (one run per start then says as much); an env whose "
        "noise comes from its own random stream does it when the reset restarts that stream"
        f"{replay}: reset to the state instead (reset_to_physics, or a function of your own), "
        f"or draw the noise in a transform (ActionNoise), which each run's seed restarts"
        f"{drawless}{physics}",
        UserWarning,
        stacklevel=3,
    )


@threads_kept()  # a ParallelEnv of workers changes torch's thread count at start and close
def _my_outcomes(
    env: EnvBase | Callable[[], EnvBase],
    workers: int,
    policy: Callable[[TensorDictBase], TensorDictBase],
    reset_to_state: ResetToState,
    episodes: tuple,
    show: bool,
    desc: str,
    mode: ExplorationType,
    sampled: bool = False,
) -> tuple:
    """``(success, first_step, steps, trace or None, observation or None, fingerprints,
    undecided or None)`` of this process's ``episodes`` (a fingerprint: the sum of an
    episode's observations, for telling copies; undecided: ended by the env where the
    boundary decided nothing, see :func:`_undecided_ends`):
    in ``workers`` processes, in a batched env, or one at a time."""
    if workers > 1:
        if sampled:
            _warn_side_by_side_draws(f"workers={workers}")
        pool = episode_workers(env, workers, reset_to_state)
        try:
            _check_batch(pool.batch_size[1:])
            return _batched_outcomes(
                pool, start_worker_episodes, policy, *episodes, show, desc, mode
            )
        finally:
            pool.close()
    env = env() if callable(env) and not isinstance(env, EnvBase) else env
    _check_batch(env.batch_size)
    if env.batch_size:
        if sampled:
            _warn_side_by_side_draws(f"a batched env of {env.batch_size.numel()}")
        start = partial(start_episodes, reset_to_state=reset_to_state)
        return _batched_outcomes(env, start, policy, *episodes, show, desc, mode)
    starts, index, seeds, max_steps, success, trace, keep = episodes
    stats = run_episodes(
        env,
        policy,
        seeds=seeds,
        starts=starts[index],
        reset_to_state=reset_to_state,
        max_steps=max_steps,
        success=success,
        progress=show,
        desc=desc,
        decided_by=_decided_by(success),
        exploration_type=mode,
    )
    return _outcomes(stats, len(seeds), success, trace, max_steps, keep)


def _warn_side_by_side_draws(how: str) -> None:
    """Warn that a policy sampling its actions draws them otherwise side by side (``how``)
    than one episode at a time: its outcomes are other draws of the same chances."""
    warnings.warn(
        f"policy: it samples its actions (a stochastic policy acting 'random'), and with {how} "
        "its episodes run side by side, each group's draws seeded by its first episode's seed: "
        "they are other draws of the same chances than the one-env run's (and than a run with "
        "other workers or envs), not the same episodes. Run one env (torchrun ranks keep the "
        "one-env episodes) where the episodes themselves must repeat",
        UserWarning,
        stacklevel=4,
    )


def _check_batch(batch_size: torch.Size) -> None:
    """An env (a worker's env) with ``batch_size`` ``[]`` or ``[N]``."""
    if len(batch_size) > 1:
        raise ValueError(f"env: expected an env with batch_size [] or [N], got {list(batch_size)}")


def _outcomes(stats, episodes: int, success, trace, horizon: int, keep: bool) -> tuple:
    """``(success, first_step, steps, trace or None, observation or None)`` of ``episodes``
    episodes ``[n, ...]`` (observations kept where ``keep``).
    Functions of the observations see one episode's ``[T, S]`` at a time: a success that
    depends on the time (a survival boundary's ``success_over_time``) counts from each
    episode's first step."""
    first = torch.where(stats.success, stats.steps - 1, torch.full_like(stats.steps, horizon))
    values = None if trace is None else torch.full((episodes, horizon), float("nan"))
    after = stats.data["next", "observation"]
    kept = _nan_padded((episodes, horizon), after) if keep else None
    observed = after.double().flatten(1).sum(-1)
    fingerprints = torch.zeros(episodes, dtype=torch.float64).index_add_(
        0, stats.data[TRAJ_KEY].reshape(-1).long(), observed
    )
    boundary = _boundary_of(success) is not None
    undecided = torch.zeros(episodes, dtype=torch.bool) if boundary else None
    if callable(success) or trace is not None or keep:  # the episodes lie one after the other
        lengths = torch.bincount(stats.data[TRAJ_KEY], minlength=episodes).tolist()
        for i, episode in enumerate(after.split(lengths)):
            if kept is not None:
                kept[i, : len(episode)] = episode
            if callable(success):  # the first success may lie before the episode's end
                hits = success(episode).reshape(-1).nonzero()
                first[i] = int(hits[0, 0]) if hits.numel() else horizon
            if undecided is not None:
                length = torch.tensor(lengths[i])
                hit = stats.success[i]
                undecided[i] = bool(_undecided_ends(success, episode, hit, length, horizon))
            if values is not None:
                row = _traced(trace, episode).reshape(-1)
                values[i, : row.numel()] = row
    return stats.success, first, stats.steps, values, kept, fingerprints, undecided


def _nan_padded(rows: tuple[int, int], observation: torch.Tensor) -> torch.Tensor:
    """``[n, T, *S]`` of NaN in the observations' floating dtype (float32 for others), to be
    filled with each episode's observations."""
    dtype = observation.dtype if observation.is_floating_point() else torch.float32
    return torch.full((*rows, *observation.shape[1:]), math.nan, dtype=dtype)


def _traced(trace: Callable[[torch.Tensor], torch.Tensor], observation: torch.Tensor) -> Any:
    """``trace(observation)``, required to give one value per step: ``[..., T]`` of the
    observations ``[..., T, S]`` (a trace of two values per step failed inside the outcomes'
    bookkeeping with a bare broadcast error)."""
    values = trace(observation)
    if not isinstance(values, torch.Tensor) or values.shape != observation.shape[:-1]:
        got = tuple(values.shape) if isinstance(values, torch.Tensor) else type(values).__name__
        raise ValueError(
            f"trace: expected one value per step of the observations {tuple(observation.shape)} "
            f"([..., T, S] -> [..., T] = {tuple(observation.shape[:-1])}), got {got}; for "
            "several values per step, run the episodes once per value or keep the one you "
            "judge by"
        )
    return values


def _gathered(part: tuple | None) -> tuple:
    """This rank's episodes, or every rank's in episode order under torch.distributed."""
    if not distributed.is_active():
        return part
    parts = [p for p in distributed.all_gather(part) if p is not None]
    return tuple(
        None if parts[0][k] is None else torch.cat([p[k] for p in parts])
        for k in range(len(parts[0]))
    )


def _batched_outcomes(
    env: EnvBase,
    start: Callable[[EnvBase, Sequence[int], torch.Tensor | TensorDictBase], TensorDictBase],
    policy: Callable[[TensorDictBase], TensorDictBase],
    starts: torch.Tensor | TensorDictBase,
    index: torch.Tensor,
    seeds: Sequence[int],
    max_steps: int,
    success: str | Callable[[torch.Tensor], torch.Tensor],
    trace: Callable[[torch.Tensor], torch.Tensor] | None,
    keep: bool,
    progress: bool,
    desc: str,
    mode: ExplorationType,
) -> tuple:
    """Episodes ``index`` (start rows) with ``seeds``, ``n = env.batch_size.numel()`` at a
    time, each chunk begun with ``start(env, seeds[n], starts[n])``: outcomes ``[len]``."""
    parts = []
    groups = episode_groups(
        env,
        policy,
        seeds,
        lambda env, group, rows: start(env, group, starts[index[rows]]),
        max_steps,
        progress=progress,
        desc=desc,
        exploration_type=mode,
    )
    for _, kept, episode in groups:  # rows past kept pad the last group: not episodes asked for
        out, fingerprints = _chunk_outcomes(episode[:kept], success, trace, max_steps, keep)
        observation = episode[:kept]["next", "observation"]
        undecided = _undecided_ends(success, observation, out.success, out.steps, max_steps)
        kept_out = [out.success, out.first_step, out.steps, out.trace, out.observation]
        parts.append([*kept_out, fingerprints, undecided])
    return tuple(None if t[0] is None else torch.cat(t) for t in zip(*parts))


def _chunk_outcomes(
    episode, success, trace, max_steps: int, keep: bool
) -> tuple[RealOutcomes, torch.Tensor]:
    """Outcomes of a batched rollout ``[N, T]`` (a sub-env's episode ends at its first done;
    its observations kept where ``keep``), and each episode's fingerprint (its observations
    summed, for telling copies)."""
    done = episode["next", "done"].reshape(episode.shape)
    ended = done.cumsum(1) - done.long() > 0  # steps after the episode's last one
    won = _success_flags(episode, success) & ~ended
    steps_run = episode.shape[1]
    length = episode_lengths(done)
    hit = won.any(1)
    decided = _decided_by(success)
    check_not_cut_short(
        episode, hit, length, max_steps if decided is None else min(max_steps, decided)
    )
    first = torch.where(hit, won.float().argmax(1), torch.full_like(length, max_steps))
    steps = torch.where(hit, first + 1, length)
    values = None
    if trace is not None:
        per_step = _traced(trace, episode["next", "observation"]).reshape(episode.shape).float()
        values = torch.full((episode.shape[0], max_steps), float("nan"))
        values[:, :steps_run] = per_step.masked_fill(ended, float("nan"))
    after = episode["next", "observation"]
    kept = None
    if keep:
        kept = _nan_padded((episode.shape[0], max_steps), after[:, 0])
        pad = ended.reshape(*ended.shape, *([1] * (after.dim() - 2)))
        kept[:, :steps_run] = after.masked_fill(pad, math.nan).to(kept.dtype)
    observed = after.double().flatten(2).sum(-1)
    outcomes = RealOutcomes(hit, first, steps, values, observation=kept)
    return outcomes, observed.masked_fill(ended, 0.0).sum(1)


def _survival_limit(boundary: SuccessBoundary | None) -> int | None:
    """The time limit of a survival boundary (what its successes lasted), else ``None``."""
    return int(boundary.time_limit) if boundary is not None and boundary.is_survival else None


def _check_steps_cover_the_boundary(success: object, max_steps: int) -> None:
    """Where ``success`` is a :class:`~rcvae_torchrl.competency.SuccessBoundary`'s method, the
    episodes must run to its time limit: a survival judged on fewer steps is never one."""
    limit = _decided_by(success)
    if limit is None:  # no boundary, or none with a time limit: the episodes' max_steps
        return
    if max_steps < limit:
        raise ValueError(
            f"max_steps: expected at least the boundary's time_limit ({limit} steps), got "
            f"{max_steps}: the episodes would stop before the boundary can judge them (a "
            "survival would never be one)"
        )


def score_forecast(
    forecast: torch.Tensor | CompetencyReport,
    outcomes: RealOutcomes,
    *,
    base_rate: float | None = None,
) -> dict[str, float]:
    """:func:`~rcvae_torchrl.competency.validate_forecasts` of forecasts ``[B]`` against the
    real outcomes (per-start error and rank correlation, AUROC, Brier over episodes and its
    skill against ``base_rate``, ECE). Its ``"gap"`` is unsigned, ``|mean forecast - real
    rate|``; :class:`~rcvae_torchrl.training.OutcomeCheck`'s is signed (forecast minus real).

    Given the :class:`~rcvae_torchrl.competency.CompetencyReport` itself, its P(success) is
    scored against the real episodes that succeeded within its deadline (its ``time_limit``
    steps): a real success later, in episodes run for more steps than the forecast looked
    ahead, is a failure of the task the forecast answers. A report whose policy acted in
    another exploration mode than the real episodes' (:attr:`RealOutcomes.acting`) is
    refused: it forecast another agent. A report's imagined times to success are scored
    against the real ones too (:func:`~rcvae_torchrl.competency.time_to_success_scores`, both
    censored at its deadline): ``time_to_success_crps`` and ``..._crps_climatology`` (in env
    steps) and ``..._skill``.

    These are scores on the start states given, with the bias's interval over them
    (``bias_low``, ``bias_high``), not a verdict: a forecast that scores well on a few start
    states can be biased on others. :meth:`OutcomeCheck.from_outcomes
    <rcvae_torchrl.training.OutcomeCheck.from_outcomes>` tests it (bias, per-start misses) and
    ``report.with_forecast_check`` makes a report say so."""
    if not isinstance(outcomes, RealOutcomes):
        raise TypeError(
            f"outcomes: expected the RealOutcomes of real_outcomes, got {type(outcomes).__name__}"
            "; for a bool [B, R] tensor of outcomes use rcvae_torchrl.competency."
            "validate_forecasts"
        )
    if not isinstance(forecast, (torch.Tensor, CompetencyReport)):
        raise TypeError(
            f"forecast: expected P(success) per start, a tensor [B], or a CompetencyReport, got "
            f"{type(forecast).__name__}"
        )
    times = {}
    if isinstance(forecast, torch.Tensor) and forecast.dim() == 1:
        _check_count("outcomes", forecast.shape[0], outcomes, "the forecast's")
    if isinstance(forecast, CompetencyReport):
        forecast = forecast.flattened()  # [2, 3] or one start: as the real outcomes count them
        limit = forecast.time_limit
        outcomes = _judged_for(forecast, outcomes, "outcomes")
        imagined = forecast.competency.get(("time_to_success", "first_step"), None)
        if imagined is not None and imagined.dim() >= 2:  # [B, E, N]: censored at the deadline
            imagined = imagined.flatten(1).clamp_max(limit).cpu().double()
            real = outcomes.first_step.double()
            tts = time_to_success_scores(imagined, real, horizon=limit)
            times = {f"time_to_success_{k}": v for k, v in tts.items()}
        forecast = forecast.competency["p_success"]
    scores = validate_forecasts(forecast.cpu(), outcomes.success, base_rate=base_rate)
    return {**scores, **times}


def score_comparison(
    a: CompetencyReport,
    b: CompetencyReport,
    real_a: RealOutcomes,
    real_b: RealOutcomes,
    *,
    confidence: float = 0.95,
) -> dict[str, float]:
    """Two agents' forecast difference (:func:`~rcvae_torchrl.competency.compare_agents` of
    reports ``a`` and ``b``) against their real one: each agent's real episodes from the same
    start states (``real_a``, ``real_b``), each checked against its own report as
    :func:`score_forecast` checks them (the agent, the boundary, the start states, successes
    within the deadline). Returns the forecast difference P_a − P_b over the start states and
    its interval (``forecast``, ``forecast_low``, ``forecast_high``), the real one and its
    interval over the start states (``real``, ``real_low``, ``real_high``: a Student's t
    interval of the mean of the per-start differences of the real rates), ``gap`` (forecast
    minus real), ``same_sign`` (1.0 where both name the same agent as the better one, or both a
    tie) and
    ``per_start_mae`` (the mean absolute error of the per-start differences)."""
    compared = compare_agents(a, b, confidence=confidence)
    a, b = a.flattened(), b.flattened()  # start by start, as the real outcomes count them
    rates = []
    for name, report, outcomes in (("real_a", a, real_a), ("real_b", b, real_b)):
        if not isinstance(outcomes, RealOutcomes):
            raise TypeError(
                f"{name}: expected the RealOutcomes of real_outcomes, got {type(outcomes).__name__}"
            )
        judged = _judged_for(report, outcomes, name, whose="the reports'")
        rates.append(judged.success.double().mean(1))
    real = rates[0] - rates[1]  # [B]
    forecast = compared.mean
    low, high = compared.interval
    mean = float(real.mean())
    real_low, real_high = mean_interval(real, confidence)
    return {
        "forecast": forecast,
        "forecast_low": low,
        "forecast_high": high,
        "real": mean,
        "real_low": real_low,
        "real_high": real_high,
        "gap": forecast - mean,
        "same_sign": float(math.copysign(1, forecast) == math.copysign(1, mean))
        if forecast and mean
        else float(forecast == mean == 0),
        "per_start_mae": float((compared.difference.cpu() - real).abs().mean()),
    }

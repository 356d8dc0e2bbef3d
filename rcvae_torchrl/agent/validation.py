"""The real agent from the forecast's start states: outcomes to hold a forecast against.

:func:`real_outcomes` runs a policy ``R`` times from each of ``B`` start states in the real env
(each run with its own seed, so a stochastic env or policy gives different episodes) and
gathers what a forecast predicts: success, the first success step and, optionally, a per-step
trace (e.g. a distance to the goal). :func:`score_forecast` scores a forecast against them,
start by start (:func:`~rcvae_torchrl.competency.validate_forecasts`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from rcvae_torchrl import distributed
from rcvae_torchrl.competency import validate_forecasts
from rcvae_torchrl.data import TRAJ_KEY

from .episodes import ResetToState, run_episodes

__all__ = ["RealOutcomes", "real_outcomes", "score_forecast"]


@dataclass
class RealOutcomes:
    """Outcomes of ``R`` real episodes from each of ``B`` start states."""

    success: torch.Tensor  #: bool ``[B, R]``
    first_step: torch.Tensor  #: int64 ``[B, R]``: index of the first success, ``T`` when none
    steps: torch.Tensor  #: int64 ``[B, R]``: the episode's length
    trace: torch.Tensor | None = None  #: ``[B, R, T]`` per-step values, NaN after the episode

    def as_dict(self) -> dict[str, torch.Tensor]:
        """Plain tensors (for ``torch.save``)."""
        out = {"success": self.success, "first_step": self.first_step, "steps": self.steps}
        if self.trace is not None:
            out["trace"] = self.trace
        return out

    @classmethod
    def from_dict(cls, values: dict[str, torch.Tensor]) -> RealOutcomes:
        """What :meth:`as_dict` gave."""
        return cls(values["success"], values["first_step"], values["steps"], values.get("trace"))


def real_outcomes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    starts: torch.Tensor | TensorDictBase,
    *,
    runs_per_start: int,
    reset_to_state: ResetToState,
    max_steps: int,
    success: str | Callable[[torch.Tensor], torch.Tensor] = "success",
    trace: Callable[[torch.Tensor], torch.Tensor] | None = None,
    seed: int = 0,
    progress: bool = True,
    desc: str = "real episodes",
) -> RealOutcomes:
    """Run ``policy`` ``runs_per_start`` times from each start ``[B, ...]``.

    Run ``r`` of start ``b`` is seeded with ``seed·100_003 + b·R + r`` (the env and its noise
    transforms, :func:`~rcvae_torchrl.data.seed_env`), then put in the start state with
    ``reset_to_state``. Under ``torch.distributed`` (:mod:`rcvae_torchrl.distributed`) the
    ``B·R`` episodes are shared out over the ranks in blocks, each rank with its own ``env``
    and ``policy``, and the outcomes gathered on every rank: the same as one process's.
    ``success`` and ``trace`` are as in :func:`~rcvae_torchrl.agent.run_episodes` (a flag the
    env writes, or a function of the observations); ``trace`` maps observations
    ``[T, S] -> [T]``.
    """
    if isinstance(runs_per_start, bool) or not isinstance(runs_per_start, int):
        raise ValueError(f"runs_per_start: expected a positive integer, got {runs_per_start!r}")
    if runs_per_start < 1:
        raise ValueError(f"runs_per_start: expected a positive integer, got {runs_per_start!r}")
    b, r = len(starts), runs_per_start
    mine = distributed.shard(b * r) if distributed.is_active() else range(b * r)
    index = torch.arange(b).repeat_interleave(r)[list(mine)]
    part = None
    if len(mine):
        stats = run_episodes(
            env,
            policy,
            seeds=[seed * 100_003 + i for i in mine],
            starts=starts[index],
            reset_to_state=reset_to_state,
            max_steps=max_steps,
            success=success,
            progress=progress and distributed.is_main(),
            desc=desc,
        )
        part = _outcomes(stats, len(mine), success, trace, max_steps)
    flat = _gathered(part)
    return RealOutcomes(*(None if v is None else v.reshape(b, r, *v.shape[1:]) for v in flat))


def _outcomes(stats, episodes: int, success, trace, horizon: int) -> tuple:
    """``(success, first_step, steps, trace or None)`` of ``episodes`` episodes ``[n, ...]``."""
    first = torch.where(stats.success, stats.steps - 1, torch.full_like(stats.steps, horizon))
    if callable(success):  # a function: the first success may lie before the episode's end
        first = _first_steps(stats.data, success, episodes, horizon)
    values = None
    if trace is not None:
        values = torch.full((episodes, horizon), float("nan"))
        ids, per_step = stats.data[TRAJ_KEY], trace(stats.data["next", "observation"])
        for i in range(episodes):
            row = per_step[ids == i]
            values[i, : row.numel()] = row
    return stats.success, first, stats.steps, values


def _gathered(part: tuple | None) -> tuple:
    """This rank's episodes, or every rank's in episode order under torch.distributed."""
    if not distributed.is_active():
        return part
    parts = [p for p in distributed.all_gather(part) if p is not None]
    return tuple(
        None if parts[0][k] is None else torch.cat([p[k] for p in parts])
        for k in range(len(parts[0]))
    )


def _first_steps(data, success, episodes: int, horizon: int) -> torch.Tensor:
    ids, won = data[TRAJ_KEY], success(data["next", "observation"]).reshape(-1)
    first = torch.full((episodes,), horizon, dtype=torch.int64)
    for i in range(episodes):
        hits = won[ids == i].nonzero()
        if hits.numel():
            first[i] = int(hits[0, 0])
    return first


def score_forecast(
    forecast: torch.Tensor, outcomes: RealOutcomes, *, base_rate: float | None = None
) -> dict[str, float]:
    """:func:`~rcvae_torchrl.competency.validate_forecasts` of forecasts ``[B]`` against the
    real outcomes (per-start error and rank correlation, AUROC, Brier over episodes and its
    skill against ``base_rate``, ECE)."""
    return validate_forecasts(forecast.cpu(), outcomes.success, base_rate=base_rate)

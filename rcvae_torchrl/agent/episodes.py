"""Running a policy for whole episodes in a real env, from its own starts or from given ones."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from tqdm.auto import tqdm

from rcvae_torchrl._checks import check_positive_int
from rcvae_torchrl.data import TRAJ_KEY, check_actions, seed_env

__all__ = ["EpisodeStats", "ResetToState", "run_episodes"]

#: ``(env, start) -> tensordict``: reset ``env`` and put it in the given start state (a row of
#: ``starts``: an observation, or a TensorDict from :func:`~rcvae_torchrl.agent.draw_starts`).
ResetToState = Callable[[EnvBase, Any], TensorDictBase]


@dataclass
class EpisodeStats:
    """Outcomes of episodes run by :func:`run_episodes`."""

    success: torch.Tensor  #: ``[n]`` bool: the success flag was raised during the episode
    steps: torch.Tensor  #: ``[n]`` int64: steps to success, or the episode's length
    data: TensorDict  #: flat transitions ``[frames]`` with episode ids under ``TRAJ_KEY``

    @property
    def success_rate(self) -> float:
        return self.success.float().mean().item()


def run_episodes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    *,
    seeds: Sequence[int],
    starts: torch.Tensor | TensorDictBase | None = None,
    reset_to_state: ResetToState | None = None,
    max_steps: int,
    success: str | Callable[[torch.Tensor], torch.Tensor] = "success",
    first_id: int = 0,
    progress: bool = True,
    desc: str = "episodes",
) -> EpisodeStats:
    """One episode per seed: seed ``env`` (:func:`~rcvae_torchrl.data.seed_env`, which also
    restarts transforms with their own noise) then reset, drawing the start state and the noise,
    or reset to the given start states ``starts`` (``[n, S]`` observations or a TensorDict
    ``[n]``) with ``reset_to_state`` (see :mod:`rcvae_torchrl.agent.starts`).

    Calls ``policy.reset()`` before each episode when the policy's class has one (a planner's
    warm start must not leak across episodes). An episode ends at the env's ``done`` or after
    ``max_steps``; it succeeds when ``success`` holds at any step: ``success`` names a flag the
    env writes under ``"next"`` (default ``"success"``), or is a function of the observations
    ``[T, S] -> [T]`` bool (for envs without a success flag).
    """
    check_positive_int("max_steps", max_steps)
    if len(seeds) == 0:
        raise ValueError("seeds: expected at least one seed (one episode each), got none")
    if starts is not None:
        if len(starts) != len(seeds):
            raise ValueError(
                f"starts: expected one start state per seed ({len(seeds)}), got {len(starts)}"
            )
        if reset_to_state is None:
            raise ValueError("reset_to_state: expected a function to start from given states")
    wins, steps, parts = [], [], []
    for i, seed in enumerate(tqdm(seeds, desc=desc, disable=not progress, leave=False)):
        seed_env(env, int(seed))
        td = env.reset() if starts is None else reset_to_state(env, starts[i])
        if hasattr(type(policy), "reset"):  # a planner's warm start (not an env's reset)
            policy.reset()
        with torch.no_grad():
            episode = env.rollout(
                max_steps, policy, auto_reset=False, tensordict=td, break_when_any_done=True
            )
        check_actions(env, episode)
        if callable(success):
            won = success(episode["next", "observation"])
            if not isinstance(won, torch.Tensor) or won.dtype != torch.bool:
                got = won.dtype if isinstance(won, torch.Tensor) else type(won).__name__
                raise TypeError(f"success: expected a bool tensor [T] of the episode, got {got}")
        else:
            won = episode["next", success]
        if won.numel() != episode.shape[0]:
            raise ValueError(
                f"success: expected one flag per step of the episode ({episode.shape[0]}), got "
                f"shape {tuple(won.shape)}"
            )
        won = won.reshape(-1)
        wins.append(bool(won.any()))
        steps.append(int(won.float().argmax()) + 1 if won.any() else episode.shape[0])
        episode[TRAJ_KEY] = torch.full(episode.shape, first_id + i, dtype=torch.int64)
        parts.append(episode.exclude("is_init"))
    return EpisodeStats(torch.tensor(wins), torch.tensor(steps), torch.cat(parts))

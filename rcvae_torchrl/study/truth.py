"""Ground truth: the same agent in the real env, from the same start states, over several seeds."""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from rcvae_torchrl.agent import run_episodes
from rcvae_torchrl.envs import ball_to_target

__all__ = ["real_outcomes"]


def real_outcomes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    starts: torch.Tensor,
    *,
    seeds_per_start: int,
    max_steps: int,
    seed: int = 0,
    progress: bool = True,
    desc: str = "real",
) -> dict[str, torch.Tensor]:
    """Run ``policy`` from each start ``[B, S]`` with ``seeds_per_start`` noise seeds.

    Returns ``success`` ``[B, R]`` bool, ``steps`` ``[B, R]`` (to success, or the episode length)
    and ``ball_to_target`` ``[B, R, T]`` padded with NaN after the episode ended.
    """
    b, r = starts.shape[0], seeds_per_start
    repeated = starts.repeat_interleave(r, dim=0)
    seeds = [seed * 100_003 + i for i in range(b * r)]
    stats = run_episodes(
        env, policy, seeds=seeds, starts=repeated, max_steps=max_steps, progress=progress, desc=desc
    )
    distance = torch.full((b * r, max_steps), float("nan"))
    ids = stats.data["collector", "traj_ids"]
    d = ball_to_target(stats.data["next", "observation"])
    for i in range(b * r):
        trace = d[ids == i]
        distance[i, : trace.numel()] = trace
    return {
        "success": stats.success.reshape(b, r),
        "steps": stats.steps.reshape(b, r),
        "ball_to_target": distance.reshape(b, r, max_steps),
    }

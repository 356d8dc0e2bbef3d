"""Collecting whole episodes with TorchRL's ``Collector``."""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase
from tqdm.auto import tqdm

__all__ = ["TRAJ_KEY", "collect_episodes"]

TRAJ_KEY = ("collector", "traj_ids")


def _end_of_last_episode(batch: TensorDictBase, episodes_left: int) -> tuple[int, int]:
    """(number of frames to keep, episodes they complete) from one flat collector batch."""
    ends = batch["next", "done"].reshape(-1).nonzero().squeeze(-1)
    if ends.numel() <= episodes_left:
        return batch.shape[0], ends.numel()
    return int(ends[episodes_left - 1]) + 1, episodes_left


def collect_episodes(
    make_env: Callable[[], EnvBase],
    policy: Callable[[TensorDictBase], TensorDictBase],
    num_episodes: int,
    *,
    seed: int = 0,
    frames_per_batch: int = 2000,
    max_frames: int | None = None,
    progress: bool = True,
    desc: str = "collect",
) -> TensorDict:
    """Run ``policy`` in fresh envs from ``make_env`` until ``num_episodes`` episodes have ended.

    Returns a flat TensorDict ``[frames]`` of whole episodes (the unfinished tail is dropped),
    with TorchRL's transition layout (``"observation"``, ``"action"``, ``("next", ...)``) and
    episode ids under :data:`TRAJ_KEY` (``("collector", "traj_ids")``), unique and increasing.

    Args:
        make_env: zero-argument env factory (e.g. ``functools.partial(make_pusher_env, ...)``).
        policy: a TorchRL policy (TensorDictModule or callable on tensordicts).
        num_episodes: episodes to collect (>= 1).
        seed: seeds the env (and so its start states and noise).
        frames_per_batch: collector batch size.
        max_frames: safety cap on frames (default: 1,000 × ``num_episodes``).
    """
    if num_episodes < 1:
        raise ValueError(f"num_episodes: expected >= 1, got {num_episodes}")
    max_frames = max_frames or 1000 * num_episodes
    env = make_env()
    env.set_seed(seed)
    collector = Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=-1,
        split_trajs=False,
        auto_register_policy_transforms=False,
    )
    parts, done = [], 0
    bar = tqdm(total=num_episodes, desc=desc, disable=not progress, leave=False)
    try:
        with torch.no_grad():
            for batch in collector:
                keep, finished = _end_of_last_episode(batch, num_episodes - done)
                parts.append(batch[:keep].clone())
                done += finished
                bar.update(finished)
                if done >= num_episodes or sum(p.shape[0] for p in parts) >= max_frames:
                    break
    finally:
        collector.shutdown()
        bar.close()
    data = torch.cat(parts)
    last_end = data["next", "done"].reshape(-1).nonzero().max()
    return data[: int(last_end) + 1]

"""Pusher inputs shared by the tests that run in this process and in spawned ranks."""

from __future__ import annotations

import torch

from rcvae_torchrl.envs import make_pusher_env


def pusher_starts(n: int) -> torch.Tensor:
    """``n`` in-distribution Pusher start observations, from the env's seeds 40, 41, ..."""
    env = make_pusher_env("deterministic")
    rows = []
    for i in range(n):
        env.set_seed(40 + i)
        rows.append(env.reset()["observation"])
    return torch.stack(rows)

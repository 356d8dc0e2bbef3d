"""The task on top of the world model: reward, success and episode ends of imagined steps.

The model predicts states only; reward and success are pure functions of the predicted state
(for the Pusher: :func:`rcvae_torchrl.envs.pusher_reward` and
:func:`rcvae_torchrl.envs.pusher_success`), the same functions the real env's numbers can be
checked against. Success terminates an imagined episode when ``terminate_on_success`` (as the
real Pusher does by default); the reward of the success step counts, later ones do not.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["RewardFn", "SuccessFn", "alive_mask", "task_reward", "task_success"]

RewardFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``(observation_next [..., S], action [..., A]) -> reward [..., 1]`` (``[...]`` accepted)."""

SuccessFn = Callable[[torch.Tensor], torch.Tensor]
"""``observation [..., S] -> success [...]`` bool (``[..., 1]`` accepted)."""


def task_reward(
    reward_fn: RewardFn, observation: torch.Tensor, action: torch.Tensor
) -> torch.Tensor:
    """``reward_fn(observation, action)`` checked and shaped ``[*B, 1]`` (observation's dtype)."""
    batch = observation.shape[:-1]
    reward = reward_fn(observation, action)
    if not isinstance(reward, torch.Tensor):
        raise TypeError(f"reward_fn: expected a tensor, got {type(reward).__name__}.")
    if reward.shape == batch:
        reward = reward.unsqueeze(-1)
    if reward.shape != (*batch, 1):
        raise ValueError(
            f"reward_fn: expected a reward of shape [*B, 1] = {(*batch, 1)} for observations "
            f"{tuple(observation.shape)}, got {tuple(reward.shape)}."
        )
    return reward.to(observation.dtype)


def task_success(success_fn: SuccessFn, observation: torch.Tensor) -> torch.Tensor:
    """``success_fn(observation)`` checked and shaped bool ``[*B, 1]``."""
    batch = observation.shape[:-1]
    success = success_fn(observation)
    if not isinstance(success, torch.Tensor):
        raise TypeError(f"success_fn: expected a tensor, got {type(success).__name__}.")
    if success.shape == batch:
        success = success.unsqueeze(-1)
    if success.shape != (*batch, 1):
        raise ValueError(
            f"success_fn: expected a flag of shape [*B] or [*B, 1] for observations "
            f"{tuple(observation.shape)}, got {tuple(success.shape)}."
        )
    return success.to(torch.bool)


def alive_mask(done: torch.Tensor, time_dim: int = -1) -> torch.Tensor:
    """Steps that belong to the episode: no ``done`` strictly before them.

    Args:
        done: bool flags of each step, time on ``time_dim``.
        time_dim: the time dimension.

    Returns:
        bool, the shape of ``done``: True up to and including the first ``done``.

    Example:
        >>> alive_mask(torch.tensor([False, True, False, True]))
        tensor([ True,  True, False, False])
    """
    done = done.to(torch.int64)
    return (done.cumsum(time_dim) - done) == 0

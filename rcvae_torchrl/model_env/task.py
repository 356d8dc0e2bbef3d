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

__all__ = [
    "RewardFn",
    "SuccessFn",
    "alive_mask",
    "checked_reward",
    "checked_success",
    "task_reward",
    "task_success",
]

RewardFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``(observation_next [..., S], action [..., A]) -> reward [..., 1]`` (``[...]`` accepted)."""

SuccessFn = Callable[[torch.Tensor], torch.Tensor]
"""``observation [..., S] -> success [...]`` bool (``[..., 1]`` accepted)."""


def _column(name: str, value: object, observation: torch.Tensor, expected: str) -> torch.Tensor:
    """A task function's output as ``[*B, 1]`` for observations ``[*B, S]``, or a clear error."""
    batch = observation.shape[:-1]
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name}: expected a tensor, got {type(value).__name__}.")
    if value.shape == batch:
        value = value.unsqueeze(-1)
    if value.shape != (*batch, 1):
        raise ValueError(
            f"{name}: expected {expected} for observations {tuple(observation.shape)}, "
            f"got {tuple(value.shape)}."
        )
    return value


def task_reward(
    reward_fn: RewardFn, observation: torch.Tensor, action: torch.Tensor
) -> torch.Tensor:
    """``reward_fn(observation, action)`` checked and shaped ``[*B, 1]`` (observation's dtype)."""
    return checked_reward(reward_fn(observation, action), observation)


def task_success(success_fn: SuccessFn, observation: torch.Tensor) -> torch.Tensor:
    """``success_fn(observation)`` checked and shaped bool ``[*B, 1]``."""
    return checked_success(success_fn(observation), observation)


def checked_reward(reward: object, observation: torch.Tensor) -> torch.Tensor:
    """A reward function's output for ``observation`` ``[*B, S]``, checked and shaped
    ``[*B, 1]`` (observation's dtype)."""
    expected = f"a reward of shape [*B, 1] = {(*observation.shape[:-1], 1)}"
    return _column("reward_fn", reward, observation, expected).to(observation.dtype)


def checked_success(success: object, observation: torch.Tensor) -> torch.Tensor:
    """A success function's output for ``observation`` ``[*B, S]``, checked and shaped bool
    ``[*B, 1]``."""
    expected = "a flag of shape [*B] or [*B, 1]"
    return _column("success_fn", success, observation, expected).to(torch.bool)


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

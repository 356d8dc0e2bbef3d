"""Reward and success of the Pusher task as pure functions of observations.

They take torch tensors with any leading batch shape, so the same quantities can be computed on
real and on imagined observations (world-model rollouts, planners, competency estimators).
"""

from __future__ import annotations

import numbers

import torch

from .layout import OBSERVATION_DIM, obs_indices

__all__ = [
    "ACTION_COST",
    "APPROACH_WEIGHT",
    "CONTACT_DISTANCE",
    "DEFAULT_SUCCESS_RADIUS",
    "ball_to_target",
    "pusher_reward",
    "pusher_success",
]

DEFAULT_SUCCESS_RADIUS = 0.03  # m, ball centre to target centre
APPROACH_WEIGHT = 0.5  # weight of the fingertip-to-ball term of the reward
CONTACT_DISTANCE = 0.025  # m, fingertip radius + ball radius: the fingertip touches the ball
ACTION_COST = 1e-3  # weight of the squared-action penalty


def _positions(name: str) -> slice:
    """The (x, y) of ``name`` as a slice: basic indexing gives views, no gather per call."""
    x, y = obs_indices(name)
    assert y == x + 1, name
    return slice(x, y + 1)


_BALL = _positions("ball")
_TARGET = _positions("target")
_FINGER = _positions("finger")


def _check_observation(observation: torch.Tensor, name: str = "observation") -> None:
    """Require a tensor ``[..., 14]`` (its shape only: no data is read, so it costs nothing on
    the imagined-step paths that call it)."""
    if not isinstance(observation, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(observation).__name__}")
    if observation.shape[-1:] != (OBSERVATION_DIM,):
        raise ValueError(
            f"{name}: expected shape [..., {OBSERVATION_DIM}], got {tuple(observation.shape)}"
        )


def ball_to_target(observation: torch.Tensor) -> torch.Tensor:
    """Distance from the ball's centre to the target's centre, ``[...]`` in metres."""
    _check_observation(observation)
    return torch.linalg.vector_norm(observation[..., _BALL] - observation[..., _TARGET], dim=-1)


def pusher_success(
    observation: torch.Tensor, radius: float = DEFAULT_SUCCESS_RADIUS
) -> torch.Tensor:
    """Whether the ball lies within ``radius`` of the target.

    Args:
        observation: ``[..., 14]`` Pusher observations.
        radius: success radius in metres (> 0).

    Returns:
        ``[...]`` bool. A NaN observation is not a success: this runs at every imagined step,
        so it reads no data to check; the model env and
        :class:`~rcvae_torchrl.competency.SuccessBoundary` refuse NaN states before it.
    """
    if isinstance(radius, bool) or not isinstance(radius, numbers.Real) or not radius > 0:
        raise ValueError(f"radius: expected a positive distance in metres, got {radius!r}")
    return ball_to_target(observation) <= radius


def pusher_reward(observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Dense shaping reward of one step, evaluated on the observation the step leads to.

    ``r = -(d(ball, target) + APPROACH_WEIGHT * max(d(finger, ball) - CONTACT_DISTANCE, 0))
    - ACTION_COST * |a|^2``. Every term is <= 0, so an agent gains nothing by lingering when
    success ends the episode.

    Args:
        observation: ``[..., 14]`` observation after the step.
        action: ``[..., 2]`` commanded action in [-1, 1] (before any actuator noise).

    Returns:
        ``[..., 1]`` reward, the shape of TorchRL's ``("next", "reward")``.
    """
    _check_observation(observation)
    if action.shape[-1:] != (2,):
        raise ValueError(f"action: expected shape [..., 2], got {tuple(action.shape)}")
    d_bt = ball_to_target(observation)
    d_fb = torch.linalg.vector_norm(observation[..., _FINGER] - observation[..., _BALL], dim=-1)
    approach = (d_fb - CONTACT_DISTANCE).clamp_min(0.0)
    cost = action.clamp(-1.0, 1.0).square().sum(-1)
    return (-(d_bt + APPROACH_WEIGHT * approach) - ACTION_COST * cost).unsqueeze(-1)

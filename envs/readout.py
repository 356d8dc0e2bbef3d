"""The Pusher's simulator state and what the task reads from it: observation, distances, reward.

NumPy, float64 in, with any leading batch shape: the dm_control task calls these on one env's
``[2]`` arrays and :class:`rcvae_torchrl.envs.batched.BatchedPusherEnv` on ``[N, 2]`` arrays, so
both compute every quantity with the same element-wise operations, hence the same bits.
:func:`rcvae_torchrl.envs.pusher_reward` is the torch twin of :func:`shaped_reward` that works
on observations (imagined ones included).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .functions import ACTION_COST, APPROACH_WEIGHT, CONTACT_DISTANCE
from .layout import OBSERVATION_DIM, OBSERVATION_PARTS

__all__ = [
    "PusherState",
    "assemble_observation",
    "planar_distance",
    "shaped_reward",
    "state_from_observation",
]

_COS, _SIN, _JOINT_VEL, _FINGER, _BALL, _BALL_VEL, _TARGET = OBSERVATION_PARTS.values()
# assemble_observation concatenates its parts in this order; _GATHER puts them in layout order.
_PART_SLOTS = [i for part in OBSERVATION_PARTS.values() for i in range(OBSERVATION_DIM)[part]]
_GATHER = np.argsort(_PART_SLOTS)


@dataclass(frozen=True)
class PusherState:
    """The whole simulator state of a Pusher episode; every field is ``[..., 2]`` float64.

    Attributes:
        arm_angles: shoulder and wrist angles (rad).
        arm_velocities: shoulder and wrist angular velocities (rad/s).
        ball: ball centre (m).
        ball_velocity: ball velocity (m/s).
        target: target centre (m).
    """

    arm_angles: np.ndarray
    arm_velocities: np.ndarray
    ball: np.ndarray
    ball_velocity: np.ndarray
    target: np.ndarray


def state_from_observation(observation: np.ndarray) -> PusherState:
    """The simulator state an observation ``[..., 14]`` describes (angles from their cos/sin).

    Example:
        >>> obs = np.zeros(OBSERVATION_DIM)
        >>> obs[OBSERVATION_PARTS["cos"]] = 1.0
        >>> state_from_observation(obs).arm_angles
        array([0., 0.])
    """
    obs = np.asarray(observation, dtype=np.float64)
    if obs.shape[-1:] != (OBSERVATION_DIM,):
        raise ValueError(
            f"observation: expected shape [..., {OBSERVATION_DIM}], got {tuple(obs.shape)}"
        )
    return PusherState(
        arm_angles=np.arctan2(obs[..., _SIN], obs[..., _COS]),
        arm_velocities=obs[..., _JOINT_VEL],
        ball=obs[..., _BALL],
        ball_velocity=obs[..., _BALL_VEL],
        target=obs[..., _TARGET],
    )


def assemble_observation(
    arm_angles: np.ndarray,
    arm_velocities: np.ndarray,
    finger: np.ndarray,
    ball: np.ndarray,
    ball_velocity: np.ndarray,
    target: np.ndarray,
) -> np.ndarray:
    """The float32 observation ``[..., 14]`` (layout :data:`OBSERVATION_LAYOUT`) of a state.

    Every argument is ``[..., 2]`` float64, as read from the simulator (``finger`` and ``ball``
    are the bodies' world positions). Angles enter as cos/sin; everything is rounded to float32
    once, at the end.

    Example:
        >>> z = np.zeros(2)
        >>> assemble_observation(z, z, z, z, z, z)[:4]
        array([1., 0., 1., 0.], dtype=float32)
    """
    parts = (
        np.cos(arm_angles),
        np.sin(arm_angles),
        arm_velocities,
        finger,
        ball,
        ball_velocity,
        target,
    )
    return np.concatenate(parts, axis=-1)[..., _GATHER].astype(np.float32)


def planar_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Euclidean distance of planar points ``[..., 2]``, ``[...]`` float64 (m)."""
    return np.hypot(a[..., 0] - b[..., 0], a[..., 1] - b[..., 1])


def shaped_reward(
    ball_to_target: np.ndarray, finger_to_ball: np.ndarray, action: np.ndarray
) -> np.ndarray:
    """The task's reward of one step, ``[...]`` float64, from the distances after the step.

    ``r = -(d(ball, target) + APPROACH_WEIGHT * max(d(finger, ball) - CONTACT_DISTANCE, 0))
    - ACTION_COST * |a|^2``, with ``action [..., 2]`` the commanded action clipped to [-1, 1]
    (before any actuator noise).

    Example:
        >>> float(shaped_reward(np.float64(0.1), np.float64(0.025), np.zeros(2)))
        -0.1
    """
    approach = np.maximum(finger_to_ball - CONTACT_DISTANCE, 0.0)
    cost = ACTION_COST * np.sum(action * action, axis=-1)
    return -(ball_to_target + APPROACH_WEIGHT * approach) - cost

"""Input features for Pusher world models: the geometry of a fingertip-ball contact.

Whether the fingertip pushes the ball in the next control step, and in which direction, depends
on the fingertip's position relative to the ball and on the fingertip's velocity. Both are
functions of the state (the velocity through the arm's Jacobian), but a small network learns
them slowly from the raw layout. :func:`pusher_input_features` writes them down, for a world
model to read besides the state.
"""

from __future__ import annotations

import torch

from .functions import _check_observation
from .layout import OBSERVATION_PARTS
from .scripted import arm_jacobian

__all__ = ["PUSHER_FEATURE_NAMES", "pusher_input_features"]

#: The features, in order.
PUSHER_FEATURE_NAMES: tuple[str, ...] = (
    "finger_minus_ball_x",
    "finger_minus_ball_y",
    "finger_ball_distance",
    "finger_vx",
    "finger_vy",
    "closing_speed",
)


# slices, not index lists: views, no gather (nor host-to-GPU copy of the list) per call
_COS, _SIN, _JOINT_VEL = (OBSERVATION_PARTS[k] for k in ("cos", "sin", "joint_vel"))
_FINGER, _BALL, _BALL_VEL = (OBSERVATION_PARTS[k] for k in ("finger", "ball", "ball_vel"))


def pusher_input_features(observation: torch.Tensor) -> torch.Tensor:
    """``[..., 14]`` Pusher observations → ``[..., 6]`` contact features.

    - fingertip minus ball position (m) and its norm;
    - fingertip velocity ``J(θ) θ̇`` (m/s) of the planar 2-link arm;
    - closing speed: the rate at which the fingertip-ball distance shrinks (m/s, > 0 when they
      approach).
    """
    _check_observation(observation)
    o = observation
    jacobian = arm_jacobian(o[..., _COS], o[..., _SIN])
    finger_vel = (jacobian @ o[..., _JOINT_VEL].unsqueeze(-1)).squeeze(-1)
    rel = o[..., _FINGER] - o[..., _BALL]
    dist = torch.linalg.vector_norm(rel, dim=-1, keepdim=True)
    unit = rel / dist.clamp_min(1e-6)
    closing = -((finger_vel - o[..., _BALL_VEL]) * unit).sum(-1, keepdim=True)
    return torch.cat([rel, dist, finger_vel, closing], dim=-1)

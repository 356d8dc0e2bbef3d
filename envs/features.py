"""Input features for Pusher world models: the geometry of a fingertip-ball contact.

Whether the fingertip pushes the ball in the next control step, and in which direction, depends
on the fingertip's position relative to the ball and on the fingertip's velocity. Both are
functions of the state (the velocity through the arm's Jacobian), but a small network learns
them slowly from the raw layout. :func:`pusher_input_features` writes them down; it is registered
as ``input_features="pusher"`` (:mod:`rcvae_torchrl.models.features`).
"""

from __future__ import annotations

import torch

from rcvae_torchrl.models.features import register_input_features

from .constraints import LINK_LENGTH
from .layout import obs_indices

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

_SC, _SS, _WC, _WS, _SV, _WV = obs_indices(
    "shoulder_cos", "shoulder_sin", "wrist_cos", "wrist_sin", "shoulder_vel", "wrist_vel"
)
_FINGER, _BALL, _BALL_VEL = obs_indices("finger"), obs_indices("ball"), obs_indices("ball_vel")


def pusher_input_features(observation: torch.Tensor) -> torch.Tensor:
    """``[..., 14]`` Pusher observations → ``[..., 6]`` contact features.

    - fingertip minus ball position (m) and its norm;
    - fingertip velocity ``J(θ) θ̇`` (m/s) of the planar 2-link arm;
    - closing speed: the rate at which the fingertip-ball distance shrinks (m/s, > 0 when they
      approach).
    """
    o = observation
    c0, s0, c1, s1 = o[..., _SC], o[..., _SS], o[..., _WC], o[..., _WS]
    w0, w01 = o[..., _SV], o[..., _SV] + o[..., _WV]
    elbow_cos, elbow_sin = c0 * c1 - s0 * s1, s0 * c1 + c0 * s1
    finger_vel = LINK_LENGTH * torch.stack(
        [-s0 * w0 - elbow_sin * w01, c0 * w0 + elbow_cos * w01], dim=-1
    )
    rel = o[..., _FINGER] - o[..., _BALL]
    dist = torch.linalg.vector_norm(rel, dim=-1, keepdim=True)
    unit = rel / dist.clamp_min(1e-6)
    closing = -((finger_vel - o[..., _BALL_VEL]) * unit).sum(-1, keepdim=True)
    return torch.cat([rel, dist, finger_vel, closing], dim=-1)


register_input_features("pusher", pusher_input_features, len(PUSHER_FEATURE_NAMES))

"""The Pusher's known state constraints, for world models (registered as ``"pusher"``).

Given the model's generated state, make it consistent with what the simulator guarantees:

- each joint's (cos, sin) lies on the unit circle (the angle the model predicts, renormalised),
  and the wrist stays within its ±160° range;
- the fingertip is at the end of the arm (forward kinematics, links 0.12 + 0.12 m);
- the ball's centre stays between the hub and the fence.
"""

from __future__ import annotations

import torch

from rcvae_torchrl.models import register_state_constraint

from .layout import obs_indices
from .pusher import ARENA_RADIUS, BALL_RADIUS, HUB_RADIUS, WRIST_RANGE

__all__ = ["pusher_state_constraint"]

_LINK = 0.12
_COS, _SIN = obs_indices("shoulder_cos", "wrist_cos"), obs_indices("shoulder_sin", "wrist_sin")
_FINGER, _BALL = obs_indices("finger"), obs_indices("ball")


def pusher_state_constraint(previous: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
    """``(s_{t-1} [..., 14], generated s_t [..., 14]) -> s_t [..., 14]`` made consistent."""
    del previous  # the constraint holds state by state
    angles = torch.atan2(state[..., _SIN], state[..., _COS])
    wrist = angles[..., 1].clamp(-float(WRIST_RANGE), float(WRIST_RANGE))
    angles = torch.stack([angles[..., 0], wrist], dim=-1)
    cos, sin = angles.cos(), angles.sin()
    out = state.clone()
    out[..., _COS], out[..., _SIN] = cos, sin
    elbow = angles.sum(-1)
    out[..., _FINGER] = _LINK * torch.stack(
        [cos[..., 0] + elbow.cos(), sin[..., 0] + elbow.sin()], dim=-1
    )
    ball = state[..., _BALL]
    radius = torch.linalg.vector_norm(ball, dim=-1, keepdim=True).clamp_min(1e-9)
    allowed = radius.clamp(HUB_RADIUS + BALL_RADIUS, ARENA_RADIUS - BALL_RADIUS)
    out[..., _BALL] = ball * (allowed / radius)
    return out


register_state_constraint("pusher", pusher_state_constraint)

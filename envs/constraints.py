"""The Pusher's known state constraints, for world models.

Given the model's generated state, make it consistent with what the simulator guarantees:

- each joint's (cos, sin) lies on the unit circle (the angle the model predicts, renormalised),
  and the wrist stays within its ±160° range;
- the fingertip is at the end of the arm (forward kinematics, links 0.12 + 0.12 m);
- the ball's centre stays between the hub and the fence.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from .functions import _check_observation
from .layout import OBSERVATION_PARTS
from .pusher import ARENA_RADIUS, BALL_RADIUS, HUB_RADIUS, WRIST_RANGE
from .readout import PusherState

__all__ = ["into_arena", "pusher_state_constraint"]

LINK_LENGTH = 0.12  # m, each of the two links (pusher.xml)
_COS, _SIN, _JOINT_VEL, _FINGER, _BALL, _BALL_VEL, _ = OBSERVATION_PARTS.values()


# the layout the output's concatenation relies on: the joints' (cos, sin) interleaved at 0..3,
# then the joint velocities, the fingertip, the ball, and the rest (left as it is)
assert (_COS, _SIN) == (slice(0, 3, 2), slice(1, 4, 2))
assert _JOINT_VEL.stop == _FINGER.start and _FINGER.stop == _BALL.start == _BALL_VEL.start - 2
# MuJoCo's contacts are soft: pushed by the fingertip, the simulated ball presses up to about
# 3 mm into the fence or the hub (measured over the study's data), so the bounds allow 4 mm.
_CONTACT_SLACK = 0.004
_BALL_MIN = HUB_RADIUS + BALL_RADIUS - _CONTACT_SLACK
_BALL_MAX = ARENA_RADIUS - BALL_RADIUS + _CONTACT_SLACK


def pusher_state_constraint(previous: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
    """``(s_{t-1} [..., 14], generated s_t [..., 14]) -> s_t [..., 14]`` made consistent.

    Basic slices and one concatenation, no copy of the state and no advanced indexing: the
    planner runs this on every imagined step (``state``'s shape is checked, not its values).
    """
    del previous  # the constraint holds state by state
    _check_observation(state, "state")
    # contiguous operands: atan2 then takes the same (vectorised) path as on gathered columns
    angles = torch.atan2(state[..., _SIN].contiguous(), state[..., _COS].contiguous())
    angles = torch.clamp(angles, *_joint_bounds(angles))  # the shoulder free, the wrist limited
    # shoulder, wrist, shoulder + wrist; then their (cos, sin) [..., 3, 2]
    angles = torch.cat([angles, angles.sum(-1, keepdim=True)], dim=-1)
    cos_sin = torch.stack([angles.cos(), angles.sin()], dim=-1)
    finger = LINK_LENGTH * (cos_sin[..., 0, :] + cos_sin[..., 2, :])
    ball = state[..., _BALL]
    radius = torch.linalg.vector_norm(ball, dim=-1, keepdim=True).clamp_min(1e-9)
    allowed = radius.clamp(_BALL_MIN, _BALL_MAX)
    return torch.cat(
        [
            cos_sin[..., :2, :].flatten(-2),
            state[..., _JOINT_VEL],
            finger,
            ball * (allowed / radius),
            state[..., _BALL_VEL.start :],
        ],
        dim=-1,
    )


def _radially_within(xy: np.ndarray, low: float, high: float) -> np.ndarray:
    """Points ``[..., 2]`` moved along their ray from the base to a distance in [low, high];
    points already there are returned as they are (the same array when all are)."""
    radius = np.hypot(xy[..., 0], xy[..., 1])
    inside = (radius >= low) & (radius <= high)
    if inside.all():
        return xy
    unit = np.where(
        radius[..., None] > 0, xy / np.where(radius > 0, radius, 1.0)[..., None], [1.0, 0.0]
    )
    return np.where(inside[..., None], xy, unit * np.clip(radius, low, high)[..., None])


def into_arena(state: PusherState) -> PusherState:
    """``state`` with the ball's centre and the target moved radially to where the ball's centre
    can be, between the hub and the fence (with the contact slack of
    :func:`pusher_state_constraint`); a state already there is returned as it is.
    What :func:`~rcvae_torchrl.envs.state.reset_to_state` loads (and the batched env's
    ``reset(..., set_state=True)``): a ball outside the fence or inside the hub, or a target
    out of the ball's reach, is not a state the Pusher can be in."""
    ball = _radially_within(state.ball, _BALL_MIN, _BALL_MAX)
    target = _radially_within(state.target, _BALL_MIN, _BALL_MAX)
    if ball is state.ball and target is state.target:
        return state
    return dataclasses.replace(state, ball=ball, target=target)


_BOUNDS: dict[tuple[torch.dtype, torch.device], tuple[torch.Tensor, torch.Tensor]] = {}


def _joint_bounds(like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper bounds of (shoulder, wrist): ``∓[inf, WRIST_RANGE]``, with the dtype and
    device of ``like`` (made once, then cached; under ``torch.compile`` made in the graph, so a
    compiled function does not depend on, nor recompile for, the state of the cache)."""
    if torch.compiler.is_compiling():
        return _make_bounds(like)
    key = (like.dtype, like.device)
    if key not in _BOUNDS:
        _BOUNDS[key] = _make_bounds(like)
    return _BOUNDS[key]


def _make_bounds(like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    # filled on the device (no tensor copied from host memory: that would break CUDA graphs)
    high = torch.cat([like.new_full((1,), torch.inf), like.new_full((1,), float(WRIST_RANGE))])
    return -high, high

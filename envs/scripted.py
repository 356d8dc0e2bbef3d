"""A scripted reference controller: Jacobian-transpose pushing, as a TorchRL policy module.

The fingertip is driven by a virtual spring-damper, ``tau = J(q)^T (k_p (p_des - p_f) - k_d v_f)``,
towards a point chosen from the scene: behind the ball on the line to the target (approach), or
into the ball along that line (push). When the straight line from the ball to the target passes
the hub, the ball is first pushed to a waypoint around it. The same code runs on any batch shape,
so it also serves as a baseline policy inside imagined rollouts.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from rcvae_torchrl._checks import check_floating, check_non_negative, check_positive

from .constraints import LINK_LENGTH as _LINK
from .functions import CONTACT_DISTANCE, _check_observation
from .layout import OBSERVATION_PARTS

__all__ = ["ScriptedPusher", "make_scripted_policy"]

_HUB_CLEARANCE = 0.09  # m: ball paths closer than this to the base would hit the hub
_WAYPOINT_RADIUS = 0.13  # m
_NEAR_HUB = 0.095  # m: a ball closer to the base than this is pushed around, not across
_NEAR_HUB_TURN = 0.3  # rad
_WRIST_BAND = (0.6, 2.4)  # rad: |wrist| outside this band is pulled back (near-singular arm)

_COS, _SIN, _QVEL = (OBSERVATION_PARTS[k] for k in ("cos", "sin", "joint_vel"))
_FINGER, _BALL, _TARGET = (OBSERVATION_PARTS[k] for k in ("finger", "ball", "target"))


def _unit(v: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(eps)


def _perp(v: torch.Tensor) -> torch.Tensor:
    return torch.stack([-v[..., 1], v[..., 0]], dim=-1)


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1, keepdim=True)


def arm_jacobian(cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """Fingertip Jacobian d(x, y)/d(q1, q2), ``[..., 2, 2]``, from joint cos/sin ``[..., 2]``."""
    c1, c2 = cos.unbind(-1)
    s1, s2 = sin.unbind(-1)
    c12 = c1 * c2 - s1 * s2
    s12 = s1 * c2 + c1 * s2
    row_x = torch.stack([-_LINK * (s1 + s12), -_LINK * s12], dim=-1)
    row_y = torch.stack([_LINK * (c1 + c12), _LINK * c12], dim=-1)
    return torch.stack([row_x, row_y], dim=-2)


def _push_goal(ball: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Where to push the ball next, ``[..., 2]``: the target, or a waypoint around the hub.

    The ball goes straight to the target unless that line passes the hub, or the ball lies next to
    the hub away from the target (the fingertip cannot get behind it there); then the waypoint is
    on a circle of radius ``_WAYPOINT_RADIUS``, at most 45 degrees further towards the target.
    """
    seg = target - ball
    t = (-_dot(ball, seg) / _dot(seg, seg).clamp_min(1e-9)).clamp(0.0, 1.0)
    closest = torch.linalg.vector_norm(ball + t * seg, dim=-1, keepdim=True)
    angle_b = torch.atan2(ball[..., 1:], ball[..., :1])
    angle_t = torch.atan2(target[..., 1:], target[..., :1])
    turn = torch.remainder(angle_t - angle_b + torch.pi, 2 * torch.pi) - torch.pi
    angle_w = angle_b + turn.clamp(-torch.pi / 4, torch.pi / 4)
    waypoint = _WAYPOINT_RADIUS * torch.cat([torch.cos(angle_w), torch.sin(angle_w)], dim=-1)
    near_hub = torch.linalg.vector_norm(ball, dim=-1, keepdim=True) < _NEAR_HUB
    blocked = (closest < _HUB_CLEARANCE) | (near_hub & (turn.abs() > _NEAR_HUB_TURN))
    return torch.where(blocked, waypoint, target)


class ScriptedPusher(nn.Module):
    """Observation ``[..., 14]`` -> action ``[..., 2]`` in [-1, 1].

    Args:
        kp: fingertip stiffness (action units per metre, after ``J^T``).
        kd: fingertip damping (action units per m/s).
        kq: joint-velocity damping (action units per rad/s).
        k_posture: pull of the wrist towards a bent posture (action units per rad).
        standoff: approach point distance behind the ball's contact surface (m).
        push_depth: how far into the ball the fingertip aims while pushing (m).
        align_angle: largest angle (rad) between the fingertip and the point behind the ball,
            seen from the ball, at which the fingertip pushes.
        max_turn: largest angle (rad) the orbiting set point leads the fingertip by.

    ``kp``, ``align_angle`` and ``max_turn`` are positive, the others finite and >= 0.
    Observations must be floating-point ``[..., 14]``; their values are not read for a check
    (the controller runs at every imagined step of a planner, where a NaN test would cost a
    device synchronisation), so a NaN observation gives NaN actions, which the envs refuse.
    """

    def __init__(
        self,
        kp: float = 120.0,
        kd: float = 6.0,
        kq: float = 0.05,
        k_posture: float = 1.0,
        standoff: float = 0.012,
        push_depth: float = 0.02,
        align_angle: float = 0.5,
        max_turn: float = 1.0,
    ) -> None:
        for name, value in (("kp", kp), ("align_angle", align_angle), ("max_turn", max_turn)):
            check_positive(name, value)
        for name, value in (
            ("kd", kd),
            ("kq", kq),
            ("k_posture", k_posture),
            ("standoff", standoff),
            ("push_depth", push_depth),
        ):
            check_non_negative(name, value)
        super().__init__()
        self.kp, self.kd, self.kq, self.k_posture = kp, kd, kq, k_posture
        self.standoff, self.push_depth = standoff, push_depth
        self.align_angle, self.max_turn = align_angle, max_turn

    def desired_fingertip(self, observation: torch.Tensor) -> torch.Tensor:
        """The fingertip set point ``[..., 2]`` for each observation.

        Aligned behind the ball: aim ``push_depth`` into it along the push direction. Otherwise:
        orbit the ball at ``CONTACT_DISTANCE + standoff``, turning at most ``max_turn`` per step
        towards the point behind it, so the fingertip never shoves the ball the wrong way.
        """
        _check_scripted_input(observation)
        return self._desired_fingertip(observation)

    def _desired_fingertip(self, observation: torch.Tensor) -> torch.Tensor:
        finger, ball = observation[..., _FINGER], observation[..., _BALL]
        goal = _push_goal(ball, observation[..., _TARGET])
        u = _unit(goal - ball)
        rel = finger - ball
        dist = torch.linalg.vector_norm(rel, dim=-1, keepdim=True)
        angle_f = torch.atan2(rel[..., 1:], rel[..., :1])
        angle_behind = torch.atan2(-u[..., 1:], -u[..., :1])
        turn = torch.remainder(angle_behind - angle_f + torch.pi, 2 * torch.pi) - torch.pi
        orbit_angle = angle_f + turn.clamp(-self.max_turn, self.max_turn)
        orbit = ball + (CONTACT_DISTANCE + self.standoff) * torch.cat(
            [torch.cos(orbit_angle), torch.sin(orbit_angle)], dim=-1
        )
        depth = torch.linalg.vector_norm(goal - ball, dim=-1, keepdim=True).clamp_max(
            self.push_depth
        )
        push = ball - u * (CONTACT_DISTANCE - depth)
        aligned = (turn.abs() < self.align_angle) & (dist < CONTACT_DISTANCE + 2 * self.standoff)
        return torch.where(aligned, push, orbit)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        _check_scripted_input(observation)
        cos, sin = observation[..., _COS], observation[..., _SIN]
        qvel = observation[..., _QVEL]
        jac = arm_jacobian(cos, sin)
        v_finger = (jac @ qvel.unsqueeze(-1)).squeeze(-1)
        force = self.kp * (self._desired_fingertip(observation) - observation[..., _FINGER])
        force = force - self.kd * v_finger
        torque = (jac.transpose(-1, -2) @ force.unsqueeze(-1)).squeeze(-1) - self.kq * qvel
        # Keep the elbow bent: a stretched or folded arm cannot move its fingertip radially.
        wrist = torch.atan2(sin[..., 1], cos[..., 1])
        bend = wrist.abs().clamp(*_WRIST_BAND) - wrist.abs()
        bend = torch.where(wrist >= 0, bend, -bend)
        torque = torque + torch.stack([torch.zeros_like(bend), self.k_posture * bend], dim=-1)
        return torque.clamp(-1.0, 1.0)


def _check_scripted_input(observation: torch.Tensor) -> None:
    """A floating-point tensor ``[..., 14]`` (shape and dtype only, no data read)."""
    _check_observation(observation)
    check_floating("observation", observation)


def make_scripted_policy(**controller_kwargs: float) -> TensorDictModule:
    """The scripted pusher wired to TorchRL keys: reads ``"observation"``, writes ``"action"``.

    Example:
        >>> from rcvae_torchrl.envs import make_pusher_env
        >>> env = make_pusher_env(seed=0)
        >>> td = env.rollout(600, make_scripted_policy(), break_when_any_done=True)
        >>> bool(td["next", "success"].any())
        True
    """
    return TensorDictModule(
        ScriptedPusher(**controller_kwargs), in_keys=["observation"], out_keys=["action"]
    )

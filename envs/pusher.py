"""Pusher domain: a planar 2-link arm pushes a ball onto a target inside a circular fence.

Written like a dm_control suite domain (``pusher.xml`` + this file): a :class:`Physics` with named
accessors and a :class:`Pusher` task whose randomness comes only from ``self.random``, so
``set_seed`` makes episodes reproducible, action noise included.

Arm as dm_control's reacher (links 0.12 + 0.12 m, motor gear 0.05, controls in [-1, 1]); the ball
moves on two slide joints; the fence (inner radius 0.21 m) and the hub (radius 0.06 m) keep it in
the arm's reach. Physics steps every 0.005 s; the agent acts every :data:`CONTROL_TIMESTEP` s.
"""

from __future__ import annotations

import collections
import math
import numbers
import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from dm_control import mujoco
from dm_control.rl import control
from dm_control.suite import base, common

from .functions import DEFAULT_SUCCESS_RADIUS
from .readout import PusherState, assemble_observation, planar_distance, shaped_reward

__all__ = [
    "CONTROL_TIMESTEP",
    "DEFAULT_TIME_LIMIT",
    "IN_DISTRIBUTION",
    "OUT_OF_DISTRIBUTION",
    "InitialStateRegion",
    "Physics",
    "Pusher",
    "check_region",
    "clip_action",
    "draw_action_noise",
    "draw_strength",
    "get_model_and_assets",
    "make_environment",
    "noisy_control",
    "sample_start",
]

CONTROL_TIMESTEP = 0.05  # s: 10 physics steps; 30 s episodes are 600 control steps
DEFAULT_TIME_LIMIT = 30.0  # s
ARENA_RADIUS = 0.21  # m, inner radius of the fence
HUB_RADIUS = 0.06  # m
BALL_RADIUS = 0.015  # m
WRIST_RANGE = np.deg2rad(160.0)
_START_CLEARANCE = 0.04  # m, fingertip-to-ball distance below which a start is resampled
_MIN_START_DISTANCE = 2 * DEFAULT_SUCCESS_RADIUS  # m, ball-to-target distance at the start
# Candidate starts sample_start rejects before it gives up on a region: the default regions
# need at most 9 candidates (in-distribution) and 4 (out-of-distribution) over 100,000 starts
# each (seeds 0-19,999, five starts a seed), about 1.4 and 1.0 on average.
_MAX_START_DRAWS = 10_000

ARM_JOINTS = slice(0, 2)  # qpos/qvel slots of the shoulder and the wrist


@dataclass(frozen=True)
class InitialStateRegion:
    """Where episodes start: ranges of uniform distributions, in SI units.

    Attributes:
        ball_radius: distance of the ball's centre from the arm's base (m).
        ball_speed: initial ball speed (m/s), in a uniformly random direction.
        joint_speed: magnitude of each arm joint's initial velocity (rad/s), random sign.
        target_radius: distance of the target from the arm's base (m).
        angle: polar angle of the ball and of the target around the base (rad), measured from
            the x axis; ``(-pi, pi)`` is the whole arena. ``low`` may exceed ``pi`` (a sector
            across the negative x axis), the span is at most ``2 pi``.
        target_angle: the target's polar angle range when it differs from the ball's (e.g. a
            target across the hub from the ball); None: ``angle``.
    """

    ball_radius: tuple[float, float]
    ball_speed: tuple[float, float]
    joint_speed: tuple[float, float]
    target_radius: tuple[float, float]
    angle: tuple[float, float] = (-math.pi, math.pi)
    target_angle: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        for name in ("ball_radius", "ball_speed", "joint_speed", "target_radius", "angle"):
            _check_pair(name, getattr(self, name))
        if self.target_angle is not None:
            _check_pair("target_angle", self.target_angle)
        low_ok = HUB_RADIUS + BALL_RADIUS
        high_ok = ARENA_RADIUS - BALL_RADIUS
        for name in ("ball_radius", "target_radius"):
            lo, hi = getattr(self, name)
            if not low_ok <= lo <= hi <= high_ok:
                raise ValueError(
                    f"{name}: expected {low_ok:.3f} <= low <= high <= {high_ok:.3f} m "
                    f"(between hub and fence), got ({lo}, {hi})"
                )
        for name in ("ball_speed", "joint_speed"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"{name}: expected 0 <= low <= high, got ({lo}, {hi})")
        for name in ("angle", "target_angle"):
            value = getattr(self, name)
            if value is None and name == "target_angle":
                continue
            lo, hi = value
            if not (lo <= hi <= lo + 2 * math.pi + 1e-12):
                raise ValueError(
                    f"{name}: expected low <= high <= low + 2 pi (rad), got ({lo}, {hi})"
                )


def _check_pair(name: str, value: object) -> None:
    """Require ``(low, high)``: two finite real numbers (their order is checked by the caller)."""
    pair = None if isinstance(value, (str, bytes)) else value
    try:
        low, high = pair
    except (TypeError, ValueError):
        low = high = None
    if not all(
        isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)
        for v in (low, high)
    ):
        raise ValueError(f"{name}: expected (low, high), two finite numbers, got {value!r}")


def check_region(region: object, *, or_none: bool = False) -> None:
    """Require an :class:`InitialStateRegion` (or None where ``or_none``), naming ``region``."""
    if region is None and or_none:
        return
    if not isinstance(region, InitialStateRegion):
        expected = "an InitialStateRegion or None" if or_none else "an InitialStateRegion"
        raise TypeError(f"region: expected {expected}, got {type(region).__name__} {region!r}")


# Training / in-distribution starts: ball and target 0.09-0.16 m from the base in the half of
# the arena in front of the arm (polar angle -90..90 degrees), at rest.
IN_DISTRIBUTION = InitialStateRegion(
    ball_radius=(0.09, 0.16),
    ball_speed=(0.0, 0.0),
    joint_speed=(0.0, 0.0),
    target_radius=(0.09, 0.16),
    angle=(-math.pi / 2, math.pi / 2),
)
# Out-of-distribution starts: the ball in a sector just past the training half (polar angle
# 100..130 degrees), at rest, and the target across the hub from it (-80..-50 degrees). The ball
# is pushed from where no training episode started and around the hub, so the model is queried
# on states it has seen little of, and the task is harder than a training one (the fingertip
# must bring the ball round the hub: a scripted pusher needs about 9 s where a training task
# takes about 4.5 s). A region that differs only in the initial velocities or the ball's
# distance is visited by the training episodes themselves and is not out of the model's
# distribution.
OUT_OF_DISTRIBUTION = InitialStateRegion(
    ball_radius=(0.09, 0.16),
    ball_speed=(0.0, 0.0),
    joint_speed=(0.0, 0.0),
    target_radius=(0.09, 0.16),
    angle=(math.radians(100.0), math.radians(130.0)),
    target_angle=(math.radians(-80.0), math.radians(-50.0)),
)


def get_model_and_assets() -> tuple[bytes, dict]:
    """The model XML string and the dm_control common assets it includes."""
    with open(os.path.join(os.path.dirname(__file__), "pusher.xml"), "rb") as f:
        return f.read(), common.ASSETS


class Physics(mujoco.Physics):
    """Physics with named accessors for the Pusher. Indices are resolved once per model."""

    def indices(self) -> dict[str, int]:
        """Ids of the ``"finger"`` and ``"ball"`` bodies and the ``"target"`` geom, and the
        qpos (``"ball_x"``) and qvel (``"ball_vx"``) addresses of the ball's x slide (y next)."""
        ids = self.__dict__.get("_pusher_ids")
        if ids is None:
            m = self.model
            ids = {
                "finger": m.name2id("finger", "body"),
                "ball": m.name2id("ball", "body"),
                "target": m.name2id("target", "geom"),
                "ball_x": m.jnt_qposadr[m.name2id("ball_x", "joint")],
                "ball_vx": m.jnt_dofadr[m.name2id("ball_x", "joint")],
            }
            self.__dict__["_pusher_ids"] = ids
        return ids

    def arm_angles(self) -> np.ndarray:
        """Shoulder and wrist angles (rad), ``[2]``."""
        return self.data.qpos[ARM_JOINTS]

    def arm_velocities(self) -> np.ndarray:
        """Shoulder and wrist angular velocities (rad/s), ``[2]``."""
        return self.data.qvel[ARM_JOINTS]

    def finger_xy(self) -> np.ndarray:
        return self.data.xpos[self.indices()["finger"], :2]

    def ball_xy(self) -> np.ndarray:
        return self.data.xpos[self.indices()["ball"], :2]

    def ball_velocity(self) -> np.ndarray:
        i = self.indices()["ball_vx"]
        return self.data.qvel[i : i + 2]

    def target_xy(self) -> np.ndarray:
        return self.model.geom_pos[self.indices()["target"], :2]

    def set_target(self, xy: np.ndarray) -> None:
        self.model.geom_pos[self.indices()["target"], :2] = xy

    def set_ball(self, xy: np.ndarray, velocity: np.ndarray) -> None:
        i, j = self.indices()["ball_x"], self.indices()["ball_vx"]
        self.data.qpos[i : i + 2] = xy
        self.data.qvel[j : j + 2] = velocity

    def set_state(self, state: PusherState) -> None:
        """Write a (single, ``[2]``-field) :class:`PusherState`; call inside ``reset_context``."""
        self.data.qpos[ARM_JOINTS] = state.arm_angles
        self.data.qvel[ARM_JOINTS] = state.arm_velocities
        self.set_ball(state.ball, state.ball_velocity)
        self.set_target(state.target)

    def ball_to_target(self) -> float:
        return float(planar_distance(self.ball_xy(), self.target_xy()))

    def finger_to_ball(self) -> float:
        return float(planar_distance(self.finger_xy(), self.ball_xy()))


def _polar(
    random: np.random.RandomState, radius: tuple[float, float], angles: tuple[float, float]
) -> np.ndarray:
    r = random.uniform(*radius)
    angle = random.uniform(*angles)
    return r * np.array([np.cos(angle), np.sin(angle)])


def sample_start(
    random: np.random.RandomState,
    region: InitialStateRegion,
    finger_to_ball: Callable[[PusherState], float],
) -> PusherState:
    """Draw an episode's start state (``[2]`` fields) from ``region`` with ``random``.

    Rejection sampling: ball and target at least ``_MIN_START_DISTANCE`` apart, the fingertip
    more than ``_START_CLEARANCE`` from the ball; ``finger_to_ball(state)`` puts a candidate in a
    simulator and returns that distance (m). The draws and their order are the task's, so a
    stream seeded alike gives the same start wherever this runs.

    Raises:
        ValueError: naming ``region`` when ``_MAX_START_DRAWS`` candidates in a row are rejected
            (a region whose ball and target can never be far enough apart, say; the default
            regions need at most a handful), or naming ``finger_to_ball`` when it returns NaN.
    """
    check_region(region)
    too_close = too_near = 0
    while too_close + too_near < _MAX_START_DRAWS:
        target_angle = region.angle if region.target_angle is None else region.target_angle
        target = _polar(random, region.target_radius, target_angle)
        ball = _polar(random, region.ball_radius, region.angle)
        if np.linalg.norm(ball - target) < _MIN_START_DISTANCE:
            too_close += 1
            continue
        direction = random.uniform(-np.pi, np.pi)
        speed = random.uniform(*region.ball_speed)
        shoulder = random.uniform(-np.pi, np.pi)
        wrist = random.uniform(-0.9, 0.9) * WRIST_RANGE
        signs = random.choice([-1.0, 1.0], size=2)
        state = PusherState(
            arm_angles=np.array([shoulder, wrist]),
            arm_velocities=signs * random.uniform(*region.joint_speed, size=2),
            ball=ball,
            ball_velocity=speed * np.array([np.cos(direction), np.sin(direction)]),
            target=target,
        )
        distance = finger_to_ball(state)
        if distance > _START_CLEARANCE:
            return state
        if math.isnan(distance):
            raise ValueError(
                f"finger_to_ball: expected a fingertip-to-ball distance (m), got NaN for the "
                f"candidate start {state}"
            )
        too_near += 1
    raise ValueError(
        f"region: no start state found in {_MAX_START_DRAWS} candidates: {too_close} had the "
        f"ball within {_MIN_START_DISTANCE} m of the target, {too_near} the fingertip within "
        f"{_START_CLEARANCE} m of the ball; expected a region whose ball and target can lie at "
        f"least {_MIN_START_DISTANCE} m apart, with room for the fingertip to start farther "
        f"than {_START_CLEARANCE} m from the ball, got {region}"
    )


def clip_action(action: np.ndarray) -> np.ndarray:
    """The commanded action ``[..., 2]`` as float64 clipped to [-1, 1]."""
    return np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)


def draw_action_noise(random: np.random.RandomState, std: float) -> np.ndarray:
    """One step's actuator noise ``[2]``, Gaussian with std ``std``, drawn from ``random``."""
    return random.standard_normal(2) * std


def noisy_control(commanded: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """What reaches the motors, ``[..., 2]``: commanded action plus noise, clipped to [-1, 1]."""
    return np.clip(commanded + noise, -1.0, 1.0)


def draw_strength(random: np.random.RandomState, strength: tuple[float, float] | None) -> float:
    """An episode's actuator strength, uniform in ``strength = (low, high)``, drawn from
    ``random`` right after the start state; ``None``: 1 and nothing is drawn (the stream stays
    as it was without it)."""
    if strength is None:
        return 1.0
    return float(random.uniform(*strength))


class Pusher(base.Task):
    """Push the ball to within ``success_radius`` of the target; success ends the episode.

    With ``terminate_on_success=False`` episodes always run to the time limit (full-length
    trajectories for world-model data and long-horizon forecast checks).

    The reward is the dense shaping of :func:`rcvae_torchrl.envs.pusher_reward`, computed here from
    the physics; it is <= 0 at every step. With ``actuator_strength = (low, high)`` every episode
    draws a strength ``g`` uniform in that range from ``self.random`` (right after its start
    state): the motors get ``g`` times the clipped command, a weaker arm for the whole
    episode that nothing in the observation shows. With ``action_noise_std > 0`` that
    command then gets Gaussian noise from ``self.random`` before it reaches the motors (then
    clipped to [-1, 1]).
    """

    def __init__(
        self,
        region: InitialStateRegion = IN_DISTRIBUTION,
        success_radius: float = DEFAULT_SUCCESS_RADIUS,
        action_noise_std: float = 0.0,
        terminate_on_success: bool = True,
        random: int | np.random.RandomState | None = None,
        actuator_strength: tuple[float, float] | None = None,
    ) -> None:
        check_region(region)
        super().__init__(random=random)
        self.region = region
        self.success_radius = float(success_radius)
        self.action_noise_std = float(action_noise_std)
        self.terminate_on_success = bool(terminate_on_success)
        self.actuator_strength = actuator_strength
        self.strength = 1.0  # this episode's actuator strength
        self._action = np.zeros(2)
        self._ball_to_target = self._finger_to_ball = math.inf
        self._obs: np.ndarray | None = None

    def initialize_episode(self, physics: Physics) -> None:
        def finger_to_ball(state: PusherState) -> float:
            physics.set_state(state)
            physics.forward()
            return physics.finger_to_ball()

        with physics.reset_context():
            sample_start(self.random, self.region, finger_to_ball)
        self.strength = draw_strength(self.random, self.actuator_strength)
        self._action = np.zeros(2)
        self.after_step(physics)
        super().initialize_episode(physics)

    def before_step(self, action: np.ndarray, physics: Physics) -> None:
        self._action = clip_action(action)
        applied = self._action if self.actuator_strength is None else self.strength * self._action
        if self.action_noise_std > 0:
            applied = noisy_control(applied, draw_action_noise(self.random, self.action_noise_std))
        physics.set_control(applied)

    def after_step(self, physics: Physics) -> None:
        """Read the state once per step: the observation, and the distances that reward,
        success and termination share (the hot path: accessors are called once each)."""
        finger, ball, target = physics.finger_xy(), physics.ball_xy(), physics.target_xy()
        self._obs = assemble_observation(
            physics.arm_angles(),
            physics.arm_velocities(),
            finger,
            ball,
            physics.ball_velocity(),
            target,
        )
        self._ball_to_target = float(planar_distance(ball, target))
        self._finger_to_ball = float(planar_distance(finger, ball))

    def get_observation(self, physics: Physics) -> collections.OrderedDict:
        if self._obs is None:  # the spec is inferred before the first episode starts
            self.after_step(physics)
        success = self._ball_to_target <= self.success_radius
        return collections.OrderedDict(observation=self._obs, success=np.array([success]))

    def get_reward(self, physics: Physics) -> float:
        return float(shaped_reward(self._ball_to_target, self._finger_to_ball, self._action))

    def get_termination(self, physics: Physics) -> float | None:
        success = self._ball_to_target <= self.success_radius
        return 0.0 if success and self.terminate_on_success else None


def make_environment(
    region: InitialStateRegion = IN_DISTRIBUTION,
    *,
    success_radius: float = DEFAULT_SUCCESS_RADIUS,
    action_noise_std: float = 0.0,
    terminate_on_success: bool = True,
    time_limit: float = DEFAULT_TIME_LIMIT,
    control_timestep: float = CONTROL_TIMESTEP,
    random: int | np.random.RandomState | None = None,
    actuator_strength: tuple[float, float] | None = None,
) -> control.Environment:
    """The raw dm_control environment (no TorchRL wrapping)."""
    physics = Physics.from_xml_string(*get_model_and_assets())
    task = Pusher(
        region,
        success_radius,
        action_noise_std,
        terminate_on_success,
        random=random,
        actuator_strength=actuator_strength,
    )
    return control.Environment(
        physics, task, time_limit=time_limit, control_timestep=control_timestep
    )

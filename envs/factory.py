"""``make_pusher_env``: the one factory for the Pusher variants, as a TorchRL env."""

from __future__ import annotations

import math

from torchrl.envs import TransformedEnv

from rcvae_torchrl._checks import check_bool, check_device

from .functions import DEFAULT_SUCCESS_RADIUS
from .pusher import (
    CONTROL_TIMESTEP,
    DEFAULT_TIME_LIMIT,
    IN_DISTRIBUTION,
    OUT_OF_DISTRIBUTION,
    InitialStateRegion,
    check_region,
    make_environment,
)
from .wrapper import PusherWrapper

__all__ = [
    "DEFAULT_ACTION_NOISE_STD",
    "VARIANTS",
    "check_env_args",
    "check_strength",
    "check_strength_range",
    "make_pusher_env",
]

VARIANTS = ("deterministic", "stochastic", "ood")
DEFAULT_ACTION_NOISE_STD = 0.5  # std of the Gaussian action noise of the stochastic variant


def _finite_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def check_env_args(
    action_noise_std: float | None,
    time_limit: float,
    control_timestep: float,
    success_radius: float,
    *,
    noise_may_be_none: bool = True,
) -> None:
    """The checks every Pusher env's arguments pass, whatever its variant (``make_pusher_env``,
    ``make_batched_pusher_env`` and ``BatchedPusherEnv`` run them): positive finite times and
    radius, a whole number of control steps, a non-negative finite noise std (or None, the
    variant's default, where ``noise_may_be_none``)."""
    for name, value, unit in (
        ("time_limit", time_limit, "seconds"),
        ("control_timestep", control_timestep, "seconds"),
        ("success_radius", success_radius, "m"),
    ):
        if not _finite_number(value) or not value > 0:
            raise ValueError(f"{name}: expected a positive finite number of {unit}, got {value!r}")
    steps = time_limit / control_timestep
    if not math.isclose(steps, round(steps), rel_tol=0, abs_tol=1e-6):
        raise ValueError(
            f"time_limit: expected a whole number of control steps of {control_timestep} s, "
            f"got {time_limit} s ({steps:.4f} steps)"
        )
    if (action_noise_std is not None or not noise_may_be_none) and not (
        _finite_number(action_noise_std) and action_noise_std >= 0
    ):
        raise ValueError(
            "action_noise_std: expected a non-negative standard deviation, "
            f"got {action_noise_std!r}"
        )


def _check_args(
    variant: str,
    action_noise_std: float | None,
    time_limit: float,
    control_timestep: float,
    success_radius: float,
) -> float:
    if variant not in VARIANTS:
        raise ValueError(f"variant: expected one of {VARIANTS}, got {variant!r}")
    check_env_args(action_noise_std, time_limit, control_timestep, success_radius)
    if action_noise_std is None:
        return DEFAULT_ACTION_NOISE_STD if variant == "stochastic" else 0.0
    if variant == "deterministic" and action_noise_std > 0:
        raise ValueError(
            f"action_noise_std: the deterministic variant takes no action noise, got "
            f"{action_noise_std}; use variant='stochastic'"
        )
    return float(action_noise_std)


def check_strength_range(
    actuator_strength: tuple[float, float] | None, name: str = "actuator_strength"
) -> tuple[float, float] | None:
    """``actuator_strength`` checked, whatever the variant: None, or ``(low, high)`` with
    ``0 < low <= high <= 1``; returns it as two floats."""
    if actuator_strength is None:
        return None
    try:
        low, high = (float(v) for v in actuator_strength)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name}: expected (low, high), two numbers, got {actuator_strength!r}"
        ) from None
    if not 0 < low <= high <= 1:
        raise ValueError(
            f"{name}: expected (low, high) with 0 < low <= high <= 1, got {actuator_strength!r}"
        )
    return (low, high)


def check_strength(
    variant: str,
    actuator_strength: tuple[float, float] | None,
    name: str = "actuator_strength",
) -> tuple[float, float] | None:
    """``actuator_strength`` checked: None, or ``(low, high)`` with ``0 < low <= high <= 1``
    (the motors clip their controls to [-1, 1], so a strength above 1 would only saturate);
    errors name the argument ``name``."""
    checked = check_strength_range(actuator_strength, name)
    if checked is not None and variant == "deterministic":
        raise ValueError(
            f"{name}: the deterministic variant's arm has a fixed strength, got "
            f"{actuator_strength!r}; use variant='stochastic'"
        )
    return checked


def _variant_region(variant: str, region: InitialStateRegion | None) -> InitialStateRegion:
    """``region`` if given, else the variant's: out of distribution for ``"ood"``."""
    check_region(region, or_none=True)
    if region is not None:
        return region
    return OUT_OF_DISTRIBUTION if variant == "ood" else IN_DISTRIBUTION


def make_pusher_env(
    variant: str = "deterministic",
    seed: int | None = None,
    *,
    action_noise_std: float | None = None,
    time_limit: float = DEFAULT_TIME_LIMIT,
    control_timestep: float = CONTROL_TIMESTEP,
    success_radius: float = DEFAULT_SUCCESS_RADIUS,
    region: InitialStateRegion | None = None,
    terminate_on_success: bool = True,
    from_pixels: bool = False,
    device: str | None = None,
    actuator_strength: tuple[float, float] | None = None,
) -> TransformedEnv:
    """A TorchRL Pusher env: a ``DMControlWrapper`` (``PusherWrapper``) in a ``TransformedEnv``.

    Output keys: ``"observation"`` float32 ``[14]`` (layout in :data:`OBSERVATION_LAYOUT`),
    ``"success"`` bool ``[1]`` (ball within ``success_radius`` of the target; success sets
    ``"terminated"``), ``"action"`` float32 ``[2]`` in [-1, 1], ``"reward"`` float32 ``[1]``;
    the time limit sets ``"truncated"``.

    Args:
        variant: ``"deterministic"``, ``"stochastic"`` (Gaussian action noise drawn from the
            task's RNG, so reproducible under ``set_seed``) or ``"ood"`` (starts from
            :data:`OUT_OF_DISTRIBUTION`, disjoint from the training region).
        seed: seeds the task's RNG (start states and action noise).
        action_noise_std: std of the action noise; default :data:`DEFAULT_ACTION_NOISE_STD` for
            ``"stochastic"``, 0 otherwise. ``"ood"`` accepts noise too.
        actuator_strength: ``(low, high)``, within (0, 1]: every episode draws its arm's
            strength uniformly from this range (from the task's RNG, right after the start
            state) and the motors get that multiple of the clipped command all episode long;
            randomness fixed per episode, unobserved. None (default): strength 1, nothing
            drawn. Not for ``"deterministic"``.
        time_limit: episode length in seconds, a whole number of control steps.
        control_timestep: seconds per agent action (10 physics steps at the default 0.05 s).
        success_radius: ball-to-target distance that counts as success (m).
        region: overrides the variant's initial-state region.
        terminate_on_success: end the episode at success (default); if False, episodes run to
            the time limit and ``"success"`` still reports each step.
        from_pixels: also return ``"pixels"`` rendered offscreen (needs ``MUJOCO_GL=egl``).
        device: torch device of the outputs (None: CPU, without per-step device casts).

    Example:
        >>> env = make_pusher_env("stochastic", seed=0)
        >>> td = env.rollout(10)
        >>> td["next", "observation"].shape
        torch.Size([10, 14])
    """
    noise = _check_args(variant, action_noise_std, time_limit, control_timestep, success_radius)
    check_bool("terminate_on_success", terminate_on_success)
    check_bool("from_pixels", from_pixels)
    check_device(device)
    dm_env = make_environment(
        _variant_region(variant, region),
        success_radius=success_radius,
        action_noise_std=noise,
        terminate_on_success=terminate_on_success,
        time_limit=time_limit,
        control_timestep=control_timestep,
        actuator_strength=check_strength(variant, actuator_strength),
    )
    base = PusherWrapper(dm_env, from_pixels=from_pixels, pixels_only=False, device=device)
    env = TransformedEnv(base)
    if seed is not None:
        env.set_seed(seed)
    return env

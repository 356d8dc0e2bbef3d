"""Named layout of the Pusher observation and the resolution of each dimension.

Every consumer (reward, success, scripted controller, world model, competency estimators) indexes
observations through :data:`OBSERVATION_LAYOUT` instead of magic slices.

:data:`OBSERVATION_RESOLUTION` is the smallest difference in each dimension that the competency
estimators treat as meaningful: it is the bin width of the histogram entropy estimator, in the
dimension's own units (metres, m/s, rad/s, or unitless for cos/sin).
"""

from __future__ import annotations

import itertools
from types import MappingProxyType

import torch

__all__ = [
    "OBSERVATION_DIM",
    "OBSERVATION_GROUPS",
    "OBSERVATION_LAYOUT",
    "OBSERVATION_NAMES",
    "OBSERVATION_PARTS",
    "OBSERVATION_RESOLUTION",
    "obs_indices",
    "obs_slice",
    "resolution_tensor",
]

OBSERVATION_NAMES: tuple[str, ...] = (
    "shoulder_cos",
    "shoulder_sin",
    "wrist_cos",
    "wrist_sin",
    "shoulder_vel",
    "wrist_vel",
    "finger_x",
    "finger_y",
    "ball_x",
    "ball_y",
    "ball_vx",
    "ball_vy",
    "target_x",
    "target_y",
)
OBSERVATION_DIM: int = len(OBSERVATION_NAMES)
OBSERVATION_LAYOUT = MappingProxyType({name: i for i, name in enumerate(OBSERVATION_NAMES)})

# Groups of dimensions that belong together (a position is two dimensions, an angle two).
OBSERVATION_GROUPS = MappingProxyType(
    {
        "shoulder": ("shoulder_cos", "shoulder_sin"),
        "wrist": ("wrist_cos", "wrist_sin"),
        "joint_vel": ("shoulder_vel", "wrist_vel"),
        "finger": ("finger_x", "finger_y"),
        "ball": ("ball_x", "ball_y"),
        "ball_vel": ("ball_vx", "ball_vy"),
        "target": ("target_x", "target_y"),
    }
)

_UNIT_RESOLUTION = {
    "cos_sin": 0.02,  # unitless; about 1.1 degrees near the axes
    "joint_vel": 0.1,  # rad/s
    "position": 0.005,  # m; a sixth of the success radius
    "velocity": 0.01,  # m/s
}
OBSERVATION_RESOLUTION = MappingProxyType(
    {
        **dict.fromkeys(
            ("shoulder_cos", "shoulder_sin", "wrist_cos", "wrist_sin"), _UNIT_RESOLUTION["cos_sin"]
        ),
        **dict.fromkeys(("shoulder_vel", "wrist_vel"), _UNIT_RESOLUTION["joint_vel"]),
        **dict.fromkeys(
            ("finger_x", "finger_y", "ball_x", "ball_y", "target_x", "target_y"),
            _UNIT_RESOLUTION["position"],
        ),
        **dict.fromkeys(("ball_vx", "ball_vy"), _UNIT_RESOLUTION["velocity"]),
    }
)


def obs_slice(*names: str) -> slice:
    """The named dimensions (:func:`obs_indices`) as one slice, when they are evenly spaced:
    indexing with it gives a view, where a list of indices gathers (and on a GPU first copies
    the list from host memory on every call).

    >>> obs_slice("shoulder_cos", "wrist_cos")
    slice(0, 3, 2)
    """
    idx = obs_indices(*names)
    step = idx[1] - idx[0] if len(idx) > 1 else 1
    if step < 1 or any(b - a != step for a, b in itertools.pairwise(idx)):
        raise ValueError(f"names: {names} are not evenly spaced dimensions ({idx})")
    return slice(idx[0], idx[-1] + 1, step)


def obs_indices(*names: str) -> list[int]:
    """Indices of the named observation dimensions or groups, in the order given.

    >>> obs_indices("ball", "target_x")
    [8, 9, 12]
    """
    out: list[int] = []
    for name in names:
        if name in OBSERVATION_GROUPS:
            out.extend(OBSERVATION_LAYOUT[n] for n in OBSERVATION_GROUPS[name])
        elif name in OBSERVATION_LAYOUT:
            out.append(OBSERVATION_LAYOUT[name])
        else:
            known = sorted({*OBSERVATION_LAYOUT, *OBSERVATION_GROUPS})
            raise KeyError(f"unknown observation name {name!r}; expected one of {known}")
    return out


def resolution_tensor(dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The per-dimension resolution as a ``[OBSERVATION_DIM]`` tensor (histogram bin widths);
    ``dtype`` is a floating-point one (an integer one would round every width to 0)."""
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise TypeError(f"dtype: expected a floating-point torch.dtype, got {dtype!r}")
    return torch.tensor([OBSERVATION_RESOLUTION[n] for n in OBSERVATION_NAMES], dtype=dtype)


#: The state's parts as slices of the observation (indexing with one gives a view): the arm's
#: cosines and sines (shoulder, wrist), its joint velocities, the fingertip, the ball, its
#: velocity and the target. What the Pusher's features, scripted policy and readout index by.
OBSERVATION_PARTS = MappingProxyType(
    {
        "cos": obs_slice("shoulder_cos", "wrist_cos"),
        "sin": obs_slice("shoulder_sin", "wrist_sin"),
        **{name: obs_slice(name) for name in ("joint_vel", "finger", "ball", "ball_vel", "target")},
    }
)

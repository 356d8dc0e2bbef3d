"""Known state constraints: functions that make a generated state consistent with what is known.

A world model learns everything from data, including facts the user knows exactly: a fingertip
sits at the end of the arm (forward kinematics), an angle's cos and sin lie on the unit circle, a
ball stays inside its fence. Such facts can be given as a constraint ``(s_{t-1}, s_t) -> s_t``
applied to every generated state (in sampling, the model env, the planner's scoring and
open-loop training steps). Constraints are registered by name, so a checkpoint's config can name
one and loading it finds the function again.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

__all__ = ["StateConstraint", "get_state_constraint", "register_state_constraint"]

#: ``(previous state [..., S], generated state [..., S]) -> constrained state [..., S]``.
StateConstraint = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]

_REGISTRY: dict[str, StateConstraint] = {}


def register_state_constraint(name: str, constraint: StateConstraint) -> None:
    """Make ``constraint`` available to configs as ``state_constraint=name``."""
    if not callable(constraint):
        raise TypeError(f"constraint: expected a callable, got {type(constraint).__name__}")
    _REGISTRY[name] = constraint


def get_state_constraint(name: str) -> StateConstraint:
    """The constraint registered under ``name`` (a clear error when there is none)."""
    if name not in _REGISTRY:
        raise KeyError(
            f"state_constraint: no constraint registered as {name!r} (known: {sorted(_REGISTRY)});"
            " import the module that registers it first (the Pusher's: rcvae_torchrl.envs)"
        )
    return _REGISTRY[name]

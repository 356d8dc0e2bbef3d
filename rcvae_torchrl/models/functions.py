"""Known functions of the state a model can use, passed explicitly and named in its config.

A world model learns everything from data, including facts the user knows exactly. Two kinds
of such knowledge can be given to an :class:`~rcvae_torchrl.models.RCVAEEnsemble`:

- a **state constraint** ``(s_{t-1} [..., S], s_t [..., S]) -> s_t [..., S]`` applied to every
  generated state (in sampling, the model env, plan scoring and open-loop training steps): an
  angle's (cos, sin) on the unit circle, an end effector at the end of its kinematic chain, a
  body inside the walls that hold it;
- **input features** ``s [..., S] -> f [..., F]`` the recurrence reads besides the state and the
  action: functions an MLP learns slowly from little data but a user can write down (e.g. a
  gripper's position relative to an object). They are normalised with statistics fitted from
  data and only add inputs: the model still predicts the state.

The config names them (``RCVAEConfig.state_constraint`` / ``input_features``) so that a
checkpoint records what it was trained with; the functions themselves are handed over in a
:class:`ModelFunctions` when the ensemble is built or loaded. Nothing is registered globally:
loading a checkpoint that names a function needs that function passed in, and the error says so.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import torch

__all__ = ["InputFeatures", "ModelFunctions", "StateConstraint"]

#: ``(previous state [..., S], generated state [..., S]) -> constrained state [..., S]``.
StateConstraint = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class InputFeatures(NamedTuple):
    """A feature function ``s [..., S] -> f [..., F]`` and the number F of features it returns."""

    fn: Callable[[torch.Tensor], torch.Tensor]
    dim: int


@dataclass(frozen=True)
class ModelFunctions:
    """The named state constraints and input features a model config may refer to.

    Args:
        state_constraints: name -> :data:`StateConstraint`.
        input_features: name -> :class:`InputFeatures` (or a ``(fn, dim)`` pair).

    Example:
        >>> def unit_first(prev, s):
        ...     return torch.cat([s[..., :1].clamp(-1, 1), s[..., 1:]], dim=-1)
        >>> functions = ModelFunctions(state_constraints={"unit_first": unit_first})
        >>> functions.state_constraint("unit_first") is unit_first
        True
    """

    state_constraints: Mapping[str, StateConstraint] = field(default_factory=dict)
    input_features: Mapping[str, InputFeatures] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, fn in self.state_constraints.items():
            if not callable(fn):
                raise TypeError(
                    f"state_constraints[{name!r}]: expected a callable, got {type(fn).__name__}"
                )
        features = {}
        for name, value in self.input_features.items():
            if not (isinstance(value, tuple) and len(value) == 2):
                raise TypeError(
                    f"input_features[{name!r}]: expected an InputFeatures(fn, dim) pair, got "
                    f"{type(value).__name__}"
                )
            fn, dim = value
            if not callable(fn):
                raise TypeError(
                    f"input_features[{name!r}].fn: expected a callable, got {type(fn).__name__}"
                )
            if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
                raise ValueError(f"input_features[{name!r}].dim: expected an int >= 1, got {dim!r}")
            features[name] = InputFeatures(fn, dim)
        object.__setattr__(self, "state_constraints", dict(self.state_constraints))
        object.__setattr__(self, "input_features", features)

    def state_constraint(self, name: str | None) -> StateConstraint | None:
        """The constraint named ``name`` (``None`` for ``None``), or a ``KeyError`` saying what
        is known and how to pass it."""
        return _lookup("state_constraint", self.state_constraints, name, "state_constraints", "fn")

    def features(self, name: str | None) -> InputFeatures | None:
        """The input features named ``name`` (``None`` for ``None``), or a ``KeyError``."""
        hint = "InputFeatures(fn, dim)"
        return _lookup("input_features", self.input_features, name, "input_features", hint)


def _lookup(setting: str, known: Mapping, name: str | None, field_name: str, value: str):
    if name is None:
        return None
    if name not in known:
        raise KeyError(
            f"{setting}: the config names {name!r}, but no such function was passed (known: "
            f"{sorted(known)}); pass functions=ModelFunctions({field_name}={{{name!r}: {value}}})"
        )
    return known[name]

"""Known input features: functions of a state that the world model reads besides the state.

An MLP can learn any function of the state, but some are hard to learn from little data and
easy to write down: for a pusher, the fingertip's position relative to the ball and the
fingertip's velocity decide whether and how a contact moves the ball. A feature function
``s [..., S] -> f [..., F]`` registered by name is computed from the previous state at every
step, normalised with statistics fitted from data (like the state) and appended to the
recurrence's input. Features only add inputs: the model still predicts the state, so the
likelihood, the generated states and every downstream consumer are unchanged. Registering by
name lets a checkpoint's config name its features and loading it find the function again.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch

__all__ = ["InputFeatures", "get_input_features", "register_input_features"]


class InputFeatures(NamedTuple):
    """A registered feature function and the number F of features it returns."""

    fn: Callable[[torch.Tensor], torch.Tensor]  #: ``s [..., S] -> f [..., F]``
    dim: int


_REGISTRY: dict[str, InputFeatures] = {}


def register_input_features(
    name: str, fn: Callable[[torch.Tensor], torch.Tensor], dim: int
) -> None:
    """Make ``fn`` (returning ``dim`` features) available to configs as ``input_features=name``."""
    if not callable(fn):
        raise TypeError(f"fn: expected a callable, got {type(fn).__name__}")
    if not isinstance(dim, int) or dim < 1:
        raise ValueError(f"dim: expected a positive int, got {dim!r}")
    _REGISTRY[name] = InputFeatures(fn, dim)


def get_input_features(name: str) -> InputFeatures:
    """The feature function registered under ``name`` (a clear error when there is none)."""
    if name not in _REGISTRY:
        raise KeyError(
            f"input_features: no feature function registered as {name!r} (known: "
            f"{sorted(_REGISTRY)}); import the module that registers it first (the Pusher's: "
            "rcvae_torchrl.envs)"
        )
    return _REGISTRY[name]

"""Argument checks shared by the planner modules.

Every check raises ``ValueError`` (or ``TypeError``) whose message names the argument, what was
expected and what was given.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def check_positive_int(name: str, value: object) -> None:
    """Require a Python integer >= 1."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")


def check_top_k(top_k: object, num_candidates: int) -> None:
    """Require ``1 <= top_k <= num_candidates``."""
    check_positive_int("top_k", top_k)
    if top_k > num_candidates:
        raise ValueError(
            f"top_k: expected at most num_candidates = {num_candidates} elites, got {top_k}"
        )


def check_momentum(momentum: object) -> None:
    """Require a number in [0, 1)."""
    if isinstance(momentum, bool) or not isinstance(momentum, (int, float)):
        raise TypeError(f"momentum: expected a float in [0, 1), got {momentum!r}")
    if not 0.0 <= momentum < 1.0:
        raise ValueError(f"momentum: expected a float in [0, 1), got {momentum!r}")


def check_unit_interval(name: str, value: object, *, include_zero: bool) -> None:
    """Require a number in [0, 1] (``include_zero``) or (0, 1]."""
    interval = "[0, 1]" if include_zero else "(0, 1]"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{name}: expected a float in {interval}, got {value!r}")
    low_ok = value >= 0.0 if include_zero else value > 0.0
    if not (low_ok and value <= 1.0):
        raise ValueError(f"{name}: expected a float in {interval}, got {value!r}")


def check_choice(name: str, value: object, choices: Sequence[str]) -> None:
    """Require ``value`` to be one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name}: expected one of {list(choices)}, got {value!r}")


def check_shape(name: str, x: Tensor, expected: Sequence[int], layout: str) -> None:
    """Require ``x.shape == expected``; ``layout`` names the axes, e.g. ``"[*B, C, H, *A]"``."""
    if tuple(x.shape) != tuple(expected):
        raise ValueError(
            f"{name}: expected shape {layout} = {tuple(expected)}, got {tuple(x.shape)}"
        )


def check_finite(name: str, x: Tensor) -> None:
    """Require every entry of a floating tensor to be finite."""
    if x.is_floating_point() and not bool(torch.isfinite(x).all()):
        n_nan = int(torch.isnan(x).sum())
        n_inf = int(torch.isinf(x).sum())
        raise ValueError(
            f"{name}: expected finite values, got {n_nan} NaN and {n_inf} inf entries "
            f"in a tensor of shape {tuple(x.shape)}"
        )

"""Input validation shared by the competency functions.

Every check raises ``ValueError`` (or ``TypeError`` for a non-tensor) whose message names the
argument, what was expected and what was given.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def as_tensor(name: str, x: object) -> Tensor:
    """Return ``x`` as a tensor, or raise ``TypeError`` naming ``name``."""
    if isinstance(x, Tensor):
        return x
    if isinstance(x, (int, float, bool, Sequence)):
        return torch.as_tensor(x)
    raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")


def check_min_rank(name: str, x: Tensor, min_rank: int, layout: str) -> None:
    """Require ``x.ndim >= min_rank``; ``layout`` describes the expected shape."""
    if x.ndim < min_rank:
        raise ValueError(
            f"{name}: expected shape {layout} (at least {min_rank} dims), "
            f"got shape {tuple(x.shape)} ({x.ndim} dims)"
        )


def check_rank(name: str, x: Tensor, rank: int, layout: str) -> None:
    """Require ``x.ndim == rank``; ``layout`` describes the expected shape."""
    if x.ndim != rank:
        raise ValueError(
            f"{name}: expected shape {layout} ({rank} dims), "
            f"got shape {tuple(x.shape)} ({x.ndim} dims)"
        )


def check_floating(name: str, x: Tensor) -> None:
    """Require a floating-point tensor."""
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")


def _all_finite(x: Tensor) -> bool:
    """True when no entry is NaN or ±inf, via min and max (NaN propagates through both).

    Unlike ``torch.isfinite(x).all()`` this allocates no tensor of the input's size.
    """
    if x.numel() == 0:
        return True
    low, high = torch.aminmax(x)
    return bool(torch.isfinite(low)) and bool(torch.isfinite(high))


def check_finite(name: str, x: Tensor) -> None:
    """Require every entry of ``x`` to be finite (no NaN, no inf)."""
    if x.is_floating_point() and not _all_finite(x):
        n_nan = int(torch.isnan(x).sum())
        n_inf = int(torch.isinf(x).sum())
        raise ValueError(
            f"{name}: expected finite values, got {n_nan} NaN and {n_inf} inf "
            f"entries in a tensor of shape {tuple(x.shape)}"
        )


def check_samples(name: str, x: Tensor, min_rank: int, layout: str) -> None:
    """Floating, finite, rank at least ``min_rank``, at least one sample on axis 0."""
    check_min_rank(name, x, min_rank, layout)
    check_floating(name, x)
    check_finite(name, x)
    if x.shape[0] < 1:
        raise ValueError(
            f"{name}: expected at least one sample on axis 0, got shape {tuple(x.shape)}"
        )


def check_members(name: str, x: Tensor, layout: str) -> None:
    """Require at least two ensemble members on axis 0 (a decomposition needs E >= 2)."""
    if x.shape[0] < 2:
        raise ValueError(
            f"{name}: expected shape {layout} with E >= 2 ensemble members on axis 0, "
            f"got E = {x.shape[0]} (shape {tuple(x.shape)})"
        )


def check_probability(name: str, x: Tensor) -> None:
    """Require finite values in [0, 1]."""
    if x.numel() == 0 or x.dtype == torch.bool:
        return
    check_finite(name, x)
    low, high = torch.aminmax(x)
    if low < 0 or high > 1:
        raise ValueError(
            f"{name}: expected probabilities in [0, 1], got values in [{float(low)}, {float(high)}]"
        )


def check_same_shape(name_a: str, a: Tensor, name_b: str, b: Tensor) -> None:
    """Require ``a`` and ``b`` to have the same shape."""
    if a.shape != b.shape:
        raise ValueError(
            f"{name_a} and {name_b}: expected the same shape, "
            f"got {tuple(a.shape)} and {tuple(b.shape)}"
        )


def check_positive(name: str, value: float | int) -> None:
    """Require a positive scalar."""
    if not value > 0:
        raise ValueError(f"{name}: expected a positive number, got {value!r}")


def check_positive_int(name: str, value: int) -> None:
    """Require a positive Python integer."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}: expected a positive integer, got {value!r}")


def check_choice(name: str, value: str, choices: Sequence[str]) -> None:
    """Require ``value`` to be one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name}: expected one of {sorted(choices)}, got {value!r}")


def bin_width_tensor(bin_width: float | Tensor | Sequence[float], dim: int, like: Tensor) -> Tensor:
    """Validate a bin width (scalar or one per dimension) and return it as a float64 tensor.

    Returns a tensor of shape ``[]`` or ``[dim]`` on ``like``'s device.
    """
    width = as_tensor("bin_width", bin_width).to(device=like.device, dtype=torch.float64)
    if width.ndim > 1 or (width.ndim == 1 and width.shape[0] not in (1, dim)):
        raise ValueError(
            f"bin_width: expected a scalar or a tensor of shape [D] = [{dim}], "
            f"got shape {tuple(width.shape)}"
        )
    if not bool(torch.isfinite(width).all()) or bool((width <= 0).any()):
        raise ValueError(f"bin_width: expected positive finite widths, got {width.tolist()}")
    return width

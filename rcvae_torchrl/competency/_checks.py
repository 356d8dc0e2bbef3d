"""Input checks of the competency functions: the library's shared checks plus those of samples,
ensemble members, probabilities and bin widths.

Every check raises ``ValueError`` (or ``TypeError`` for a non-tensor) whose message names the
argument, what was expected and what was given.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from rcvae_torchrl._checks import (  # noqa: F401  (re-exported for the competency modules)
    as_tensor,
    check_bool,
    check_choice,
    check_dtype,
    check_finite,
    check_floating,
    check_min_rank,
    check_names,
    check_non_negative_int,
    check_positive,
    check_positive_int,
    check_rank,
    check_same_shape,
    check_tensor,
    check_unit_interval,
)


def check_confidence(confidence: object) -> None:
    """Require the coverage of an interval: a number in (0, 1)."""
    if isinstance(confidence, bool) or not isinstance(confidence, (int, float)):
        raise TypeError(f"confidence: expected a number in (0, 1), got {confidence!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence: expected a number in (0, 1), got {confidence!r}")


def check_samples(name: str, x: Tensor, min_rank: int, layout: str) -> None:
    """Floating, finite, rank at least ``min_rank``, at least one sample on axis 0."""
    check_min_rank(name, x, min_rank, layout)
    check_floating(name, x)
    check_finite(name, x)
    if x.shape[0] < 1:
        raise ValueError(
            f"{name}: expected at least one sample on axis 0, got shape {tuple(x.shape)}"
        )
    if x.shape[-1] < 1:
        raise ValueError(
            f"{name}: expected at least one dimension D on the last axis of {layout}, got "
            f"shape {tuple(x.shape)}"
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


def bin_width_tensor(bin_width: float | Tensor | Sequence[float], dim: int, like: Tensor) -> Tensor:
    """Validate a bin width (scalar or one per dimension) and return it as a float64 tensor.

    Returns a tensor of shape ``[]`` or ``[dim]`` on ``like``'s device.
    """
    if not isinstance(bin_width, Tensor):  # numbers as given: torch's default float32 rounds
        as_tensor("bin_width", bin_width)  # (0.1 became 0.10000000149)
        bin_width = torch.as_tensor(bin_width, dtype=torch.float64)
    width = bin_width.to(device=like.device, dtype=torch.float64)
    if width.ndim > 1 or (width.ndim == 1 and width.shape[0] not in (1, dim)):
        raise ValueError(
            f"bin_width: expected a scalar or a tensor of shape [D] = [{dim}], "
            f"got shape {tuple(width.shape)}"
        )
    if not bool(torch.isfinite(width).all()) or bool((width <= 0).any()):
        raise ValueError(f"bin_width: expected positive finite widths, got {width.tolist()}")
    return width

"""Input checks with errors that name the argument, what was expected and what was given."""

from __future__ import annotations

import torch

__all__ = [
    "check_batch_shapes",
    "check_dtype",
    "check_finite",
    "check_member",
    "check_trailing",
]


def check_finite(name: str, x: torch.Tensor) -> None:
    """Raise ``ValueError`` if ``x`` holds NaN or ±inf."""
    if not torch.is_floating_point(x):
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}.")
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        count = int(bad.sum())
        raise ValueError(
            f"{name}: expected finite values, got {count} NaN/inf entr"
            f"{'y' if count == 1 else 'ies'} (shape {tuple(x.shape)})."
        )


def check_trailing(name: str, x: torch.Tensor, trailing: tuple[int, ...], what: str) -> None:
    """Raise ``ValueError`` unless ``x.shape`` ends with ``trailing``.

    Args:
        name: the argument's name.
        x: the tensor.
        trailing: expected trailing sizes.
        what: a description of the layout, e.g. ``"[*B, S=14]"``.
    """
    n = len(trailing)
    if x.dim() < n or tuple(x.shape[x.dim() - n :]) != tuple(trailing):
        raise ValueError(f"{name}: expected shape {what}, got {tuple(x.shape)}.")


def check_batch_shapes(names: tuple[str, str], a: torch.Size, b: torch.Size) -> None:
    """Raise ``ValueError`` if the batch shapes of two arguments differ."""
    if tuple(a) != tuple(b):
        raise ValueError(
            f"{names[1]}: expected batch shape {tuple(a)} (that of {names[0]}), got {tuple(b)}."
        )


def check_member(member: torch.Tensor, ensemble_size: int, name: str = "member") -> None:
    """Raise unless ``member`` is an integer tensor with values in ``[0, ensemble_size)``."""
    if member.dtype not in (torch.int64, torch.int32):
        raise TypeError(f"{name}: expected an int64 tensor, got dtype {member.dtype}.")
    if member.numel() and (int(member.min()) < 0 or int(member.max()) >= ensemble_size):
        raise ValueError(
            f"{name}: expected values in [0, {ensemble_size}), got range "
            f"[{int(member.min())}, {int(member.max())}]."
        )


def check_dtype(name: str, x: torch.Tensor, dtype: torch.dtype) -> None:
    """Raise ``TypeError`` unless ``x`` has the model's floating dtype."""
    if x.dtype != dtype:
        raise TypeError(f"{name}: expected dtype {dtype} (the model's), got {x.dtype}.")

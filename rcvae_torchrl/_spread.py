"""Indices spread evenly over a length: the steps of an episode a check looks at (one home for
the novelty check's episode steps and the uncertainty metric's look at its bins)."""

from __future__ import annotations

import torch
from torch import Tensor

from rcvae_torchrl._checks import check_positive_int


def spread_steps(length: int, count: int) -> Tensor:
    """``min(length, count)`` step indices spread evenly over an episode of ``length`` steps
    (its first and last among them); ``length`` and ``count`` positive ints."""
    check_positive_int("length", length)
    check_positive_int("count", count)
    return torch.linspace(0, length - 1, min(length, count)).round().long().unique()

"""The conformal level of a sample: what a new draw from the same distribution stays at or
below with a given probability, whatever the distribution (split conformal prediction)."""

from __future__ import annotations

import math

from torch import Tensor

from rcvae_torchrl._checks import check_unit_interval


def conformal_level(values: Tensor, quantile: float) -> tuple[float, float]:
    """The level of ``n`` exchangeable ``values`` that a new one stays at or below with
    probability at least ``quantile``, and the probability kept: the ceil((n + 1) q)-th
    smallest; with too few values for that, the largest, which covers n / (n + 1) (the
    quantile kept). An interpolated quantile of the sample would cover less: with 20 values
    and q = 0.95, about 0.91.

    Raises ``ValueError`` for no values, or a ``quantile`` outside (0, 1] (a quantile of 0
    took the largest value, as if it were the highest).
    """
    check_unit_interval("quantile", quantile, include_zero=False)
    count = values.numel()
    if count == 0:
        raise ValueError("values: expected at least one value, got none")
    kept = min(float(quantile), count / (count + 1))
    rank = min(math.ceil((count + 1) * kept - 1e-9), count)
    return float(values.reshape(-1).double().sort().values[rank - 1]), kept

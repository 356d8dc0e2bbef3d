"""Confidence intervals for a success probability estimated from ``n`` trajectories."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from rcvae_torchrl.competency import _checks

__all__ = [
    "binomial_interval",
    "mean_interval",
    "mean_p_value",
    "paired_difference_interval",
    "without_spread",
]


def binomial_interval(
    successes: Tensor,
    trials: int | Tensor,
    confidence: float = 0.95,
    method: Literal["jeffreys", "wilson"] = "jeffreys",
) -> tuple[Tensor, Tensor]:
    """Two-sided interval for a binomial proportion, elementwise.

    - ``"jeffreys"``: equal-tailed quantiles of the Beta(k + ½, n - k + ½) posterior (Jeffreys
      prior), with the lower end 0 at ``k = 0`` and the upper end 1 at ``k = n`` (Brown, Cai &
      DasGupta, 2001), from :data:`scipy.stats.beta`.
    - ``"wilson"``: Wilson's score interval (Wilson, 1927).

    The interval treats the ``n`` trajectories as independent draws, i.e. it covers the sampling
    noise of the Monte-Carlo forecast, not the disagreement between members (see
    :func:`~rcvae_torchrl.competency.outcome_uncertainty` for that).

    Args:
        successes: ``[*batch]`` success counts ``k`` (integers in ``[0, n]``).
        trials: ``n``, a positive int or a ``[*batch]`` tensor.
        confidence: coverage in (0, 1).
        method: ``"jeffreys"`` or ``"wilson"``.

    Returns:
        ``(low, high)``, float ``[*batch]`` in [0, 1].

    Example:
        >>> low, high = binomial_interval(torch.tensor(0), 100)
        >>> float(low), round(float(high), 4)
        (0.0, 0.0247)
    """
    _checks.check_choice("method", method, ("jeffreys", "wilson"))
    _checks.check_confidence(confidence)
    k = torch.as_tensor(successes, dtype=torch.float64)
    n = torch.as_tensor(trials, dtype=torch.float64, device=k.device).expand_as(k)
    whole = bool((k == k.round()).all()) and bool((n == n.round()).all())  # NaN is not
    if not whole or bool((n <= 0).any()) or bool((k < 0).any()) or bool((k > n).any()):
        raise ValueError(
            f"successes, trials: expected whole counts 0 <= successes <= trials and trials > 0, "
            f"got successes "
            f"in [{float(k.min())}, {float(k.max())}] and trials in "
            f"[{float(n.min())}, {float(n.max())}]"
        )
    alpha = 1.0 - confidence
    if method == "jeffreys":
        low, high = _jeffreys(k, n, alpha)
    else:
        low, high = _wilson(k, n, alpha)
    return low.float(), high.float()


def _jeffreys(k: Tensor, n: Tensor, alpha: float) -> tuple[Tensor, Tensor]:
    from scipy import stats  # imported here: scipy adds ~0.5 s to importing the library

    k_np, n_np = k.cpu().numpy(), n.cpu().numpy()
    low = np.where(k_np > 0, stats.beta.ppf(alpha / 2, k_np + 0.5, n_np - k_np + 0.5), 0.0)
    high = np.where(k_np < n_np, stats.beta.ppf(1 - alpha / 2, k_np + 0.5, n_np - k_np + 0.5), 1.0)
    return torch.as_tensor(low).to(k.device), torch.as_tensor(high).to(k.device)


def _wilson(k: Tensor, n: Tensor, alpha: float) -> tuple[Tensor, Tensor]:
    from scipy import stats

    z = float(stats.norm.ppf(1 - alpha / 2))
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * torch.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    low = torch.where(k == 0, 0.0, (centre - half).clamp(0.0, 1.0))
    high = torch.where(k == n, 1.0, (centre + half).clamp(0.0, 1.0))
    return low, high


def paired_difference_interval(
    a: Tensor, b: Tensor, confidence: float = 0.95
) -> tuple[Tensor, Tensor]:
    """Two-sided interval for P(a) − P(b) from ``n`` paired outcomes, ``a`` and ``b`` bool
    ``[*batch, n]`` (pair ``i``: ``a[..., i]`` and ``b[..., i]``): Newcombe's hybrid score
    interval for paired proportions (Newcombe, 1998, method 10). Each proportion's Wilson
    interval, combined through the pairs' correlation (phi, continuity-corrected; 0 where a
    margin of the 2x2 table is empty). Unlike a normal interval it keeps a width where every
    pair agrees (all successes: a normal interval has none), and it stays within [-1, 1].

    Returns:
        ``(low, high)``, float64 ``[*batch]``.

    Example:
        >>> a = torch.tensor([True] * 65 + [False] * 96)  # 59 + 6 successes of a
        >>> b = torch.tensor([True] * 59 + [False] * 6 + [True] * 16 + [False] * 80)
        >>> [round(float(x), 4) for x in paired_difference_interval(a, b)]
        [-0.1186, -0.0046]
    """
    _checks.check_confidence(confidence)
    for name, x in (("a", a), ("b", b)):
        if not isinstance(x, Tensor) or x.dtype != torch.bool or x.dim() < 1 or x.shape[-1] < 1:
            got = (
                f"a {x.dtype} tensor of shape {tuple(x.shape)}"
                if isinstance(x, Tensor)
                else type(x).__name__
            )
            raise TypeError(f"{name}: expected bool outcomes [*batch, n] with n >= 1, got {got}")
    if a.shape != b.shape:
        raise ValueError(
            f"b: expected the shape of a, {tuple(a.shape)} (one outcome per pair), got "
            f"{tuple(b.shape)}"
        )

    def count(x: Tensor) -> Tensor:
        return x.sum(-1, dtype=torch.float64)

    both, a_only, b_only = count(a & b), count(a & ~b), count(~a & b)
    neither = count(~a & ~b)
    n = torch.full_like(both, float(a.shape[-1]))
    alpha = 1.0 - confidence
    p1, p2 = (both + a_only) / n, (both + b_only) / n
    low1, high1 = _wilson(both + a_only, n, alpha)
    low2, high2 = _wilson(both + b_only, n, alpha)
    margins = (both + a_only) * (b_only + neither) * (both + b_only) * (a_only + neither)
    product = both * neither - a_only * b_only
    corrected = torch.where(product > n / 2, product - n / 2, product.clamp(max=0.0))
    phi = torch.where(margins > 0, corrected / margins.clamp(min=1.0).sqrt(), 0.0)

    def half(x: Tensor, y: Tensor) -> Tensor:
        return (x.square() - 2 * phi * x * y + y.square()).clamp(min=0.0).sqrt()

    difference = p1 - p2
    low = difference - half(p1 - low1, high2 - p2)
    high = difference + half(p2 - low2, high1 - p1)
    return low.clamp(-1.0, 1.0), high.clamp(-1.0, 1.0)


def mean_interval(values: Tensor, confidence: float) -> tuple[float, float]:
    """A Student's t interval at ``confidence`` of the mean of differences ``values`` ``[n]``,
    one per start state (its standard error from their spread, with ``n - 1`` degrees of
    freedom: a normal interval over a handful of start states is too narrow, 2.2 times too
    narrow at 95 % with 3; ``n = 1``: the value itself), within ``[-1, 1]``."""
    mean, n = float(values.mean()), values.numel()
    if n < 2:
        return max(mean, -1.0), min(mean, 1.0)
    from scipy import stats

    quantile = float(stats.t.ppf(0.5 + confidence / 2, n - 1))
    half = quantile * float(values.std()) / math.sqrt(n)
    return max(mean - half, -1.0), min(mean + half, 1.0)


#: Differences whose spread is at most this are taken as one value repeated (no t-test).
_NO_SPREAD = 1e-9


def without_spread(values: Tensor) -> bool:
    """Whether at least 2 ``values`` ``[n]`` are all the same up to rounding (a population
    standard deviation of at most 1e-9): then a t-test has no spread to test against, and
    :func:`mean_p_value` gives 1 or 0 by whether that value is 0."""
    values = values.to(torch.float64)
    return values.numel() >= 2 and float(values.std(correction=0)) <= _NO_SPREAD


def mean_p_value(values: Tensor) -> float:
    """The two-sided p-value of "their mean is 0" for differences ``values`` ``[n]`` (a
    one-sample Student's t-test, the test of :func:`mean_interval`'s interval); NaN with fewer
    than 2. Where every value is the same (no spread to test against), 1 where that value is 0
    and 0 otherwise."""
    values = values.to(torch.float64)
    if values.numel() < 2:
        return math.nan
    if without_spread(values):  # the same difference everywhere
        return 1.0 if abs(float(values.mean())) <= _NO_SPREAD else 0.0
    from scipy.stats import ttest_1samp

    return float(ttest_1samp(values.cpu().numpy(), 0.0).pvalue)

"""Calibration of probability forecasts against observed binary outcomes.

Forecasts ``f`` (e.g. the forecast P(success) per start state) and outcomes ``o`` (did the real
agent succeed from that start state) have the layout ``[N, *batch]``: ``N`` forecast cases first,
then any batch axes (one calibration per batch element). Outcomes may carry one more trailing
axis ``R`` of repeated runs of each case (``[N, *batch, R]``, e.g. several real episodes from
each start state): every run then counts as a case with the same forecast. Bins split [0, 1]
into ``n_bins`` equal intervals ``[k/n, (k+1)/n)``, the last one closed.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import torch
from torch import Tensor

from rcvae_torchrl.competency import _checks

__all__ = [
    "BrierDecomposition",
    "ReliabilityDiagram",
    "brier_decomposition",
    "brier_score",
    "expected_calibration_error",
    "reliability_diagram",
]

_LAYOUT = "[N, *batch]"


class BrierDecomposition(NamedTuple):
    """Murphy (1973) decomposition with the within-bin terms of Stephenson et al. (2008).

    ``brier = reliability - resolution + uncertainty + within_bin_variance
    - within_bin_covariance`` holds exactly; the last two terms vanish when the forecasts are
    constant within each bin (binned forecasts), leaving Murphy's identity. All ``[*batch]``.
    """

    brier: Tensor
    reliability: Tensor
    resolution: Tensor
    uncertainty: Tensor
    within_bin_variance: Tensor
    within_bin_covariance: Tensor


class ReliabilityDiagram(NamedTuple):
    """Per-bin data of a reliability diagram; empty bins hold NaN means and count 0."""

    bin_edges: Tensor  #: ``[n_bins + 1]``
    mean_forecast: Tensor  #: ``[*batch, n_bins]``
    frequency: Tensor  #: ``[*batch, n_bins]`` observed frequency of the outcome
    counts: Tensor  #: ``[*batch, n_bins]`` int64


def _check_pair(forecast: Tensor, outcome: Tensor) -> tuple[Tensor, Tensor]:
    """Validate forecasts in [0, 1] and binary outcomes of the same shape; return float64.

    Outcomes with one more trailing axis ``R`` are repeated runs of each forecast case: every
    run is a case of its own (the forecast repeated), ``[N·R, *batch]``.
    """
    _checks.check_min_rank("forecast", forecast, 1, _LAYOUT)
    _checks.check_probability("forecast", forecast)
    if not isinstance(outcome, Tensor):
        raise TypeError(
            f"outcome: expected a tensor {_LAYOUT} (bool or 0/1), got {type(outcome).__name__}"
        )
    if outcome.ndim == forecast.ndim + 1 and outcome.shape[:-1] == forecast.shape:
        forecast = forecast.unsqueeze(-1).expand_as(outcome).movedim(-1, 1).flatten(0, 1)
        outcome = outcome.movedim(-1, 1).flatten(0, 1)
    _checks.check_same_shape("forecast", forecast, "outcome", outcome)
    if forecast.shape[0] == 0:
        raise ValueError(
            f"forecast, outcome: expected at least one case (N >= 1 on dim 0), got shape "
            f"{tuple(forecast.shape)}"
        )
    if outcome.dtype != torch.bool and bool(((outcome != 0) & (outcome != 1)).any()):
        raise ValueError(
            f"outcome: expected binary outcomes (bool or 0/1), got values "
            f"{torch.unique(outcome)[:5].tolist()}..."
        )
    return forecast.to(torch.float64), outcome.to(torch.float64)


def brier_score(forecast: Tensor, outcome: Tensor) -> Tensor:
    """Mean squared error ``mean_i (f_i - o_i)²`` of probability forecasts.

    Args:
        forecast: ``[N, *batch]`` in [0, 1].
        outcome: ``[N, *batch]`` bool or 0/1.

    Returns:
        ``[*batch]`` in [0, 1].

    Example:
        >>> brier_score(torch.tensor([0.9, 0.2]), torch.tensor([True, False]))
        tensor(0.0250)
    """
    f, o = _check_pair(forecast, outcome)
    return (f - o).square().mean(dim=0).float()


def _bin_sums(f: Tensor, o: Tensor, n_bins: int) -> dict[str, Tensor]:
    """Per-bin count and sums of f, o, f², f·o: each ``[*batch, n_bins]``."""
    index = (f * n_bins).long().clamp_(0, n_bins - 1).movedim(0, -1)
    f, o = f.movedim(0, -1), o.movedim(0, -1)
    values = {"n": torch.ones_like(f), "f": f, "o": o, "ff": f * f, "fo": f * o}
    out = {}
    for name, value in values.items():
        zeros = torch.zeros((*f.shape[:-1], n_bins), dtype=torch.float64, device=f.device)
        out[name] = zeros.scatter_add_(-1, index, value)
    return out


def brier_decomposition(forecast: Tensor, outcome: Tensor, n_bins: int = 10) -> BrierDecomposition:
    """Brier score and its reliability / resolution / uncertainty decomposition.

    ``REL = Σ_k n_k/N (f̄_k - ō_k)²``, ``RES = Σ_k n_k/N (ō_k - ō)²``, ``UNC = ō (1 - ō)``
    (Murphy, 1973), plus the within-bin variance and covariance of the forecasts (Stephenson,
    Coelho & Jolliffe, 2008) so that the identity is exact for any forecasts.

    Args:
        forecast: ``[N, *batch]`` in [0, 1].
        outcome: ``[N, *batch]`` bool or 0/1.
        n_bins: number of equal-width bins on [0, 1].

    Returns:
        :class:`BrierDecomposition` of ``[*batch]`` tensors.

    Example:
        >>> f = torch.tensor([0.25, 0.25, 0.75, 0.75]); o = torch.tensor([0, 1, 1, 1])
        >>> d = brier_decomposition(f, o, n_bins=4)
        >>> float(d.brier), float(d.reliability - d.resolution + d.uncertainty)
        (0.1875, 0.1875)
    """
    _checks.check_positive_int("n_bins", n_bins)
    f, o = _check_pair(forecast, outcome)
    sums = _bin_sums(f, o, n_bins)
    total = float(f.shape[0])
    n = sums["n"].clamp_min(1.0)
    f_bar, o_bar = sums["f"] / n, sums["o"] / n
    climatology = o.mean(dim=0, keepdim=True).movedim(0, -1)
    terms = (
        (f - o).square().mean(dim=0),
        (sums["n"] * (f_bar - o_bar).square()).sum(-1) / total,
        (sums["n"] * (o_bar - climatology).square()).sum(-1) / total,
        (climatology * (1 - climatology)).squeeze(-1),
        (sums["ff"] - sums["f"] * f_bar).sum(-1) / total,
        2.0 * (sums["fo"] - sums["f"] * o_bar).sum(-1) / total,
    )
    return BrierDecomposition(*(t.float() for t in terms))


def reliability_diagram(forecast: Tensor, outcome: Tensor, n_bins: int = 10) -> ReliabilityDiagram:
    """Mean forecast, observed frequency and count per forecast bin.

    Args:
        forecast: ``[N, *batch]`` in [0, 1].
        outcome: ``[N, *batch]`` bool or 0/1.
        n_bins: number of equal-width bins on [0, 1].

    Returns:
        :class:`ReliabilityDiagram`.

    Example:
        >>> r = reliability_diagram(torch.tensor([0.1, 0.15, 0.9]), torch.tensor([0, 1, 1]), 2)
        >>> r.counts.tolist(), r.frequency.tolist()
        ([2, 1], [0.5, 1.0])
    """
    _checks.check_positive_int("n_bins", n_bins)
    f, o = _check_pair(forecast, outcome)
    sums = _bin_sums(f, o, n_bins)
    n = sums["n"]
    empty = n == 0
    nan = torch.full_like(n, float("nan"))
    mean_forecast = torch.where(empty, nan, sums["f"] / n.clamp_min(1))
    frequency = torch.where(empty, nan, sums["o"] / n.clamp_min(1))
    edges = torch.linspace(0.0, 1.0, n_bins + 1, device=f.device)
    return ReliabilityDiagram(edges, mean_forecast.float(), frequency.float(), n.long())


def expected_calibration_error(
    forecast: Tensor,
    outcome: Tensor,
    n_bins: int = 10,
    norm: Literal["l1", "l2", "max"] = "l1",
) -> Tensor:
    """Binned calibration error of probability forecasts for a binary outcome.

    ``l1`` (ECE): ``Σ_k n_k/N |f̄_k - ō_k|``; ``l2``: ``sqrt(Σ_k n_k/N (f̄_k - ō_k)²)``;
    ``max``: ``max_k |f̄_k - ō_k|`` over non-empty bins. The same definitions as
    ``torchmetrics.functional.classification.binary_calibration_error`` (which puts forecasts
    equal to 1 in a bin of their own; here they join the last bin).

    Args:
        forecast: ``[N, *batch]`` in [0, 1].
        outcome: ``[N, *batch]`` bool or 0/1.
        n_bins: number of equal-width bins on [0, 1].
        norm: ``"l1"``, ``"l2"`` or ``"max"``.

    Returns:
        ``[*batch]``.

    Example:
        >>> expected_calibration_error(torch.tensor([0.2, 0.2, 0.8]), torch.tensor([0, 0, 1]))
        tensor(0.2000)
    """
    _checks.check_choice("norm", norm, ("l1", "l2", "max"))
    _checks.check_positive_int("n_bins", n_bins)
    f, o = _check_pair(forecast, outcome)
    sums = _bin_sums(f, o, n_bins)
    n = sums["n"]
    gap = (sums["f"] - sums["o"]).abs() / n.clamp_min(1)
    weight = n / f.shape[0]
    if norm == "l1":
        error = (weight * gap).sum(-1)
    elif norm == "l2":
        error = (weight * gap.square()).sum(-1).sqrt()
    else:
        error = gap.amax(dim=-1)
    return error.float()

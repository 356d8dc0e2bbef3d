"""Outcome assessment (FaMSeC) from sampled returns or ordinal outcome distributions.

The "outcome assessment" self-confidence factor of the Factorized Machine Self-Confidence
framework (Aitken, 2016) compares the mass of outcomes above and below a threshold with upper
and lower partial moments; the generalised outcome assessment (GOA) works on a distribution over
ordinal outcome bins. xO lies in [-1, 1] (GOA in [0, 1], see below): -1 means confident of
failing, +1 confident of succeeding.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rcvae_torchrl.competency import _checks

__all__ = [
    "famsec_outcome_assessment",
    "generalized_outcome_assessment",
    "ordinal_distribution",
    "partial_moments",
]


def partial_moments(rewards: Tensor, threshold: float = 0.0) -> tuple[Tensor, Tensor]:
    """Upper and lower partial moments ``UPM = Σ_{r>=r*} |r| / N``, ``LPM = Σ_{r<r*} |r| / N``.

    Args:
        rewards: ``[N, *batch]`` finite sampled returns (sample axis first).
        threshold: ``r*``.

    Returns:
        ``(upm, lpm)``, each ``[*batch]``.
    """
    _checks.check_samples("rewards", rewards, 1, "[N, *batch]")
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)):
        raise TypeError(f"threshold: expected a finite number, got {threshold!r}")
    if not math.isfinite(threshold):
        raise ValueError(f"threshold: expected a finite number, got {threshold!r}")
    magnitude = rewards.abs()
    above = rewards >= threshold
    upm = torch.where(above, magnitude, 0).mean(dim=0)
    lpm = torch.where(above, 0, magnitude).mean(dim=0)
    return upm, lpm


def famsec_outcome_assessment(rewards: Tensor, threshold: float = 0.0, k: float = 1.0) -> Tensor:
    """FaMSeC outcome assessment ``xO = 2 / (1 + exp(-k·ln(UPM / LPM))) - 1``.

    Computed as ``tanh(k/2 · (ln UPM - ln LPM))`` (the same value, without the powers that
    overflow or underflow for a large ``k`` or returns far from 1), so that ``LPM = 0`` gives +1
    (no outcome below the threshold; also when ``UPM = 0``) and ``UPM = 0 < LPM`` gives -1.

    Args:
        rewards: ``[N, *batch]`` finite sampled returns.
        threshold: ``r*``, the return that counts as acceptable.
        k: steepness, positive.

    Returns:
        ``[*batch]`` in [-1, 1].

    Example:
        >>> famsec_outcome_assessment(torch.tensor([-5.0, 25.0]))  # UPM/LPM = 5: 2/(1+1/5) - 1
        tensor(0.6667)
    """
    _checks.check_positive("k", k)
    upm, lpm = partial_moments(rewards.to(torch.float64), threshold)
    xo = torch.where(lpm == 0, 1.0, torch.tanh(0.5 * k * (upm.log() - lpm.log())))
    return xo.to(rewards.dtype if rewards.is_floating_point() else torch.float32)


def ordinal_distribution(outcomes: Tensor, bin_edges: Tensor) -> Tensor:
    """Empirical distribution over ordinal bins of sampled outcomes.

    Bin ``i`` holds ``edges[i-1] <= x < edges[i]`` (bin 0 everything below ``edges[0]``, bin
    ``Z-1`` everything from ``edges[-1]`` up).

    Args:
        outcomes: ``[N, *batch]`` finite samples.
        bin_edges: increasing ``[Z-1]``.

    Returns:
        ``[*batch, Z]`` probabilities.
    """
    _checks.check_samples("outcomes", outcomes, 1, "[N, *batch]")
    _checks.check_rank("bin_edges", bin_edges, 1, "[Z-1]")
    _checks.check_finite("bin_edges", bin_edges)
    if bin_edges.numel() > 1 and not bool((bin_edges[1:] > bin_edges[:-1]).all()):
        raise ValueError(f"bin_edges: expected strictly increasing edges, got {bin_edges.tolist()}")
    index = torch.bucketize(outcomes, bin_edges.to(outcomes), right=True)
    one_hot = torch.nn.functional.one_hot(index, bin_edges.numel() + 1)
    return one_hot.to(outcomes.dtype).mean(dim=0)


def generalized_outcome_assessment(
    probabilities: Tensor, threshold_bin: int, scale: float = 0.3
) -> Tensor:
    """Generalised outcome assessment over ordinal outcome bins ``0..Z-1`` (worst to best).

    ``D_LPM = Σ_{i<z*} (z*-i)·p_i``, ``D_UPM = Σ_{i>=z*} (i-z*+1)·p_i``,
    ``GOA = 2 / (1 + exp(-scale·D_UPM / D_LPM)) - 1``; ``D_LPM = 0`` gives 1. As the ratio is
    non-negative, GOA lies in [0, 1]. Rows are normalised to sum 1 (counts are accepted as long
    as they are given as probabilities in [0, 1]).

    Args:
        probabilities: ``[*batch, Z]`` in [0, 1].
        threshold_bin: ``z*`` in ``[0, Z)``, the first acceptable bin.
        scale: the slope, 0.3 by default.

    Returns:
        ``[*batch]``.

    Example:
        >>> p = torch.tensor([0.25, 0.25, 0.5])  # z* = 1: D_LPM = 0.25, D_UPM = 0.25 + 2·0.5
        >>> round(float(generalized_outcome_assessment(p, 1)), 4)  # 2/(1+exp(-0.3·5)) - 1
        0.6351
    """
    _checks.check_min_rank("probabilities", probabilities, 1, "[*batch, Z]")
    _checks.check_probability("probabilities", probabilities)
    bins = probabilities.shape[-1]
    if (
        isinstance(threshold_bin, bool)
        or not isinstance(threshold_bin, int)
        or not 0 <= threshold_bin < bins
    ):
        raise ValueError(
            f"threshold_bin: expected an integer in [0, {bins}), got {threshold_bin!r}"
        )
    _checks.check_positive("scale", scale)
    p = probabilities.to(torch.float64)
    if p.numel() and not bool((p.sum(dim=-1) > 0).all()):
        raise ValueError(
            "probabilities: expected every row to hold some probability, got a row of zeros "
            "(no outcome to assess)"
        )
    p = p / p.sum(dim=-1, keepdim=True).clamp_min(torch.finfo(torch.float64).tiny)
    i = torch.arange(bins, dtype=torch.float64, device=p.device)
    d_lpm = (torch.where(i < threshold_bin, threshold_bin - i, 0.0) * p).sum(dim=-1)
    d_upm = (torch.where(i >= threshold_bin, i - threshold_bin + 1, 0.0) * p).sum(dim=-1)
    ratio = d_upm / d_lpm.clamp_min(torch.finfo(torch.float64).tiny)
    goa = torch.where(d_lpm == 0, 1.0, 2.0 / (1.0 + torch.exp(-scale * ratio)) - 1.0)
    return goa.to(probabilities.dtype if probabilities.is_floating_point() else torch.float32)

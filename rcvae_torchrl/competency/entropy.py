"""Entropy estimators from samples, in bits.

Layout: the sample axis comes first, the last axis is the state dimension ``D`` and every axis in
between is a batch axis (start state, time, ...). All estimators are vectorised over batch and
dimension; the histogram and k-NN estimators work through the batch in chunks of bounded memory.

These are the ``H[·]`` of the paper's equations 2 and 3 (Acharya, Russell & Ahmed, 2022).

Degenerate input (all samples equal) never gives NaN:

- :func:`histogram_entropy` gives exactly 0;
- :func:`gaussian_entropy` clamps the variance (eigenvalues of the covariance) at ``min_variance``
  and gives ``0.5·log2(2πe·min_variance)`` per dimension (≈ -17.9 bits for the default 1e-12);
- :func:`knn_entropy` clamps the neighbour distances at ``min_distance`` and gives a finite,
  strongly negative value;
- with ``bin_width`` the Gaussian and k-NN estimators return discretised entropies, clamped at 0,
  so degenerate input gives exactly 0 as with the histogram.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from rcvae_torchrl.competency import _checks
from rcvae_torchrl.competency._binning import (
    CHUNK_ELEMENTS,
    LN2,
    batch_chunks,
    bin_ids,
    grouped_entropies,
)

__all__ = ["gaussian_entropy", "histogram_entropy", "knn_entropy"]

_LAYOUT = "[N, *batch, D]"
_LOG2_2PIE = math.log2(2.0 * math.pi * math.e)
BinWidth = float | Tensor | Sequence[float]


def histogram_entropy(
    samples: Tensor, bin_width: BinWidth, *, chunk_elements: int = CHUNK_ELEMENTS
) -> Tensor:
    """Entropy in bits of the samples discretised on a fixed grid, per dimension.

    Bin ``i`` of dimension ``d`` is ``[i·w_d, (i+1)·w_d)``: the grid is anchored at 0, not at the
    data, so different groups of samples (ensemble members) share bins. The plug-in entropy
    ``-Σ p_i log2 p_i`` of the bin frequencies is returned. For a density ``f`` and a small width
    it approaches ``h(f) - log2(w)`` (``h`` the differential entropy in bits).

    Vectorised: bin counts come from one ``bincount`` per chunk over integer cell codes (each
    column owning a block of cells); when the columns span far more bins than they hold samples
    the codes are first compressed to ranks. The batch is processed in chunks of at most
    ``chunk_elements`` sample entries.

    Args:
        samples: ``[N, *batch, D]`` finite floats.
        bin_width: positive width, a scalar or one per dimension ``[D]``, in the samples' units.
        chunk_elements: memory bound (entries per chunk).

    Returns:
        ``[*batch, D]``, in ``[0, log2 N]``; exactly 0 when all samples of a column are equal.

    Example:
        >>> x = torch.rand(10_000, 3, 2)  # uniform on [0, 1): 10 bins of width 0.1
        >>> h = histogram_entropy(x, 0.1)
        >>> h.shape, bool(((h - math.log2(10)).abs() < 0.01).all())
        (torch.Size([3, 2]), True)
    """
    _checks.check_samples("samples", samples, 2, _LAYOUT)
    _checks.check_positive_int("chunk_elements", chunk_elements)
    width = _checks.bin_width_tensor(bin_width, samples.shape[-1], samples)
    n, dim = samples.shape[0], samples.shape[-1]
    flat = samples.reshape(n, -1, dim)
    parts = [
        _histogram_chunk(flat[:, part], width)
        for part in batch_chunks(flat.shape[1], n * dim, chunk_elements)
    ]
    return torch.cat(parts).reshape(samples.shape[1:]).clamp_min(0).to(samples.dtype)


def _histogram_chunk(x: Tensor, width: Tensor) -> Tensor:
    """``[N, m, D]`` -> float64 ``[m·D]`` histogram entropies."""
    return grouped_entropies(bin_ids(x, width).unsqueeze(0))[0]


def gaussian_entropy(
    samples: Tensor,
    *,
    joint: bool = False,
    bin_width: BinWidth | None = None,
    min_variance: float = 1e-12,
) -> Tensor:
    """Entropy in bits of the Gaussian with the samples' mean and (biased) covariance.

    Per dimension ``h_d = ½·log2(2πe·σ_d²)``; jointly ``h = ½·log2((2πe)^D·det Σ)``, with the
    log-determinant taken from eigenvalues clamped at ``min_variance`` (never NaN). With
    ``bin_width`` the discretised entropy ``h - log2(w)`` (``h - Σ_d log2 w_d`` jointly) is
    returned, clamped at 0, which is what :func:`histogram_entropy` estimates for a Gaussian
    wider than a few bins.

    Args:
        samples: ``[N, *batch, D]`` finite floats, ``N >= 2``.
        joint: entropy of the joint distribution over ``D`` instead of one per dimension.
        bin_width: optional positive width, scalar or ``[D]``.
        min_variance: floor for variances / covariance eigenvalues.

    Returns:
        ``[*batch, D]``, or ``[*batch]`` if ``joint``.

    Example:
        >>> x = 2.0 * torch.randn(100_000, 1)
        >>> h = gaussian_entropy(x)  # ½·log2(2πe·4) ≈ 3.047 bits
        >>> bool((h - 3.047).abs().max() < 0.01)
        True
    """
    _checks.check_samples("samples", samples, 2, _LAYOUT)
    _checks.check_positive("min_variance", min_variance)
    _checks.check_bool("joint", joint)
    if samples.shape[0] < 2:
        raise ValueError(
            f"samples: expected at least 2 samples on axis 0 to estimate a variance, got "
            f"N = {samples.shape[0]} (shape {tuple(samples.shape)})"
        )
    x = samples.to(torch.float64)
    centred = x - x.mean(dim=0)
    if joint:
        h = _joint_gaussian_bits(centred, min_variance)
    else:
        h = 0.5 * (_LOG2_2PIE + torch.log2(centred.square().mean(dim=0).clamp_min(min_variance)))
    return _discretise(h, bin_width, joint, samples).to(samples.dtype)


def _joint_gaussian_bits(centred: Tensor, min_variance: float) -> Tensor:
    """``[N, *batch, D]`` centred samples -> ``[*batch]`` joint Gaussian entropy in bits."""
    cov = torch.einsum("n...i,n...j->...ij", centred, centred) / centred.shape[0]
    eigenvalues = torch.linalg.eigvalsh(cov).clamp_min(min_variance)
    dim = centred.shape[-1]
    return 0.5 * (dim * _LOG2_2PIE + torch.log2(eigenvalues).sum(dim=-1))


def _discretise(h: Tensor, bin_width: BinWidth | None, joint: bool, samples: Tensor) -> Tensor:
    """Differential entropy ``h`` (bits) -> discretised entropy ``max(h - log2 w, 0)``."""
    if bin_width is None:
        return h
    log_width = torch.log2(_checks.bin_width_tensor(bin_width, samples.shape[-1], samples))
    if joint:
        log_width = log_width.expand(samples.shape[-1]).sum()
    return (h - log_width).clamp_min(0)


def knn_entropy(
    samples: Tensor,
    k: int = 3,
    *,
    bin_width: BinWidth | None = None,
    min_distance: float = 1e-10,
    chunk_elements: int = CHUNK_ELEMENTS,
) -> Tensor:
    """Kozachenko–Leonenko k-nearest-neighbour estimate of the joint entropy, in bits.

    ``h = ψ(N) - ψ(k) + log V_D + (D/N)·Σ_i log ε_i`` (nats, then divided by ln 2), with ``ε_i``
    the Euclidean distance from sample ``i`` to its k-th nearest other sample and
    ``V_D = π^(D/2) / Γ(D/2 + 1)`` the volume of the unit ball (Kozachenko & Leonenko, 1987;
    Kraskov, Stögbauer & Grassberger, 2004, eq. 20, whose ε is twice our ε_i). Its bias shrinks
    as ``N`` grows.

    Duplicate samples give zero distances; distances are clamped at ``min_distance`` so the
    result stays finite. With ``bin_width`` the discretised entropy ``max(h - Σ_d log2 w_d, 0)``
    is returned (see :func:`gaussian_entropy`). Squared pairwise distances are computed in
    float64 with one batched matrix product, a chunk of the batch at a time (``N²`` entries per
    batch element).

    Args:
        samples: ``[N, *batch, D]`` finite floats, ``N > k``.
        k: neighbour order.
        bin_width: optional positive width, scalar or ``[D]``.
        min_distance: floor on neighbour distances.
        chunk_elements: memory bound (distance-matrix entries per chunk).

    Returns:
        ``[*batch]``.

    Example:
        >>> x = torch.randn(2_000, 4, 2)  # h = log2(2πe) ≈ 4.094 bits for a 2-D standard normal
        >>> h = knn_entropy(x, k=3)
        >>> h.shape, bool((h - 4.094).abs().max() < 0.15)
        (torch.Size([4]), True)
    """
    _checks.check_samples("samples", samples, 2, _LAYOUT)
    _checks.check_positive_int("k", k)
    _checks.check_positive("min_distance", min_distance)
    n, dim = samples.shape[0], samples.shape[-1]
    if n <= k:
        raise ValueError(f"samples: expected more than k = {k} samples on axis 0, got N = {n}")
    flat = samples.movedim(0, -2).reshape(-1, n, dim)
    parts = [
        _mean_log_knn_distance(flat[part], k, min_distance)
        for part in batch_chunks(flat.shape[0], n * n, chunk_elements)
    ]
    log_ball = 0.5 * dim * math.log(math.pi) - math.lgamma(0.5 * dim + 1.0)
    nats = dim * torch.cat(parts) + _digamma(n) - _digamma(k) + log_ball
    h = nats / LN2
    h = _discretise(h.reshape(samples.shape[1:-1]), bin_width, True, samples)
    return h.to(samples.dtype)


def _mean_log_knn_distance(x: Tensor, k: int, min_distance: float) -> Tensor:
    """``[m, N, D]`` -> float64 ``[m]``: mean over samples of ``log`` k-th neighbour distance."""
    x = x.to(torch.float64)
    x = x - x.mean(dim=1, keepdim=True)  # centring keeps |x|² + |y|² - 2·x·y accurate
    norms = x.square().sum(dim=-1)
    squared = torch.baddbmm(norms.unsqueeze(-1) + norms.unsqueeze(-2), x, x.mT, alpha=-2.0)
    # The smallest entry of each row is the point itself (0), so the k-th neighbour is the
    # (k+1)-th smallest, also when duplicates add more zeros.
    kth = squared.topk(k + 1, dim=-1, largest=False).values[..., k]
    return 0.5 * kth.clamp_min(min_distance**2).log().mean(dim=-1)


def _digamma(n: int) -> float:
    """ψ(n) for a positive integer."""
    return float(torch.special.digamma(torch.tensor(float(n), dtype=torch.float64)))

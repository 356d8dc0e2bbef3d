"""Bounds on the entropy of a Gaussian mixture from pairwise distances, in bits.

Kolchinsky & Tracey (2017), "Estimating Mixture Entropy with Pairwise Distances", Entropy 19(7):
for a mixture ``p = Σ_i w_i p_i`` and a pairwise distance ``D``,

    Ĥ_D = Σ_i w_i H(p_i) - Σ_i w_i ln Σ_j w_j exp(-D(p_i, p_j))

is a lower bound on ``H(p)`` with the Bhattacharyya distance (their eq. 10) and an upper bound with
the Kullback–Leibler divergence (their eq. 9); both are exact for a single component and for
components that are identical or infinitely far apart. The first term ``H(X|C) = Σ_i w_i H(p_i)``
is the entropy of the mixture given the component, the aleatoric part of the paper's equation 3.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from rcvae_torchrl.competency import _checks
from rcvae_torchrl.competency._binning import LN2

__all__ = [
    "EntropyBounds",
    "fit_gaussian_mixture_entropy_bounds",
    "gaussian_mixture_entropy_bounds",
]

_LN_2PIE = math.log(2.0 * math.pi * math.e)


class EntropyBounds(NamedTuple):
    """Lower and upper bounds on a mixture entropy, and the conditional entropy, in bits.

    ``conditional`` is ``H(X|C) = Σ_i w_i H(p_i)``; ``conditional <= lower <= upper``.
    """

    lower: Tensor
    upper: Tensor
    conditional: Tensor


def gaussian_mixture_entropy_bounds(
    weights: Tensor, means: Tensor, covariances: Tensor, *, min_variance: float = 1e-12
) -> EntropyBounds:
    """Kolchinsky–Tracey bounds on the entropy of a Gaussian mixture, in bits.

    Args:
        weights: ``[*batch, K]`` mixture weights in [0, 1] (normalised to sum 1 here).
        means: ``[*batch, K, D]``.
        covariances: diagonal variances ``[*batch, K, D]`` (clamped at ``min_variance``) or full
            covariances ``[*batch, K, D, D]`` (``min_variance·I`` added).
        min_variance: variance floor / jitter, so degenerate components stay finite.

    Returns:
        :class:`EntropyBounds` of ``[*batch]`` tensors.

    Example:
        >>> means = torch.tensor([[0.0], [100.0]])  # two far-apart unit Gaussians: H = h + 1 bit
        >>> weights, variances = torch.tensor([0.5, 0.5]), torch.ones(2, 1)
        >>> bounds = gaussian_mixture_entropy_bounds(weights, means, variances)
        >>> round(float(bounds.lower), 3), round(float(bounds.upper), 3)
        (3.047, 3.047)
    """
    dtype = means.dtype
    weights, means, covariances = _check_mixture(weights, means, covariances)
    log_w = torch.log(weights / weights.sum(dim=-1, keepdim=True))
    if covariances.ndim == means.ndim:
        terms = _diagonal_terms(means, covariances.clamp_min(min_variance))
    else:
        eye = torch.eye(means.shape[-1], dtype=torch.float64, device=means.device)
        terms = _full_terms(means, covariances + min_variance * eye)
    entropies, kl, bhattacharyya = terms
    w = log_w.exp()
    conditional = (w * entropies).sum(dim=-1)
    lower = conditional - _pairwise_term(log_w, bhattacharyya)
    upper = conditional - _pairwise_term(log_w, kl)
    return EntropyBounds(*(t.div(LN2).to(dtype) for t in (lower, upper, conditional)))


def _check_mixture(weights: Tensor, means: Tensor, covariances: Tensor) -> tuple[Tensor, ...]:
    """Validate shapes and values; return float64 copies."""
    _checks.check_samples("means", means, 2, "[*batch, K, D]")
    _checks.check_min_rank("weights", weights, 1, "[*batch, K]")
    _checks.check_probability("weights", weights)
    if weights.shape != means.shape[:-1]:
        raise ValueError(
            f"weights: expected shape [*batch, K] = {tuple(means.shape[:-1])} matching means "
            f"[*batch, K, D] = {tuple(means.shape)}, got {tuple(weights.shape)}"
        )
    if not bool((weights.sum(dim=-1) > 0).all()):
        raise ValueError("weights: expected a positive sum over the K components, got 0")
    full_shape = (*means.shape, means.shape[-1])
    if covariances.shape not in (means.shape, full_shape):
        raise ValueError(
            f"covariances: expected shape {tuple(means.shape)} (diagonal) or {full_shape} "
            f"(full), got {tuple(covariances.shape)}"
        )
    _checks.check_finite("covariances", covariances)
    return tuple(t.to(torch.float64) for t in (weights, means, covariances))


def _pairwise_term(log_w: Tensor, distance: Tensor) -> Tensor:
    """``Σ_i w_i ln Σ_j w_j exp(-D_ij)``: ``[*batch, K]``, ``[*batch, K, K]`` -> ``[*batch]``."""
    inner = torch.logsumexp(log_w.unsqueeze(-2) - distance, dim=-1)
    return (log_w.exp() * inner).sum(dim=-1)


def _diagonal_terms(means: Tensor, var: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Component entropies ``[*b, K]``, KL and Bhattacharyya ``[*b, K, K]`` in nats (diagonal)."""
    entropies = 0.5 * (_LN_2PIE + var.log()).sum(dim=-1)
    var_i, var_j = var.unsqueeze(-2), var.unsqueeze(-3)
    diff2 = (means.unsqueeze(-2) - means.unsqueeze(-3)).square()
    kl = 0.5 * (var_i / var_j + diff2 / var_j - 1.0 + var_j.log() - var_i.log()).sum(dim=-1)
    var_mid = 0.5 * (var_i + var_j)
    log_ratio = var_mid.log() - 0.5 * (var_i.log() + var_j.log())
    bhattacharyya = (diff2 / (8.0 * var_mid) + 0.5 * log_ratio).sum(dim=-1)
    return entropies, kl, bhattacharyya


def _full_terms(means: Tensor, cov: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """As :func:`_diagonal_terms` for full covariances ``[*b, K, D, D]``."""
    dim = means.shape[-1]
    chol = torch.linalg.cholesky(cov)
    logdet = 2.0 * chol.diagonal(dim1=-2, dim2=-1).log().sum(dim=-1)
    entropies = 0.5 * (dim * _LN_2PIE + logdet)
    diff = (means.unsqueeze(-2) - means.unsqueeze(-3)).unsqueeze(-1)  # [*b, K, K, D, 1]
    chol_j = chol.unsqueeze(-4)
    trace = torch.cholesky_solve(cov.unsqueeze(-3), chol_j).diagonal(dim1=-2, dim2=-1).sum(-1)
    mahalanobis = torch.linalg.solve_triangular(chol_j, diff, upper=False).square().sum((-2, -1))
    logdet_i, logdet_j = logdet.unsqueeze(-1), logdet.unsqueeze(-2)
    kl = 0.5 * (trace + mahalanobis - dim + logdet_j - logdet_i)
    cov_mid = 0.5 * (cov.unsqueeze(-3) + cov.unsqueeze(-4))
    chol_mid = torch.linalg.cholesky(cov_mid)
    logdet_mid = 2.0 * chol_mid.diagonal(dim1=-2, dim2=-1).log().sum(dim=-1)
    quad_mid = torch.linalg.solve_triangular(chol_mid, diff, upper=False).square().sum((-2, -1))
    bhattacharyya = quad_mid / 8.0 + 0.5 * (logdet_mid - 0.5 * (logdet_i + logdet_j))
    return entropies, kl, bhattacharyya


def fit_gaussian_mixture_entropy_bounds(
    samples: Tensor, *, full_covariance: bool = False, min_variance: float = 1e-12
) -> EntropyBounds:
    """Fit one Gaussian per ensemble member and bound the entropy of their equal-weight mixture.

    Each member's mean and (biased) covariance are estimated from its ``N`` samples.

    Args:
        samples: ``[E, N, *batch, D]`` (member, sample, batch, dimension).
        full_covariance: fit full covariances instead of diagonal ones.
        min_variance: see :func:`gaussian_mixture_entropy_bounds`.

    Returns:
        :class:`EntropyBounds` of ``[*batch]`` tensors, in bits.

    Example:
        >>> samples = torch.randn(3, 500, 7, 2)
        >>> bounds = fit_gaussian_mixture_entropy_bounds(samples)
        >>> bounds.lower.shape, bool((bounds.lower <= bounds.upper).all())
        (torch.Size([7]), True)
    """
    _checks.check_samples("samples", samples, 3, "[E, N, *batch, D]")
    _checks.check_bool("full_covariance", full_covariance)
    x = samples.to(torch.float64)
    means = x.mean(dim=1)
    centred = x - means.unsqueeze(1)
    if full_covariance:
        cov = torch.einsum("en...i,en...j->e...ij", centred, centred) / x.shape[1]
        cov = cov.movedim(0, -3)
    else:
        cov = centred.square().mean(dim=1).movedim(0, -2)
    means = means.movedim(0, -2)
    weights = torch.full(means.shape[:-1], 1.0 / x.shape[0], dtype=torch.float64)
    bounds = gaussian_mixture_entropy_bounds(weights, means, cov, min_variance=min_variance)
    return EntropyBounds(*(t.to(samples.dtype) for t in bounds))

"""Total / aleatoric / epistemic split of ensemble samples (the paper's equations 2 and 3).

Samples ``x[m, n, ...]`` of member ``m`` (``E`` members) and sample ``n`` (``N`` per member):

- ``total     = H[pooled E·N samples]``   entropy of the ensemble mixture;
- ``aleatoric = mean_m H[samples of m]``  expected entropy (equation 3);
- ``epistemic = total - aleatoric``       mutual information between member and sample
  (equation 2).

Acharya, Russell & Ahmed (2022), after Depeweg et al. (2018).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor

from rcvae_torchrl.competency import _checks
from rcvae_torchrl.competency._binning import (
    CHUNK_ELEMENTS,
    batch_chunks,
    bin_ids,
    grouped_entropies,
    shuffled_labels,
)
from rcvae_torchrl.competency.entropy import BinWidth, gaussian_entropy, knn_entropy
from rcvae_torchrl.competency.mixture import fit_gaussian_mixture_entropy_bounds

__all__ = [
    "ESTIMATORS",
    "UncertaintyDecomposition",
    "decompose_uncertainty",
    "variance_decomposition",
]

_LAYOUT = "[E, N, *batch, D]"
Estimator = Literal["histogram", "gaussian", "knn", "mixture"]


@dataclass(frozen=True)
class UncertaintyDecomposition:
    """``total = aleatoric + epistemic`` (bits for entropies, squared units for variances).

    All three tensors have the same shape.
    """

    total: Tensor
    aleatoric: Tensor
    epistemic: Tensor

    def as_dict(self) -> dict[str, Tensor]:
        """``{"total": ..., "aleatoric": ..., "epistemic": ...}``."""
        return {"total": self.total, "aleatoric": self.aleatoric, "epistemic": self.epistemic}


def decompose_uncertainty(
    samples: Tensor,
    estimator: Estimator = "histogram",
    *,
    ended: Tensor | None = None,
    **estimator_args: Any,
) -> UncertaintyDecomposition:
    """Split the entropy of ensemble samples into aleatoric and epistemic parts, in bits.

    Estimators and their arguments:

    - ``"histogram"`` (``bin_width``, required; ``bias_correction``, ``shuffles``,
      ``generator``): per dimension, bins shared by all members
      (:func:`~rcvae_torchrl.competency.histogram_entropy`). The epistemic part is then a
      Jensen–Shannon divergence, ``0 <= epistemic <= log2 E`` (float round-off clamped).
      With ``bias_correction="shuffle"`` the plug-in divergence is corrected for its sampling
      bias (see below).
    - ``"gaussian"`` (``joint``, ``bin_width``, ``min_variance``): moment-matched Gaussians
      (:func:`~rcvae_torchrl.competency.gaussian_entropy`); ``epistemic >= 0`` (clamped: with
      ``bin_width`` each member's discretised entropy is clamped at 0, and their mean can
      exceed the pooled one's). Not bounded by ``log2 E``: a moment-matched Gaussian's entropy
      is above the mixture's, so members far apart read more epistemic bits than the
      mixture's mutual information can hold (two members 10 std apart: 2.35 bits, where 1 is
      the most); prefer the histogram or the mixture bounds there.
    - ``"knn"`` (``k``, ``bin_width``, ``min_distance``): Kozachenko–Leonenko, joint over
      dimensions (:func:`~rcvae_torchrl.competency.knn_entropy`). Epistemic clamped to
      ``[0, log2 E]``, the bounds of the mixture's mutual information: the estimator's bias
      differs between the ``E·N`` pooled samples and a member's ``N``, by bits in many
      dimensions (identical members of a 78-dimensional state read -14.7 epistemic bits).
      Where members overlap, in many dimensions, its split is biased however it is clamped:
      prefer the histogram there.
    - ``"mixture"`` (``bound`` = ``"upper"`` (default) or ``"lower"``, ``full_covariance``,
      ``min_variance``): one Gaussian fitted per member; aleatoric is the mean entropy of the
      fitted Gaussians (exact), total is the Kolchinsky–Tracey bound on the entropy of their
      mixture (KL upper bound by default, Bhattacharyya lower bound with ``bound="lower"``), so
      epistemic is an upper (lower) bound on the mixture's mutual information, in
      ``[0, log2 E]``.

    Where an estimator's epistemic part is clamped, ``aleatoric = total - epistemic``: the
    pooled total is kept, so ``total = aleatoric + epistemic`` holds for every estimator.

    **Ended episodes** (histogram only). Samples of trajectories that have ended (success,
    failure or time limit: an absorbing terminal state, as a TorchRL ``done``) have no state
    left to be uncertain about. With ``ended`` they all count in one extra bin per dimension,
    shared by all members: the entropy at a step is then that of the process over
    ``states ∪ {ended}``, so a step where every sample has ended has no uncertainty, and
    members that disagree on *when* episodes end contribute epistemic uncertainty.

    **Sampling bias of the epistemic part** (histogram, ``bias_correction="shuffle"``). With
    ``N`` samples spread over many bins the plug-in entropy of each member is biased low far
    more than the pooled one (``E·N`` samples), so the plug-in Jensen–Shannon divergence is
    positive even when all members forecast the same distribution (it reaches ``log2 E`` when
    every sample has a bin of its own). The shuffle correction (Panzeri et al., 2007, *J.
    Neurophysiol.* 98: 1064) subtracts the divergence of the same pooled samples with the
    member labels randomly permuted (``shuffles`` permutations, drawn with ``generator``): the
    value the estimator gives when the members do not disagree. ``epistemic = clamp(JS -
    JS_shuffled, 0, log2 E)`` and ``aleatoric = total - epistemic`` (the per-member entropies
    are the biased ones). When the members are sampled well (``N`` much larger than the bins
    they occupy) the correction vanishes; when they disagree completely and are undersampled
    it under-estimates the divergence, as the null bias then over-states the real one.

    Args:
        samples: ``[E, N, *batch, D]``, ``E >= 2`` members, ``N`` samples each.
        estimator: one of :data:`ESTIMATORS`.
        ended: optional bool ``[E, N, *batch]``, True for samples whose trajectory has ended
            (histogram estimator only).
        **estimator_args: passed to the estimator.

    Returns:
        :class:`UncertaintyDecomposition` of ``[*batch, D]`` tensors (histogram, per-dimension
        Gaussian) or ``[*batch]`` tensors (joint estimators: knn, joint Gaussian, mixture).

    Example:
        >>> samples = torch.randn(5, 100, 600, 14)  # E, N, T, D
        >>> u = decompose_uncertainty(samples, "histogram", bin_width=0.1)
        >>> u.total.shape, bool((u.epistemic <= math.log2(5)).all())
        (torch.Size([600, 14]), True)
    """
    _checks.check_choice("estimator", estimator, tuple(ESTIMATORS))
    _checks.check_samples("samples", samples, 3, _LAYOUT)
    _checks.check_members("samples", samples, _LAYOUT)
    check_estimator_args(estimator, estimator_args)
    _check_sample_count(estimator, samples, estimator_args)
    if ended is not None:
        if estimator != "histogram":
            raise ValueError(
                f"ended: only the histogram estimator has a bin for ended trajectories, got "
                f"estimator={estimator!r}"
            )
        _check_ended(ended, samples)
        estimator_args["ended"] = ended
    batch = samples.shape[2:-1]
    if 0 in batch:  # an empty batch: empty results of the estimator's shapes
        shape = (*batch, samples.shape[-1]) if _per_dimension(estimator, estimator_args) else batch
        empty = samples.new_zeros(shape)
        return UncertaintyDecomposition(empty, empty.clone(), empty.clone())
    total, aleatoric, upper = ESTIMATORS[estimator](samples, **estimator_args)
    raw = total - aleatoric
    epistemic = raw if upper is None else raw.clamp(0.0, upper)
    # where the clamp moved it, the pooled total (E·N samples) stands and aleatoric is what is
    # left of it, as the shuffle correction does: the parts still add up to the total
    aleatoric = torch.where(epistemic != raw, total - epistemic, aleatoric)
    return UncertaintyDecomposition(total, aleatoric, epistemic)


def _per_dimension(estimator: str, args: dict[str, Any]) -> bool:
    """Whether the estimator gives one value per dimension (else one per batch element)."""
    return estimator == "histogram" or (estimator == "gaussian" and not args.get("joint", False))


def _check_sample_count(estimator: str, samples: Tensor, args: dict[str, Any]) -> None:
    """N (axis 1) large enough for the estimator: 1 for a histogram, 2 for a variance
    (gaussian, mixture), more than k for the k-th nearest neighbour."""
    n = samples.shape[1]
    least = {"histogram": 1, "gaussian": 2, "mixture": 2}.get(estimator)
    reason = "samples per member"
    if estimator == "knn":
        least, reason = (
            int(args.get("k", 3)) + 1,
            f"samples per member (more than k = {args.get('k', 3)})",
        )
    elif least == 2:
        reason = "samples per member to estimate a variance"
    if n < least:
        raise ValueError(
            f"samples: the {estimator!r} estimator needs at least {least} {reason} on axis 1 "
            f"of {_LAYOUT}, got N = {n} (shape {tuple(samples.shape)})"
        )


def _check_ended(ended: Tensor, samples: Tensor) -> None:
    if not isinstance(ended, Tensor) or ended.dtype != torch.bool:
        got = ended.dtype if isinstance(ended, Tensor) else type(ended).__name__
        raise TypeError(f"ended: expected a bool tensor, got {got}")
    if ended.shape != samples.shape[:-1]:
        raise ValueError(
            f"ended: expected shape {tuple(samples.shape[:-1])} (the samples' [E, N, *batch]), "
            f"got {tuple(ended.shape)}"
        )


BiasCorrection = Literal["none", "shuffle"]


def check_shuffle_samples(bias_correction: str, samples_per_member: int) -> None:
    """Refuse the shuffle correction with one sample per member: each member's one sample is
    then its own shuffle, the corrected divergence is 0, and so is every epistemic part."""
    if bias_correction == "shuffle" and samples_per_member < 2:
        raise ValueError(
            f"samples_per_member: the shuffle correction (bias_correction='shuffle') needs at "
            f"least 2 samples per member, got {samples_per_member}: with one, the epistemic part "
            "is 0 by construction; draw more, or use bias_correction='none'"
        )


def _histogram(
    samples: Tensor,
    *,
    bin_width: BinWidth | None = None,
    ended: Tensor | None = None,
    bias_correction: BiasCorrection = "none",
    shuffles: int = 4,
    generator: torch.Generator | None = None,
    chunk_elements: int = CHUNK_ELEMENTS,
) -> tuple[Tensor, Tensor, float]:
    """Total and aleatoric histogram entropies; bins shared by all members."""
    if bin_width is None:
        raise ValueError(
            "bin_width: expected a positive width for the histogram estimator, got None"
        )
    _checks.check_positive_int("chunk_elements", chunk_elements)
    _checks.check_choice("bias_correction", bias_correction, ("none", "shuffle"))
    _checks.check_positive_int("shuffles", shuffles)
    width = _checks.bin_width_tensor(bin_width, samples.shape[-1], samples)
    members, n, dim = samples.shape[0], samples.shape[1], samples.shape[-1]
    check_shuffle_samples(bias_correction, n)
    flat = samples.reshape(members, n, -1, dim)
    flat_ended = None if ended is None else ended.reshape(members, n, -1, 1)
    relabels = None
    if bias_correction == "shuffle":
        perms = [torch.randperm(members * n, generator=generator) for _ in range(shuffles)]
        relabels = shuffled_labels(torch.stack(perms).to(samples.device), n)
    parts = []
    for part in batch_chunks(flat.shape[2], members * n * dim, chunk_elements):
        part_ended = None if flat_ended is None else flat_ended[:, :, part]
        total, aleatoric, shuffled = grouped_entropies(
            bin_ids(flat[:, :, part], width), part_ended, relabels
        )
        if shuffled is not None:
            aleatoric = _shuffle_corrected(total, aleatoric, shuffled, members)
        parts.append((total, aleatoric))
    total, aleatoric = (
        torch.cat(p).reshape(samples.shape[2:]).to(samples.dtype) for p in zip(*parts)
    )
    return total, aleatoric, math.log2(members)


def _shuffle_corrected(total: Tensor, aleatoric: Tensor, shuffled: Tensor, members: int) -> Tensor:
    """Aleatoric entropy after subtracting the shuffled-label Jensen–Shannon divergence.

    ``shuffled`` ``[S, C]``: the mean member entropy under each of ``S`` label permutations.
    """
    null = torch.zeros_like(total)
    for one in shuffled:
        null += (total - one) / len(shuffled)
    epistemic = (total - aleatoric - null).clamp(0.0, math.log2(members))
    return total - epistemic


def _per_member(
    entropy: Callable[..., Tensor], samples: Tensor, **kwargs: Any
) -> tuple[Tensor, Tensor]:
    """Total (pooled samples) and aleatoric (mean over members) for any estimator."""
    members, n = samples.shape[0], samples.shape[1]
    total = entropy(samples.reshape(members * n, *samples.shape[2:]), **kwargs)
    aleatoric = entropy(samples.transpose(0, 1), **kwargs).mean(dim=0)
    return total, aleatoric


def _gaussian(samples: Tensor, **kwargs: Any) -> tuple[Tensor, Tensor, float]:
    total, aleatoric = _per_member(gaussian_entropy, samples, **kwargs)
    return total, aleatoric, math.inf


def _knn(samples: Tensor, **kwargs: Any) -> tuple[Tensor, Tensor, float]:
    total, aleatoric = _per_member(knn_entropy, samples, **kwargs)
    return total, aleatoric, math.log2(samples.shape[0])


def _mixture(
    samples: Tensor, *, bound: Literal["lower", "upper"] = "upper", **kwargs: Any
) -> tuple[Tensor, Tensor, float]:
    _checks.check_choice("bound", bound, ("lower", "upper"))
    bounds = fit_gaussian_mixture_entropy_bounds(samples, **kwargs)
    total = bounds.upper if bound == "upper" else bounds.lower
    return total, bounds.conditional, math.log2(samples.shape[0])


#: Estimator name -> function returning (total, aleatoric, clamp bound for epistemic or None).
ESTIMATORS: dict[str, Callable[..., tuple[Tensor, Tensor, float | None]]] = {
    "histogram": _histogram,
    "gaussian": _gaussian,
    "knn": _knn,
    "mixture": _mixture,
}

#: The functions whose keyword arguments each estimator passes on (beside its own).
_FORWARDED: dict[str, tuple[Callable[..., Any], ...]] = {
    "histogram": (),
    "gaussian": (gaussian_entropy,),
    "knn": (knn_entropy,),
    "mixture": (fit_gaussian_mixture_entropy_bounds,),
}


def estimator_arg_names(estimator: str) -> tuple[set[str], set[str]]:
    """The keyword arguments ``estimator`` takes, and those of them that are switches (a
    bool default)."""
    _checks.check_choice("estimator", estimator, tuple(ESTIMATORS))
    names: set[str] = set()
    flags: set[str] = set()  # the switches (a bool default): a truthy string is not one
    for fn in (ESTIMATORS[estimator], *_FORWARDED[estimator]):
        params = inspect.signature(fn).parameters.values()
        taken = [p for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)]
        names |= {p.name for p in taken}
        flags |= {p.name for p in taken if isinstance(p.default, bool)}
    return names - {"samples", "x"}, flags


def check_estimator_args(estimator: str, args: Mapping[str, Any]) -> None:
    """Refuse keyword arguments that ``estimator`` does not take (e.g. a misspelt
    ``bin_widht``), naming them and the ones it takes, before any sample is drawn."""
    names, flags = estimator_arg_names(estimator)
    for name in sorted(flags & set(args)):
        _checks.check_bool(name, args[name])
    unknown = sorted(set(args) - names - {"ended"})
    if unknown:
        raise TypeError(
            f"estimator_args: the {estimator!r} estimator takes {sorted(names)}, got unknown "
            f"{unknown}"
        )


def variance_decomposition(samples: Tensor) -> UncertaintyDecomposition:
    """Law of total variance over ensemble members, per dimension.

    ``Var[x] = E_m[Var[x | m]] + Var_m[E[x | m]]``: total = variance of the pooled samples,
    aleatoric = mean of the member variances, epistemic = variance of the member means (all
    biased, so the identity holds to round-off).

    Args:
        samples: ``[E, N, *batch, D]``, ``E >= 2``, ``N >= 2`` (a member's variance from one
            sample is 0, not its spread).

    Returns:
        :class:`UncertaintyDecomposition` of ``[*batch, D]`` variances (squared units, not bits).

    Example:
        >>> v = variance_decomposition(torch.randn(4, 200, 3))
        >>> bool(torch.allclose(v.total, v.aleatoric + v.epistemic, atol=1e-5))
        True
    """
    _checks.check_samples("samples", samples, 3, _LAYOUT)
    _checks.check_members("samples", samples, _LAYOUT)
    if samples.shape[1] < 2:
        raise ValueError(
            f"samples: expected at least 2 samples per member on axis 1 of {_LAYOUT} (a "
            f"member's variance from one is 0), got N = 1 (shape {tuple(samples.shape)})"
        )
    x = samples.to(torch.float64)
    member_var, member_mean = torch.var_mean(x, dim=1, correction=0)
    aleatoric = member_var.mean(dim=0)
    epistemic = member_mean.var(dim=0, correction=0)
    total = x.flatten(0, 1).var(dim=0, correction=0)
    return UncertaintyDecomposition(*(t.to(samples.dtype) for t in (total, aleatoric, epistemic)))

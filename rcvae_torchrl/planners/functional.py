"""The cross-entropy method (CEM) as pure tensor functions.

Layout: a plan is a Gaussian over action sequences, a ``mean`` and a ``std`` of shape
``[*B, H, *A]`` (batch of start states, horizon, action shape); candidates drawn from it have shape
``[*B, C, H, *A]`` (C candidates per start state) and their scores ``[*B, C]`` (higher is better).

References: Rubinstein & Kroese, *The Cross-Entropy Method* (2004); Botev et al. (2013); the
momentum update ``new = α·old + (1 − α)·elite_stat`` of PETS (Chua et al., 2018) and mbrl-lib's
``CEMOptimizer``. Unlike mbrl-lib, non-finite scores (NaN, ±inf) are never elites.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rcvae_torchrl._checks import broadcasts_to
from rcvae_torchrl.planners import _checks

__all__ = ["action_prior", "cem_update", "elite_mask", "sample_candidates", "shift_plan"]


def action_prior(
    low: Tensor, high: Tensor, init_std: float | Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Prior mean and std of one action, from the action bounds.

    Bounded dimensions get the midpoint and ``(high − low) / 4`` (mbrl-lib's initial variance
    ``(high − low)² / 16``); unbounded ones (an infinite or ``finfo.max`` range) get 0 clipped into
    the bounds and std 1. ``init_std``, when given, replaces the std (broadcast to ``[*A]``).

    Args:
        low, high: ``[*A]`` action bounds.
        init_std: scalar or ``[*A]`` prior std, positive.

    Returns:
        ``(mean, std)``, each ``[*A]``.
    """
    for name, value in (("low", low), ("high", high)):
        if not isinstance(value, Tensor):
            raise TypeError(f"{name}: expected a tensor [*A], got {type(value).__name__}")
    _checks.check_shape("high", high, low.shape, "[*A] (the shape of low)")
    _checks.check_bounds("low, high", low, high)
    bounded = torch.isfinite(high - low)
    mean = torch.where(bounded, (low + high) / 2, torch.zeros_like(low).clamp(low, high))
    std = torch.where(bounded, (high - low) / 4, torch.ones_like(low))
    if init_std is not None:
        try:  # a number, a tensor or a sequence of numbers
            if isinstance(init_std, (str, bytes, bool)):
                raise TypeError(type(init_std).__name__)
            given = torch.as_tensor(init_std, dtype=low.dtype, device=low.device)
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(
                f"init_std: expected a positive number or a tensor [*A], got {init_std!r}"
            ) from err
        if not bool((given > 0).all()) or not bool(torch.isfinite(given).all()):
            raise ValueError(f"init_std: expected positive finite values, got {given.tolist()}")
        if not broadcasts_to(given.shape, low.shape):
            raise ValueError(
                f"init_std: expected a scalar or shape [*A] = {tuple(low.shape)}, "
                f"got shape {tuple(given.shape)}"
            )
        std = given.expand_as(low).clone()
    return mean, std


def sample_candidates(
    mean: Tensor,
    std: Tensor,
    num_candidates: int,
    low: Tensor,
    high: Tensor,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Draw ``num_candidates`` action sequences from ``N(mean, std²)``, clamped to the bounds.

    Args:
        mean, std: ``[*B, H, *A]``.
        num_candidates: C.
        low, high: ``[*A]`` action bounds.
        generator: source of the Gaussian noise (exact reproducibility).

    Returns:
        ``[*B, C, H, *A]`` candidates inside ``[low, high]``.
    """
    _checks.check_shape("std", std, mean.shape, "[*B, H, *A] (the shape of mean)")
    _checks.check_positive_int("num_candidates", num_candidates)
    _checks.check_shape("high", high, low.shape, "[*A] (the shape of low)")
    _checks.check_bounds("low, high", low, high)
    if mean.ndim < low.ndim + 1 or mean.shape[mean.ndim - low.ndim :] != low.shape:
        raise ValueError(
            f"mean: expected [*B, H, *A] with *A = {tuple(low.shape)} (the shape of low), got "
            f"{tuple(mean.shape)}"
        )
    return _draw_candidates(mean, std, num_candidates, low, high, generator)


def _draw_candidates(
    mean: Tensor,
    std: Tensor,
    num_candidates: int,
    low: Tensor,
    high: Tensor,
    generator: torch.Generator | None = None,
) -> Tensor:
    """:func:`sample_candidates` without its checks of the arguments: the planner's inner loop,
    whose plan and bounds were checked once (a check of the bounds' order would wait for a
    GPU at every iteration)."""
    batch_dims = mean.ndim - 1 - low.ndim
    shape = (*mean.shape[:batch_dims], num_candidates, *mean.shape[batch_dims:])
    noise = torch.randn(shape, generator=generator, dtype=mean.dtype, device=mean.device)
    candidates = mean.unsqueeze(batch_dims) + std.unsqueeze(batch_dims) * noise
    return torch.clamp(candidates, min=low, max=high)


def elite_mask(scores: Tensor, top_k: int) -> Tensor:
    """The ``top_k`` best candidates per batch element, never a non-finite one.

    Args:
        scores: ``[*B, C]``, higher is better; NaN and ±inf rank last.
        top_k: number of elites, ``1 <= top_k <= C``.

    Returns:
        ``[*B, C]`` bool; fewer than ``top_k`` entries are set where fewer scores are finite.
    """
    if not isinstance(scores, Tensor) or scores.ndim < 1 or not scores.is_floating_point():
        got = f"{scores.dtype} {tuple(scores.shape)}" if isinstance(scores, Tensor) else scores
        raise ValueError(f"scores: expected a floating tensor [*B, C], got {got!r}")
    _checks.check_top_k(top_k, scores.shape[-1])
    finite = torch.isfinite(scores)
    ranked = torch.where(finite, scores, torch.full_like(scores, -torch.inf))
    index = ranked.topk(top_k, dim=-1).indices
    chosen = torch.zeros_like(finite).scatter_(-1, index, True)
    return chosen & finite


def cem_update(
    mean: Tensor,
    std: Tensor,
    candidates: Tensor,
    scores: Tensor,
    top_k: int,
    momentum: float,
) -> tuple[Tensor, Tensor]:
    """One CEM step: refit the plan to the elites, with momentum.

    ``new = momentum · old + (1 − momentum) · elite_stat`` for the mean and for the std; the elite
    std is the population std (``correction=0``, so ``top_k = 1`` is allowed). A batch element
    whose scores are all non-finite keeps its plan.

    Args:
        mean, std: ``[*B, *D]`` current plan (``D = (H, *A)``).
        candidates: ``[*B, C, *D]``.
        scores: ``[*B, C]``, higher is better; NaN and ±inf are never elites.
        top_k: number of elites, ``1 <= top_k <= C``.
        momentum: α in [0, 1).

    Returns:
        ``(mean, std)``, each ``[*B, *D]``.

    Example:
        >>> mean, std = torch.zeros(1), torch.ones(1)
        >>> cands = torch.tensor([[0.0], [1.0], [3.0]])
        >>> scores = torch.tensor([0.0, 1.0, float("nan")])
        >>> cem_update(mean, std, cands, scores, top_k=2, momentum=0.5)
        (tensor([0.2500]), tensor([0.7500]))
    """
    _check_update_shapes(mean, std, candidates, scores)
    _checks.check_momentum(momentum)
    batch_dims = scores.ndim - 1
    elite = elite_mask(scores, top_k)
    elite = elite.reshape(*elite.shape, *([1] * (candidates.ndim - scores.ndim)))
    count = elite.sum(batch_dims, dtype=candidates.dtype)
    # selected, not weighted: a candidate that is not an elite (e.g. NaN, scored NaN) adds 0
    elite_mean = candidates.where(elite, 0.0).sum(batch_dims) / count.clamp_min(1)
    deviation = candidates - elite_mean.unsqueeze(batch_dims)
    elite_std = (deviation.square().where(elite, 0.0).sum(batch_dims) / count.clamp_min(1)).sqrt()
    any_elite = count > 0
    elite_mean = torch.where(any_elite, elite_mean, mean)
    elite_std = torch.where(any_elite, elite_std, std)
    return (
        momentum * mean + (1 - momentum) * elite_mean,
        momentum * std + (1 - momentum) * elite_std,
    )


def _check_update_shapes(mean: Tensor, std: Tensor, candidates: Tensor, scores: Tensor) -> None:
    if scores.ndim < 1:
        raise ValueError(
            f"scores: expected shape [*B, C], got a scalar of shape {tuple(scores.shape)}"
        )
    batch_dims = scores.ndim - 1
    _checks.check_shape("std", std, mean.shape, "[*B, *D] (the shape of mean)")
    expected = (*scores.shape, *mean.shape[batch_dims:])
    _checks.check_shape("candidates", candidates, expected, "[*B, C, *D]")
    if mean.shape[:batch_dims] != scores.shape[:batch_dims]:
        raise ValueError(
            f"mean: expected batch shape [*B] = {tuple(scores.shape[:batch_dims])} "
            f"(from scores), got shape {tuple(mean.shape)}"
        )


def shift_plan(plan: Tensor, fill: Tensor, time_dim: int) -> Tensor:
    """Advance a plan by one step: drop step 0, append ``fill`` as the last step.

    Args:
        plan: ``[*B, H, *A]``.
        fill: ``[*A]`` (or broadcastable to ``[*B, *A]``), e.g. the prior mean or std.
        time_dim: index of ``H`` in ``plan`` (``len(B)``).

    Returns:
        ``[*B, H, *A]``: ``out[..., t, :] = plan[..., t + 1, :]``, ``out[..., H-1, :] = fill``.
    """
    if (
        isinstance(time_dim, bool)
        or not isinstance(time_dim, int)
        or not (0 <= time_dim < plan.ndim and plan.shape[time_dim] >= 1)
    ):
        raise ValueError(
            f"time_dim: expected the index of H >= 1 in plan of shape {tuple(plan.shape)}, "
            f"got {time_dim!r}"
        )
    step = plan.select(time_dim, 0).shape
    if not isinstance(fill, Tensor) or not broadcasts_to(fill.shape, step):
        got = tuple(fill.shape) if isinstance(fill, Tensor) else type(fill).__name__
        raise ValueError(f"fill: expected a tensor that broadcasts to {tuple(step)}, got {got}")
    tail = plan.narrow(time_dim, 1, plan.shape[time_dim] - 1)
    last = fill.expand(step).unsqueeze(time_dim)
    return torch.cat([tail, last], dim=time_dim)

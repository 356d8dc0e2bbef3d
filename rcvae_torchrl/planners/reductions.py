"""Planning objectives: reductions of per-particle returns to one score per candidate.

Returns have shape ``[*B, C, P]`` (start state, candidate, particle); every reduction gives
``[*B, C]``, higher is better. A candidate with any non-finite particle return (NaN, ±inf) scores
NaN, which the CEM update ranks last.

- ``"mean"``: expected return (PETS).
- ``"quantile"``: the ``risk_level`` lower quantile of the returns (value at risk).
- ``"cvar"``: conditional value at risk, the mean of the worst ``risk_level`` fraction of the
  particles, with a fractional weight on the boundary particle (Rockafellar & Uryasev, 2000).
- ``"success"``: probability of success (mean over particles of a success indicator), ties broken
  by the expected return.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rcvae_torchrl.planners import _checks

__all__ = [
    "OBJECTIVES",
    "cvar_return",
    "expected_return",
    "lexicographic_score",
    "quantile_return",
    "reduce_particles",
    "success_fraction",
]

OBJECTIVES = ("mean", "quantile", "cvar", "success")


def _nan_where_nonfinite(score: Tensor, returns: Tensor) -> Tensor:
    """``score`` with NaN wherever a candidate has a non-finite particle return."""
    finite = torch.isfinite(returns).all(dim=-1)
    return torch.where(finite, score, torch.full_like(score, torch.nan))


def _check_returns(returns: Tensor) -> None:
    if not isinstance(returns, Tensor):
        raise TypeError(f"returns: expected a tensor [*B, C, P], got {type(returns).__name__}")
    if returns.ndim < 2 or not returns.is_floating_point() or returns.shape[-1] < 1:
        raise ValueError(
            f"returns: expected a floating tensor of shape [*B, C, P] with P >= 1, got dtype "
            f"{returns.dtype} and shape {tuple(returns.shape)}"
        )


def expected_return(returns: Tensor) -> Tensor:
    """Mean return over particles: ``[*B, C, P] -> [*B, C]``.

    Example:
        >>> expected_return(torch.tensor([[1.0, 3.0], [0.0, float("inf")]]))
        tensor([2., nan])
    """
    _check_returns(returns)
    return _nan_where_nonfinite(returns.mean(dim=-1), returns)


def quantile_return(returns: Tensor, risk_level: float) -> Tensor:
    """Lower ``risk_level`` quantile of the returns over particles (linear interpolation).

    ``[*B, C, P] -> [*B, C]``; ``risk_level`` in [0, 1] (0 is the worst particle, 0.5 the median).

    Example:
        >>> quantile_return(torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0]]), 0.25)
        tensor([1.])
    """
    _check_returns(returns)
    _checks.check_unit_interval("risk_level", risk_level, include_zero=True)
    safe = torch.nan_to_num(returns)  # non-finite candidates are set to NaN below
    return _nan_where_nonfinite(torch.quantile(safe, risk_level, dim=-1), returns)


def cvar_return(returns: Tensor, risk_level: float) -> Tensor:
    """Conditional value at risk: mean of the worst ``risk_level`` fraction of the particles.

    With ``k = risk_level · P`` the worst ``⌊k⌋`` particles get weight 1 and the next one weight
    ``k − ⌊k⌋``; the weighted sum is divided by ``k``. ``risk_level = 1`` is the mean.

    ``[*B, C, P] -> [*B, C]``; ``risk_level`` in (0, 1].

    Example:
        >>> cvar_return(torch.tensor([[4.0, 0.0, 2.0, 1.0]]), 0.375)  # k = 1.5: (0 + 0.5·1) / 1.5
        tensor([0.3333])
    """
    _check_returns(returns)
    _checks.check_unit_interval("risk_level", risk_level, include_zero=False)
    num_particles = returns.shape[-1]
    k = risk_level * num_particles
    rank = torch.arange(num_particles, dtype=returns.dtype, device=returns.device)
    weight = (k - rank).clamp(0.0, 1.0)
    worst_first = torch.nan_to_num(returns).sort(dim=-1).values
    return _nan_where_nonfinite((worst_first * weight).sum(dim=-1) / k, returns)


def success_fraction(success: Tensor) -> Tensor:
    """Fraction of successful particles: ``[*B, C, P]`` bool (or [0, 1] floats) ``-> [*B, C]``.

    Example:
        >>> success_fraction(torch.tensor([[True, False, True, True]]))
        tensor([0.7500])
    """
    if success.ndim < 2:
        raise ValueError(f"success: expected shape [*B, C, P], got {tuple(success.shape)}")
    if success.dtype != torch.bool and not bool(((success >= 0) & (success <= 1)).all()):
        bad = success[~((success >= 0) & (success <= 1))]
        raise ValueError(
            f"success: expected a bool indicator or values in [0, 1], got {bad[:3].tolist()} "
            f"among {success.numel()} values"
        )
    return success.to(torch.get_default_dtype()).mean(dim=-1)


def lexicographic_score(primary: Tensor, secondary: Tensor) -> Tensor:
    """A score ordering candidates by ``primary``, ties broken by ``secondary``.

    Both ``[*B, C]``; the result is ``[*B, C]`` float64 (``C · rank(primary) + rank(secondary)``,
    ranks over the candidate axis), exact for any ``C < 2**26``. NaN ranks lowest in either.
    """
    if not isinstance(primary, Tensor) or primary.ndim < 1:
        got = tuple(primary.shape) if isinstance(primary, Tensor) else type(primary).__name__
        raise ValueError(f"primary: expected a tensor [*B, C], got {got}")
    _checks.check_shape("secondary", secondary, primary.shape, "[*B, C] (the shape of primary)")
    num_candidates = primary.shape[-1]
    primary = primary.masked_fill(primary.isnan(), -torch.inf)
    ordered = primary.sort(dim=-1).values.contiguous()
    primary_rank = torch.searchsorted(ordered, primary.contiguous(), side="left")
    filled = torch.nan_to_num(secondary, nan=-torch.inf)
    secondary_rank = filled.argsort(dim=-1, stable=True).argsort(dim=-1)
    return (primary_rank * num_candidates + secondary_rank).to(torch.float64)


def reduce_particles(
    returns: Tensor,
    objective: str = "mean",
    risk_level: float = 0.1,
    success: Tensor | None = None,
) -> Tensor:
    """Score candidates by ``objective`` (one of :data:`OBJECTIVES`).

    Args:
        returns: ``[*B, C, P]`` per-particle returns.
        objective: ``"mean"``, ``"quantile"``, ``"cvar"`` or ``"success"``.
        risk_level: quantile level or CVaR fraction (ignored by ``"mean"`` and ``"success"``).
        success: ``[*B, C, P]`` success indicator, required by ``"success"``.

    Returns:
        ``[*B, C]`` scores, higher is better, NaN for candidates with non-finite returns.
        For ``"success"`` the score is a rank (see :func:`lexicographic_score`), not P(success).
    """
    _checks.check_choice("objective", objective, OBJECTIVES)
    if objective == "mean":
        return expected_return(returns)
    if objective == "quantile":
        return quantile_return(returns, risk_level)
    if objective == "cvar":
        return cvar_return(returns, risk_level)
    if success is None:
        raise ValueError(
            'success: expected a [*B, C, P] indicator for objective="success", got None'
        )
    _checks.check_shape("success", success, returns.shape, "[*B, C, P] (the shape of returns)")
    mean = expected_return(returns)
    score = lexicographic_score(success_fraction(success), mean)
    return torch.where(torch.isfinite(mean), score, torch.full_like(score, torch.nan))

"""Recalibrating forecasts of success on real episodes, with an honest split.

A forecast can rank the start states well and still be biased as a whole (e.g. too optimistic
out of distribution). Platt scaling maps a forecast ``f`` to ``σ(a·logit(f) + b)``, with ``a``
and ``b`` fitted by maximum likelihood on real episodes. Fitted and scored on the same start
states it would flatter the forecast, so :func:`cross_fitted_recalibration` splits the start
states into folds and recalibrates each fold with the map fitted on the *other* folds only:
every start's recalibrated forecast is made without its own outcomes.

The fit is penalised towards the identity map (``a = 1``, ``b = 0``) with weight ``ridge``:
without it a condition whose real episodes all agree (every episode a success) has no finite
maximum-likelihood map.

Layouts as in :mod:`rcvae_torchrl.competency.validation`: forecasts ``[B]``, outcomes
``[B, R]`` bool, an optional ``mask`` ``[B, R]``.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import torch
from torch import Tensor

from rcvae_torchrl.competency import _checks
from rcvae_torchrl.competency.validation import _outcomes

__all__ = ["PlattMap", "apply_platt", "cross_fitted_recalibration", "fit_platt"]

#: Forecasts are clamped to [EPS, 1 - EPS] before the logit.
EPS = 1e-4


class PlattMap(NamedTuple):
    """``f -> σ(slope·logit(f) + intercept)``."""

    slope: float
    intercept: float


def _logit(f: Tensor) -> Tensor:
    f = f.to(torch.float64).clamp(EPS, 1 - EPS)
    return torch.log(f) - torch.log1p(-f)


def fit_platt(
    forecast: Tensor,
    outcome: Tensor,
    mask: Tensor | None = None,
    *,
    ridge: float = 1.0,
    iterations: int = 50,
) -> PlattMap:
    """The Platt map maximising the likelihood of the episodes' outcomes, every episode one
    observation, minus ``ridge / 2 · ((a - 1)² + b²)``: Newton's method from the identity, each
    step halved until the objective rises (the objective is strictly concave, so this
    converges; a full step overshoots where forecasts of 0 or 1 meet outcomes that disagree).

    Raises:
        RuntimeError: no convergence within ``iterations`` steps.
    """
    _checks.check_positive("ridge", ridge)
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iterations: expected a positive integer, got {iterations!r}")
    f, mask = _outcomes(forecast, outcome, mask)
    x = _logit(f)[:, None].expand_as(outcome)[mask]
    y = outcome[mask].to(torch.float64)
    design = torch.stack([x, torch.ones_like(x)], dim=-1)  # [n, 2]
    prior = torch.tensor([1.0, 0.0], dtype=torch.float64)
    penalty = ridge * torch.eye(2, dtype=torch.float64)

    def objective(theta: Tensor) -> float:
        z = design @ theta
        fit = (y * z - torch.nn.functional.softplus(z)).sum()
        return float(fit - ridge / 2 * (theta - prior).square().sum())

    theta, value, converged = prior.clone(), objective(prior), False
    for _ in range(iterations):
        p = torch.sigmoid(design @ theta)
        grad = design.T @ (p - y) + ridge * (theta - prior)
        hess = (design * (p * (1 - p))[:, None]).T @ design + penalty
        step = torch.linalg.solve(hess, grad)
        for _ in range(60):  # halve the step until the objective does not fall
            trial = objective(theta - step)
            if trial >= value:
                break
            step = step / 2
        theta, value = theta - step, max(trial, value)
        if float(step.abs().max()) < 1e-10:
            converged = True
            break
    if not converged:
        raise RuntimeError(
            f"fit_platt: Newton's method did not converge in {iterations} iterations (last "
            f"step {float(step.abs().max()):.3g}); raise iterations"
        )
    if float(theta[0]) <= 0:
        warnings.warn(
            "fit_platt: the fitted slope is not positive: in these episodes success does not "
            "rise with the forecast, and the map flattens or reverses the forecasts' order; "
            "they do not rank these starts, which no map can mend (it may still move their "
            "mean)",
            UserWarning,
            stacklevel=2,
        )
    return PlattMap(float(theta[0]), float(theta[1]))


def apply_platt(forecast: Tensor, platt: PlattMap) -> Tensor:
    """``σ(slope·logit(f) + intercept)`` ``[B]``, in the forecast's dtype."""
    _checks.check_tensor("forecast", forecast)
    _checks.check_floating("forecast", forecast)
    _checks.check_probability("forecast", forecast)
    if not isinstance(platt, PlattMap):
        raise TypeError(
            f"platt: expected a PlattMap (fit_platt's; PlattMap(slope, intercept)), got "
            f"{type(platt).__name__}"
        )
    numbers = all(
        isinstance(v, (int, float)) and not isinstance(v, bool)
        for v in (platt.slope, platt.intercept)
    )
    if not (numbers and math.isfinite(platt.slope) and math.isfinite(platt.intercept)):
        raise ValueError(f"platt: expected a finite slope and intercept, got {platt}")
    z = platt.slope * _logit(forecast) + platt.intercept
    return torch.sigmoid(z).to(forecast.dtype)


def cross_fitted_recalibration(
    forecast: Tensor,
    outcome: Tensor,
    mask: Tensor | None = None,
    *,
    folds: int = 5,
    seed: int = 0,
    ridge: float = 1.0,
) -> Tensor:
    """Forecasts ``[B]`` recalibrated fold by fold: the start states are split at random
    (``seed``) into ``folds`` folds of nearly equal size, and each fold's forecasts go through
    the Platt map fitted (:func:`fit_platt`) on the episodes of the other folds' starts."""
    f, mask = _outcomes(forecast, outcome, mask)
    b = f.shape[0]
    if isinstance(folds, bool) or not isinstance(folds, int) or not 2 <= folds <= b:
        raise ValueError(
            f"folds: expected an integer between 2 and the number of start states ({b}), "
            f"got {folds!r}"
        )
    order = torch.randperm(b, generator=torch.Generator().manual_seed(int(seed)))
    out = torch.empty_like(forecast)
    for held in order.tensor_split(folds):
        train = torch.ones(b, dtype=torch.bool)
        train[held] = False
        platt = fit_platt(forecast[train], outcome[train], mask[train], ridge=ridge)
        out[held] = apply_platt(forecast[held], platt)
    return out

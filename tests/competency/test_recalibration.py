"""Platt recalibration on real episodes, and its cross-fitted (honest) form."""

from __future__ import annotations

import warnings

import pytest
import torch

from rcvae_torchrl.competency import (
    PlattMap,
    apply_platt,
    cross_fitted_recalibration,
    episode_brier,
    fit_platt,
)


def _draw(true_p: torch.Tensor, runs: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(true_p.shape[0], runs, generator=g, dtype=torch.float64) < true_p[:, None]


def _forecasts(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, generator=g, dtype=torch.float64) * 0.9 + 0.05


def test_the_fit_recovers_a_known_map():
    f = _forecasts(4000, 0)
    logit = torch.log(f) - torch.log1p(-f)
    true_p = torch.sigmoid(2.0 * logit - 1.0)  # over-confident and too optimistic
    platt = fit_platt(f, _draw(true_p, 1, 1), ridge=1e-3)
    assert platt.slope == pytest.approx(2.0, abs=0.15)
    assert platt.intercept == pytest.approx(-1.0, abs=0.1)


def test_the_identity_map_changes_nothing():
    f = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    torch.testing.assert_close(apply_platt(f, PlattMap(1.0, 0.0)), f)


def test_a_biased_forecast_is_corrected_on_held_out_starts():
    f = _forecasts(200, 2)
    outcome = _draw((f - 0.2).clamp(0.01, 0.99), 10, 3)  # the forecast 0.2 too optimistic
    real = outcome.double().mean()
    recalibrated = cross_fitted_recalibration(f, outcome, folds=5, seed=0)
    assert float(f.mean() - real) > 0.15
    assert abs(float(recalibrated.mean() - real)) < 0.03
    assert episode_brier(recalibrated, outcome) < episode_brier(f, outcome)


def test_a_calibrated_forecast_stays_nearly_as_it_is():
    f = _forecasts(200, 4)
    outcome = _draw(f, 10, 5)
    recalibrated = cross_fitted_recalibration(f, outcome, folds=5, seed=0)
    assert float((recalibrated - f).abs().mean()) < 0.03


def test_a_start_is_never_recalibrated_with_its_own_outcomes():
    f = _forecasts(20, 6)
    outcome = _draw(f, 5, 7)
    flipped = outcome.clone()
    flipped[0] = ~flipped[0]
    a = cross_fitted_recalibration(f, outcome, folds=4, seed=1)
    b = cross_fitted_recalibration(f, flipped, folds=4, seed=1)
    assert a[0] == b[0]  # start 0's map was fitted on the other folds only
    assert not torch.equal(a, b)  # ...and its outcomes moved the other folds' maps


def test_episodes_that_all_agree_give_a_finite_map():
    f = torch.tensor([0.9, 0.95, 0.99, 0.8])
    platt = fit_platt(f, torch.ones(4, 3, dtype=torch.bool))
    assert all(map(torch.isfinite, map(torch.tensor, platt)))
    assert (apply_platt(f, platt) >= f).all()  # all succeeded: the map leans to success


def test_masked_runs_are_left_out():
    f = torch.tensor([0.3, 0.6, 0.7, 0.4], dtype=torch.float64)
    outcome = torch.tensor([[True, False], [True, True], [False, True], [False, False]])
    mask = torch.tensor([[True, False], [True, True], [True, True], [True, False]])
    reference = fit_platt(f, outcome & mask, mask)
    changed = outcome.clone()
    changed[~mask] = ~changed[~mask]
    assert fit_platt(f, changed, mask) == reference


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"folds": 1}, "folds: expected an integer between 2 and the number of start states"),
        ({"folds": 9}, r"folds: .*\(8\), got 9"),
        ({"folds": 2.5}, "folds"),
        ({"ridge": 0.0}, "ridge: expected a positive number"),
    ],
)
def test_bad_arguments_are_named(kwargs, match):
    f = _forecasts(8, 8)
    with pytest.raises(ValueError, match=match):
        cross_fitted_recalibration(f, _draw(f, 2, 9), **kwargs)


def test_a_map_must_be_a_platt_map():
    with pytest.raises(TypeError, match=r"^platt: expected a PlattMap .*, got tuple"):
        apply_platt(torch.tensor([0.5]), (1.0, 0.0))


def test_outcomes_must_be_episodes():
    with pytest.raises(TypeError, match="outcome: expected bool"):
        fit_platt(torch.tensor([0.5, 0.5]), torch.ones(2, 3))


def test_a_map_that_reverses_the_forecasts_order_is_warned():
    # success falls as the forecast rises: the fitted slope is negative
    forecast = torch.linspace(0.1, 0.9, 40, dtype=torch.float64)
    outcome = (torch.arange(20)[None, :] < (20 * (1 - forecast))[:, None]).bool()
    with pytest.warns(UserWarning, match="fit_platt: the fitted slope is not positive"):
        platt = fit_platt(forecast, outcome)
    assert platt.slope < 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an increasing relation: no warning
        assert fit_platt(forecast, outcome.flip(0)).slope > 0


def _penalised_optimum(forecast: torch.Tensor, outcome: torch.Tensor, ridge: float) -> PlattMap:
    """The penalised likelihood's maximum found by scipy's Nelder-Mead (no derivatives)."""
    import numpy as np
    from scipy.optimize import minimize

    f = forecast.double().clamp(1e-4, 1 - 1e-4)
    x = (torch.log(f) - torch.log1p(-f))[:, None].expand_as(outcome).reshape(-1).numpy()
    y = outcome.reshape(-1).double().numpy()

    def loss(t):
        z = t[0] * x + t[1]
        return -(y * z - np.logaddexp(0, z)).sum() + ridge / 2 * ((t[0] - 1) ** 2 + t[1] ** 2)

    best = minimize(loss, [1.0, 0.0], method="Nelder-Mead", options={"xatol": 1e-9, "fatol": 1e-12})
    return PlattMap(*map(float, best.x))


@pytest.mark.parametrize("certain", [1, 2, 3])
def test_forecasts_of_certainty_that_fail_do_not_throw_the_fit(certain):
    # forecasts of exactly 1 whose episodes all fail sit at logit(1 - 1e-4) ~ 9.2, where a full
    # Newton step from the identity overshoots: the fit must still find the optimum
    f = torch.linspace(0.05, 0.95, 30)
    outcome = torch.rand(30, 4, generator=torch.Generator().manual_seed(certain)) < f[:, None]
    f[:certain], outcome[:certain] = 1.0, False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # some of these optima flatten the map
        platt = fit_platt(f, outcome)
    expected = _penalised_optimum(f, outcome, ridge=1.0)
    assert platt.slope == pytest.approx(expected.slope, abs=1e-4)
    assert platt.intercept == pytest.approx(expected.intercept, abs=1e-4)
    assert abs(platt.slope) < 1.0  # the failures flatten the map, they do not steepen it


def test_a_fit_that_has_not_converged_is_an_error():
    f = _forecasts(50, 10)
    with pytest.raises(RuntimeError, match="fit_platt: Newton's method did not converge in 1 "):
        fit_platt(f, _draw((f - 0.3).clamp(0.01, 0.99), 5, 11), iterations=1)

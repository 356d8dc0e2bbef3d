"""Brier score, Murphy decomposition, ECE and reliability-diagram data."""

import pytest
import torch

from rcvae_torchrl.competency import (
    brier_decomposition,
    brier_score,
    expected_calibration_error,
    reliability_diagram,
)


def test_murphy_identity_for_binned_forecasts():
    forecast = (torch.randint(0, 10, (5000, 3)).float() + 0.5) / 10  # bin centres: binned
    outcome = torch.rand(5000, 3) < forecast**2  # miscalibrated on purpose
    d = brier_decomposition(forecast, outcome, n_bins=10)
    assert torch.allclose(d.within_bin_variance, torch.zeros(3), atol=1e-6)
    assert torch.allclose(d.brier, d.reliability - d.resolution + d.uncertainty, atol=1e-6)
    assert torch.allclose(d.brier, brier_score(forecast, outcome))
    assert (d.reliability > 0.01).all()


def test_generalised_identity_for_continuous_forecasts():
    forecast = torch.rand(2000, 4)
    outcome = torch.rand(2000, 4) < forecast
    d = brier_decomposition(forecast, outcome, n_bins=7)
    rebuilt = (
        d.reliability
        - d.resolution
        + d.uncertainty
        + d.within_bin_variance
        - d.within_bin_covariance
    )
    assert torch.allclose(d.brier, rebuilt, atol=1e-6)


def test_uncertainty_term_is_climatological_variance():
    outcome = torch.tensor([1, 1, 1, 0])
    d = brier_decomposition(torch.full((4,), 0.75), outcome)
    assert d.uncertainty.item() == pytest.approx(0.1875)
    assert d.reliability.item() == pytest.approx(0.0) and d.resolution.item() == pytest.approx(0.0)


def test_ece_of_calibrated_forecasts_is_near_zero():
    forecast = torch.rand(200_000)
    outcome = torch.rand(200_000) < forecast
    assert expected_calibration_error(forecast, outcome).item() < 0.01
    overconfident = (forecast - 0.5) * 1.6 + 0.5
    assert expected_calibration_error(overconfident.clamp(0, 1), outcome).item() > 0.05


def test_ece_norms_on_a_known_case():
    forecast = torch.tensor([0.15, 0.15, 0.85, 0.85])
    outcome = torch.tensor([0, 1, 1, 1])
    # bins 1 and 8: gaps |0.15 - 0.5| = 0.35 and |0.85 - 1| = 0.15, half the cases each
    assert expected_calibration_error(forecast, outcome).item() == pytest.approx(0.25)
    l2 = expected_calibration_error(forecast, outcome, norm="l2").item()
    assert l2 == pytest.approx((0.5 * 0.35**2 + 0.5 * 0.15**2) ** 0.5)
    assert expected_calibration_error(forecast, outcome, norm="max").item() == pytest.approx(0.35)


def test_reliability_diagram_data():
    forecast = torch.tensor([0.05, 0.1, 0.55, 1.0])
    outcome = torch.tensor([False, True, True, True])
    r = reliability_diagram(forecast, outcome, n_bins=4)
    assert r.bin_edges.tolist() == pytest.approx([0, 0.25, 0.5, 0.75, 1.0])
    assert r.counts.tolist() == [2, 0, 1, 1]
    assert r.mean_forecast[0].item() == pytest.approx(0.075)
    assert r.frequency[[0, 2, 3]].tolist() == [0.5, 1.0, 1.0]
    assert torch.isnan(r.frequency[1]) and torch.isnan(r.mean_forecast[1])


@pytest.mark.parametrize("score", [brier_score, expected_calibration_error])
def test_no_cases_is_an_error_not_nan(score):
    with pytest.raises(ValueError, match=r"forecast, outcome: expected at least one case"):
        score(torch.zeros(0), torch.zeros(0, dtype=torch.bool))

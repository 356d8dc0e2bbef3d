"""FaMSeC outcome assessment and the generalised outcome assessment (GOA)."""

import math

import pytest
import torch

from rcvae_torchrl.competency import (
    famsec_outcome_assessment,
    generalized_outcome_assessment,
    ordinal_distribution,
    partial_moments,
)


def test_famsec_reference_cases():
    assert famsec_outcome_assessment(torch.tensor([-5.0, 25.0])).item() == pytest.approx(2 / 3)
    assert famsec_outcome_assessment(torch.tensor([-10.0, 10.0, 10.0, 10.0])).item() == 0.5


def test_famsec_matches_logistic_formula_with_k_and_threshold():
    rewards = torch.tensor([[-3.0, 1.0], [2.0, 4.0], [7.0, -2.0]], dtype=torch.float64)
    upm, lpm = partial_moments(rewards, threshold=1.5)
    assert upm.tolist() == pytest.approx([3.0, 4 / 3])
    assert lpm.tolist() == pytest.approx([1.0, 1.0])
    xo = famsec_outcome_assessment(rewards, threshold=1.5, k=2.0)
    expected = 2 / (1 + torch.exp(-2.0 * torch.log(upm / lpm))) - 1
    assert torch.allclose(xo, expected)


def test_famsec_extremes():
    rewards = torch.tensor([[1.0, -1.0, 0.0], [2.0, -3.0, 0.0]])
    assert famsec_outcome_assessment(rewards).tolist() == [1.0, -1.0, 1.0]


def test_goa_formula_and_extremes():
    p = torch.tensor([[0.1, 0.2, 0.3, 0.4], [0.0, 0.0, 0.5, 0.5], [1.0, 0.0, 0.0, 0.0]])
    goa = generalized_outcome_assessment(p, threshold_bin=2)
    d_lpm = 2 * 0.1 + 1 * 0.2
    d_upm = 1 * 0.3 + 2 * 0.4
    assert goa[0].item() == pytest.approx(2 / (1 + math.exp(-0.3 * d_upm / d_lpm)) - 1, abs=1e-6)
    assert goa[1].item() == 1.0  # D_LPM = 0
    assert goa[2].item() == 0.0  # D_UPM = 0


def test_ordinal_distribution_bins():
    outcomes = torch.tensor([[-1.0, 0.5], [0.2, 0.5], [3.0, 2.5], [0.9, 0.0]])
    p = ordinal_distribution(outcomes, torch.tensor([0.0, 1.0]))
    assert p.tolist() == [[0.25, 0.5, 0.25], [0.0, 0.75, 0.25]]


@pytest.mark.parametrize(
    ("rewards", "k", "expected"),
    [
        ([-50.0, 100.0], 200.0, math.tanh(100 * math.log(2))),  # the powers overflowed: NaN
        ([-1e200, 2e200], 2.0, 0.6),  # 2 / (1 + 1/4) - 1
        ([-1e-200, 2e-200], 2.0, 0.6),  # the powers underflowed to 0
        ([-5.0, 25.0], 1.0, 2 / (1 + 1 / 5) - 1),
    ],
)
def test_famsec_is_finite_for_any_steepness_and_scale(rewards, k, expected):
    got = famsec_outcome_assessment(torch.tensor(rewards, dtype=torch.float64), k=k)
    assert got.item() == pytest.approx(expected, rel=1e-12)

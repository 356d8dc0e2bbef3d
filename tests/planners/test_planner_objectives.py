"""Objective reductions over particles against hand-computed values."""

from __future__ import annotations

import math

import pytest
import torch

from rcvae_torchrl.planners import (
    cvar_return,
    expected_return,
    lexicographic_score,
    quantile_return,
    reduce_particles,
    success_fraction,
)

RETURNS = torch.tensor([[[4.0, 1.0, 3.0, 2.0], [0.0, 10.0, -6.0, 4.0]]])  # [B=1, C=2, P=4]


def test_expected_return():
    torch.testing.assert_close(expected_return(RETURNS), torch.tensor([[2.5, 2.0]]))


@pytest.mark.parametrize(
    ("level", "expected"),
    [(0.0, [1.0, -6.0]), (0.25, [1.75, -1.5]), (0.5, [2.5, 2.0]), (1.0, [4.0, 10.0])],
)
def test_quantile_return(level, expected):
    # linear interpolation at position level * (P - 1) of the sorted particles
    torch.testing.assert_close(quantile_return(RETURNS, level), torch.tensor([expected]))


@pytest.mark.parametrize(
    ("level", "expected"),
    [
        (0.25, [1.0, -6.0]),  # the worst particle
        (0.5, [1.5, -3.0]),  # mean of the worst two
        (0.375, [(1.0 + 0.5 * 2.0) / 1.5, (-6.0 + 0.5 * 0.0) / 1.5]),  # k = 1.5
        (1.0, [2.5, 2.0]),  # the mean
    ],
)
def test_cvar_return(level, expected):
    torch.testing.assert_close(cvar_return(RETURNS, level), torch.tensor([expected]))


def test_success_probability_and_lexicographic_ties():
    success = torch.tensor([[True, False], [True, False], [True, True], [False, False]])
    p = success_fraction(success)
    torch.testing.assert_close(p, torch.tensor([0.5, 0.5, 1.0, 0.0]))
    score = lexicographic_score(p, torch.tensor([3.0, 5.0, -1.0, 100.0]))
    assert score.dtype == torch.float64
    assert score.argsort(descending=True).tolist() == [2, 1, 0, 3]


def test_success_objective_prefers_success_then_return():
    returns = torch.tensor([[-5.0, -5.0], [-1.0, -1.0], [-3.0, -2.0]])
    success = torch.tensor([[True, True], [False, True], [True, True]])
    score = reduce_particles(returns, "success", success=success)
    assert score.argmax().item() == 2  # both succeed; the better return wins the tie
    assert score.argmin().item() == 1  # the best return but only half succeed


@pytest.mark.parametrize("objective", ["mean", "quantile", "cvar", "success"])
def test_nonfinite_particle_poisons_candidate(objective):
    returns = torch.tensor([[1.0, 2.0], [float("nan"), 9.0], [float("inf"), 9.0], [0.0, 0.0]])
    success = torch.ones(4, 2, dtype=torch.bool)
    score = reduce_particles(returns, objective, risk_level=0.5, success=success)
    assert torch.isnan(score[1:3]).all() and torch.isfinite(score[[0, 3]]).all()


def test_risk_averse_objectives_prefer_the_safe_candidate():
    z = torch.linspace(-1.0, 1.0, 20)
    risky = 1.0 + 3.0 * (z - z.mean()) / z.std()
    returns = torch.stack([risky, torch.full((20,), 0.5)])  # [C=2, P=20]
    assert reduce_particles(returns, "mean").argmax().item() == 0
    assert reduce_particles(returns, "quantile", risk_level=0.1).argmax().item() == 1
    assert reduce_particles(returns, "cvar", risk_level=0.1).argmax().item() == 1


def test_reduction_errors():
    with pytest.raises(ValueError, match="objective: expected one of"):
        reduce_particles(RETURNS, "median")
    with pytest.raises(ValueError, match=r"risk_level: expected a float in \(0, 1\]"):
        cvar_return(RETURNS, 0.0)
    with pytest.raises(ValueError, match=r"risk_level: expected a float in \[0, 1\]"):
        quantile_return(RETURNS, 1.5)
    with pytest.raises(ValueError, match="success: expected a"):
        reduce_particles(RETURNS, "success")
    with pytest.raises(
        ValueError, match=r"returns: expected a floating tensor of shape \[\*B, C, P\]"
    ):
        expected_return(torch.ones(3))
    assert math.isclose(float(cvar_return(torch.tensor([[2.0]]), 0.1)), 2.0)

"""``benchmarks/ensemble_members.py``: the Brier skill of k members, and its two ceilings."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import ensemble_members

from rcvae_torchrl.competency import pool_outcomes, validate_forecasts


def _study(seed: int = 0):
    """Forecasts of 5 members around each start's true chance, and real outcomes of a varied
    condition (30 runs per start) pooled with a fixed one (one run per start)."""
    g = torch.Generator().manual_seed(seed)
    chance = torch.rand(60, generator=g)
    fixed = torch.rand(40, generator=g) < 0.8
    varied = torch.rand(60, 30, generator=g) < chance[:, None]
    truth = torch.cat([chance, fixed.double()])  # each start's true chance, in pooled order
    members = (truth[:, None] + 0.2 * torch.randn(100, 5, generator=g).double()).clamp(0, 1)
    outcome, mask = pool_outcomes([varied, fixed[:, None]])
    return members, outcome, mask, truth


def test_the_closed_form_equals_the_mean_over_every_subset_of_k_members():
    members, outcome, mask, _ = _study()
    by_subsets = ensemble_members.subset_skills(members, outcome, mask)
    for k, skill in enumerate(by_subsets, start=1):
        assert ensemble_members.members_skill(members, outcome, mask, k) == pytest.approx(
            skill, abs=1e-12
        )
    limit = ensemble_members.members_skill(members, outcome, mask, float("inf"))
    assert by_subsets == sorted(by_subsets) and limit > by_subsets[-1]


def test_the_true_chance_ceiling_is_the_expected_skill_of_the_chances_below_the_oracle():
    # over many draws of the outcomes, the estimate averages to the skill of forecasting each
    # start's true chance; the in-sample oracle (each start's own rate) is above it
    estimates, truths, oracles = [], [], []
    for seed in range(40):
        _, outcome, mask, chance = _study(seed)
        estimates.append(ensemble_members.true_chance_skill(outcome, mask))
        truths.append(validate_forecasts(chance, outcome, mask)["brier_skill"])
        rates = (outcome & mask).sum(1).double() / mask.sum(1)
        oracles.append(validate_forecasts(rates, outcome, mask)["brier_skill"])
    mean = sum(estimates) / len(estimates)
    assert mean == pytest.approx(sum(truths) / len(truths), abs=0.01)
    assert all(o > e for o, e in zip(oracles, estimates))

"""``benchmarks/ensemble_members.py``: the Brier skill of k members and of infinitely many."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import ensemble_members

from rcvae_torchrl.competency import members_brier_skill, pool_outcomes


def _study(seed: int = 0):
    """Forecasts of 5 members around each start's true chance, and real outcomes of a varied
    condition (30 runs per start) pooled with a fixed one (one run per start)."""
    g = torch.Generator().manual_seed(seed)
    chance = torch.rand(60, generator=g)
    fixed = torch.rand(40, generator=g) < 0.8
    varied = torch.rand(60, 30, generator=g) < chance[:, None]
    truth = torch.cat([chance, fixed.double()])  # each start's true chance, as pooled
    members = (truth[:, None] + 0.2 * torch.randn(100, 5, generator=g).double()).clamp(0, 1)
    outcome, mask = pool_outcomes([varied, fixed[:, None]])
    return members, outcome, mask


def test_the_library_closed_form_equals_the_mean_over_every_subset_of_k_members():
    members, outcome, mask = _study()
    by_subsets = ensemble_members.subset_skills(members, outcome, mask)
    for k, skill in enumerate(by_subsets, start=1):
        assert members_brier_skill(members, outcome, mask, k) == pytest.approx(skill, abs=1e-12)
    limit = members_brier_skill(members, outcome, mask)
    assert by_subsets == sorted(by_subsets) and limit > by_subsets[-1]

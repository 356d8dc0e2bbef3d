"""A start's paragraph says where the members' own P(success) differ beyond the chance of their
imagined samples: the interval beside P covers that chance only."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from rcvae_torchrl.competency import same_chance_p_value
from rcvae_torchrl.competency.report import MEMBERS_ALPHA
from tests.competency.test_assessor import E, S, make_assessor, make_ensemble, make_env
from tests.competency.test_comparison import _agent

N = 10


def test_the_members_test_in_closed_form():
    # two members of 10 samples, 0.8 and 0.2: chi-square 10 * (0.3^2 + 0.3^2) / 0.25 = 7.2, 1 df
    assert same_chance_p_value(torch.tensor([0.8, 0.2]), 10) == pytest.approx(0.0072903, rel=1e-4)
    assert same_chance_p_value(torch.tensor([0.5, 0.5, 0.5]), 10) == pytest.approx(1.0)
    # nothing to test: one member, or every sample alike
    assert same_chance_p_value(torch.tensor([0.3]), 10) == 1.0
    assert same_chance_p_value(torch.tensor([1.0, 1.0]), 10) == 1.0
    assert same_chance_p_value(torch.tensor([0.0, 0.0]), 10) == 1.0


def test_a_sparse_table_is_tested_by_drawing_its_successes():
    """Under 5 expected successes per group the chi-square law does not hold; the p-value is
    the permutation test's. Two groups of 10 with 3 successes, all in one: the chance that 3
    successes fall in one group is 2 C(10, 3) / C(20, 3) = 0.2105 (chi-square: 0.060). One
    success: every placement is as extreme, p = 1 (chi-square: 0.305). Seeded: one number."""
    from math import comb

    drawn = same_chance_p_value(torch.tensor([0.3, 0.0]), 10)
    assert drawn == pytest.approx(2 * comb(10, 3) / comb(20, 3), abs=0.02)
    assert drawn == same_chance_p_value(torch.tensor([0.0, 0.3]), 10)
    assert same_chance_p_value(torch.tensor([0.1, 0.0]), 10) == 1.0
    # failures sparse alike: 3 failures in one group of two
    assert same_chance_p_value(torch.tensor([0.7, 1.0]), 10) == pytest.approx(drawn, abs=0.02)


def _with_members(report, per_member: list[float]):
    """The report's one start with member m succeeding in the first ``per_member[m] * N`` of
    its samples (its success, P and each member's P replaced)."""
    success = torch.zeros(1, E, N, dtype=torch.bool)
    for m, share in enumerate(per_member):
        success[0, m, : round(share * N)] = True
    data = report.data.clone()
    data["competency", "success"] = success
    data["competency", "p_success_member"] = (
        success.double().mean(-1).to(data["competency", "p_success_member"].dtype)
    )
    data["competency", "p_success"] = (
        success.double().mean((-1, -2)).to(data["competency", "p_success"].dtype)
    )
    return dataclasses.replace(report, data=data)


def test_members_that_disagree_beyond_their_samples_chance_are_said_to():
    assessor = make_assessor(make_env(make_ensemble()), samples_per_member=N)
    report = assessor.assess(torch.zeros(1, S), policy=_agent(0.5), seed=0)
    assert E == 3
    apart = _with_members(report, [0.9, 0.5, 0.1])  # chi-square 10 * 0.32 / 0.25 = 12.8, 2 df
    assert same_chance_p_value(apart.data["competency", "p_success_member"][0], N) < MEMBERS_ALPHA
    text = apart.summary(index=0)
    assert (
        "The members disagree on it: their own P(success within 0.3 s) run from 0.10 to 0.90, "
        "more than their imagined samples' chance allows (p = 0.0017): part of the doubt about "
        "this outcome is what the model has not learned (epistemic), which the interval does "
        "not cover."
    ) in text
    assert apart.members_disagree.tolist() == [True]
    assert (
        "In 1 of the 1 start states the members' own P(success within 0.3 s) differ beyond their "
        "imagined samples' chance (each paragraph gives their range): the intervals beside P "
        "leave that doubt out."
    ) in apart.overall()
    # members a sample or two apart: within their chance, nothing said
    close = _with_members(report, [0.6, 0.5, 0.4])
    assert "The members disagree on it" not in close.summary(index=0)
    assert close.members_disagree.tolist() == [False]
    assert "the members' own P" not in close.overall()

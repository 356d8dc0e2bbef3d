"""Two agents on the same tasks: the difference of their chances, its interval, and whether the
world model's members agree on which is better."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from rcvae_torchrl.competency import AgentComparison, compare_agents
from tests.competency.test_assessor import E, S, make_assessor, make_ensemble, make_env

N = 8


class _Constant(nn.Module):
    """The same action everywhere (a weight, so agents differ by their weights)."""

    def __init__(self, value: float) -> None:
        super().__init__()
        self.value = nn.Parameter(torch.full((2,), value))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.value.expand(*observation.shape[:-1], 2)


def _agent(value: float) -> TensorDictModule:
    return TensorDictModule(_Constant(value), in_keys=["observation"], out_keys=["action"])


def _reports():
    assessor = make_assessor(make_env(make_ensemble()), samples_per_member=N)
    starts = torch.randn(2, S, generator=torch.Generator().manual_seed(0)) * 0.1
    return (
        assessor,
        starts,
        [assessor.assess(starts, policy=_agent(v), seed=0) for v in (0.5, -0.5)],
    )


def _with_success(report, success: torch.Tensor):
    """The report with its imagined outcomes replaced: ``success`` bool ``[B, E, N]``."""
    data = report.data.clone()
    data["competency", "success"] = success
    return dataclasses.replace(report, data=data)


def test_the_difference_and_its_interval_in_closed_form():
    _, _, (a, b) = _reports()
    ones = torch.ones(2, E, N, dtype=torch.bool)
    b_success = ones.clone()
    b_success[:, 0] = False  # member 0: B never succeeds
    b_success[:, 1, N // 2 :] = False  # member 1: half the time
    compared = compare_agents(_with_success(a, ones), _with_success(b, b_success))
    assert isinstance(compared, AgentComparison)
    torch.testing.assert_close(compared.difference, torch.full((2,), 0.5, dtype=torch.float64))
    torch.testing.assert_close(
        compared.by_member, torch.tensor([[1.0, 0.5, 0.0]] * 2, dtype=torch.float64)
    )
    # paired differences: 12 ones and 12 zeros of 24: mean 0.5, sample sd sqrt(6 / 23)
    half = 1.959964 * math.sqrt(6 / 23) / math.sqrt(E * N)
    torch.testing.assert_close(compared.low, torch.full((2,), 0.5 - half, dtype=torch.float64))
    torch.testing.assert_close(compared.high, torch.full((2,), 0.5 + half, dtype=torch.float64))
    assert compared.interval == pytest.approx((0.5, 0.5))  # alike starts: no spread over tasks
    assert not compared.members_agree  # member 2 ties: it does not tell them apart
    text = compared.summary()
    assert text.startswith("Over 2 start states: P(success within 0.3 s) 1.00 for A and 0.50")
    assert "A − B = +0.50 (95% interval +0.50 to +0.50)." in text
    assert "The members disagree: 2 of 3 give A the higher chance" in text


def test_members_that_agree_and_an_interval_that_holds_zero():
    _, _, (a, b) = _reports()
    g = torch.Generator().manual_seed(3)
    a_success = torch.rand(2, E, N, generator=g) < torch.tensor([0.9, 0.2])[:, None, None]
    b_success = torch.rand(2, E, N, generator=g) < torch.tensor([0.6, 0.1])[:, None, None]
    compared = compare_agents(
        _with_success(a, a_success),
        _with_success(b, b_success),
        names=(
            "planner",
            "policy",
        ),
    )
    low, high = compared.interval
    d = compared.difference.double()
    half = 1.959964 * float(d.std()) / math.sqrt(2)
    assert (low, high) == pytest.approx((compared.mean - half, compared.mean + half))
    text = compared.summary()
    assert "for planner and" in text and "planner − policy =" in text
    # these draws: every member gives the planner the higher chance, and 0 is outside
    assert compared.members_agree and bool((compared.members > 0).all()) and low > 0
    assert f"All {E} members of the world model agree on the sign (each gives +" in text
    assert "The interval holds 0" not in text
    same = compare_agents(a, a)
    assert not bool(same.difference.any()) and not bool(same.by_member.any())
    said = same.summary()
    assert f"No member of the world model tells them apart (each of the {E} gives 0.00)" in said
    assert said.endswith("The interval holds 0: the imagined chances do not tell the agents apart.")


def test_reports_of_another_task_or_other_starts_are_refused():
    assessor, starts, (a, b) = _reports()
    other_task = make_assessor(make_env(make_ensemble(seed=1)), samples_per_member=N).assess(
        starts, policy=_agent(0.5), seed=0
    )
    with pytest.raises(ValueError, match=r"^b: expected a report of the same task as a"):
        compare_agents(a, other_task)
    moved = assessor.assess(starts + 0.01, policy=_agent(0.5), seed=0)
    with pytest.raises(ValueError, match=r"^b: expected the same start states as a"):
        compare_agents(a, moved)
    fewer = make_assessor(make_env(make_ensemble()), samples_per_member=4).assess(
        starts, policy=_agent(0.5), seed=0
    )
    with pytest.raises(ValueError, match=r"^b: expected as many members and samples per member"):
        compare_agents(a, fewer)
    with pytest.raises(TypeError, match=r"^b: expected a CompetencyReport"):
        compare_agents(a, b.competency)
    with pytest.raises(ValueError, match=r"^confidence: expected"):
        compare_agents(a, b, confidence=1.5)
    with pytest.raises(ValueError, match=r"^names: expected two non-empty names"):
        compare_agents(a, b, names=("A",))


def test_a_report_that_is_not_trustworthy_opens_the_comparison():
    _, _, (a, b) = _reports()
    doubtful = dataclasses.replace(b, model_warning="the world model has not learned b")
    text = compare_agents(a, doubtful, names=("planner", "policy")).summary()
    assert text.startswith("Warning: policy's report: the world model has not learned b. Over 2")
    assert not compare_agents(a, b).summary().startswith("Warning")
    both = compare_agents(doubtful, doubtful).summary()
    assert both.startswith("Warning: both reports: the world model has not learned b. Over 2")

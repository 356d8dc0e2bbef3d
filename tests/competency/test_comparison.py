"""Two agents on the same tasks: the difference of their chances, its interval, and whether the
world model's members agree on which is better."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from rcvae_torchrl.competency import AgentComparison, SuccessBoundary, compare_agents
from rcvae_torchrl.competency.intervals import mean_interval
from rcvae_torchrl.envs import obs_indices
from tests.competency.test_assessor import (
    DT,
    E,
    S,
    T,
    boundary,
    make_assessor,
    make_ensemble,
    make_env,
)

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
    # 24 pairs per start: 12 where both succeed, 12 where A alone does (a margin of the 2x2
    # table is empty: no correlation term); Newcombe's interval from the Wilson intervals of
    # 24 of 24 and 12 of 24
    z, n = 1.959963984540054, E * N

    def wilson(k: int) -> tuple[float, float]:  # of k successes in n
        p = k / n
        centre, half = (p + z * z / (2 * n)), z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
        return (centre - half) / (1 + z * z / n), (centre + half) / (1 + z * z / n)

    (low_a, _), (low_b, high_b) = wilson(n), wilson(n // 2)
    low = 0.5 - math.sqrt((1 - low_a) ** 2 + (high_b - 0.5) ** 2)
    high = 0.5 + (0.5 - low_b)
    torch.testing.assert_close(compared.low, torch.full((2,), low, dtype=torch.float64))
    torch.testing.assert_close(compared.high, torch.full((2,), high, dtype=torch.float64))
    # alike starts: no spread over tasks, but the 48 samples' own chance (their paired interval
    # pooled: 24 pairs both succeed, 24 A alone)
    n = 2 * E * N
    (low_a, _), (low_b, high_b) = wilson(n), wilson(n // 2)
    pooled = (0.5 - math.sqrt((1 - low_a) ** 2 + (high_b - 0.5) ** 2), 1 - low_b)
    assert compared.interval == pytest.approx(pooled)
    # outcomes read back as 0/1 numbers (a record) compare as the flags do
    numbers = compare_agents(_with_success(a, ones.float()), _with_success(b, b_success.float()))
    torch.testing.assert_close(numbers.low, compared.low)
    assert numbers.interval == compared.interval
    # member 0 always, member 1 half the time: beyond chance; member 2 ties
    assert compared.member_verdicts.tolist() == [1, 1, 0]
    assert not compared.members_agree and not compared.members_disagree
    text = compared.summary()
    assert text.startswith("Over 2 start states: P(success within 0.3 s) 1.00 for A and 0.50")
    assert f"A − B = +0.50 (95% interval {pooled[0]:+.2f} to {pooled[1]:+.2f})." in text
    assert (
        "2 of 3 members give A the higher chance beyond their imagined samples' chance, the "
        "others tell the agents apart no better than chance (differences +0.00 to +1.00)."
    ) in text
    assert text.endswith(
        "Neither report's forecasts are checked against real episodes (with_forecast_check): "
        "this is the world model's verdict."
    )
    # members on both sides, each beyond its chance: epistemic doubt
    flipped = b_success.clone()
    flipped[:, 2] = True
    a_success = ones.clone()
    a_success[:, 2] = False
    split = compare_agents(_with_success(a, a_success), _with_success(b, flipped))
    assert split.member_verdicts.tolist() == [1, 1, -1] and split.members_disagree
    assert "The members disagree: 2 of 3 give A the higher chance and 1 give B" in split.summary()


def test_members_that_agree_and_an_interval_that_holds_zero():
    _, _, (a, b) = _reports()
    g = torch.Generator().manual_seed(3)
    a_success = torch.rand(2, E, N, generator=g) < torch.tensor([0.95, 0.9])[:, None, None]
    b_success = torch.rand(2, E, N, generator=g) < torch.tensor([0.1, 0.2])[:, None, None]
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
    # Student's t over the 2 start states (1 degree of freedom: 12.706 at 95 %)
    half = 12.706205 * float(d.std()) / math.sqrt(2)
    assert (low, high) == pytest.approx(
        (max(compared.mean - half, -1.0), min(compared.mean + half, 1.0))
    )
    text = compared.summary()
    assert "for planner and" in text and "planner − policy =" in text
    # these draws: every member gives the planner the higher chance at both starts, but two
    # start states cannot tell the mean over start states from 0: the words say which
    assert compared.members_agree and compared.member_verdicts.tolist() == [1] * E
    assert bool((compared.low > 0).all()) and low <= 0
    assert f"All {E} members of the world model give planner the higher chance (each +" in text
    assert (
        "The interval holds 0: over these start states the imagined chances do not tell the "
        "agents apart (the start states' spread and the imagined samples' chance; more start "
        "states narrow it)."
    ) in text
    # the same two differences over 6 start states: the interval no longer holds 0
    six_low, _ = mean_interval(d.repeat(3), 0.95)
    assert six_low > 0 and six_low == pytest.approx(
        float(d.mean()) - 2.570582 * float(d.repeat(3).std()) / math.sqrt(6)
    )
    same = compare_agents(a, a)
    assert not bool(same.difference.any()) and not bool(same.by_member.any())
    said = same.summary()
    assert "No member of the world model tells them apart beyond its imagined samples' chance" in (
        said
    )
    one = "Both reports are of one agent (the same weights, or a controller's same settings)"
    assert one in said
    assert "The interval holds 0: over these start states the imagined chances do not" in said


def test_reports_of_another_task_or_other_starts_are_refused():
    assessor, starts, (a, b) = _reports()
    other_task = make_assessor(make_env(make_ensemble(seed=1)), samples_per_member=N).assess(
        starts, policy=_agent(0.5), seed=0
    )
    other = r"^b: expected a report of the same task as a, got one of {}"
    with pytest.raises(
        ValueError, match=other.format(r"another world model \(its weights, config or functions\)")
    ):
        compare_agents(a, other_task)
    shorter = make_assessor(
        make_env(make_ensemble()), samples_per_member=N, boundary=boundary(time_limit=T - 2)
    ).assess(starts, policy=_agent(0.5), seed=0)
    with pytest.raises(
        ValueError,
        match=other.format(rf"another deadline \({T - 2} steps there, {T} steps here\);"),
    ):
        compare_agents(a, shorter)
    wider = SuccessBoundary.ball(
        obs_indices("ball"), 0.05, target=obs_indices("target"), time_limit=T, dt=DT
    )
    radius = make_assessor(make_env(make_ensemble()), samples_per_member=N, boundary=wider)
    with pytest.raises(ValueError, match=other.format("another boundary")):
        compare_agents(a, radius.assess(starts, policy=_agent(0.5), seed=0))
    shifted = starts.clone()
    shifted[1] += 0.01
    moved = assessor.assess(shifted, policy=_agent(0.5), seed=0)
    elsewhere = r"^b: expected a report from the forecast's start states, in its order, got 1 of 2"
    with pytest.raises(ValueError, match=elsewhere + r" other ones \(the first: start 1\)"):
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


def test_mean_p_value_is_the_one_sample_t_test_and_its_interval_holds_zero_where_it_passes():
    """The p-value of "mean 0" is Student's one-sample t-test; at level a it is below a
    exactly where mean_interval at 1 - a leaves 0 out; one value: NaN; no spread: 0 or 1."""
    from scipy import stats

    from rcvae_torchrl.competency.intervals import mean_p_value

    values = torch.tensor([0.05, 0.12, -0.02, 0.09, 0.07, 0.11], dtype=torch.float64)
    expected = stats.ttest_1samp(values.numpy(), 0.0).pvalue
    assert mean_p_value(values) == pytest.approx(expected, rel=1e-12)
    for level in (0.05, 0.01, 0.001):
        low, high = mean_interval(values, 1 - level)
        assert (mean_p_value(values) < level) == (low > 0 or high < 0)
    assert math.isnan(mean_p_value(values[:1]))
    assert mean_p_value(torch.zeros(4)) == 1.0 and mean_p_value(torch.full((4,), 0.2)) == 0.0


def test_without_spread_is_one_value_repeated_up_to_rounding():
    """Two or more equal values (float32 rounding of one difference included) have no spread;
    one value, or values 1e-6 apart, are not."""
    from rcvae_torchrl.competency.intervals import without_spread

    repeated = torch.tensor([0.3], dtype=torch.float32) - torch.tensor([0.1] * 5)
    assert without_spread(repeated) and without_spread(torch.zeros(2, dtype=torch.float64))
    assert not without_spread(torch.tensor([0.2]))
    assert not without_spread(torch.tensor([0.2, 0.2 + 1e-6], dtype=torch.float64))

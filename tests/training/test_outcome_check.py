"""OutcomeCheck: forecasts of success against the real success rates of the same starts; its
statistics against closed forms, its verdicts on known truths, its refusals."""

from __future__ import annotations

import json
import math
import warnings

import pytest
import torch
from scipy import stats

from rcvae_torchrl.training import OutcomeCheck

WHAT = "the agent's forecasts from held-out starts"


def _forecast(n: int = 40, seed: int = 0) -> torch.Tensor:
    return torch.rand(n, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def test_real_outcomes_drawn_from_the_forecast_pass_and_a_shifted_truth_is_named():
    forecast = _forecast()
    g = torch.Generator().manual_seed(5)
    drawn = torch.rand(40, 30, generator=g, dtype=torch.float64) < forecast[:, None]
    fair = OutcomeCheck.from_outcomes(forecast, drawn, what=WHAT)
    assert fair.passed and not fair.biased and fair.message() == ""
    assert fair.runs == 30 and fair.starts == 40 and abs(fair.gap) < 0.05
    assert torch.equal(fair.real, drawn.double().mean(1))
    low, high = fair.interval()
    assert low < 0 < high
    shifted = torch.rand(40, 30, generator=g, dtype=torch.float64) < forecast[:, None] + 0.15
    biased = OutcomeCheck.from_outcomes(forecast, shifted, what=WHAT)
    assert biased.biased and not biased.passed and -0.2 < biased.gap < -0.05
    assert biased.message().startswith(
        f"{WHAT} are too pessimistic: from 40 start states they forecast success "
        f"{float(forecast.mean()):.2f} on average where 30 real episodes from each succeeded"
    )
    optimistic = OutcomeCheck.from_outcomes(forecast, drawn & (forecast[:, None] > 0.7))
    assert optimistic.biased and "the forecasts are too optimistic" in optimistic.message()
    # a pass is described too, with its gap and its interval at the test's own level
    assert fair.describe().startswith(f"{WHAT} are unbiased as far as the tests can tell: ")
    assert f"(gap {fair.gap:+.3f}, 99 % interval {low:+.3f} to {high:+.3f}" in fair.describe()
    assert biased.describe() == biased.message()


def test_the_interval_holds_zero_exactly_when_the_check_passes():
    forecast = _forecast(30, seed=1)
    g = torch.Generator().manual_seed(2)
    for shift in torch.linspace(-0.15, 0.15, 13).tolist():
        truth = forecast[:, None] + shift
        check = OutcomeCheck.from_outcomes(
            forecast, torch.rand(30, 10, generator=g, dtype=torch.float64) < truth
        )
        low, high = check.interval()
        assert (low <= 0 <= high) == check.passed, shift
        assert check.interval() == check.interval(1 - check.alpha)


def test_statistics_against_closed_forms():
    forecast = torch.tensor([0.2, 0.5, 0.9, 0.4], dtype=torch.float64)
    real = torch.tensor([0.4, 0.5, 1.0, 0.8], dtype=torch.float64)
    check = OutcomeCheck(forecast, real, runs=10, alpha=0.05, min_starts=4)
    diff = (real - forecast).numpy()
    assert check.gap == pytest.approx(-0.175)
    assert check.p_value == pytest.approx(stats.ttest_1samp(diff, 0.0).pvalue)
    low, high = check.interval(0.9)
    half = stats.t.ppf(0.95, 3) * diff.std(ddof=1) / 2
    assert (low, high) == pytest.approx((-0.175 - half, -0.175 + half))
    assert check.standard_error == pytest.approx(diff.std(ddof=1) / 2)
    # one 0/1 outcome per start: at most about 0.5 / sqrt(n), whatever the rate
    single = torch.rand(400, 1, generator=torch.Generator().manual_seed(3)) < 0.5
    half_half = OutcomeCheck.from_outcomes(torch.full((400,), 0.5, dtype=torch.float64), single)
    assert half_half.standard_error == pytest.approx(0.5 / 20, rel=0.01)
    both = max(check.p_value, check.exact_p_value)  # the t-test and the outcomes' chance
    assert check.measured and check.biased == (both < 0.05)
    # the same difference at every start: certain to the t-test, either way (rounding is not
    # spread); a pass needs the count of real outcomes to rule out a bias of the tolerance too
    same = OutcomeCheck(forecast, forecast.clone(), runs=1, min_starts=4)
    assert same.p_value == 1.0 and not same.precise  # 4 outcomes rule out nothing
    assert OutcomeCheck(forecast, forecast.clone(), runs=100, min_starts=4).passed
    off = OutcomeCheck(forecast, forecast + 0.1, runs=1, min_starts=4)
    assert off.p_value == 0.0  # to the t-test the same difference everywhere is certain
    # but 4 single outcomes cannot show a gap of 0.1: by the outcomes' chance it is no bias
    assert off.exact_p_value > 0.5 and not off.biased
    # and the sentence says why the gap, outside the t-test's interval, is not named a bias
    assert off.describe().startswith(
        f"{off.what} are not named biased: a bias is named only where both tests find the gap "
        "beyond chance, and only the t-test does; the outcomes' exact chance allows it: "
    )
    all_won = torch.ones(40, 1, dtype=torch.bool)  # 40 of 40 where 0.5 was forecast
    sure = OutcomeCheck.from_outcomes(torch.full((40,), 0.5, dtype=torch.float64), all_won)
    assert sure.p_value == 0.0 and sure.exact_p_value < 0.001 and sure.biased
    # too few starts: unmeasured, not passed, and said so
    few = OutcomeCheck(forecast, real, runs=10, min_starts=10, what=WHAT)
    assert not few.measured and not few.passed and not few.biased
    assert (
        few.message()
        == f"{WHAT} are not measured by the outcome check: 4 start states, where it needs 10"
    )
    empty = OutcomeCheck(forecast[:0], real[:0], runs=3)
    assert math.isnan(empty.gap) and math.isnan(empty.p_value) and not empty.passed
    assert math.isnan(empty.standard_error) and all(map(math.isnan, empty.interval()))
    back = OutcomeCheck.from_dict(check.as_dict())
    assert torch.equal(back.forecast, check.forecast) and torch.equal(back.real, check.real)
    assert back.p_value == check.p_value and back.as_dict() == check.as_dict()
    # a record missing an entry (a service's JSON of another version) is named, not a KeyError
    cut = {k: v for k, v in check.as_dict().items() if k != "forecast"}
    with pytest.raises(ValueError, match=r"^values: expected the entries \['forecast', 'real'"):
        OutcomeCheck.from_dict(cut)
    with pytest.raises(
        ValueError, match=r"\(an OutcomeCheck.as_dict\(\)\), missing \['forecast'\]"
    ):
        OutcomeCheck.from_dict(cut)
    with pytest.raises(TypeError, match=r"^values: expected a mapping .*, got list"):
        OutcomeCheck.from_dict([1, 2])
    # a trial's team set the real rates to the forecasts in the saved JSON: a check that had
    # failed read back as passed; its stored gap, which the edit left, now refuses it
    edited = {**check.as_dict(), "real": check.as_dict()["forecast"]}
    with pytest.raises(ValueError, match=r"^values: the stored gap [-+]\d\.\d+ is not the one"):
        OutcomeCheck.from_dict(edited)
    old = {k: v for k, v in edited.items() if k != "gap"}  # a record without its figures
    with pytest.warns(UserWarning, match=r"^values\['passed'\]: the record says False, but"):
        assert OutcomeCheck.from_dict(old).gap == pytest.approx(0.0)  # its verdict said
    single = OutcomeCheck(check.forecast.float(), check.real.float(), runs=check.runs)
    assert OutcomeCheck.from_dict(json.loads(json.dumps(single.as_dict()))).gap == pytest.approx(
        single.gap
    )  # float32 rates read back in float64: their gap's rounding is no edit


def test_records_read_back_name_their_missing_entries():
    """Every record a service keeps beside its model (real outcomes, a novelty check) names
    the entries a record of another version lacks, as a forecast check's does."""
    from rcvae_torchrl.agent import RealOutcomes
    from rcvae_torchrl.training import StateNovelty

    outcomes = RealOutcomes(torch.ones(3, 2, dtype=torch.bool), torch.zeros(3, 2), torch.ones(3, 2))
    kept = {k: v for k, v in outcomes.as_dict().items() if k != "first_step"}
    with pytest.raises(ValueError, match=r"\(a RealOutcomes.as_dict\(\)\), missing \['first_"):
        RealOutcomes.from_dict(kept)
    g = torch.Generator().manual_seed(0)
    novelty = StateNovelty.fit(torch.randn(200, 2, generator=g), torch.randn(50, 2, generator=g))
    kept = {k: v for k, v in novelty.as_dict().items() if k != "level"}
    with pytest.raises(ValueError, match=r"^novelty: expected the entries .* missing \['level'\]"):
        StateNovelty.from_dict(kept)


def test_bad_inputs_are_named():
    forecast, real = _forecast(12), torch.zeros(12, 2, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"real_success: expected a bool tensor \[n=12, R >= 1\]"):
        OutcomeCheck.from_outcomes(forecast, real.float())
    with pytest.raises(ValueError, match=r"real_success: expected a bool tensor .*shape \(11, 2\)"):
        OutcomeCheck.from_outcomes(forecast, real[1:])
    with pytest.raises(ValueError, match="real_success: expected at least one real episode"):
        OutcomeCheck.from_outcomes(forecast, real[:, :0])
    with pytest.raises(ValueError, match=r"forecast: expected probabilities in \[0, 1\]"):
        OutcomeCheck.from_outcomes(forecast + 1, real)
    with pytest.raises(ValueError, match=r"forecast: expected finite values, got \d+ NaN"):
        OutcomeCheck.from_outcomes(torch.where(forecast > 0.9, torch.nan, forecast), real)
    with pytest.raises(ValueError, match=r"forecast: expected shape \[n\]"):
        OutcomeCheck.from_outcomes(forecast[:, None], real)
    with pytest.raises(ValueError, match="alpha"):
        OutcomeCheck.from_outcomes(forecast, real, alpha=0.0)
    with pytest.raises(ValueError, match="min_starts: expected a positive integer"):
        OutcomeCheck.from_outcomes(forecast, real, min_starts=0)


def _drawn(truth: torch.Tensor, runs: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(truth.numel(), runs, generator=g, dtype=torch.float64) < truth[:, None]


def test_forecasts_right_on_average_but_wrong_per_start_are_named():
    forecast = _forecast()
    fair = OutcomeCheck.from_outcomes(forecast, _drawn(forecast, 30, seed=5), what=WHAT)
    assert fair.per_start_measured and not fair.scattered and fair.per_start_p_value > 0.05
    assert fair.excess_error < 0.05
    assert (
        "per start they miss their start's real rate by no more than the chance of 30 episodes "
        "can hide (p = "
    ) in fair.describe()
    # each start's chance mirrored about 1/2: the mean holds, no start's forecast does
    mirrored = OutcomeCheck.from_outcomes(forecast, _drawn(1 - forecast, 30, seed=6), what=WHAT)
    assert abs(mirrored.gap) < 0.1 and mirrored.scattered and mirrored.per_start_p_value < 0.001
    rms = float((2 * forecast - 1).square().mean().sqrt())  # |f - (1 - f)| per start
    assert mirrored.excess_error == pytest.approx(rms, abs=0.05)
    assert "per start they miss their start's real rate by more than the chance of 30 " in (
        mirrored.describe()
    )
    assert mirrored.per_start_p_value == mirrored.per_start_p_value  # seeded: the same again
    low, high = mirrored.excess_error_interval(0.9)
    assert low < mirrored.excess_error < high and low > 0.2  # far from 0: a real miss
    assert (low, high) == mirrored.excess_error_interval(0.9)  # seeded
    assert mirrored.excess_error_interval(0.5)[1] < high  # narrower at a lower confidence
    assert (
        f"by about {mirrored.excess_error:.2f} (root mean square, 90 % interval {low:.2f} to "
        in (mirrored.describe())
    )
    fair_low, fair_high = fair.excess_error_interval()
    assert fair_low == 0.0 and fair_high < low  # right per start: the interval reaches 0
    with pytest.raises(ValueError, match="confidence"):
        fair.excess_error_interval(0.0)


def test_the_per_start_test_holds_its_level_when_the_forecasts_are_the_truth():
    rejected = 0
    for seed in range(40):
        forecast = _forecast(25, seed=100 + seed)
        check = OutcomeCheck.from_outcomes(forecast, _drawn(forecast, 10, seed=seed), alpha=0.1)
        rejected += check.scattered
    assert rejected <= 9  # 4 expected at the 10 % level; 10 or more has a chance below 1 %


def test_settled_starts_do_not_hide_the_misses_of_the_others():
    """20 starts forecast 0.999 that always succeed beside 12 that miss by 0.8 in logit: the
    deviance finds the misses as it does without the settled starts (Pearson's statistic gave
    p = 0.03 to 0.28 here: a settled start's rare failure in the draws buries them), and
    still holds its level where the forecasts are the truth."""
    live = torch.linspace(0.2, 0.8, 12, dtype=torch.float64)
    truth = torch.sigmoid(live.logit() + 0.8 * torch.tensor([1.0, -1.0] * 6, dtype=torch.float64))
    forecast = torch.cat([torch.full((20,), 0.999, dtype=torch.float64), live])
    chance = torch.cat([torch.ones(20, dtype=torch.float64), truth])
    for seed in range(4):
        real = _drawn(chance, 30, seed=seed)
        check = OutcomeCheck.from_outcomes(forecast, real)
        assert check.scattered and check.per_start_p_value < 0.001, seed
        assert OutcomeCheck.from_outcomes(live, real[20:]).per_start_p_value < 0.001
    rejected = 0
    for seed in range(40):
        right = torch.cat([torch.full((20,), 0.999, dtype=torch.float64), _forecast(12, seed)])
        check = OutcomeCheck.from_outcomes(right, _drawn(right, 30, seed=50 + seed), alpha=0.1)
        rejected += check.scattered
    assert rejected <= 9  # 4 expected at the 10 % level; 10 or more has a chance below 1 %


def test_sure_forecasts_that_are_right_pass_for_sure_forecasts_alone():
    """A near-exact model of a deterministic env forecasts almost every start 0 or 1: with 28
    such starts right (one run each) and 2 in doubt, the check passes for sure forecasts alone,
    its bound the exact 1 - 0.01 ** (1 / 28); 19 sure starts bound it above 0.2, unchecked."""
    sure = torch.tensor([1.0, 0.0] * 14, dtype=torch.float64)
    forecast = torch.cat([sure, torch.tensor([0.4, 0.7], dtype=torch.float64)])
    real = torch.cat([sure.bool(), torch.tensor([False, True])])[:, None]
    began = torch.zeros(30, dtype=torch.bool)  # no start settled before the agent acted
    check = OutcomeCheck.from_outcomes(forecast, real, what=WHAT, began_settled=began)
    assert not check.measured and check.sure == 28 and check.sure_misses == 0
    assert check.sure_bound == pytest.approx(1 - 0.01 ** (1 / 28))
    assert check.sure_only and check.passed and check.verdict == "passed"
    assert check.describe() == (
        f"{WHAT} are right where they are sure, as far as the check can tell: 28 of the 30 start "
        "states were forecast 0 or 1 (within 0.001) from a start whose outcome was not yet "
        "settled, and their real runs agreed in every one (at most 15.2% of such forecasts "
        "wrong, 99% bound); the 2 start states in doubt are too few to check forecasts in doubt "
        "(the outcome check needs 10), so it vouches for forecasts of 0 or 1 alone"
    )
    few = OutcomeCheck.from_outcomes(forecast[9:], real[9:], began_settled=began[9:])  # 19 sure
    assert few.sure_bound == pytest.approx(1 - 0.01 ** (1 / 19)) and few.sure_bound > 0.2
    assert not few.sure_only and not few.passed and few.verdict == "not measured"
    # two sure forecasts wrong in 40: bounded by the beta quantile, 0.194 <= 0.2
    sure = torch.tensor([1.0, 0.0] * 20, dtype=torch.float64)
    wrong = sure.bool().clone()
    wrong[:2] = ~wrong[:2]
    missed = OutcomeCheck.from_outcomes(
        sure, wrong[:, None], began_settled=torch.zeros(40, dtype=torch.bool)
    )
    from scipy.stats import beta

    assert missed.sure_misses == 2 and missed.sure_bound == pytest.approx(beta.ppf(0.99, 3, 38))
    assert missed.sure_only and "agreed in all but 2" in missed.describe()
    # starts whose outcome was settled before the agent acted show nothing of the model
    settled = {**check.as_dict(), "began_settled": [True] * 20 + [False] * 10}
    with pytest.warns(UserWarning, match=r"^values\['passed'\]: the record says True"):
        began = OutcomeCheck.from_dict(settled)  # its stored verdict is not the numbers' now
    assert began.sure == 8 and not began.sure_only and not began.passed
    assert torch.equal(OutcomeCheck.from_dict(began.as_dict()).began_settled, began.began_settled)
    with pytest.raises(ValueError, match=r"began_settled: expected a bool tensor \[n=30\]"):
        OutcomeCheck.from_dict({**check.as_dict(), "began_settled": [True] * 29})
    # unknown (bare forecasts): any start may have been settled before the agent acted
    unknown = OutcomeCheck.from_outcomes(forecast, real)
    assert unknown.sure == 28 and not unknown.sure_only and unknown.verdict == "not measured"


def test_the_excess_error_against_its_closed_form():
    from scipy.optimize import brentq
    from scipy.special import expit, logit

    forecast = torch.tensor([0.1, 0.9, 0.5, 0.2] * 3, dtype=torch.float64)
    real = torch.arange(20)[None, :].expand(12, 20) < 5  # every start: 5 of 20
    check = OutcomeCheck.from_outcomes(forecast, real)
    # the shared shift: one logit offset that brings the forecasts' mean to the real 0.25
    z = logit(forecast.numpy())
    offset = brentq(lambda c: expit(z + c).mean() - 0.25, -30, 30, xtol=1e-14)
    shifted = torch.from_numpy(expit(z + offset))
    torch.testing.assert_close(check.shifted(), shifted)
    noise = float((shifted * (1 - shifted)).mean()) / 20
    expected = (float((shifted - 0.25).square().mean()) - noise) ** 0.5
    assert check.excess_error == pytest.approx(expected) and expected > 0.2
    values = check.as_dict()
    assert values["excess_error"] == check.excess_error
    assert values["per_start_p_value"] == check.per_start_p_value


def test_a_shift_all_starts_share_is_a_bias_not_a_scatter():
    scattered, biased = 0, 0
    for seed in range(20):
        forecast = 0.1 + 0.7 * _forecast(20, seed=200 + seed)
        check = OutcomeCheck.from_outcomes(forecast, _drawn(forecast - 0.1, 20, seed=seed))
        scattered += check.scattered
        biased += check.biased
    assert biased >= 18 and scattered <= 2  # 0.2 expected at the 1 % level
    assert "beyond the shift they share" in check.describe()
    assert "trust them on average" not in check.describe()


def test_a_forecast_of_zero_that_successes_contradict_is_a_miss():
    # (10 forecasts of 0: those whose runs all failed are settled, and show nothing)
    forecast = torch.cat([torch.zeros(10), torch.full((10,), 0.5)]).double()
    real = _drawn(forecast, 20, seed=3)
    real[0, :4] = True  # 4 of 20 where 0 was forecast
    check = OutcomeCheck.from_outcomes(forecast, real)
    assert check.scattered and check.per_start_p_value < 0.001
    # one success in 200 episodes forecast at 0: a forecast made from finitely many imagined
    # episodes does not tell a chance of 1/1000 from 0, so that alone is no miss
    real[0, 1:4] = False
    assert not OutcomeCheck.from_outcomes(forecast, real).scattered


def test_the_per_start_test_needs_independent_runs():
    forecast = _forecast(20)
    # a deterministic env: a start's runs are one outcome repeated
    repeated = OutcomeCheck.from_outcomes(forecast, (forecast > 0.5)[:, None].expand(20, 5))
    assert not repeated.per_start_measured and not repeated.scattered
    assert math.isnan(repeated.per_start_p_value) and math.isnan(repeated.excess_error)
    assert repeated.describe().endswith(
        "; per start not tested: each start's 5 episodes agree, so they are taken for one "
        "outcome repeated (a deterministic env's; in a stochastic one, no start's outcome "
        "varied in these runs) and tell no start's chance"
    )
    single = OutcomeCheck.from_outcomes(forecast, _drawn(forecast, 1, seed=0))
    assert not single.per_start_measured and "per start" not in single.describe()


def test_forecasts_that_score_below_a_constant_are_said_to_with_one_outcome_per_start():
    # one outcome per start (a deterministic env): the per-start test cannot run, and 20
    # starts cannot name a constant 0.45 biased where 4 succeeded, but the words say what the
    # episodes show: Brier (4 * 0.55^2 + 16 * 0.45^2) / 20 = 0.2225 against 0.2 * 0.8 = 0.16
    forecast = torch.full((20,), 0.45, dtype=torch.float64)
    real = torch.zeros(20, 1, dtype=torch.bool)
    real[:4] = True
    check = OutcomeCheck.from_outcomes(forecast, real)
    assert not check.per_start_measured and not check.biased and not check.passed
    assert check.brier_skill == pytest.approx(1 - 0.2225 / 0.16)
    said = (
        "; they also scored no better than one forecast of 0.20 for every start (Brier skill "
        "-0.391 over the real episodes): nothing here shows that they tell one start state's "
        "task from another"
    )
    assert check.describe().endswith(said) and check.message() == check.describe()
    # the same outcomes repeated 3 times per start (runs that agree): the same words
    repeated = OutcomeCheck.from_outcomes(forecast, real.expand(20, 3))
    assert repeated.describe().endswith("tell no start's chance" + said)
    # forecasts that tell the starts apart better than one number: nothing added
    apart = forecast.clone()
    apart[:4], apart[4:] = 0.6, 0.15
    better = OutcomeCheck.from_outcomes(apart, real)
    assert better.brier_skill > 0 and "no better than one forecast" not in better.describe()


def test_the_tasks_spread_against_its_closed_form_and_alike_tasks_said():
    from rcvae_torchrl.competency import same_chance_p_value

    # 4 starts of 10 runs at rates 0.2, 0.4, 0.6, 0.8: var 0.0667 (Bessel), noise
    # mean(r(1 - r)) / 9 = 0.2 / 9 = 0.0222: spread sqrt(0.0444)
    real = torch.arange(10)[None, :] < torch.tensor([2, 4, 6, 8])[:, None]
    check = OutcomeCheck.from_outcomes(
        torch.tensor([0.2, 0.4, 0.6, 0.8], dtype=torch.float64), real, min_starts=4
    )
    assert check.task_spread == pytest.approx((0.2 / 3 - 0.2 / 9) ** 0.5)
    assert check.as_dict()["task_spread"] == check.task_spread
    # alike tasks (every start's true chance 0.5, 12 runs each): the rates differ by chance
    # alone, so a per-start miss that is not shown says nothing of telling tasks apart
    truth = torch.full((25,), 0.5, dtype=torch.float64)
    alike = _drawn(truth, 12, seed=4)
    forecast = torch.rand(25, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    check = OutcomeCheck.from_outcomes(0.4 + 0.2 * forecast, alike)
    assert check.per_start_measured and not check.scattered
    assert same_chance_p_value(check.real, 12) >= check.alpha  # the rates alike by the test
    assert check.describe().endswith(
        "; nor do the real rates differ between starts more than the chance of 12 episodes "
        "makes them (no task shown easier or harder than another), so nothing here shows "
        "whether the forecasts tell one task from another"
    )
    # tasks that differ (chances 0.1 to 0.9): not said
    apart = _forecast()
    differ = OutcomeCheck.from_outcomes(apart, _drawn(apart, 12, seed=4))
    assert same_chance_p_value(differ.real, 12) < differ.alpha
    assert "nor do the real rates differ" not in differ.describe()


def test_a_gap_only_the_exact_test_rejects_is_not_called_unbiased():
    # a deterministic env, one run per start: forecasts near 0 at starts that succeed are
    # beyond the outcomes' chance, while the per-start differences' spread keeps the t-test
    forecast = torch.full((30,), 0.5, dtype=torch.float64)
    forecast[:6] = 0.005
    real = torch.zeros(30, 1, dtype=torch.bool)
    real[:6] = True  # the starts forecast 0.005 all succeed
    real[6:19] = True  # the others at about their forecast
    check = OutcomeCheck.from_outcomes(forecast, real)
    assert check.exact_p_value < check.alpha <= check.p_value and not check.biased
    assert check.describe().startswith(
        f"{check.what} are not named biased: a bias is named only where both tests find the "
        "gap beyond chance, and only the outcomes' exact chance does; the t-test over the starts "
        "allows it (its interval holds 0)"
    )


def test_rare_successes_forecast_right_are_no_bias():
    # 12 starts of 8 episodes at a chance of 0.05: the t-test alone called about 4.5 % of such
    # right forecasts biased at its 1 % level (its spread rests on a handful of successes)
    forecast = torch.full((12,), 0.05, dtype=torch.float64)
    g = torch.Generator().manual_seed(1)
    t_test, both = 0, 0
    for _ in range(400):
        check = OutcomeCheck.from_outcomes(forecast, torch.rand(12, 8, generator=g) < 0.05)
        t_test += check.p_value < 0.01
        both += check.biased
    assert t_test >= 10 and both <= 9  # 4 expected at the 1 % level; 10 or more: chance < 1 %
    # forecasts of 0 that 5 successes in 240 episodes contradict: the outcomes' chance rules
    # them out
    zero = torch.zeros(12, dtype=torch.float64)
    won = torch.zeros(12, 20, dtype=torch.bool)
    won[:5, 0] = True
    assert OutcomeCheck.from_outcomes(zero, won).exact_p_value < 0.001


def test_a_check_built_by_hand_names_what_does_not_fit():
    forecast = torch.full((4,), 0.5, dtype=torch.float64)
    with pytest.raises(
        ValueError, match=r"^real: expected one success rate per forecast \(4\), got 3"
    ):
        OutcomeCheck(forecast, forecast[:3], runs=2)
    with pytest.raises(ValueError, match=r"^runs: expected a positive integer, got 0"):
        OutcomeCheck(forecast, forecast, runs=0)
    with pytest.raises(TypeError, match=r"^forecast: expected a torch.Tensor, got list"):
        OutcomeCheck([0.5], forecast[:1], runs=1)


def test_an_exact_p_value_at_the_draws_floor_is_said_to_be_below_it():
    """With 4,000 draws the smallest exact p-value is 2 / 4,001: a gap beyond every draw is
    said to be below it, not to be it."""
    far = OutcomeCheck.from_outcomes(
        torch.full((30,), 0.9, dtype=torch.float64), torch.zeros(30, 10, dtype=torch.bool)
    )
    assert far.exact_p_value == pytest.approx(2 / 4001)
    assert ", < 0.0005 by the outcomes' exact chance, 4,000 draws)" in far.describe()
    outcomes = torch.rand(30, 10, generator=torch.Generator().manual_seed(0)) < 0.5
    near = OutcomeCheck.from_outcomes(torch.full((30,), 0.5, dtype=torch.float64), outcomes)
    assert near.exact_p_value > 0.01
    assert f", {near.exact_p_value:.2g} by the outcomes' exact chance, 4,000 draws)" in (
        near.describe()
    )


def test_a_check_too_wide_to_see_a_bias_that_matters_has_not_passed():
    """A trial's useless forecast: 0.5 for every one of 12 starts, whose single real episodes
    succeeded 2 times in 12. No test names the gap of +0.33 at level 0.01, but its interval
    (about -0.02 to +0.68) hides a bias that large: unchecked, not passed."""
    real = torch.zeros(12, 1, dtype=torch.bool)
    real[:2] = True
    useless = OutcomeCheck.from_outcomes(torch.full((12,), 0.5, dtype=torch.float64), real)
    low, high = useless.interval()
    assert not useless.biased and (high - low) / 2 > 0.2
    assert not useless.precise and not useless.passed and useless.verdict == "too imprecise"
    assert useless.message().startswith(
        "the forecasts are checked too imprecisely to pass: from 12 start "
    )
    assert useless.message().endswith(
        "(gap +0.333, 99 % interval -0.016 to +0.682; p = 0.013 by a t-test over the starts, "
        "0.042 by the outcomes' exact chance, 4,000 draws): no bias is named, but the interval "
        "reaches beyond ±0.2, so a bias that large is not ruled out and the check has not "
        "passed; check more start states; they also scored no better than one forecast of "
        "0.17 for every start (Brier skill -0.800 over the real episodes): nothing here shows "
        "that they tell one start state's task from another"
    )
    # the same forecasts against 200 starts: the interval is narrow, and now the bias shows
    many = torch.zeros(200, 1, dtype=torch.bool)
    many[::6] = True
    wide = OutcomeCheck.from_outcomes(torch.full((200,), 0.5, dtype=torch.float64), many)
    assert wide.biased and wide.verdict == "too optimistic"
    # a tolerance of one's own, kept in the record
    loose = OutcomeCheck.from_outcomes(useless.forecast, real, tolerance=0.7)
    assert loose.passed and OutcomeCheck.from_dict(loose.as_dict()).tolerance == 0.7
    # an interval no wider than ±0.2 that still reaches past +0.2 rules out no bias that large
    # (an acrobot trial: gap +0.134, interval -0.000 to +0.268, passed; 0.26 too optimistic on
    # the starts scored)
    g = torch.Generator().manual_seed(31)
    chance = torch.rand(30, generator=g, dtype=torch.float64) * 0.5
    drawn = torch.rand(30, 5, generator=g, dtype=torch.float64) < chance[:, None]
    shifted = OutcomeCheck.from_outcomes((chance + 0.13).clamp(0, 1), drawn)
    low, high = shifted.interval()
    assert shifted.measured and not shifted.biased
    assert (high - low) / 2 < 0.2 < high and shifted.verdict == "too imprecise"
    with pytest.raises(ValueError, match=r"^tolerance: expected"):
        OutcomeCheck.from_outcomes(useless.forecast, real, tolerance=0.0)


def test_a_report_and_its_real_outcomes_count_successes_within_its_deadline():
    """Real episodes run past the forecast's deadline: a success after it is a failure of the
    task the forecast answers (a trial's mountain car: 1.0 real within 400 steps, 0.68 within
    the forecast's 200)."""
    from types import SimpleNamespace

    from rcvae_torchrl.agent import RealOutcomes

    first = torch.tensor([[3, 30], [12, 40], [5, 8]] * 4)  # [12, 2]
    outcomes = RealOutcomes(torch.ones(12, 2, dtype=torch.bool), first, first + 1)
    forecast = torch.full((12,), 0.5, dtype=torch.float64)
    report = SimpleNamespace(competency={"p_success": forecast}, time_limit=10)
    check = OutcomeCheck.from_outcomes(report, outcomes)
    assert torch.equal(check.real, (first < 10).double().mean(1))
    assert torch.equal(outcomes.within(10).success, first < 10)
    # the tensors alone know no deadline: every success counts
    assert bool((OutcomeCheck.from_outcomes(forecast, outcomes).real == 1.0).all())


def test_start_states_settled_from_the_start_show_nothing():
    """A trial's walker: check starts already lying (forecast 0, every real run failed) passed
    with an interval of zero width, and made a report 0.18 off 'trustworthy'."""
    lying = OutcomeCheck.from_outcomes(
        torch.zeros(40, dtype=torch.float64), torch.zeros(40, 8, dtype=torch.bool)
    )
    assert lying.settled == 40 and not lying.measured and not lying.passed
    assert lying.verdict == "not measured"
    assert lying.describe() == (
        "the forecasts are not measured by the outcome check: 40 of the 40 start states were "
        "forecast 0 or 1 and every real run agreed (forecast 0 where every one failed, or 1 "
        "where every one succeeded), which shows nothing of the forecasts in doubt, and it "
        "needs 10 others; "
        "check start states whose outcome is in doubt"
    )
    # a reacher trial: 13 right forecasts of 0 or 1 from starts not settled before the agent
    # acted, 3 in doubt: too few of either, and the sentence says how many the sure ones need
    forecast = torch.cat([torch.zeros(7), torch.ones(6), torch.full((3,), 0.5)]).double()
    real = torch.cat([torch.zeros(7, 10), torch.ones(6, 10), torch.ones(3, 10)]).bool()
    real[13:, :5] = False
    few = OutcomeCheck.from_outcomes(
        forecast, real, began_settled=torch.zeros(16, dtype=torch.bool)
    )
    assert few.sure == 13 and few.settled == 13 and not few.sure_only and not few.passed
    bound = 1 - 0.01 ** (1 / 13)  # the exact one-sided bound for 0 wrong of 13
    assert few.sure_bound == pytest.approx(bound)
    assert (
        "and it needs 10 others; nor can it vouch for the forecasts of 0 or 1 "
        "alone: none wrong of the 13 made from starts not settled before the agent acted bound "
        f"the share wrong at {bound:.0%} (99% bound), above the tolerance 0.2 (with none wrong it "
        "takes 21 such starts); check start states whose outcome is in doubt"
    ) in few.describe()
    assert 1 - 0.01 ** (1 / 21) <= 0.2 < 1 - 0.01 ** (1 / 20)  # 21, the fewest that pass
    # a forecast of 0.0005 is 0 at the tests' resolution; one of 0.01, or one success, is not
    # settled, and ten such starts beside the settled ones make the check
    forecast = torch.cat([torch.full((30,), 5e-4), torch.full((10,), 0.5)]).double()
    real = torch.zeros(40, 8, dtype=torch.bool)
    real[30:, :4] = True
    mixed = OutcomeCheck.from_outcomes(forecast, real)
    assert mixed.settled == 30 and mixed.measured and mixed.passed
    real[0, 0] = True
    assert OutcomeCheck.from_outcomes(forecast, real).settled == 29


def test_a_bias_is_named_with_fewer_starts_in_doubt_than_a_pass_needs():
    """A pendulum trial: starts forecast 0.95-1.0 whose real runs all failed read 'not
    measured', as if nothing were known. Too few starts keep a check from passing, not from
    naming a bias both tests find."""
    forecast = torch.tensor([0.99, 0.98, 0.95, 0.99, 1.0, 1.0, 0.97, 0.96], dtype=torch.float64)
    wrong = OutcomeCheck.from_outcomes(forecast, torch.zeros(8, 10, dtype=torch.bool))
    assert not wrong.measured and wrong.biased and not wrong.passed
    assert wrong.verdict == "too optimistic"
    assert wrong.describe().startswith(
        "the forecasts are too optimistic: from 8 start states they forecast success 0.98"
    )
    # right forecasts of as few starts name no bias, and stay unchecked
    chance = torch.tensor([0.3, 0.7, 0.5, 0.2, 0.8, 0.6, 0.4, 0.5], dtype=torch.float64)
    real = torch.rand(8, 10, generator=torch.Generator().manual_seed(0)) < chance[:, None]
    right = OutcomeCheck.from_outcomes(chance, real)
    assert not right.biased and right.verdict == "not measured"
    # one start alone names nothing (no t-test), however far off
    assert OutcomeCheck.from_outcomes(
        forecast[:1], torch.zeros(1, 10, dtype=torch.bool)
    ).verdict == ("not measured")


def test_a_check_too_small_to_measure_says_where_its_starts_in_doubt_lean():
    """Among settled starts, the few in doubt that the outcomes' exact chance already finds
    off (the t-test over all starts, diluted by the settled ones, does not)."""
    forecast = torch.tensor([1.0] * 14 + [0.99, 0.98, 0.95, 0.99, 1.0, 1.0], dtype=torch.float64)
    real = torch.cat([torch.ones(14, 10, dtype=torch.bool), torch.zeros(6, 10, dtype=torch.bool)])
    check = OutcomeCheck.from_outcomes(forecast, real)
    assert check.p_value > check.alpha > check.exact_p_value
    assert check.verdict == "not measured" and not check.passed
    assert check.describe().endswith(
        "check start states whose outcome is in doubt; the 6 other starts already lean optimistic: "
        "they forecast 0.98 on average where their real episodes succeeded 0.00 (< 0.0005 by "
        "the outcomes' exact chance; the t-test over all 20 starts, p = 0.0102, does not name it)"
    )


def test_brier_skill_against_one_forecast_for_every_start_on_known_numbers():
    both = torch.tensor([[False] * 4, [True] * 4])
    sharp = OutcomeCheck.from_outcomes(torch.tensor([0.2, 0.8], dtype=torch.float64), both)
    assert sharp.brier_skill == pytest.approx(1 - 0.04 / 0.25)  # B = 0.04, B_0 = 0.25
    flat = OutcomeCheck.from_outcomes(torch.tensor([0.5, 0.5], dtype=torch.float64), both)
    assert flat.brier_skill == pytest.approx(0.0)
    # runs that vary within a start: each run scored, their own spread in both
    half = torch.tensor([[True, False, True, False], [True] * 4])
    rates = OutcomeCheck.from_outcomes(torch.tensor([0.5, 1.0], dtype=torch.float64), half)
    noise = (0.5 * 0.5 + 0.0) / 2
    assert rates.brier_skill == pytest.approx(1 - noise / ((0.25**2 * 2) / 2 + noise))
    alike = OutcomeCheck.from_outcomes(torch.tensor([0.3, 0.6]), torch.ones(2, 4, dtype=torch.bool))
    assert math.isnan(alike.brier_skill)  # every run alike: nothing to tell apart


def test_forecasts_that_do_not_tell_the_starts_apart_do_not_pass():
    """A cart-pole trial: a model after 150 training steps forecast 0.04-0.16 for starts whose
    real rates ran from 0 to 0.88; right on average, the check passed and the report read
    trustworthy. Per start it missed by 0.33 beyond chance, and one number would have done
    better."""
    g = torch.Generator().manual_seed(0)
    chance = torch.cat([torch.zeros(30), torch.full((10,), 0.85)]).double()
    real = torch.rand(40, 8, generator=g, dtype=torch.float64) < chance[:, None]
    flat = (0.21 + 0.04 * torch.randn(40, generator=g, dtype=torch.float64)).clamp(0.02, 0.98)
    check = OutcomeCheck.from_outcomes(flat, real)
    assert check.precise and not check.biased and check.scattered
    assert check.brier_skill <= 0 and check.no_better_than_constant
    assert check.verdict == "no better than a constant" and not check.passed
    assert "they do not tell one start state's task from another" in check.describe()
    assert check.as_dict()["no_better_than_constant"] is True
    # the same starts forecast at their chances pass
    right = OutcomeCheck.from_outcomes(chance.clamp(0.02, 0.98), real)
    assert right.passed and right.brier_skill > 0.5 and not right.no_better_than_constant


def test_a_check_covers_starts_in_the_training_states_units():
    """A quadruped trial: 27 of 78 dimensions of its starts varied by float noise alone
    (1e-15). In their own spread they counted as much as the one that mattered, and starts
    far off in it were called covered; in the training states' spread (the report's novelty
    check) they count as the noise they are. A start moved by 1e-5 in a dimension the check's
    starts never varied is then no longer 'unlike' them either."""
    g = torch.Generator().manual_seed(1)
    own = torch.zeros(60, 28, dtype=torch.float64)
    own[:, 0] = torch.randn(60, generator=g, dtype=torch.float64)  # the dimension that matters
    own[:, 1:] = 1e-15 * torch.randn(60, 27, generator=g, dtype=torch.float64)
    forecast = torch.full((60,), 0.5, dtype=torch.float64)
    real = torch.rand(60, 4, generator=g) < 0.5
    far = own[:15].clone()
    far[:, 0] += 6.0  # six spreads off, where it matters
    unit = torch.ones(28, dtype=torch.float64)  # every dimension spread over 1 in training
    own_units = OutcomeCheck.from_outcomes(forecast, real, start_states=own)
    trained = OutcomeCheck.from_outcomes(forecast, real, start_states=own, state_scale=unit)
    assert float(own_units.covers(far).double().mean()) > 0.5  # diluted: the old failure
    assert not bool(trained.covers(far).any()) and trained.coverage_p_value(far) < 1e-6
    nudged = own[:15].clone()
    nudged[:, 5] += 1e-5
    assert bool(trained.covers(nudged).all())
    assert torch.equal(OutcomeCheck.from_dict(trained.as_dict()).covers(far), trained.covers(far))
    with pytest.raises(ValueError, match=r"state_scale: expected one positive unit per dim"):
        OutcomeCheck.from_outcomes(forecast, real, start_states=own, state_scale=unit[:3])
    with pytest.raises(ValueError, match=r"state_scale: expected positive units, got one <= 0"):
        OutcomeCheck.from_outcomes(forecast, real, start_states=own, state_scale=unit * 0)


def test_a_check_covers_start_states_drawn_like_its_own_and_not_others():
    """A cart-pole trial: a check made on hanging starts made the report of starts with the
    cart moving 4 m/s 'trustworthy', forecasts 0.3 off. A check vouches for starts like its
    own: within the distance 99 % of its starts keep to their nearest other (each dimension in
    their spread), which a start drawn like them exceeds with chance 1 / (n + 1) here."""
    g = torch.Generator().manual_seed(0)
    own = torch.randn(60, 3, generator=g, dtype=torch.float64)
    forecast = torch.full((60,), 0.5, dtype=torch.float64)
    real = torch.rand(60, 10, generator=g) < 0.5
    check = OutcomeCheck.from_outcomes(forecast, real, start_states=own)
    alike = torch.randn(2000, 3, generator=g, dtype=torch.float64)
    share = 1 - float(check.covers(alike).double().mean())
    assert 0.0 < share < 0.05  # at most 1 / 61 in expectation over the check's draws
    assert bool(check.covers(own).all())  # its own starts lie within
    assert check.coverage_p_value(alike[:100]) > 0.01
    moved = alike[:100] + torch.tensor([0.0, 0.0, 4.0], dtype=torch.float64)  # 4 spreads off
    assert float(check.covers(moved).double().mean()) < 0.5  # the largest distance: loose
    assert check.coverage_p_value(moved) < 1e-6
    # a dimension the check's starts never varied: any other value lies outside
    fixed = own.clone()
    fixed[:, 2] = 1.0
    flat = OutcomeCheck.from_outcomes(forecast, real, start_states=fixed)
    assert bool(flat.covers(fixed[:5]).all()) and not bool(flat.covers(fixed[:1] + 0.01).any())
    # kept through as_dict / from_dict; none without start states, or with one
    again = OutcomeCheck.from_dict(check.as_dict())
    assert torch.equal(again.covers(moved), check.covers(moved))
    assert OutcomeCheck.from_outcomes(forecast, real).covers(own) is None
    assert math.isnan(OutcomeCheck.from_outcomes(forecast, real).coverage_p_value(own))
    with pytest.raises(ValueError, match=r"states: expected start states \[m, D=3\] like the"):
        check.covers(own[:, :2])
    with pytest.raises(ValueError, match=r"start_states: expected one start state per forecast"):
        OutcomeCheck.from_outcomes(forecast, real, start_states=own[:5])


def test_forecasts_that_do_not_tell_starts_apart_are_named_so_however_wide_the_interval():
    """A pendulum trial's model with another constraint function: 100 starts of 10 runs, a
    per-start error of 0.65 and a Brier skill of -1.35, got the verdict "too imprecise" and the
    advice to check more start states, which would not mend forecasts that rank the starts
    backwards."""
    easy = torch.arange(40) % 2 == 0
    forecast = torch.where(easy, 0.35, 0.85).double()  # backwards: low where it is easy
    real = torch.zeros(40, 10, dtype=torch.bool)
    real[easy, :9] = True  # 9 of 10 runs from an easy start succeed
    real[~easy, :3] = True  # 3 of 10 from a hard one: right on average (0.6)
    check = OutcomeCheck.from_outcomes(forecast, real)
    low, high = check.interval()
    assert not check.biased and max(-low, high) > check.tolerance  # no bias, a wide interval
    assert check.no_better_than_constant and check.brier_skill < -0.5
    assert check.verdict == "no better than a constant" and not check.passed
    said = check.describe()
    assert said.startswith("the forecasts are no better than a constant: from 40 start states")
    assert "check more start states" not in said
    assert "they do not tell one start state's task from another" in said


def test_a_stored_verdict_that_its_numbers_do_not_give_is_warned_of_not_taken():
    """A trial edited ``"passed": true`` to ``false`` in a check written without a checksum;
    it read back passed, without a word."""
    forecast = torch.full((40,), 0.5, dtype=torch.float64)
    real = torch.rand(40, 20, generator=torch.Generator().manual_seed(0)) < 0.5
    check = OutcomeCheck.from_outcomes(forecast, real)
    record = json.loads(json.dumps(check.as_dict()))
    assert check.passed and record["passed"] is True
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert OutcomeCheck.from_dict(record).passed  # as written: no word
    record["passed"] = False
    said = r"^values\['passed'\]: the record says False, but its forecasts and real rates give True"
    with pytest.warns(UserWarning, match=said):
        assert OutcomeCheck.from_dict(record).passed
    with pytest.raises(TypeError, match=r"^values\['passed'\]: expected True or False, got 'tr"):
        OutcomeCheck.from_dict({**record, "passed": "true"})
    with pytest.raises(TypeError, match=r"^values\['gap'\]: expected a number"):
        OutcomeCheck.from_dict({**record, "gap": "0.5"})


def test_episodes_to_find_is_the_binomial_sample_size():
    """The outcomes a check needs to name a bias: ((z(1 - a/2) + z(power)) * 0.5 / bias)^2,
    rounded up; more for a smaller bias, a stricter level or more power."""
    z = stats.norm.ppf(0.995) + stats.norm.ppf(0.9)
    assert OutcomeCheck.episodes_to_find(0.10) == math.ceil((z * 0.5 / 0.10) ** 2) == 372
    assert OutcomeCheck.episodes_to_find(0.05) == math.ceil((z * 0.5 / 0.05) ** 2)
    assert OutcomeCheck.episodes_to_find(0.10, alpha=0.05) < 372
    assert OutcomeCheck.episodes_to_find(0.10, power=0.99) > 372
    # at power 0.5 and level 0.3173 (z = 0 and 1): exactly (0.5 / bias)^2, not rounded up
    assert OutcomeCheck.episodes_to_find(0.5, alpha=2 * stats.norm.sf(1.0), power=0.5) == 1


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"bias": 0.0}, r"^bias: expected a float in \(0, 1\], got 0.0"),
        ({"bias": 1.5}, r"^bias: expected a float in \(0, 1\], got 1.5"),
        ({"bias": 0.1, "alpha": 1.0}, r"^alpha: expected a float in \(0, 1\), got 1.0"),
        ({"bias": 0.1, "power": 0.0}, r"^power: expected a float in \(0, 1\], got 0.0"),
        ({"bias": 0.1, "power": 1.0}, r"^power: expected a float in \(0, 1\), got 1.0"),
    ],
)
def test_episodes_to_find_names_a_bad_argument(kwargs, match):
    bias = kwargs.pop("bias")
    with pytest.raises(ValueError, match=match):
        OutcomeCheck.episodes_to_find(bias, **kwargs)


def test_a_check_of_that_size_names_the_bias_it_was_sized_for():
    """Forecasts 0.10 too optimistic, one outcome per start (a deterministic env): a check of
    episodes_to_find(0.10) starts names them in at least 85 of 100 draws (power 0.9 at a
    success rate of 0.5; 0.92 in 400 draws of this case, where both tests must find the gap);
    one of 100 starts in at most half."""
    n = OutcomeCheck.episodes_to_find(0.10)
    g = torch.Generator().manual_seed(3)
    named = {n: 0, 100: 0}
    for _ in range(100):
        for size in named:
            chance = 0.2 + 0.6 * torch.rand(size, generator=g, dtype=torch.float64)
            outcome = torch.rand(size, 1, generator=g, dtype=torch.float64) < chance[:, None]
            check = OutcomeCheck.from_outcomes(chance + 0.10, outcome)
            named[size] += check.biased and check.gap > 0
    assert named[n] >= 85, named
    assert named[100] <= 50, named


def test_a_check_of_rates_outside_zero_to_one_or_of_a_bad_level_is_refused():
    forecast, real = torch.full((12,), 0.5), torch.full((12,), 0.5)
    bad = [
        (
            {"forecast": torch.full((12,), math.nan)},
            ValueError,
            r"forecast: expected values in \[0, 1\]",
        ),
        ({"real": torch.full((12,), 7.0)}, ValueError, r"real: expected values in \[0, 1\]"),
        ({"alpha": 1.0}, ValueError, r"alpha: expected a level in \(0, 1\), got 1.0"),
        ({"alpha": "0.1"}, TypeError, r"alpha: expected a level in \(0, 1\)"),
        ({"min_starts": -3}, ValueError, "min_starts: expected a positive integer"),
        ({"task": 5}, TypeError, "task: expected a str or None, got 5"),
    ]
    for change, error, said in bad:
        args = {"forecast": forecast, "real": real, "runs": 3, **change}
        with pytest.raises(error, match=said):
            OutcomeCheck(args.pop("forecast"), args.pop("real"), **args)
    record = OutcomeCheck(forecast, real, runs=3).as_dict()
    with pytest.raises(TypeError, match=r"values\['runs'\]: expected an integer, got 2.7"):
        OutcomeCheck.from_dict({**record, "runs": 2.7})
    nan = {**record, "forecast": [math.nan, *record["forecast"][1:]]}
    with pytest.raises(ValueError, match=r"forecast: expected values in \[0, 1\]"):
        OutcomeCheck.from_dict(nan)


def test_the_interval_stays_within_the_gaps_range_and_a_gap_without_spread_is_named():
    """Three starts forecast 0 that each succeeded once: every gap is -1, no spread to test.
    The interval stays within [-1, 1], as the validation's own bias interval; the message says
    there was nothing for a t-test (it read 'p = 0 by a t-test over the starts')."""
    check = OutcomeCheck.from_outcomes(
        torch.zeros(3, dtype=torch.float64), torch.ones(3, 1, dtype=torch.bool)
    )
    assert check.interval() == (-1.0, -1.0)
    assert "p = 0: every start's gap the same, no spread for a t-test" in check.message()
    real = torch.ones(10, 1, dtype=torch.bool)
    real[0] = False
    wide = OutcomeCheck.from_outcomes(torch.full((10,), 0.05, dtype=torch.float64), real)
    diff = wide.forecast - wide.real
    half = float(stats.t.ppf(0.995, 9) * diff.std() / math.sqrt(10))
    assert float(diff.mean()) - half < -1.0  # the t interval reaches below -1: clipped there
    assert wide.interval() == (-1.0, pytest.approx(float(diff.mean()) + half, abs=1e-12))
    assert "by a t-test over the starts" in wide.message()


def test_outcomes_that_all_agree_do_not_make_a_check_precise_by_their_count_alone():
    """Ten starts forecast 0.02 whose ten runs all failed: every gap is +0.02, so the t interval
    has no width, but ten failures leave a real rate up to about 0.4 (a chance of 0.22 fails ten
    runs in 8 % of draws): too imprecise to pass, and the message says why."""
    check = OutcomeCheck.from_outcomes(
        torch.full((10,), 0.02, dtype=torch.float64), torch.zeros(10, 1, dtype=torch.bool)
    )
    assert check.interval() == pytest.approx((0.02, 0.02))
    assert not check.precise and not check.passed and check.verdict == "too imprecise"
    assert "the count of real successes leaves the gap anywhere in -0.379 to +0.020" in (
        check.message()
    )
    g = torch.Generator().manual_seed(0)
    chance = torch.rand(400, generator=g, dtype=torch.float64) * 0.9 + 0.05
    runs = torch.rand(400, 1, generator=g, dtype=torch.float64) < chance[:, None]
    calibrated = OutcomeCheck.from_outcomes(chance, runs)
    assert calibrated.precise and calibrated.passed  # enough outcomes: the count rules it out

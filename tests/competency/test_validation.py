"""Forecasts against real episodes: scores checked against closed forms and brute force."""

from __future__ import annotations

import itertools
import math

import pytest
import scipy.stats
import torch

from rcvae_torchrl.competency import (
    auroc,
    brier_score,
    brier_skill_score,
    chance_brier_skill,
    crps_samples,
    episode_brier,
    expected_calibration_error,
    members_brier_skill,
    per_start_rates,
    pool_outcomes,
    rank_correlation,
    rate_reliability,
    reliability_diagram,
    start_reliability,
    validate_forecasts,
)


def _toy(seed: int = 0, starts: int = 40, runs: int = 30):
    g = torch.Generator().manual_seed(seed)
    truth = torch.rand(starts, generator=g)
    outcome = torch.rand(starts, runs, generator=g) < truth[:, None]
    forecast = (truth + 0.05 * torch.randn(starts, generator=g)).clamp(0, 1)
    return forecast, outcome, truth


def test_rank_correlation_matches_scipy_with_ties():
    g = torch.Generator().manual_seed(1)
    x = torch.randint(0, 5, (50,), generator=g).double()
    y = x + torch.randint(0, 3, (50,), generator=g).double()
    expected = scipy.stats.spearmanr(x.numpy(), y.numpy()).statistic
    assert float(rank_correlation(x, y)) == pytest.approx(expected, abs=1e-12)
    assert math.isnan(float(rank_correlation(torch.ones(4), torch.arange(4.0))))


def test_auroc_equals_the_pairwise_count():
    g = torch.Generator().manual_seed(2)
    score = torch.randint(0, 4, (60,), generator=g).double() / 3
    label = torch.rand(60, generator=g) < 0.5
    pos, neg = score[label], score[~label]
    pairs = (pos[:, None] > neg[None, :]).double() + 0.5 * (pos[:, None] == neg[None, :]).double()
    assert float(auroc(score, label)) == pytest.approx(float(pairs.mean()), abs=1e-12)
    assert math.isnan(float(auroc(score, torch.ones(60, dtype=torch.bool))))
    with pytest.raises(TypeError, match="label: expected a bool tensor"):
        auroc(score, label.float())


def test_episode_brier_and_brier_score_with_repeated_runs_agree():
    forecast, outcome, _ = _toy()
    expected = ((forecast[:, None] - outcome.double()) ** 2).mean()
    assert float(episode_brier(forecast, outcome)) == pytest.approx(float(expected))
    assert float(brier_score(forecast, outcome)) == pytest.approx(float(expected), rel=1e-6)
    ece = expected_calibration_error(forecast, outcome, n_bins=5)
    flat = expected_calibration_error(
        forecast[:, None].expand_as(outcome).reshape(-1), outcome.reshape(-1), n_bins=5
    )
    assert float(ece) == pytest.approx(float(flat))
    diagram = reliability_diagram(forecast, outcome, n_bins=5)
    assert int(diagram.counts.sum()) == outcome.numel()


def test_mask_drops_runs_that_do_not_exist():
    forecast = torch.tensor([0.5, 1.0])
    outcome = torch.tensor([[True, False, True], [True, True, False]])
    mask = torch.tensor([[True, True, False], [True, True, False]])
    assert float(episode_brier(forecast, outcome, mask)) == pytest.approx(0.125)
    rates, runs = per_start_rates(outcome, mask)
    assert rates.tolist() == [0.5, 1.0] and runs.tolist() == [2, 2]
    with pytest.raises(ValueError, match="mask: expected at least one run per start state"):
        episode_brier(forecast, outcome, torch.zeros_like(mask))


def test_pooled_outcomes_score_every_episode_once():
    # three sets of starts with 1, 4 and 2 runs: the pooled Brier is the mean over the 11
    # episodes of (forecast - outcome)^2, whatever the padding holds
    g = torch.Generator().manual_seed(3)
    parts = [torch.rand(b, r, generator=g) < 0.5 for b, r in ((3, 1), (1, 4), (2, 2))]
    forecasts = [torch.rand(p.shape[0], generator=g) for p in parts]
    outcome, mask = pool_outcomes(parts)
    assert outcome.shape == (6, 4) and mask.sum(1).tolist() == [1, 1, 1, 4, 2, 2]
    assert torch.equal(outcome[mask], torch.cat([p.reshape(-1) for p in parts]))
    squares = [((f[:, None] - p.double()) ** 2).reshape(-1) for f, p in zip(forecasts, parts)]
    expected = torch.cat(squares).mean()
    pooled = episode_brier(torch.cat(forecasts), outcome, mask)
    assert float(pooled) == pytest.approx(float(expected), abs=1e-12)


@pytest.mark.parametrize(
    ("parts", "error", "match"),
    [
        ([], ValueError, "parts: expected at least one"),
        ([torch.ones(3, dtype=torch.bool)], ValueError, r"parts\[0\]"),
        ([torch.ones(2, 1, dtype=torch.bool), torch.ones(2, 3)], TypeError, r"parts\[1\]: .*bool"),
        ([torch.ones(2, 0, dtype=torch.bool)], ValueError, "at least one run per start"),
    ],
)
def test_pool_outcomes_names_the_bad_part(parts, error, match):
    with pytest.raises(error, match=match):
        pool_outcomes(parts)


def test_the_true_chance_skill_is_unbiased_and_below_the_in_sample_oracle():
    # starts of known chances run 30 times, pooled with starts of a fixed outcome run once:
    # over many draws of the outcomes the estimate averages to the skill of forecasting the
    # true chances, and in every draw the oracle of the observed rates scores above it
    estimates, truths = [], []
    for seed in range(40):
        g = torch.Generator().manual_seed(seed)
        chance = torch.rand(60, generator=g)
        fixed = torch.rand(40, 1, generator=g) < 0.8
        varied = torch.rand(60, 30, generator=g) < chance[:, None]
        outcome, mask = pool_outcomes([varied, fixed])
        truth = torch.cat([chance, fixed[:, 0].double()])
        estimates.append(chance_brier_skill(outcome, mask))
        truths.append(validate_forecasts(truth, outcome, mask)["brier_skill"])
        rates, _ = per_start_rates(outcome, mask)
        assert validate_forecasts(rates, outcome, mask)["brier_skill"] > estimates[-1]
    assert sum(estimates) / 40 == pytest.approx(sum(truths) / 40, abs=0.01)
    with pytest.raises(TypeError, match="outcome: expected bool"):
        chance_brier_skill(outcome.float())


def test_members_brier_skill_by_subsets_and_its_limit():
    # every subset of k of 4 members, their mean forecast scored: the closed form's value at k
    g = torch.Generator().manual_seed(4)
    outcome = torch.rand(30, 6, generator=g) < 0.6
    members = torch.rand(30, 4, generator=g, dtype=torch.float64)
    for k in range(1, 5):
        subsets = list(itertools.combinations(range(4), k))
        briers = [episode_brier(members[:, list(s)].mean(1), outcome) for s in subsets]
        reference = episode_brier(torch.full((30,), outcome.double().mean().item()), outcome)
        expected = 1 - float(sum(briers) / len(briers)) / float(reference)
        assert members_brier_skill(members, outcome, members=k) == pytest.approx(expected)
    # members that agree have nothing to average away: their limit is their skill
    same = members[:, :1].expand(30, 3)
    assert members_brier_skill(same, outcome) == pytest.approx(
        members_brier_skill(same, outcome, members=1)
    )


@pytest.mark.parametrize(
    ("members", "k", "match"),
    [
        (torch.rand(5, 1), math.inf, r"member_forecasts: .*at least 2 members"),
        (torch.rand(5), math.inf, r"member_forecasts"),
        (torch.rand(5, 2) + 1.0, math.inf, r"member_forecasts"),
        (torch.rand(5, 2), 0, r"members: expected a number of members >= 1"),
    ],
)
def test_members_brier_skill_names_the_bad_argument(members, k, match):
    with pytest.raises(ValueError, match=match):
        members_brier_skill(members, torch.ones(5, 2, dtype=torch.bool), members=k)


def test_rate_reliability_against_the_binomial_closed_form():
    """True chances p_b, R runs each: the rates' reliability is var(p) / (var(p) + E[p(1-p)]/R)
    (the share of their variance that is the starts' own); more runs, more reliable."""
    g = torch.Generator().manual_seed(0)
    p = torch.rand(4000, generator=g, dtype=torch.float64) * 0.6 + 0.2
    for runs in (10, 30, 90):
        outcome = torch.rand(4000, runs, generator=g, dtype=torch.float64) < p[:, None]
        truth = p.var() / (p.var() + (p * (1 - p)).mean() / runs)
        assert rate_reliability(outcome) == pytest.approx(float(truth), abs=0.03)
    # a mask: the runs that exist are dealt into halves, the others left out
    outcome = torch.rand(4000, 40, generator=g, dtype=torch.float64) < p[:, None]
    mask = torch.ones_like(outcome)
    mask[:, 30:] = False
    noisy = outcome.clone()
    noisy[:, 30:] = ~noisy[:, 30:]  # what the mask hides cannot move the result
    assert rate_reliability(noisy, mask) == rate_reliability(outcome[:, :30])
    # one run per start: nothing to split
    assert math.isnan(rate_reliability(outcome[:, :1]))
    with pytest.raises(TypeError, match="outcome: expected bool outcomes"):
        rate_reliability(outcome.double())


def test_brier_skill_score():
    assert float(brier_skill_score(0.05, 0.25)) == pytest.approx(0.8)
    assert float(brier_skill_score(0.25, 0.25)) == 0.0
    assert math.isnan(float(brier_skill_score(0.0, 0.0)))


def test_crps_of_samples_approaches_the_gaussian_closed_form():
    g = torch.Generator().manual_seed(3)
    samples = torch.randn(4000, generator=g, dtype=torch.float64)
    y = torch.tensor([0.0, 1.0, -2.0], dtype=torch.float64)
    normal = torch.distributions.Normal(0.0, 1.0)
    closed = y * (2 * normal.cdf(y) - 1) + 2 * normal.log_prob(y).exp() - 1 / math.sqrt(math.pi)
    torch.testing.assert_close(crps_samples(samples, y), closed, atol=0.02, rtol=0)
    assert crps_samples(torch.tensor([2.0]), torch.tensor([2.0])).item() == 0.0


def test_start_reliability_bins_and_intervals():
    forecast = torch.tensor([0.1, 0.15, 0.9, 0.95])
    outcome = torch.tensor([[False] * 9 + [True], [False] * 10, [True] * 10, [True] * 9 + [False]])
    r = start_reliability(forecast, outcome, n_bins=2)
    assert r.starts.tolist() == [2, 2] and r.episodes.tolist() == [20, 20]
    assert r.frequency.tolist() == [0.05, 0.95]
    assert bool((r.low <= r.frequency).all() and (r.frequency <= r.high).all())
    assert float(r.high[0] - r.low[0]) < 0.3


def test_validate_forecasts_on_informative_and_uninformative_forecasts():
    forecast, outcome, _ = _toy()
    good = validate_forecasts(forecast, outcome)
    # uniform true rates leave 1 - (1/6)/(1/4) = 1/3 of skill even to the truth itself
    assert good["spearman"] > 0.8 and good["auroc"] > 0.75 and good["brier_skill"] > 0.25
    assert good["per_start_mae"] < 0.15 and good["episodes"] == outcome.numel()
    assert good["real_rate_span"] > 0.5
    constant = torch.full_like(forecast, float(outcome.double().mean()))
    flat = validate_forecasts(constant, outcome)
    assert abs(flat["brier_skill"]) < 1e-9 and math.isnan(flat["spearman"])
    assert flat["auroc"] == 0.5 and flat["gap"] < 1e-6
    with pytest.raises(TypeError, match="outcome: expected bool outcomes"):
        validate_forecasts(forecast, outcome.float())
    with pytest.raises(ValueError, match=r"outcome: expected one row of runs per forecast"):
        validate_forecasts(forecast, outcome[:3])


def test_the_bias_interval_is_student_s_t_over_the_start_states():
    """Errors 0.1, 0.1, 0.35, -0.15: mean 0.1, sd sqrt(0.125 / 3), t(0.975, 3) = 3.182446."""
    forecast = torch.full((4,), 0.6, dtype=torch.float64)
    hits = torch.tensor([2, 2, 1, 3])
    outcome = torch.arange(4)[None, :] < hits[:, None]  # [4, 4]: rates 0.5, 0.5, 0.25, 0.75
    scores = validate_forecasts(forecast, outcome)
    half = 3.182446 * math.sqrt(0.125 / 3) / 2
    assert scores["bias"] == pytest.approx(0.1)
    assert scores["bias_low"] == pytest.approx(0.1 - half, abs=1e-6)
    assert scores["bias_high"] == pytest.approx(0.1 + half, abs=1e-6)
    assert scores["gap"] == pytest.approx(abs(scores["bias"]))  # equal runs: the same mean


def test_success_on_grid_is_first_hitting_within_the_deadline():
    from rcvae_torchrl.competency import success_on_grid

    g = torch.Generator().manual_seed(4)
    distance = torch.rand(6, 30, generator=g)
    distance[0, 10:] = float("nan")  # an episode that ended early without success
    radii, deadlines = torch.tensor([0.05, 0.2, 0.5]), torch.tensor([1, 7, 30])
    grid = success_on_grid(distance, radii, deadlines)
    assert grid.shape == (6, 3, 3)
    for b in range(6):
        for i, r in enumerate(radii):
            for j, d in enumerate(deadlines):
                expected = bool((distance[b, :d] <= r).any())
                assert bool(grid[b, i, j]) == expected
    assert bool((grid[:, :, 1:] >= grid[:, :, :-1]).all())  # later deadlines: never fewer
    assert bool((grid[:, 1:] >= grid[:, :-1]).all())  # larger radii: never fewer
    with pytest.raises(ValueError, match=r"deadlines: expected steps in \[1, T=30\]"):
        success_on_grid(distance, radii, torch.tensor([0, 31]))


def test_time_to_success_crps_beats_climatology_only_when_informative():
    from rcvae_torchrl.competency import time_to_success_scores

    g = torch.Generator().manual_seed(5)
    centre = torch.arange(10.0) * 10  # starts differ in how long they take
    real = centre[:, None] + torch.randn(10, 20, generator=g)
    good = centre[:, None] + torch.randn(10, 200, generator=g)
    scores = time_to_success_scores(good, real)
    assert scores["crps"] < 0.2 * scores["crps_climatology"] and scores["skill"] > 0.8
    blind = real.reshape(-1)[torch.randperm(200, generator=g)].reshape(10, 20)
    assert time_to_success_scores(blind, real)["skill"] < 0.1


def test_forecasts_that_rank_the_outcomes_backwards_are_named():
    """A cart-pole trial counted its real successes with a survival boundary's failure
    predicate: AUROC 0.027, read as a forecast "too optimistic" by 0.59, with nothing said of
    the swapped outcomes. Below an AUROC of 0.2 over 10 starts or more, the scores warn; a weak
    forecast (AUROC near 0.5) and fewer starts do not."""
    import warnings

    forecast = torch.linspace(0.05, 0.95, 12)
    runs = torch.arange(10)[None, :] < torch.round(forecast * 10)[:, None]  # the forecast's rates
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert validate_forecasts(forecast, runs)["auroc"] > 0.8
        validate_forecasts(forecast.flip(0)[:9], runs[:9])  # backwards, but 9 starts
        validate_forecasts(torch.full((12,), 0.5), runs)  # tells nothing: AUROC 0.5
    with pytest.warns(UserWarning, match=r"^outcome: the forecasts rank the real outcomes backw"):
        assert validate_forecasts(forecast, ~runs)["auroc"] < 0.2


def test_the_ece_and_the_start_reliability_weigh_each_episode_alike():
    """Starts with different numbers of runs: a bin's mean forecast counts a start once per
    episode, as its frequency does, so the validation's ECE is the episodes' own
    (it averaged the forecasts per start: 0.105 here against the episodes' 0.029)."""
    f = torch.tensor([0.0, 0.19], dtype=torch.float64)
    outcome = torch.zeros(2, 9, dtype=torch.bool)
    mask = torch.zeros_like(outcome)
    mask[0, 0], mask[1, :] = True, True
    outcome[1, :2] = True
    scores = validate_forecasts(f, outcome, mask, n_bins=5)
    episodes = f[:, None].expand_as(outcome)[mask]
    want = expected_calibration_error(episodes, outcome[mask].to(torch.float64), n_bins=5)
    assert scores["ece"] == pytest.approx(float(want), abs=1e-7)
    diagram = start_reliability(f, outcome, mask, n_bins=5)
    assert float(diagram.mean_forecast[0]) == pytest.approx(0.19 * 9 / 10, abs=1e-12)
    assert int(diagram.starts[0]) == 2 and int(diagram.episodes[0]) == 10

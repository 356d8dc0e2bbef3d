"""The study's per-task validation on constructed forecasts and outcomes with known answers."""

from __future__ import annotations

import math

import pytest
import torch
from scipy import stats

from rcvae_torchrl.competency import PlattMap
from recipes.pusher_competency.trust import (
    THROUGH_MAP,
    competency_surfaces,
    trust_checks,
    validation,
    validation_figures,
)

CONDITIONS = ("deterministic", "stochastic", "out-of-distribution")


def _case(perfect: bool):
    """Start b of a condition reaches the goal (distance 0) at step 2b in every imagined sample
    and real run, or never (a far start); a forecast that is ``perfect`` or constant."""
    forecasts, truths = {}, {}
    for runs, c in zip((1, 30, 1), CONDITIONS):
        b, t = 8, 20
        reach = torch.arange(b) % 2 == 0  # even starts succeed
        first = torch.where(reach, 2 * torch.arange(b), torch.full((b,), t))
        steps = torch.arange(t)
        d = (steps[None] < first[:, None]).float()  # 1 m until the first success, then 0
        p = reach.float() if perfect else torch.full((b,), 0.5)
        forecasts[c] = {"p_success": p, "ball_to_target": d[:, None].expand(b, 10, t).clone()}
        truths[c] = {
            "success": reach[:, None].expand(b, runs).clone(),
            "first_step": first[:, None].expand(b, runs).clone(),
            "trace": d[:, None].expand(b, runs, t).clone(),
        }
    return forecasts, truths


def test_a_perfect_forecast_scores_perfectly():
    forecasts, truths = _case(perfect=True)
    scores = validation(forecasts, truths, radius=0.03)
    for c in CONDITIONS:
        s = scores[c]
        assert s["gap"] == 0 and s["per_start_mae"] == 0 and s["brier"] == 0
        assert s["spearman"] == pytest.approx(1.0) and s["auroc"] == 1.0
        assert s["bss_overall"] == 1.0 and s["brier_skill"] == 1.0
        assert s["tts_crps"] == 0 and s["tts_crps_climatology"] > 0 and s["tts_skill"] == 1.0
        assert s["gap_signed"] == s["gap_se"] == s["gap_low"] == s["gap_high"] == 0
    assert scores["overall"]["episodes"] == 8 + 8 * 30 + 8
    # each stochastic start succeeds in all its runs or in none: the rates are noiseless, a
    # Spearman of 1 is in reach; one run per start has no reliability to split
    assert scores["stochastic"]["oracle_spearman"] == 1.0
    assert math.isnan(scores["deterministic"]["oracle_spearman"])
    assert "oracle_spearman" not in scores["overall"]
    assert scores["overall"]["bss_tasks"] == 1.0 and scores["overall"]["oracle_auroc"] == 1.0
    surfaces = competency_surfaces(forecasts, truths, [0.03, 0.5], [1, 5, 20])
    for c in CONDITIONS:
        assert surfaces[c]["max_gap"] == 0 and surfaces[c]["per_start_mae"] == 0
        # even starts succeed, start b at step 2b: before step 5, starts 0 and 2 (of 8)
        torch.testing.assert_close(surfaces[c]["real"], torch.tensor([[1 / 8, 2 / 8, 4 / 8]] * 2))
    checks = trust_checks(scores, surfaces)
    failed = [name for name, c in checks.items() if not c["met"]]
    # the constructed out-of-distribution condition succeeds in half its episodes: in range
    assert failed == [], failed
    diagrams = validation_figures(forecasts, truths)
    assert set(diagrams) == {*CONDITIONS, "all"}
    assert int(diagrams["all"].episodes.sum()) == 8 + 240 + 8


def test_a_constant_forecast_has_no_skill_and_fails_the_checks():
    forecasts, truths = _case(perfect=False)
    scores = validation(forecasts, truths, radius=0.03)
    for c in CONDITIONS:
        assert scores[c]["brier_skill"] == pytest.approx(0.0, abs=1e-12)  # base rate is 0.5
        assert scores[c]["auroc"] == 0.5 and scores[c]["oracle_brier_skill"] == 1.0
        # per start 0.5 - 1 or 0.5 - 0: no bias, an interval from the spread over the 8 starts
        se = (8 * 0.25 / 7) ** 0.5 / 8**0.5
        half = stats.t.ppf(0.975, 7) * se
        assert scores[c]["gap_signed"] == pytest.approx(0.0, abs=1e-12)
        assert scores[c]["gap_se"] == pytest.approx(se)
        assert (scores[c]["gap_low"], scores[c]["gap_high"]) == pytest.approx((-half, half))
    assert scores["overall"]["bss_tasks"] == pytest.approx(0.0, abs=1e-12)
    checks = trust_checks(scores, competency_surfaces(forecasts, truths, [0.03], [20]))
    assert not checks["AUROC >= 0.75 (all episodes)"]["met"]
    assert not checks["Brier skill vs the overall base rate >= 0.3"]["met"]
    assert not checks["Brier skill vs the condition's base rate > 0 (stochastic)"]["met"]


def test_a_condition_no_real_episode_succeeded_in_has_no_times_to_score():
    """No real success in a condition: its time-to-success CRPS has no real times and no
    climatology, so the check is left out (as the Brier skill against a rate of 0 is), not
    counted a miss; the other conditions keep theirs."""
    forecasts, truths = _case(perfect=True)
    c = "out-of-distribution"
    truths[c]["success"][:] = False
    truths[c]["first_step"][:] = 20
    truths[c]["trace"][:] = 1.0
    scores = validation(forecasts, truths, radius=0.03)
    assert math.isnan(scores[c]["tts_skill"])
    checks = trust_checks(scores, competency_surfaces(forecasts, truths, [0.03], [20]))
    assert f"time-to-success CRPS skill > 0 ({c})" not in checks
    assert f"Brier skill vs the condition's base rate > 0 ({c})" not in checks
    assert checks["time-to-success CRPS skill > 0 (stochastic)"]["met"]


def test_the_members_limit_removes_their_disagreement_not_their_shared_error():
    forecasts, truths = _case(perfect=True)
    scores = validation(forecasts, truths, radius=0.03)  # no members' forecasts: no limit
    assert math.isnan(scores["stochastic"]["brier_skill_members_limit"])
    assert "brier_skill_members_limit" not in scores["overall"]
    for shared in (0.0, 0.1):
        for c in CONDITIONS:
            # two members: one 0.1 off the right answer, the other right; both off by `shared`
            reach = truths[c]["success"][:, 0]
            right = reach.double()
            sign = torch.where(reach, -1.0, 1.0).double()
            members = torch.stack([right + sign * (0.1 + shared), right + sign * shared], -1)
            forecasts[c]["p_success_member"] = members
            forecasts[c]["p_success"] = members.mean(-1)
        scores = validation(forecasts, truths, radius=0.03)
        for c in (*CONDITIONS, "overall"):  # every base rate is 0.5: a reference Brier of 0.25
            # the mean is 0.05 + shared off; two members 0.1 apart vary by 0.005, whose half
            # the limit takes off the Brier score
            mean_off = 0.05 + shared
            assert scores[c]["brier_skill"] == pytest.approx(1 - mean_off**2 / 0.25)
            limit = 1 - (mean_off**2 - 0.005 / 2) / 0.25
            assert scores[c]["brier_skill_members_limit"] == pytest.approx(limit)


def test_the_recalibrated_scores_sit_beside_the_forecasts_own():
    forecasts, truths = _case(perfect=True)
    for c in CONDITIONS:  # ranks right, but 0.2 too optimistic on average
        forecasts[c]["p_success"] = torch.where(forecasts[c]["p_success"] > 0, 0.8, 0.6)
    scores = validation(forecasts, truths, radius=0.03)
    for c in (*CONDITIONS, "overall"):
        assert scores[c]["gap"] == pytest.approx(0.2)
        assert set(scores[c]["recalibrated"]) == {
            "forecast", "gap", "per_start_mae", "brier_skill", "ece", "auroc"
        }  # fmt: skip
    # 30 episodes per start: the held-out maps pull the forecast to the real rate
    after = scores["stochastic"]["recalibrated"]
    assert after["gap"] < 0.05 and after["brier_skill"] > scores["stochastic"]["brier_skill"]
    checks = trust_checks(scores, competency_surfaces(forecasts, truths, [0.03], [20]))
    assert not any("recalibrat" in name for name in checks)  # the checks score the forecast


def test_a_map_fitted_elsewhere_recalibrates_the_scored_forecasts_beside_them():
    """``held_out_maps``: each scored forecast through a map fitted on other start states,
    reported beside the forecast's own scores (which it leaves as they are) for the
    conditions that have one."""
    forecasts, truths = _case(perfect=True)
    for c in CONDITIONS:  # ranks right, but too pessimistic: 0.6 and 0.2 for 1 and 0
        forecasts[c]["p_success"] = torch.where(forecasts[c]["p_success"] > 0, 0.6, 0.2)
    plain = validation(forecasts, truths, radius=0.03)
    identity, sharper = PlattMap(1.0, 0.0), PlattMap(3.0, 1.5)
    maps = {"deterministic": identity, "stochastic": sharper}
    scores = validation(forecasts, truths, radius=0.03, held_out_maps=maps)
    assert "recalibrated_held_out" not in scores["out-of-distribution"]
    assert "recalibrated_held_out" not in scores["overall"]
    for c in CONDITIONS:
        own = {k: v for k, v in scores[c].items() if k != "recalibrated_held_out"}
        assert own == plain[c]
    same = scores["deterministic"]["recalibrated_held_out"]
    assert same["gap"] == pytest.approx(plain["deterministic"]["gap"])
    assert (same["slope"], same["intercept"]) == (1.0, 0.0)
    after = scores["stochastic"]["recalibrated_held_out"]
    # logit 0.6 = 0.405 -> 2.72 (0.938); logit 0.2 = -1.386 -> -2.66 (0.065)
    assert after["forecast"] == pytest.approx((0.9381 + 0.0654) / 2, abs=1e-3)
    assert after["gap"] < 0.01 < plain["stochastic"]["gap"]
    assert after["brier_skill"] > plain["stochastic"]["brier_skill"]
    assert after["auroc"] == plain["stochastic"]["auroc"]  # a monotone map keeps the ranks
    # a map for every condition: the pooled scores through them too (the map leaves the
    # out-of-distribution forecasts alone here, so the pool is the two maps' and the plain one)
    everywhere = validation(
        forecasts, truths, radius=0.03, held_out_maps={**maps, "out-of-distribution": identity}
    )
    pooled = everywhere["overall"]["recalibrated_held_out"]
    expected = (
        scores["deterministic"]["recalibrated_held_out"]["forecast"] * 8
        + after["forecast"] * 240
        + plain["out-of-distribution"]["forecast"] * 8
    ) / 256  # episode-weighted: 8, 8 x 30 and 8 episodes
    assert pooled["forecast"] == pytest.approx(expected)
    assert pooled["brier_skill"] > plain["overall"]["brier_skill"]


def test_the_held_out_map_has_checks_of_its_own_beside_the_forecasts():
    """Through a map fitted on other start states, the calibration and skill targets are
    checked again, each named as such; the forecast's own checks stay as they were."""
    forecasts, truths = _case(perfect=True)
    for c in CONDITIONS:  # ranks right, but too pessimistic: 0.6 and 0.2 for 1 and 0
        forecasts[c]["p_success"] = torch.where(forecasts[c]["p_success"] > 0, 0.6, 0.2)
    surfaces = competency_surfaces(forecasts, truths, [0.03], [20])
    plain = trust_checks(validation(forecasts, truths, radius=0.03), surfaces)
    assert not any(THROUGH_MAP in name for name in plain)
    sharper = PlattMap(3.0, 1.5)  # 0.6 -> 0.938, 0.2 -> 0.065
    maps = {c: sharper for c in CONDITIONS}
    checks = trust_checks(validation(forecasts, truths, 0.03, held_out_maps=maps), surfaces)
    assert {k: v for k, v in checks.items() if THROUGH_MAP not in k} == plain
    through = {k: v for k, v in checks.items() if THROUGH_MAP in k}
    for c in CONDITIONS:
        gap = through[f"|forecast - empirical| <= 0.10 through the held-out map ({c})"]
        assert gap["met"] and gap["value"] < 0.01
        own = through[
            f"Brier skill vs the condition's base rate > 0 through the held-out map ({c})"
        ]
        assert own["met"] and own["value"] > 0.9
    assert through["AUROC >= 0.75 (all episodes) through the held-out map"]["met"]
    overall = through["Brier skill vs the overall base rate >= 0.3 through the held-out map"]
    assert (
        overall["met"]
        and overall["value"] > plain["Brier skill vs the overall base rate >= 0.3"]["value"]
    )
    # a map for some conditions only: no pooled checks, the others' own
    some = trust_checks(
        validation(forecasts, truths, 0.03, held_out_maps={"stochastic": sharper}), surfaces
    )
    assert sorted(k for k in some if THROUGH_MAP in k) == [
        "Brier skill vs the condition's base rate > 0 through the held-out map (stochastic)",
        "|forecast - empirical| <= 0.10 through the held-out map (stochastic)",
    ]

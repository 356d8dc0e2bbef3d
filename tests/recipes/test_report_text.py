"""The report's text sections read as text and tables, not as Python dicts."""

from __future__ import annotations

import pytest
import torch

from recipes.pusher_competency.config import AgentStudyConfig
from recipes.pusher_competency.report import (
    DAGGER_COLUMNS,
    _novelty_text,
    agent_section,
    novelty_rows,
)

AGENT = {
    "mpc_noisy_success_rate": 0.8666666666666667,
    "mpc_median_steps": 95.0,
    "pairs": 3120.0,
    "policy_success_before": 0.9,
    "train_mse": 0.031912826001644135,
    "val_mse": 0.004118418388068676,
    "epochs": 41.0,
    "dagger": [
        {"round": 0, "pairs": 1500.0, "train_mse": 0.0235, "val_mse": 0.0127, "epochs": 30.0},
        {
            "round": 1,
            "pairs": 3120.0,
            "policy_success_before": 0.9,
            "train_mse": 0.0319,
            "val_mse": 0.0041,
            "epochs": 41.0,
        },
    ],
    "policy_success_rate": 0.95,
    "policy_median_steps": 88.0,
    "seconds": 312.4,
}


def test_agent_section_is_readable():
    text = agent_section(AGENT, AgentStudyConfig(mpc_episodes=15, dagger_rounds=1))
    assert "{" not in text and "[" not in text  # no dict or list reprs
    lines = text.splitlines()
    assert lines[0] == (
        "Settings: 15 MPC episodes with action noise of std 0.3, then 1 DAgger round(s) of 10 "
        "policy episodes, the agent evaluated on 20 episodes."
    )
    assert "| MPC episodes (executed actions perturbed): success rate | 0.867 |" in lines
    assert "| the agent in its evaluation episodes: median steps | 88 |" in lines
    header = "| " + " | ".join(DAGGER_COLUMNS.values()) + " |"
    rows = lines[lines.index(header) + 2 :]
    assert rows == [
        "| 0 | 1500 | – | 0.024 | 0.013 | 30 |",
        "| 1 | 3120 | 0.900 | 0.032 | 0.0041 | 41 |",
    ]


def test_agent_section_without_dagger_rounds():
    text = agent_section({"policy_success_rate": 1.0}, AgentStudyConfig(dagger_rounds=0))
    assert "| the agent in its evaluation episodes: success rate | 1 |" in text
    assert "Distillation rounds" not in text and "| round |" not in text


def test_model_checks_section_names_each_verdict_and_the_coverage():
    import torch

    from rcvae_torchrl.training import ModelChecks
    from recipes.pusher_competency.report import _model_checks_text

    zeros = torch.zeros(3, dtype=torch.float64)

    def checks(covered):
        return ModelChecks(
            ("x", "y", "z"), zeros, zeros + 1, zeros + 1, zeros, zeros + 1, 5, (0, 1), 0.05,
            covered=torch.tensor(covered, dtype=torch.float64), episodes=32,
            coverage_steps=20, interval=0.9,
        )  # fmt: skip

    text = _model_checks_text({"good": checks([30, 29, 0]), "bad": checks([30, 12, 0])})
    assert "- **good**: passed." in text
    assert "- **bad**: the world model is overconfident" in text and "y (12 of 32)" in text
    assert "| model | x | y |" in text  # the checked dimensions only
    assert "| good | 0.94 | 0.91 |" in text and "| bad | 0.94 | 0.38 |" in text
    assert "90% interval after 20 steps (32 held-out episodes)" in text
    # a spread too wide does not fail the checks, and is said beside the verdict
    import dataclasses

    wide = dataclasses.replace(
        checks([30, 29, 0]), covered_half=torch.tensor([30.0, 16.0, 0.0]), half_interval=0.5
    )
    assert f"- **wide**: passed; but {wide.wide_sentence()}." in _model_checks_text({"wide": wide})
    assert "x (30 of 32)" in wide.wide_sentence()


def test_far_checks_section_names_overconfident_dimensions_and_unmeasured_models():
    import torch

    from rcvae_torchrl.training import ModelChecks
    from recipes.pusher_competency.report import _far_checks_text

    zeros = torch.zeros(3, dtype=torch.float64)

    def checks(covered, steps, episodes=32):
        return ModelChecks(
            ("x", "y", "z"), zeros, zeros + 1, zeros + 1, zeros, zeros + 1, 5, (0, 1), 0.05,
            covered=None if covered is None else torch.tensor(covered, dtype=torch.float64),
            episodes=episodes, coverage_steps=steps, interval=0.9,
        )  # fmt: skip

    text = _far_checks_text(
        {
            "good": [checks([30, 29, 0], 60), checks([31, 28, 0], 240)],
            "bad": [checks([30, 12, 0], 60), checks([30, 29, 0], 240)],
            "short": [checks(None, 60, 0), checks(None, 240, 0)],
        }
    )
    assert "| model | 60 steps | 240 steps |" in text
    assert "| good | 29 of 32 | 28 of 32 |" in text
    assert "| bad | 12 of 32 ✗ y | 29 of 32 |" in text
    assert "| short | not measured | not measured |" in text
    assert "- **good**: covered as often as it should at every horizon." in text
    assert "- **bad**: overconfident on y 60 steps ahead: forecasts made with it (none" in text
    assert "- **short**: not measured" in text
    assert _far_checks_text({}) == ""
    text = _far_checks_text({"deterministic": [checks([30, 12, 0], 60)]})
    assert "forecasts made with it (deterministic, out-of-distribution)" in text


def test_forecast_checks_section_gives_each_verdict():
    import torch

    from rcvae_torchrl.training import OutcomeCheck
    from recipes.pusher_competency.report import _forecast_checks_text

    forecast = torch.linspace(0.2, 0.8, 12, dtype=torch.float64)
    noise = torch.linspace(-0.05, 0.05, 12, dtype=torch.float64)
    text = _forecast_checks_text(
        {
            "fair": OutcomeCheck(forecast, forecast + noise, runs=30),
            "low": OutcomeCheck(forecast, forecast + 0.15 + noise, runs=30, what="the low ones"),
            "few": OutcomeCheck(forecast[:3], forecast[:3], runs=1, what="the few ones"),
            "sure": OutcomeCheck(
                torch.ones(30, dtype=torch.float64),
                torch.ones(30, dtype=torch.float64),
                runs=1,
                what="the sure ones",
                began_settled=torch.zeros(30, dtype=torch.bool),
            ),
            # 87 of 100 starts forecast 0.95 succeed: the outcomes' exact chance finds the gap
            # (p = 0.003), the t-test over the starts does not (0.02): passed, and said
            "leaning": OutcomeCheck(
                torch.full((100,), 0.95, dtype=torch.float64),
                (torch.arange(100) < 87).double(),
                runs=1,
                what="the leaning ones",
            ),
        }
    )
    assert "| condition | starts | real runs each | forecast | real |" in text
    assert "| fair | 12 | 30 | 0.500 | 0.500 | " in text and "| passed |" in text
    assert "| low | 12 | 30 | 0.500 | 0.650 | -0.150 (" in text and "| too pessimistic |" in text
    assert "| few | 3 | 1 | | | | | not measured |" in text
    assert "- **low**: the low ones are too pessimistic: from 12 start states" in text
    assert (
        "- **few**: the few ones are not measured by the outcome check: 3 start states, where "
        "it needs 10." in text
    )
    assert "- **fair**" not in text  # a passed check needs no sentence
    # passed for sure forecasts alone: its row, and the sentence that says what it vouches for
    assert "| sure | 30 | 1 | 1.000 | 1.000 | +0.000 (" in text and text.count("| passed |") == 3
    assert "| leaning | 100 | 1 | 0.950 | 0.870 | +0.080 (" in text
    assert (
        "- **leaning**: the leaning ones are not named biased: a bias is named only where both "
        "tests find the gap beyond chance, and only the outcomes' exact chance does" in text
    )
    assert "- **sure**: the sure ones are right where they are sure, as far as the check" in text
    assert _forecast_checks_text({}) == ""


def test_the_report_opens_with_what_each_forecast_can_be_trusted_for():
    """Before any scored outcome: each condition's mean forecast and its forecast check's
    verdict; a named bias with the forecast through the map fitted on the check's episodes."""
    import torch

    from rcvae_torchrl.training import OutcomeCheck
    from recipes.pusher_competency.report import _told_text

    forecast = torch.linspace(0.2, 0.8, 12, dtype=torch.float64)
    noise = torch.linspace(-0.05, 0.05, 12, dtype=torch.float64)
    checks = {
        "fair": OutcomeCheck(forecast, forecast + noise, runs=30),
        "high": OutcomeCheck(forecast, forecast - 0.15 + noise, runs=30),
        "few": OutcomeCheck(forecast[:3], forecast[:3], runs=1),
        "wide": OutcomeCheck(forecast, (forecast > 0.5).double(), runs=1),
    }
    rows = {c: {"forecast_p_success": 0.5} for c in checks}
    scores = {"high": {"recalibrated_held_out": {"forecast": 0.352}}}
    text = _told_text(rows, checks, scores)
    assert text.startswith("## What the forecasts can be trusted for\n")
    assert "- **fair**: forecast 0.50: the check finds no bias (gap +0.000 on 12 start" in text
    assert (
        "- **high**: forecast 0.50, **too optimistic** (gap +0.150 on 12 start states, 99 % "
        "interval +0.1" in text
    )
    assert "; through the map fitted on the check's episodes it reads 0.35." in text
    assert "- **few**: forecast 0.50: not measured (the check's 3 start states)." in text
    assert checks["wide"].verdict == "too imprecise"
    assert "- **wide**: forecast 0.50: not vouched for, too imprecise (gap " in text


def test_the_gap_is_given_with_its_interval():
    from recipes.pusher_competency.report import _gap_text

    scores = {
        "deterministic": {"gap_signed": 0.113, "gap_low": 0.041, "gap_high": 0.185},
        "stochastic": {"gap_signed": -0.014, "gap_low": -0.03, "gap_high": 0.002},
        "overall": {"gap": 0.02},  # pooled: no per-start interval
    }
    text = "\n".join(_gap_text(scores))
    assert "deterministic +0.113 (+0.041 to +0.185); stochastic -0.014 (-0.030 to +0.002)." in text
    assert "95% interval" in text and "overall" not in text
    assert _gap_text({"overall": {"gap": 0.02}}) == []


def test_novelty_rows_split_the_per_start_error_by_the_caution():
    forecast = {
        "p_success": torch.tensor([0.9, 0.5, 0.2, 1.0]),
        "novelty_start": torch.tensor([0.3, 1.4, 0.8, 0.2]),
        "novel": torch.tensor([False, True, True, False]),
    }
    # two real episodes per start: rates 1.0, 0.0, 0.5, 1.0
    success = torch.tensor([[1, 1], [0, 0], [1, 0], [1, 1]], dtype=torch.bool)
    rows = novelty_rows(
        {"a": forecast, "b": {"p_success": torch.ones(4)}}, {"a": {"success": success}}
    )
    assert list(rows) == ["a"]  # a forecast without the check has no row
    row = rows["a"]
    assert (row["starts"], row["start_unlike"], row["cautioned"]) == (4, 1, 2)
    assert row["mae_cautioned"] == pytest.approx((0.5 + 0.3) / 2)
    assert row["mae_rest"] == pytest.approx((0.1 + 0.0) / 2)
    none = novelty_rows(
        {"a": {**forecast, "novel": torch.zeros(4, dtype=torch.bool)}}, {"a": {"success": success}}
    )
    assert "| a | 4 | 1 | 0 | – | 0.225 |" in _novelty_text(none)
    assert _novelty_text({}) == ""


def test_dynamics_checks_section_gives_each_verdict_and_an_unmeasured_one():
    """A passed, a failed (its dimension named) and an unmeasured check (every episode too
    short): one row and one sentence each; only measured ones are checks."""
    from rcvae_torchrl.training import DynamicsCheck
    from recipes.pusher_competency.report import (
        DYNAMICS_CHECK,
        _dynamics_checks_text,
        dynamics_rows,
    )

    def check(episodes: int, p: list[float]) -> DynamicsCheck:
        p_values = torch.tensor(p, dtype=torch.float64)
        ratios = torch.where(p_values.isnan(), p_values, torch.tensor([0.9, 3.0]))
        return DynamicsCheck(
            episodes=episodes, short=0 if episodes else 5, beyond=2 if episodes else 0,
            rate=0.05, alpha=0.01, tolerance=1.1, p_values=p_values, ratios=ratios,
            names=("arm", "ball"), model="m",
        )  # fmt: skip

    checks = {
        "same": check(40, [0.5, 0.6]),
        "changed": check(40, [0.9, 1e-5]),
        "short": check(0, [float("nan"), float("nan")]),
    }
    text = _dynamics_checks_text(checks)
    assert text.startswith("### Does each env move as its world model learned?")
    assert "| same | 40 | 2 | 1 | passed |" in text
    assert "| changed | 40 | 2 | 2e-05 | failed |" in text
    assert "| short | 0 | 0 |  | not measured |" in text
    assert "- **changed**: failed: " in text and "larger in ball (3.0 times" in text
    assert "- **short**: not measured: no episode long enough to check (5 shorter" in text
    rows = dynamics_rows(checks)
    assert rows == {
        DYNAMICS_CHECK.format("same"): {"value": 1.0, "met": True},
        DYNAMICS_CHECK.format("changed"): {"value": pytest.approx(2e-5), "met": False},
    }
    assert _dynamics_checks_text({}) == ""

"""The pattern diagnostic over the first seconds of the forecasts."""

import math

import pytest
import torch

from recipes.pusher_competency.report import pattern_by_window


def _forecast(aleatoric_early, aleatoric_late, epistemic_early, epistemic_late, steps=40):
    t = torch.arange(steps)
    ale = torch.where(t < 10, aleatoric_early, aleatoric_late).float()
    epi = torch.where(t < 10, epistemic_early, epistemic_late).float()
    # [B=3, T, D=2]: each of the two dims carries half of the bits
    return {
        "aleatoric": (ale / 2)[None, :, None].expand(3, steps, 2),
        "epistemic": (epi / 2)[None, :, None].expand(3, steps, 2),
    }


def test_ratios_per_window_match_the_bits_averaged_over_that_window():
    forecasts = {
        "deterministic": _forecast(1.0, 4.0, 1.0, 2.0),
        "stochastic": _forecast(3.0, 4.0, 1.0, 2.0),
        "out-of-distribution": _forecast(1.0, 4.0, 2.0, 2.0),
    }
    out = pattern_by_window(forecasts, dt=0.1, windows_s=(1.0, 2.0))
    assert list(out) == ["1s", "2s", "4s"]  # the horizon (40 steps of 0.1 s) is added
    early = out["1s"]
    assert early["aleatoric_stochastic_over_deterministic"] == pytest.approx(3.0)
    assert early["epistemic_ood_over_deterministic"] == pytest.approx(2.0)
    assert early["aleatoric_ood_over_deterministic"] == pytest.approx(1.0)
    # over 2 s: (10·3 + 10·4) / (10·1 + 10·4) for aleatoric
    assert out["2s"]["aleatoric_stochastic_over_deterministic"] == pytest.approx(70 / 50)
    whole = out["4s"]
    assert whole["aleatoric_stochastic_over_deterministic"] == pytest.approx(150 / 130)
    assert whole["epistemic_ood_over_deterministic"] == pytest.approx(80 / 70)


def _ended(bits_alive: float, epistemic_alive: float, life: int, steps: int = 40):
    """A forecast whose episodes all run ``life`` steps, with these bits while they run."""
    alive = torch.arange(steps) < life
    ale = torch.where(alive, bits_alive, 0.0)
    epi = torch.where(alive, epistemic_alive, 0.0)
    return {
        "aleatoric": (ale / 2)[None, :, None].expand(3, steps, 2),
        "epistemic": (epi / 2)[None, :, None].expand(3, steps, 2),
        "live": alive.float()[None].expand(3, steps),
    }


def test_per_live_step_takes_the_episodes_lengths_out():
    # the same bits per step alive; the deterministic episodes end after 10 steps, the others
    # after 40 (the horizon) and 20: the time means differ by the lengths alone
    forecasts = {
        "deterministic": _ended(2.0, 1.0, life=10),
        "stochastic": _ended(2.0, 1.0, life=40),
        "out-of-distribution": _ended(2.0, 1.5, life=20),
    }
    out = pattern_by_window(forecasts, dt=0.1, windows_s=(1.0,))
    assert list(out) == ["1s", "4s", "per live step"]
    assert out["4s"]["aleatoric_stochastic_over_deterministic"] == pytest.approx(4.0)
    assert out["4s"]["aleatoric_ood_over_deterministic"] == pytest.approx(2.0)
    live = out["per live step"]
    assert live["aleatoric_stochastic_over_deterministic"] == pytest.approx(1.0)
    assert live["aleatoric_ood_over_deterministic"] == pytest.approx(1.0)
    assert live["epistemic_ood_over_deterministic"] == pytest.approx(1.5)


def test_per_live_step_needs_every_forecast_to_hold_live():
    forecasts = {
        "deterministic": _ended(2.0, 1.0, life=10),
        "stochastic": _forecast(3.0, 4.0, 1.0, 2.0),  # saved without "live"
        "out-of-distribution": _ended(2.0, 1.5, life=20),
    }
    assert "per live step" not in pattern_by_window(forecasts, dt=0.1, windows_s=(1.0,))


def test_nothing_over_nothing_is_no_ratio_and_meets_no_check():
    """A trial with one sample per member: every epistemic part was 0, and the check
    'epistemic out-of-distribution / deterministic >= 1.3' read inf and passed."""
    forecasts = {
        "deterministic": _forecast(1.0, 1.0, 0.0, 0.0),
        "stochastic": _forecast(3.0, 3.0, 0.0, 0.0),
        "out-of-distribution": _forecast(1.0, 1.0, 0.0, 0.0),
    }
    ratios = pattern_by_window(forecasts, dt=0.1, windows_s=())["4s"]
    assert math.isnan(ratios["epistemic_ood_over_deterministic"])
    assert not ratios["epistemic_ood_over_deterministic"] >= 1.3
    assert ratios["aleatoric_stochastic_over_deterministic"] == pytest.approx(3.0)
    # a rise from nothing stays infinite
    forecasts["out-of-distribution"] = _forecast(1.0, 1.0, 0.5, 0.5)
    rose = pattern_by_window(forecasts, dt=0.1, windows_s=())["4s"]
    assert rose["epistemic_ood_over_deterministic"] == math.inf


def test_the_pattern_checks_on_known_numbers():
    from recipes.pusher_competency.report import pattern_checks

    def row(aleatoric, epistemic, forecast, real):
        return {
            "aleatoric_bits": aleatoric,
            "epistemic_bits": epistemic,
            "forecast_p_success": forecast,
            "empirical_p_success": real,
        }

    rows = {
        "deterministic": row(1.0, 0.0, 1.0, 1.0),
        "stochastic": row(2.0, 0.0, 0.5, 0.5),
        "out-of-distribution": row(1.0, 0.0, 1.0, 1.0),
    }
    checks = pattern_checks(rows, {"brier": 0.0, "constant_brier": 0.0})
    # one sample per member left every epistemic part 0: no ratio, no check met
    assert not checks["epistemic out-of-distribution / deterministic >= 1.3"]["met"]
    assert checks["aleatoric stochastic / deterministic >= 1.5"]["met"]
    # a perfect forecast where every start is alike (a trial's single start state)
    assert checks["Brier < constant forecast (all start states)"]["met"]
    assert not pattern_checks(rows, {"brier": 0.1, "constant_brier": 0.1})[
        "Brier < constant forecast (all start states)"
    ]["met"]

"""``benchmarks/survival_forecast.py`` runs end to end on micro budgets: a survival boundary on
an env the project did not write, forecast and held against real episodes."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import survival_forecast


def test_micro_run_writes_every_row(tmp_path, monkeypatch):
    out = tmp_path / "survival"
    args = ["--seeds", "0", "--steps", "20", "--short-steps", "10", "--episodes", "2"]
    args += ["--episode-steps", "30", "--runs", "2", "--seconds", "0.5", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["survival_forecast.py", *args])
    survival_forecast.main()
    rows = json.loads(out.with_suffix(".json").read_text())["rows"]
    assert [(r["variant"], r["train_steps"]) for r in rows] == [
        ("deterministic", 10),
        ("deterministic", 20),
        ("stochastic", 10),
        ("stochastic", 20),
    ]
    for row in rows:
        assert 0.0 <= row["forecast"] <= 1.0 and 0.0 <= row["real"] <= 1.0
        # micro budgets: few starts, some of them settled; any of the check's verdicts
        verdicts = (
            "passed",
            "too optimistic",
            "too pessimistic",
            "too imprecise",
            "no better than a constant",
        )
        assert row["held_out_check"] in (*verdicts, "not measured")
        assert row["ood_cause"] in (None, "aleatoric", "epistemic")
    # the real episodes do not depend on the model: the same rate for both budgets
    assert rows[0]["real"] == rows[1]["real"] and rows[2]["real"] == rows[3]["real"]

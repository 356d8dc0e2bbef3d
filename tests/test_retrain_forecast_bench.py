"""``benchmarks/retrain_forecast.py`` reads its settings as typed values and refuses what it
cannot measure, naming the argument."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import closed_loop_data
import retrain_forecast


def test_settings_are_read_as_typed_values():
    assert retrain_forecast.parse_setting("train.batch_windows=64") == (
        "train",
        "batch_windows",
        64,
    )
    assert retrain_forecast.parse_setting("train.lr=3e-3") == ("train", "lr", 0.003)
    assert retrain_forecast.parse_setting("data.stochastic_strength=[0.2, 0.4]") == (
        "data",
        "stochastic_strength",
        [0.2, 0.4],
    )
    assert retrain_forecast.parse_setting("model.state_constraint=None") == (
        "model",
        "state_constraint",
        None,
    )
    assert retrain_forecast.parse_setting("train.name=abc") == ("train", "name", "abc")


def _finished(run: Path) -> Path:
    """A directory with every part of a finished run (empty)."""
    for part in closed_loop_data.FINISHED:
        path = run / part
        if path.suffix:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
        else:
            path.mkdir(parents=True, exist_ok=True)
    return run


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            ["--set", "batch_windows=64"],
            "--set: expected SECTION.KEY=VALUE .* got 'batch_windows=64'",
        ),
        (["--set", "train.batch_windows"], "--set: expected SECTION.KEY=VALUE"),
        (["--set", "train.batch_windows=64"], "run_dirs: expected finished study runs, .* lacks"),
    ],
)
def test_bad_arguments_are_named(tmp_path, monkeypatch, args, message):
    monkeypatch.setattr(sys, "argv", ["retrain_forecast.py", str(tmp_path), *args])
    with pytest.raises(SystemExit, match=message):
        retrain_forecast.main()


def test_models_trained_with_other_settings_are_not_reused(tmp_path, monkeypatch):
    run = _finished(tmp_path / "runs" / "seed3")
    work = tmp_path / "work"
    (work / "runs_seed3").mkdir(parents=True)
    (work / "runs_seed3" / "settings.json").write_text(json.dumps({"train": {"lr": 0.01}}))
    argv = [str(run), "--set", "train.batch_windows=64", "--work-dir", str(work)]
    monkeypatch.setattr(sys, "argv", ["retrain_forecast.py", *argv])
    with pytest.raises(
        SystemExit, match=r"--work-dir: .* holds models trained with other settings"
    ):
        retrain_forecast.main()

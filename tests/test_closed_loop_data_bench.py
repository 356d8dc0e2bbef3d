"""``benchmarks/closed_loop_data.py`` refuses what it cannot measure, naming the argument."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import closed_loop_data


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--episodes", "0"], "--episodes: expected at least 1, got 0"),
        (["--steps", "-3"], "--steps: expected at least 1, got -3"),
        (["--lr", "0"], "--lr: expected a positive learning rate, got 0.0"),
        ([], "run_dirs: expected finished study runs, .* lacks data, models, agent/policy.pt"),
    ],
)
def test_bad_arguments_are_named(tmp_path, monkeypatch, args, message):
    monkeypatch.setattr(sys, "argv", ["closed_loop_data.py", str(tmp_path), *args])
    with pytest.raises(SystemExit, match=message):
        closed_loop_data.main()

"""``benchmarks/demonstrations.py`` refuses what it cannot measure, naming the argument."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import demonstrations


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--side-by-side", "1"], "--side-by-side: expected at least 2 envs, got 1"),
        ([], "run_dir: expected a finished study run"),
    ],
)
def test_bad_arguments_are_named(tmp_path, monkeypatch, args, message):
    monkeypatch.setattr(sys, "argv", ["demonstrations.py", str(tmp_path), *args])
    with pytest.raises(SystemExit, match=message):
        demonstrations.main()

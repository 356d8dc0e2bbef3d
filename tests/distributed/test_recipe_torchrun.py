"""The Pusher recipe under ``torchrun`` with 2 ranks writes what a single process writes: the
same models, forecasts and real outcomes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from recipes._settings import CHECKPOINTS
from tests.recipes.micro import MICRO as QUICK_MICRO

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "pusher_competency" / "main.py"
MICRO = (
    *(o for o in QUICK_MICRO if not o.startswith("assess.start_states=")),
    "assess.start_states=3",
    "assess.start_chunk=1",
)


def _run(launcher: list[str], run_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    # no GL backend forced: the caller's, else the package's own choice (EGL only where it imports)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [*launcher, str(RECIPE), *MICRO, *overrides, f"run_dir={run_dir}"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def _assert_same(a, b, where: str) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _assert_same(a[key], b[key], f"{where}/{key}")
    elif isinstance(a, torch.Tensor):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True, msg=where)


@pytest.mark.slow
def test_recipe_under_torchrun_equals_one_process(tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    _run([sys.executable], one)
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2"]
    out = _run([*torchrun, "--standalone"], two).stdout
    assert out.count("ranks=2") == 1  # rank 0 alone prints
    # the two variants' data and world models made at once, one per rank (distributed.parts)
    for stage in ("data", "models"):
        assert f"[{stage}] deterministic, stochastic side by side on 2 parts of the ranks" in out
    for name in ("data/deterministic.pt", "data/stochastic.pt"):
        assert (one / name).read_bytes() == (two / name).read_bytes(), name
    for name in ("models/deterministic.pt", "models/stochastic.pt"):
        a, b = (torch.load(d / name, weights_only=False) for d in (one, two))
        _assert_same(a["state_dict"], b["state_dict"], name)
    for stage in ("forecast", "truth"):
        for path in sorted((one / stage).glob("*.pt")):
            a, b = (torch.load(d / stage / path.name) for d in (one, two))
            _assert_same(a, b, f"{stage}/{path.name}")
    assert (one / "table.csv").read_text() == (two / "table.csv").read_text()
    # the report's checks, those of the forecast checks from held-out start states included
    # (their forecasts and real episodes shared over the ranks)
    checks = [json.loads((d / "summary.json").read_text())["checks"] for d in (one, two)]
    assert checks[0] == checks[1]
    assert any("held-out" in name for name in checks[0])
    assert not list((two / "models").glob("*.members-*.pt"))  # block checkpoints removed


@pytest.mark.slow
def test_recipe_under_torchrun_trains_data_parallel(tmp_path):
    """``train.data_parallel=2``: both ranks train every member, each on half the windows."""
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2"]
    _run([*torchrun, "--standalone"], tmp_path, "train.data_parallel=2")
    for name in ("deterministic", "stochastic"):
        training = torch.load(tmp_path / "models" / CHECKPOINTS / f"{name}.pt", weights_only=False)
        assert training["training"]["config"]["data_parallel"] == 2
        assert training["training"]["state"]["finished"]
    assert (tmp_path / "table.csv").is_file()
    assert not list((tmp_path / "models").glob("*.members-*.pt"))

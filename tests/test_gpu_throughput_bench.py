"""``benchmarks/gpu_throughput.py`` on a CPU (its rows, units and records), and what a GPU needs
of the study's model step: no tensor made from host data (each would be a blocking copy per
step on a GPU, and breaks CUDA-graph capture)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import gpu_throughput
from model_step import dispatched, model_steps_alone, study_ensemble

from envs.constraints import _make_bounds
from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.rollout import Task

#: ATen calls that turn host data (a Python list or number) into a tensor.
FROM_HOST = {"lift_fresh", "lift_fresh_copy"}


def _from_host(call) -> list[str]:
    call()  # caches filled by a first call
    return [str(f) for f, *_ in dispatched(call) if f.overloadpacket.__name__ in FROM_HOST]


def test_the_study_step_makes_no_tensor_from_host_data():
    model = study_ensemble()
    task = Task(pusher_reward, pusher_success, terminate_on_success=True)
    assert _from_host(lambda: model_steps_alone(model, 4, 3, task)) == []


def test_the_constraint_bounds_are_filled_on_the_device():
    """Under ``torch.compile`` the bounds are made in the graph on every call: from host data
    they would be a copy per call."""
    like = torch.zeros(3)
    assert _from_host(lambda: _make_bounds(like)) == []
    low, high = _make_bounds(like)
    assert high.tolist()[0] == float("inf") and torch.equal(low, -high)


def test_the_benchmark_on_a_cpu(tmp_path, monkeypatch, capsys):
    out = tmp_path / "gpu"
    argv = ["gpu_throughput.py", "--device", "cpu", "--sizes", "4", "10", "--windows", "3"]
    monkeypatch.setattr(sys, "argv", [*argv, "--repeats", "1", "--no-compile", "--out", str(out)])
    gpu_throughput.main()
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["conditions"]["device"] == "cpu" and record["members"] == 5
    scoring = record["plan_scoring"]["10"]["eager"]
    # 10 trajectories per member: 10 candidates x 5 particles, 12 steps
    assert scoring["per_s"] == pytest.approx(10 * 5 * 12 / scoring["median_s"])
    steps = record["imagination_steps"]["4"]
    assert set(steps) == {"eager"}  # no CUDA-graph rows on a CPU, no compiled rows asked for
    assert steps["eager"]["per_s"] == pytest.approx(5 * 4 * 20 / steps["eager"]["median_s"])
    assert set(record["forecast_imagine"]["4"]) == {
        "imagine, chunks of 1024",
        "imagine, one chunk",
        'imagine, chunk_size="auto"',
    }
    train = record["training"]["3"]["eager"]
    assert train["per_s"] == pytest.approx(5 * 3 * 32 / train["median_s"])
    loop = record["training_loop"]["3"]
    assert set(loop) == {"train_ensemble"}  # no compiled row asked for
    steps = gpu_throughput.LOOP_STEPS
    assert loop["train_ensemble"]["per_s"] == pytest.approx(
        5 * 3 * 32 * steps / loop["train_ensemble"]["median_s"]
    )
    assert 0 < scoring["peak_share"] < 1
    best = max(
        r["per_s"]
        for s in ("plan_scoring", "imagination_steps", "forecast_imagine")
        for rows in record[s].values()
        for r in rows.values()
    )
    assert record["best_model_steps_per_s"] == best
    assert "best imagination" in capsys.readouterr().out


def test_a_failing_row_is_recorded_not_raised():
    rows = {"fails": (lambda: 1 / 0, 10), "runs": (lambda: None, 10)}
    result = gpu_throughput.measure(rows, 1, torch.device("cpu"), None, 1.0)
    assert result["fails"] == {"error": "ZeroDivisionError: division by zero"}
    assert result["runs"]["per_s"] > 0


def test_bad_counts_are_refused(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["gpu_throughput.py", "--device", "cpu", "--sizes", "0"])
    with pytest.raises(SystemExit, match=r"--sizes: expected positive counts, got \[0\]"):
        gpu_throughput.main()


def test_importing_the_compile_benchmark_leaves_the_inductor_cache_alone(tmp_path):
    """``gpu_throughput`` imports ``compiled_step``, whose cold-compile cache (an empty
    temporary directory) belongs to its own ``main``: the import does not point the importer's
    inductor cache there and leaves no such directory behind."""
    import os
    import subprocess

    code = (
        "import os, sys; sys.path.insert(0, 'benchmarks'); import compiled_step; "
        "print(os.environ.get('TORCHINDUCTOR_CACHE_DIR', 'unset'))"
    )
    env = {k: v for k, v in os.environ.items() if k != "TORCHINDUCTOR_CACHE_DIR"}
    env["TMPDIR"] = str(tmp_path)
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, check=True
    )
    # unset or torch's own default (something imported may ask inductor for its directory)
    assert "compiled_step_inductor" not in out.stdout, out.stdout
    assert not list(tmp_path.glob("compiled_step_inductor_*"))

"""``benchmarks/model_step.py``'s ceilings and device handling: the replayed matrix products,
the rows at another batch size, and ``--device``."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from _report import benchmark_device, conditions, device_name, interleaved_median_times
from model_step import (
    MODEL_ALONE,
    _alone_of,
    _flop_of,
    matmuls_alone,
    model_rows,
    model_steps_alone,
    op_counts,
    ops_of,
    study_ensemble,
    transcendentals_of,
)

from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.rollout import Task


def _mlp_call():
    """A call with an addmm (Linear), a bmm and a baddbmm, and elementwise ops between them."""
    linear = torch.nn.Linear(6, 5)
    a, b = torch.randn(4, 3, 6), torch.randn(4, 5, 2)
    bias = torch.randn(4, 1, 2)

    def call() -> None:
        x = torch.tanh(linear(a.reshape(12, 6))).reshape(4, 3, 5)
        y = torch.bmm(x, b).sigmoid()
        torch.baddbmm(bias, x, b) + y

    return call


def test_matmuls_alone_replays_the_same_products_and_nothing_else():
    call = _mlp_call()
    replay = matmuls_alone(call)
    assert _flop_of(replay) == _flop_of(call) == 2 * (12 * 6 * 5 + 2 * 4 * 3 * 5 * 2)
    seen = []

    class Ops(torch.utils._python_dispatch.TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            seen.append(func.overloadpacket.__name__)
            return func(*args, **(kwargs or {}))

    with Ops():
        replay()
    assert seen == ["addmm", "bmm", "baddbmm"]


def test_matmuls_alone_of_a_model_step_counts_the_step_flop():
    model = study_ensemble()
    task = Task(pusher_reward, pusher_success, terminate_on_success=True)

    def call() -> None:
        model_steps_alone(model, 3, 2, task)

    assert _flop_of(matmuls_alone(call)) == pytest.approx(_flop_of(call))


def test_rows_at_a_scale_take_their_candidates_from_the_trajectories_per_member():
    model = study_ensemble()
    task = Task(pusher_reward, pusher_success, terminate_on_success=True)
    rows = model_rows(model, task, 64)
    assert {name: n for name, (_, n) in rows.items()} == {
        "evaluate_action_sequences, eager": 64,
        MODEL_ALONE: 64,
    }
    scaled = model_rows(model, task, 7, ", 7 per member")
    assert [n for _, n in scaled.values()] == [7, 7]
    assert _alone_of("evaluate_action_sequences, eager, 7 per member") == (
        f"{MODEL_ALONE}, 7 per member"
    )
    assert _alone_of("evaluate_action_sequences, compile=True") == MODEL_ALONE
    for call, _ in scaled.values():
        call()


def test_device_option_takes_the_cpu_and_refuses_a_missing_gpu():
    assert benchmark_device("cpu") == torch.device("cpu")
    assert device_name("cpu") == "cpu"
    assert conditions("cpu")["device"] == "cpu"
    assert "device" not in conditions()
    with pytest.raises(SystemExit, match="--device: expected cpu, cuda or cuda:N, got 'tpu'"):
        benchmark_device("tpu")
    with pytest.raises(SystemExit, match=r"got .meta."):
        benchmark_device("meta")
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit, match="no CUDA device"):
            benchmark_device("cuda")


def test_interleaved_times_on_a_device_time_every_call():
    calls = []
    times = interleaved_median_times({"a": lambda: calls.append(1)}, repeats=3, device="cpu")
    assert len(calls) == 4  # one warm-up round, three timed
    assert times["a"]["wall_s"] >= 0.0


def test_op_counts_of_a_step_hold_its_task_parts():
    model = study_ensemble()
    task = Task(pusher_reward, pusher_success, terminate_on_success=True)
    counts = op_counts(model, task, 4)
    assert counts == op_counts(model, task, 64)  # the batch does not change the calls
    inside = counts["input features (in the step)"] + counts["state constraint (in the step)"]
    assert 0 < inside < counts["model step"]
    assert counts["reward"] > 0 and counts["success"] > 0
    assert ops_of(lambda: torch.zeros(3).add_(1.0).mul(2.0)) == 3


def test_transcendentals_count_the_elements_of_costly_functions_only():
    x = torch.randn(4, 6)
    w = torch.ones(6, 2)

    def call() -> None:  # sigmoid (24) and exp (24) count; relu, add and matmul do not
        (torch.sigmoid(x).exp() + torch.relu(x)) @ w

    assert transcendentals_of(call) == 48

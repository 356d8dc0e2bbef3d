"""Throughput of the study's world model at a GPU's batch sizes: imagination and training.

The study's model (E = 5, H = MLP = 64, Z = 8, the Pusher's input features and state
constraint; untrained, normaliser fitted on random data: speed does not depend on the weights),
on one device, float32. Each section's rows are timed once per round, in turn (medians of
interleaved rounds, every call timed until its kernels have run); compiled rows report the
seconds of their first call (compiling, with whatever inductor cache the machine has) apart.

1. **Plan scoring** (``evaluate_action_sequences``: P = 5 particles, H = 12 steps, the Pusher's
   reward and success): eager and ``compile=True``, at N trajectories per member.
2. **Imagination steps** (H = 20 ``ensemble.step`` calls, noise drawn up front): eager, eager
   captured in one CUDA graph, ``torch.compile`` (dynamic shapes, one compile for every N), and
   the compiled steps captured in one CUDA graph.
3. **Forecast imagination** (``imagine``, H = 20, open loop, every step's states kept, as the
   competency estimators read them): chunks of 1024 trajectories per member (the CPU's
   default), all in one chunk, and the default ``chunk_size="auto"`` (by device).
4. **Training** (``RCVAELoss`` forward and backward and an Adam step on ``[E, W, L = 32]``
   windows): eager and with the loss under ``torch.compile``, at W windows per member.
5. **Training loop** (``train_ensemble``, ``LOOP_STEPS`` steps and one validation, on random
   episodes of the Pusher's shapes): what a training run pays per step on top of section 4,
   the windows sampled on the host and copied to the device, the per-member gradient
   clipping, the learning-rate schedule and the validation; eager and with
   ``TrainConfig(compile=True)``, at W windows per member.

Model steps are member x trajectory x step; rows also give their share of the device's float32
matrix-product peak (measured here: an 8192² product on a GPU, 1024² on a CPU core).

    python benchmarks/gpu_throughput.py --device cuda [--sizes 1024 16384 131072]
                                        [--windows 64 1024 8192] [--repeats 5] [--no-compile]
                                        [--sections training training_loop ...]

On a CPU (``--device cpu``, small ``--sizes``) the CUDA-graph rows are left out. Writes
``benchmarks/results/gpu_throughput.json`` (``--out`` names another file).
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections.abc import Callable
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch
from _report import (
    benchmark_device,
    conditions,
    interleaved_median_times,
    print_table,
    synchronize,
    write_json,
)
from compiled_step import HORIZON as IMAGINE_HORIZON
from compiled_step import first_call_s, imagination
from model_step import (
    HORIZON,
    MEMBERS,
    PARTICLES,
    matmul_peak_flops,
    scoring_call,
    step_flop,
    study_ensemble,
)
from tensordict import TensorDict
from world_model_speed import DEFAULT, train_step

from rcvae_torchrl.data import TRAJ_KEY
from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout import Task, imagine
from rcvae_torchrl.training import TrainConfig, train_ensemble

SECTIONS = ("plan_scoring", "imagination_steps", "forecast_imagine", "training", "training_loop")
TRAINING_SECTIONS = ("training", "training_loop")
LENGTH = 32
LOOP_STEPS = 100
SIZES = (1024, 16384, 131072)
WINDOWS = (64, 1024, 8192)
GOAL_STEPS_PER_S = 50e6  # imagination on one H100, the study model


def cuda_graph(run: Callable[[], None]) -> Callable[[], None]:
    """``run`` captured in one CUDA graph; returns its replay. ``run`` must make the same kernel
    launches on every call and no host synchronisation (warmed up twice on a side stream first,
    as capture requires)."""
    stream = torch.cuda.Stream()
    stream.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(stream):
        run()
        run()
    torch.cuda.current_stream().wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        run()
    return graph.replay


def scoring_rows(model: RCVAEEnsemble, task: Task, per_member: int, compile_: bool) -> dict:
    """``{row: (call, model steps per call)}`` for plan scoring at ``per_member``."""
    candidates = math.ceil(per_member * MEMBERS / PARTICLES)
    steps = candidates * PARTICLES * HORIZON
    rows = {"eager": (lambda: scoring_call(model, task, candidates), steps)}
    if compile_:
        rows["compile=True"] = (lambda: scoring_call(model, task, candidates, True), steps)
    return rows


def step_rows(
    model: RCVAEEnsemble, per_member: int, compiled_step: Callable | None, graphs: bool
) -> dict:
    """``{row: (call, model steps per call)}`` for ``IMAGINE_HORIZON`` bare model steps."""
    device, steps = model.device, MEMBERS * per_member * IMAGINE_HORIZON
    calls = {"eager": imagination(model, per_member, False)}
    if compiled_step is not None:
        calls["torch.compile"] = imagination(model, per_member, True, step=compiled_step)
    rows = {name: (call, steps, first_call_s(call, device)) for name, call in calls.items()}
    if graphs:  # first call: the capture (after the first calls above)
        for name, call in calls.items():
            start = time.perf_counter()
            try:
                replay = cuda_graph(call)
            except Exception as error:  # (recorded as the row's result)
                rows[f"{name} + CUDA graph"] = (error, steps)
                continue
            rows[f"{name} + CUDA graph"] = (replay, steps, time.perf_counter() - start)
    return rows


def forecast_rows(model: RCVAEEnsemble, per_member: int) -> dict:
    """``{row: (call, model steps per call)}`` for the forecast's ``imagine``."""
    device = model.device
    gen = torch.Generator(device).manual_seed(0)
    start = torch.zeros(14, device=device)
    actions = torch.rand(IMAGINE_HORIZON, 2, generator=gen, device=device) * 2 - 1
    steps = MEMBERS * per_member * IMAGINE_HORIZON

    def run(chunk: int | str | None) -> None:
        imagine(model, start, actions, samples_per_member=per_member, chunk_size=chunk)

    return {
        "imagine, chunks of 1024": (lambda: run(1024), steps),
        "imagine, one chunk": (lambda: run(None), steps),
        'imagine, chunk_size="auto"': (lambda: run("auto"), steps),
    }


def training_rows(windows: int, device: torch.device, compile_: bool) -> dict:
    """``{row: (call, transitions per call)}`` for a training step on ``windows`` per member."""
    transitions = MEMBERS * windows * LENGTH
    rows = {"eager": (train_step(DEFAULT, MEMBERS, device, windows, LENGTH), transitions)}
    if compile_:
        call = train_step(DEFAULT, MEMBERS, device, windows, LENGTH, compiled=True)
        rows["loss under torch.compile"] = (call, transitions)
    return rows


def random_episodes(episodes: int, steps: int, seed: int) -> TensorDict:
    """Flat episodes ``[frames]`` of the Pusher's shapes (S = 14, A = 2): random walks (speed
    does not depend on the values)."""
    gen = torch.Generator().manual_seed(seed)
    states = torch.randn(episodes, steps + 1, 14, generator=gen).cumsum(1) * 0.01
    data = TensorDict(
        {
            "observation": states[:, :-1],
            "action": torch.rand(episodes, steps, 2, generator=gen) * 2 - 1,
            ("next", "observation"): states[:, 1:],
            TRAJ_KEY: torch.arange(episodes)[:, None].expand(episodes, steps),
            ("next", "done"): torch.zeros(episodes, steps, 1, dtype=torch.bool),
        },
        batch_size=[episodes, steps],
    )
    data["next", "done"][:, -1] = True
    return data.reshape(-1)


def loop_rows(windows: int, device: torch.device, compile_: bool) -> dict:
    """``{row: (call, transitions per call)}`` for ``LOOP_STEPS`` steps of ``train_ensemble``
    (one validation at the end) on ``windows`` per member."""
    train, val = random_episodes(40, 200, seed=0), random_episodes(8, 200, seed=1)
    val[TRAJ_KEY] += 40
    transitions = MEMBERS * windows * LENGTH * LOOP_STEPS
    rows = {}
    for name, compiled in (("train_ensemble", False), ("train_ensemble, compile=True", True)):
        if compiled and not compile_:
            continue
        model = study_ensemble(device)
        config = TrainConfig(
            max_steps=LOOP_STEPS,
            batch_windows=windows,
            window=LENGTH,
            val_every=LOOP_STEPS,
            compile=compiled,
        )

        def run(model: RCVAEEnsemble = model, config: TrainConfig = config) -> None:
            # 8 validation episodes measure no dynamics check: none asked for (no warning)
            train_ensemble(model, train, val, config, progress=False, checks=False, dynamics=False)

        rows[name] = (run, transitions)
    return rows


def measure(
    rows: dict[str, tuple],
    repeats: int,
    device: torch.device,
    flop_per_unit: float | None,
    peak: float,
) -> dict[str, dict[str, Any]]:
    """Each row ``(call, units per call[, seconds of its first call])``: its first call (unless
    given), then interleaved medians; units (model steps or transitions) per second, and with
    ``flop_per_unit`` the share of ``peak``. A row that fails records why."""
    first, runs, out = {}, {}, {}
    for name, (call, _, *first_s) in rows.items():
        if isinstance(call, Exception):  # the row could not be built
            out[name] = {"error": _error(call)}
            continue
        try:
            first[name] = first_s[0] if first_s else first_call_s(call, device)
            runs[name] = call
        except Exception as error:  # (one failing variant must not end the run)
            out[name] = {"error": _error(error)}
    times = interleaved_median_times(runs, repeats, warmup=1, device=device)
    for name, t in times.items():
        units = rows[name][1]
        out[name] = {
            "first_call_s": first[name],
            "median_s": t["wall_s"],
            "per_s": units / t["wall_s"],
        }
        if flop_per_unit is not None:
            out[name]["peak_share"] = units * flop_per_unit / t["wall_s"] / peak
    return out


def _error(error: Exception) -> str:
    return f"{type(error).__name__}: {error}"[:500]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="cuda, cuda:N or cpu")
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    parser.add_argument("--windows", type=int, nargs="+", default=list(WINDOWS))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-compile", action="store_true", help="eager rows only")
    parser.add_argument(
        "--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS), help="what to run"
    )
    parser.add_argument("--out", default="gpu_throughput", help="results/<out>.json")
    args = parser.parse_args()
    device = benchmark_device(args.device)
    for name in ("sizes", "windows"):
        if min(getattr(args, name)) < 1:
            raise SystemExit(f"--{name}: expected positive counts, got {getattr(args, name)}")
    compile_, graphs = not args.no_compile, device.type == "cuda"
    started = time.perf_counter()
    peak = matmul_peak_flops(device)
    model = study_ensemble(device)
    task = Task(pusher_reward, pusher_success, terminate_on_success=True)
    flop = step_flop(model, 64)
    compiled_step = torch.compile(model.step, dynamic=True) if compile_ else None
    record: dict[str, Any] = {
        "conditions": conditions(device),
        "torch": torch.__version__,
        "matmul_peak_flops": peak,
        "step_kflop": flop / 1e3,
        "goal_model_steps_per_s": GOAL_STEPS_PER_S,
        "members": MEMBERS,
        "repeats": args.repeats,
    }
    sections = {
        "plan_scoring": lambda n: scoring_rows(model, task, n, compile_),
        "imagination_steps": lambda n: step_rows(model, n, compiled_step, graphs),
        "forecast_imagine": lambda n: forecast_rows(model, n),
    }
    sections = {name: rows_of for name, rows_of in sections.items() if name in args.sections}
    table = []
    for section, rows_of in sections.items():
        record[section] = {}
        for n in args.sizes:
            try:
                with torch.no_grad():
                    result = measure(rows_of(n), args.repeats, device, flop, peak)
            except Exception as error:  # (the other sections still run)
                result = {"all rows": {"error": _error(error)}}
            record[section][str(n)] = result
            for name, r in result.items():
                table.append([section, n, name, *_cells(r, scale=1e6)])
            write_json(args.out, record)  # what has run so far survives a later failure
    rows_of_training = {"training": training_rows, "training_loop": loop_rows}
    for section in (s for s in TRAINING_SECTIONS if s in args.sections):
        record[section] = {}
        for w in args.windows:
            rows = rows_of_training[section](w, device, compile_)
            result = measure(rows, args.repeats, device, None, peak)
            record[section][str(w)] = result
            for name, r in result.items():
                table.append([section, w, name, *_cells(r, scale=1e6)])
            write_json(args.out, record)
    best = max(
        (r["per_s"] for s in sections for rows in record[s].values() for r in rows.values()
         if "per_s" in r),
        default=0.0,
    )  # fmt: skip
    record["best_model_steps_per_s"] = best
    record["total_s"] = time.perf_counter() - started
    print_table(
        f"{record['conditions']['device']}, fp32 matmul peak {peak / 1e12:.1f} TFLOP/s, "
        f"{flop / 1e3:.1f} kFLOP per model step (M = million model steps or transitions)",
        ["section", "N or W per member", "row", "M/s", "median s", "first call s", "% peak"],
        table,
    )
    print(f"\nbest imagination: {best / 1e6:.1f} M model steps/s "
          f"(goal {GOAL_STEPS_PER_S / 1e6:.0f} M/s on one H100)")  # fmt: skip
    write_json(args.out, record)
    synchronize(device)


def _cells(result: dict[str, Any], scale: float) -> list[Any]:
    if "error" in result:
        return [result["error"][:60], "", "", ""]
    share = result.get("peak_share")
    return [
        result["per_s"] / scale,
        result["median_s"],
        result["first_call_s"],
        "" if share is None else f"{100 * share:.1f}",
    ]


if __name__ == "__main__":
    main()

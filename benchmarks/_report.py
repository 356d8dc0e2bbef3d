"""Shared helpers of the benchmark scripts: timing medians, a printed table, atomic JSON."""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

RESULTS_DIR = Path(__file__).resolve().parent / "results"
# the benchmarks of a study import its recipe (not installed): the repository root
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rcvae_torchrl.io import write_json as atomic_json  # noqa: E402  (after the path is set)


def conditions(device: torch.device | str | None = None) -> dict[str, Any]:
    """What a timing ran under: torch's intra-op threads and the machine's 1-minute load average
    (runnable processes, all users; on a 2-core machine anything above 1 means this benchmark
    shared its cores), and with ``device`` the device's name (a GPU's model). Recorded next to
    every figure."""
    out = {"threads": torch.get_num_threads(), "load_1min": round(os.getloadavg()[0], 2)}
    if device is not None:
        out["device"] = device_name(device)
    return out


def device_name(device: torch.device | str) -> str:
    """``"cpu"``, or a CUDA device with its model (``"cuda:0 (NVIDIA H100 80GB HBM3)"``)."""
    device = torch.device(device)
    if device.type != "cuda":
        return str(device)
    index = device.index if device.index is not None else torch.cuda.current_device()
    return f"cuda:{index} ({torch.cuda.get_device_name(index)})"


def benchmark_device(name: str) -> torch.device:
    """The ``--device`` of a benchmark: ``cpu``, ``cuda`` or ``cuda:N``, refused with the reason
    when this machine has no such device."""
    try:
        device = torch.device(name)
    except RuntimeError:
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise SystemExit(f"--device: expected cpu, cuda or cuda:N, got {name!r}")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"--device: {name!r} asked for, but torch sees no CUDA device here")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        raise SystemExit(
            f"--device: {name!r} asked for, but torch sees {torch.cuda.device_count()} GPU(s)"
        )
    return device


def synchronize(device: torch.device | str | None) -> None:
    """Wait for the work queued on ``device`` (a GPU runs kernels asynchronously: a timing
    must end when they have run, not when they were launched); nothing on the CPU."""
    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def median_time(fn: Callable[[], Any], repeats: int = 5, warmup: int = 1) -> float:
    """Median wall-clock seconds of ``fn()`` over ``repeats`` calls, after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def interleaved_median_times(
    fns: Mapping[str, Callable[[], Any]],
    repeats: int = 5,
    warmup: int = 1,
    device: torch.device | str | None = None,
) -> dict[str, dict[str, float]]:
    """Median seconds of each ``fn()``, every fn timed once per round, in turn, after ``warmup``
    rounds: on a shared machine the load drifts, and interleaving spreads it over all fns alike,
    so their ratios hold up better than those of back-to-back timings.

    Returns ``{name: {"wall_s": ..., "cpu_s": ..., "threads": ..., "load_1min": ...}}``:
    wall-clock seconds, and CPU seconds of this process (all its threads, not its child
    processes), which other jobs on the machine barely change: for a single-threaded fn, what it
    would take on a free core; the thread count and the highest 1-minute load average seen
    while timing (see :func:`conditions`). On a CUDA ``device`` every call is timed until its
    kernels have run (:func:`synchronize`).
    """
    for _ in range(warmup):
        for fn in fns.values():
            fn()
            synchronize(device)
    wall: dict[str, list[float]] = {name: [] for name in fns}
    cpu: dict[str, list[float]] = {name: [] for name in fns}
    load = [os.getloadavg()[0]]
    for _ in range(repeats):
        for name, fn in fns.items():
            start, start_cpu = time.perf_counter(), time.process_time()
            fn()
            synchronize(device)
            wall[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
        load.append(os.getloadavg()[0])
    return {
        name: {
            "wall_s": statistics.median(wall[name]),
            "cpu_s": statistics.median(cpu[name]),
            "threads": torch.get_num_threads(),
            "load_1min": round(max(load), 2),
        }
        for name in fns
    }


def print_table(title: str, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Print rows as a fixed-width table (floats with 4 significant digits)."""
    cells = [[f"{c:.4g}" if isinstance(c, float) else str(c) for c in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) for i, h in enumerate(header)]
    print(f"\n{title}")
    print("  ".join(h.ljust(w) for h, w in zip(header, widths)))
    print("  ".join("-" * w for w in widths))
    for row in cells:
        print("  ".join(c.ljust(w) for c, w in zip(row, widths)))


def machine_info() -> dict[str, Any]:
    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
        # figures differ by processor: the same 2-core VM has been an Intel Xeon and an AMD EPYC
        "cpu_model": _cpu_model(),
    }


def _cpu_model() -> str | None:
    """The processor's name as the OS gives it (``/proc/cpuinfo``'s model name on Linux)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def write_json(name: str, payload: dict[str, Any]) -> Path:
    """Write ``payload`` (plus machine info) to ``benchmarks/results/<name>.json`` atomically."""
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    path = RESULTS_DIR / f"{name}.json"
    payload = {"benchmark": name, "machine": machine_info(), **payload}
    atomic_json(path, payload)  # the user's umask, like every file of the project
    print(f"\nwrote {path}")
    return path

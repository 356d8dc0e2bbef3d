"""Does a second torch thread pay, and does ``threads="auto"`` ever lose to one thread?

Times, at 1 thread, at every core (torch's default) and at the count ``choose_threads`` picks,
each op once per round in turn (medians of interleaved rounds, wall seconds), with the thread
count and the machine's load next to every figure: float32 matmuls of the world model's width
(64 -> 192, the GRU gates) at the row counts of a training step (5 members x 32 windows), of
plan scoring (5 x 64 trajectories x particles) and larger; and the histogram decomposition with
the study's settings. Writes ``benchmarks/results/threads.json``.

    python benchmarks/threads.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import time

import torch
from _report import conditions, print_table, write_json
from competency import study_settings_cases

from rcvae_torchrl.competency import decompose_uncertainty
from rcvae_torchrl.threads import choose_threads

ROWS = [160, 1280, 10_240, 81_920]


def matmul_case(rows: int) -> tuple[functools.partial, float]:
    gen = torch.Generator().manual_seed(0)
    x, w = torch.randn(rows, 64, generator=gen), torch.randn(64, 192, generator=gen)
    return functools.partial(torch.mm, x, w), 2.0 * rows * 64 * 192


def timed(fn, threads: int, repeats: int) -> float:
    """Median wall seconds of ``fn`` with ``threads`` threads, enough calls to last ~20 ms."""
    torch.set_num_threads(threads)
    fn()
    start = time.perf_counter()
    fn()
    calls = max(1, int(0.02 / max(time.perf_counter() - start, 1e-7)))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        times.append((time.perf_counter() - start) / calls)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    cores = len(os.sched_getaffinity(0))
    cases = {f"matmul [{r}, 64] x [64, 192]": matmul_case(r) for r in ROWS}
    samples, study = study_settings_cases((5, 100, 600, 14))[
        "study: resolution bins + episode end + shuffle (4)"
    ]
    cases["decomposition, study settings [5, 100, 600, 14]"] = (
        functools.partial(decompose_uncertainty, samples, **study),
        None,
    )
    rows = []
    for name, (fn, flop) in cases.items():
        auto = choose_threads(flop)
        counts = sorted({1, cores, auto})
        seconds = {t: [] for t in counts}
        for _ in range(3):  # interleave the thread counts
            for t in counts:
                seconds[t].append(timed(fn, t, args.repeats))
        median = {t: sorted(v)[1] for t, v in seconds.items()}
        rows.append(
            {
                "case": name,
                "op_flop": flop,
                "seconds_by_threads": median,
                "auto_threads": auto,
                "auto_over_1": median[auto] / median[1],
                "all_cores_over_1": median[cores] / median[1],
                **conditions(),
            }
        )
    torch.set_num_threads(1)
    print_table(
        f"seconds per call by thread count ({cores} cores); auto = choose_threads(op FLOP)",
        ["case", "load", "1 thread s", f"{cores} threads s", "auto", "auto/1", f"{cores}/1"],
        [
            [
                r["case"], r["load_1min"], r["seconds_by_threads"][1],
                r["seconds_by_threads"][cores], r["auto_threads"], r["auto_over_1"],
                r["all_cores_over_1"],
            ]
            for r in rows
        ],
    )  # fmt: skip
    write_json("threads", {"cores": cores, "rows": rows})


if __name__ == "__main__":
    main()

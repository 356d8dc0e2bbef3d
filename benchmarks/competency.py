"""Speed and memory of the competency estimators.

First, the histogram decomposition with the study's settings (per-dimension resolution bins, an
episode-end mask, the shuffle correction with 4 permutations) on [E, N, T, D] = [5, 100, 600, 14],
against the implementation it replaced (``_decomposition_before.py``) in the same run: every case
timed once per round, in turn (medians of interleaved rounds, wall and CPU seconds), and both
results compared. The samples are random walks in the Pusher's units (the resolution bins span
12-500 bins per column, about 110 on average); every sample ends at a uniformly drawn step.

Times ``decompose_uncertainty`` on imagined rollouts of the paper's size (E=5 members, N=100
samples each, T=600 steps, D=14 dimensions) for every estimator (median of ``--repeats``; k-NN
3 repeats), with one intra-op thread and with torch's default (on a shared 2-core machine other
jobs make the threaded timings noisy, so both are recorded with the load average), and runs
the histogram decomposition once on N·T = 1e7 (E=5, N=1000, T=10000, D=2) in a child process to
report its peak resident memory next to the input's size. Last, ``CompetencyAssessor``: a 30 s
open-loop forecast (600 steps of 0.05 s) plus the full report and its summary for one start
state with a Pusher-sized ensemble (E=5 members, N=20 samples each, untrained, normaliser fitted
on random data), with 1 and 2 intra-op threads (target: at most 2 s).

    python benchmarks/competency.py [--repeats 5] [--quick]
"""

from __future__ import annotations

import argparse
import functools
import math
import multiprocessing
import os
import resource
import time
from typing import Any

import torch
from _decomposition_before import histogram_decomposition_before
from _report import conditions, interleaved_median_times, median_time, print_table, write_json

from rcvae_torchrl.competency import CompetencyAssessor, SuccessBoundary, decompose_uncertainty
from rcvae_torchrl.competency import decomposition as decomposition_module
from rcvae_torchrl.envs import (
    OBSERVATION_NAMES,
    obs_indices,
    pusher_reward,
    pusher_success,
    resolution_tensor,
)
from rcvae_torchrl.model_env import RCVAEEnsembleEnv
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble

ASSESSOR_TARGET_S = 2.0
STUDY_SETTINGS_TARGET_S = 0.5

# name, estimator, arguments; bin width 0.1 spans ~80 bins per unit-variance dimension (counting
# path), 0.002 spans ~4000 (sorting path).
CASES: list[tuple[str, str, dict[str, Any]]] = [
    ("histogram", "histogram", {"bin_width": 0.1}),
    ("histogram, fine bins (sort path)", "histogram", {"bin_width": 0.002}),
    (
        "histogram, shuffle-corrected (4 permutations)",
        "histogram",
        {"bin_width": 0.1, "bias_correction": "shuffle"},
    ),
    ("gaussian per dim", "gaussian", {}),
    ("gaussian joint", "gaussian", {"joint": True}),
    ("mixture bounds (diagonal)", "mixture", {}),
    ("mixture bounds (full cov)", "mixture", {"full_covariance": True}),
    ("knn (k=3)", "knn", {"k": 3}),
]


def rollout_like(members: int, samples: int, steps: int, dim: int) -> torch.Tensor:
    """Random-walk trajectories ``[E, N, T, D]`` whose members drift apart over time."""
    gen = torch.Generator().manual_seed(0)
    drift = torch.randn(members, 1, 1, dim, generator=gen) * 0.01
    steps_noise = torch.randn(members, samples, steps, dim, generator=gen) * 0.05
    return (steps_noise + drift).cumsum(dim=2) + torch.randn(dim, generator=gen)


def _before_estimator(
    samples: torch.Tensor,
    *,
    bin_width: Any,
    ended: torch.Tensor | None = None,
    bias_correction: str = "none",
    shuffles: int = 4,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The replaced histogram estimator, with the library's estimator signature."""
    width = torch.as_tensor(bin_width).to(torch.float64)
    count = shuffles if bias_correction == "shuffle" else 0
    total, aleatoric = histogram_decomposition_before(samples, width, ended, count, generator)
    return total, aleatoric, math.log2(samples.shape[0])


def _decompose(samples: torch.Tensor, implementation: str, **args: Any) -> Any:
    """``decompose_uncertainty`` (checks included) with the current or the replaced estimator."""
    estimators = decomposition_module.ESTIMATORS
    current = estimators["histogram"]
    if implementation == "before":
        estimators["histogram"] = _before_estimator
    try:
        return decompose_uncertainty(samples, "histogram", **args)
    finally:
        estimators["histogram"] = current


def study_settings_cases(
    shape: tuple[int, int, int, int],
) -> dict[str, tuple[torch.Tensor, dict[str, Any]]]:
    """Samples in the Pusher's units and the settings, from the plain call to the study's; last,
    the study's settings on samples spread 10 times wider (hundreds to thousands of bins per
    column: the sorting path of the replaced implementation)."""
    members, n, steps, _ = shape
    samples = rollout_like(*shape) * 0.1
    gen = torch.Generator().manual_seed(2)
    ended = torch.rand(members, n, 1, generator=gen) * steps < torch.arange(steps)
    width = resolution_tensor()
    study = {"bin_width": width, "ended": ended, "bias_correction": "shuffle"}
    return {
        "plain (one width 0.01)": (samples, {"bin_width": 0.01}),
        "resolution bins": (samples, {"bin_width": width}),
        "resolution bins + episode end": (samples, {"bin_width": width, "ended": ended}),
        "study: resolution bins + episode end + shuffle (4)": (samples, study),
        "study settings, samples spread 10x wider": (samples * 10.0, study),
    }


def time_study_settings(shape: tuple[int, int, int, int], repeats: int) -> list[dict[str, Any]]:
    """Before vs now for each setting, interleaved, with the largest difference of results."""
    cases = study_settings_cases(shape)
    runs = {}
    for case, (samples, args) in cases.items():
        for implementation in ("before", "now"):
            runs[case, implementation] = functools.partial(
                _decompose, samples, implementation, generator=torch.Generator(), **args
            )
    times = interleaved_median_times(runs, repeats)
    rows = []
    for case, (samples, args) in cases.items():
        before, now = (
            _decompose(samples, impl, generator=torch.Generator().manual_seed(0), **args)
            for impl in ("before", "now")
        )
        differences = [
            float((getattr(before, k) - getattr(now, k)).abs().max())
            for k in ("total", "aleatoric", "epistemic")
        ]
        rows.append(
            {
                "case": case,
                "shape": list(shape),
                "before": times[case, "before"],
                "now": times[case, "now"],
                "before_over_now_wall": times[case, "before"]["wall_s"]
                / times[case, "now"]["wall_s"],
                "before_over_now_cpu": times[case, "before"]["cpu_s"] / times[case, "now"]["cpu_s"],
                "max_abs_difference_bits": max(differences),
                "repeats": repeats,
            }
        )
    plain = rows[0]["now"]["cpu_s"]
    for row in rows:
        row["now_over_plain_cpu"] = row["now"]["cpu_s"] / plain
    return rows


def time_estimators(
    shape: tuple[int, int, int, int], repeats: int, threads: int
) -> list[dict[str, Any]]:
    """Median seconds of each case with ``threads`` intra-op threads."""
    samples = rollout_like(*shape)
    default_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    results = []
    try:
        for name, estimator, args in CASES:
            reps = repeats if estimator != "knn" else min(repeats, 3)
            run = functools.partial(decompose_uncertainty, samples, estimator, **args)
            results.append(
                {
                    "case": name,
                    "estimator": estimator,
                    "args": args,
                    "shape": list(shape),
                    "threads": threads,
                    "repeats": reps,
                    "median_s": median_time(run, reps),
                    **conditions(),
                }
            )
    finally:
        torch.set_num_threads(default_threads)
    return results


def _peak_rss_mib() -> float:
    """High-water mark of this process's resident memory."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _current_rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _memory_child(shape: tuple[int, int, int, int], queue: multiprocessing.Queue) -> None:
    samples = torch.randn(*shape, generator=torch.Generator().manual_seed(0))
    with_input = _current_rss_mib()
    start = time.perf_counter()
    u = decompose_uncertainty(samples, bin_width=0.1)
    seconds = time.perf_counter() - start
    queue.put(
        {
            "shape": list(shape),
            "n_times_t": shape[1] * shape[2],
            "input_mib": samples.numel() * samples.element_size() / 2**20,
            "rss_with_input_mib": with_input,
            "peak_rss_mib": _peak_rss_mib(),
            "peak_over_rss_with_input_mib": max(0.0, _peak_rss_mib() - with_input),
            "seconds": seconds,
            "epistemic_mean_bits": float(u.epistemic.mean()),
        }
    )


def memory_bounded_run(shape: tuple[int, int, int, int]) -> dict[str, Any]:
    """Histogram decomposition in a fresh process, so its peak RSS is its own."""
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    child = context.Process(target=_memory_child, args=(shape, queue))
    child.start()
    result = queue.get()
    child.join()
    return result


def pusher_assessor(members: int, samples: int, steps: int, dt: float) -> CompetencyAssessor:
    """An assessor over an untrained Pusher-sized ensemble (normaliser fitted on random data)."""
    gen = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    config = RCVAEConfig(14, 2, hidden_dim=64, mlp_dim=64, passthrough_dims=(12, 13))
    model = RCVAEEnsemble(config, ensemble_size=members)
    obs = torch.randn(2000, 14, generator=gen) * 0.1
    actions = torch.rand(2000, 2, generator=gen) * 2 - 1
    model.fit_normalizer(obs, actions, next_observations=obs + 0.01 * torch.randn_like(obs))
    env = RCVAEEnsembleEnv(model, pusher_reward, pusher_success, seed=0)
    boundary = SuccessBoundary.ball(
        obs_indices("ball"), 0.03, target=obs_indices("target"), time_limit=steps, dt=dt
    )
    return CompetencyAssessor(
        env,
        boundary,
        bin_width=resolution_tensor(),
        dim_names=OBSERVATION_NAMES,
        samples_per_member=samples,
    )


def time_assessor(
    steps: int, repeats: int, threads: int, members: int = 5, samples: int = 20
) -> dict[str, Any]:
    """Median seconds of one open-loop assessment (imagine + report + summary), one start."""
    dt = 0.05
    assessor = pusher_assessor(members, samples, steps, dt)
    gen = torch.Generator().manual_seed(1)
    start = torch.randn(14, generator=gen) * 0.1
    plan = torch.rand(steps, 2, generator=gen) * 2 - 1

    def run() -> str:
        return assessor.assess(start, actions=plan, generator=gen).summary()

    default_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        seconds = median_time(run, repeats)
        measured_under = conditions()
    finally:
        torch.set_num_threads(default_threads)
    return {
        "case": "open-loop forecast + full report + summary, one start state",
        "members": members,
        "samples_per_member": samples,
        "steps": steps,
        "horizon_s": steps * dt,
        **measured_under,
        "repeats": repeats,
        "median_s": seconds,
        "target_s": ASSESSOR_TARGET_S,
        "summary": run(),
    }


def report_study_settings(shape: tuple[int, int, int, int], repeats: int) -> list[dict[str, Any]]:
    """Time and print the before/now table of the study's settings (1 thread)."""
    default_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        study = time_study_settings(shape, repeats)
    finally:
        torch.set_num_threads(default_threads)
    print_table(
        f"histogram decomposition on {list(shape)}, before vs now (medians of {repeats} "
        f"interleaved rounds; target <= {STUDY_SETTINGS_TARGET_S} s with the study's settings)",
        [
            "case", "threads", "load", "before s", "now s", "before/now", "before cpu s",
            "now cpu s", "before/now cpu", "now/plain cpu", "max |diff| bits",
        ],
        [
            [
                r["case"], r["now"]["threads"], r["now"]["load_1min"], r["before"]["wall_s"],
                r["now"]["wall_s"], r["before_over_now_wall"], r["before"]["cpu_s"],
                r["now"]["cpu_s"], r["before_over_now_cpu"], r["now_over_plain_cpu"],
                r["max_abs_difference_bits"],
            ]
            for r in study
        ],
    )  # fmt: skip
    return study


def report_estimators(shape: tuple[int, int, int, int], repeats: int) -> list[dict[str, Any]]:
    thread_counts = sorted({1, torch.get_num_threads()})
    timings = [r for t in thread_counts for r in time_estimators(shape, repeats, t)]
    print_table(
        f"decompose_uncertainty on [E, N, T, D] = {list(shape)} (median of repeats)",
        ["case", "threads", "load", "repeats", "median s"],
        [[r["case"], r["threads"], r["load_1min"], r["repeats"], r["median_s"]] for r in timings],
    )
    return timings


def report_memory(shape: tuple[int, int, int, int]) -> dict[str, Any]:
    memory = memory_bounded_run(shape)
    print_table(
        f"histogram decomposition, N·T = {memory['n_times_t']:.0e}, shape {memory['shape']}",
        ["input MiB", "RSS with input MiB", "peak RSS MiB", "peak over that MiB", "seconds"],
        [
            [
                memory["input_mib"],
                memory["rss_with_input_mib"],
                memory["peak_rss_mib"],
                memory["peak_over_rss_with_input_mib"],
                memory["seconds"],
            ]
        ],
    )
    return memory


def report_assessor(steps: int, repeats: int) -> list[dict[str, Any]]:
    assessor = [time_assessor(steps, repeats, t) for t in (1, 2)]
    print_table(
        f"CompetencyAssessor, {steps} steps x 0.05 s open loop, E=5, N=20, one start state "
        f"(median of repeats; target <= {ASSESSOR_TARGET_S} s for 600 steps)",
        ["threads", "load", "repeats", "median s"],
        [[r["threads"], r["load_1min"], r["repeats"], r["median_s"]] for r in assessor],
    )
    print(f"\nsummary: {assessor[0]['summary']}")
    return assessor


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per case (>= 5)")
    parser.add_argument("--quick", action="store_true", help="small shapes, for a smoke run")
    parser.add_argument(
        "--only-study-settings",
        action="store_true",
        help="time only the before/now table of the study's settings",
    )
    args = parser.parse_args()
    if args.repeats < 5:
        parser.error(f"--repeats: expected at least 5, got {args.repeats}")
    shape = (5, 20, 100, 14) if args.quick else (5, 100, 600, 14)
    load_before = os.getloadavg()
    payload: dict[str, Any] = {
        "quick": args.quick,
        "study_settings": report_study_settings(shape, args.repeats),
    }
    if not args.only_study_settings:
        big = (5, 100, 1000, 2) if args.quick else (5, 1000, 10_000, 2)
        payload["timings"] = report_estimators(shape, args.repeats)
        payload["memory_bounded"] = report_memory(big)
        payload["assessor"] = report_assessor(100 if args.quick else 600, args.repeats)
    name = "competency_study_settings" if args.only_study_settings else "competency"
    write_json(
        name,
        {**payload, "load_average_before": load_before, "load_average_after": os.getloadavg()},
    )


if __name__ == "__main__":
    main()

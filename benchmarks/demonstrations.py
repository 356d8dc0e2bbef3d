"""The agent's MPC demonstrations one at a time against side by side (``agent.demo_envs``), and
one plan at the run's budget, on a finished Pusher study run's deterministic world model.

    python benchmarks/demonstrations.py RUN_DIR [--side-by-side 15] [--repeats 3] \\
        [--threads 1] [--device cpu] [--out demonstrations]

Times the study's MPC demonstrations (``agent.mpc_episodes`` episodes with the executed action
perturbed, the run's own settings) with ``agent.demo_envs`` 1 and ``--side-by-side``, every
setting once per round in turn (medians over ``--repeats`` rounds), and one plan from a start
state (median of 5). Prints a table and writes ``benchmarks/results/<out>.json`` with the thread
count, the load and the device. Side by side the planner and the noise draw for all states at
once, so the episodes differ from the one-at-a-time run's: their success rate and median length
are reported beside the times. ``--plan-only`` times the plan alone (for budgets whose
demonstrations take too long where the benchmark runs, e.g. the ``full`` profile on a CPU).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import torch
from _report import (
    benchmark_device,
    conditions,
    interleaved_median_times,
    median_time,
    print_table,
    write_json,
)

from recipes.pusher_competency.pipeline import study_of_run


def measure(
    run_dir: Path, side_by_side: int, repeats: int, device: torch.device, plan_only: bool = False
) -> dict:
    """The time of one plan, and unless ``plan_only`` the demonstrations' times and outcomes at
    ``demo_envs`` 1 and ``side_by_side``."""
    studies = {
        n: study_of_run(run_dir, device, changes={"agent": {"demo_envs": n}})
        for n in (1, side_by_side)
    }
    model = studies[1].load_model("deterministic")
    horizon = studies[1].cfg.assess.horizon_s
    env = studies[1].env("deterministic", time_limit=horizon)
    planner, start = studies[1].planner(model, env), env.reset()

    def plan() -> None:
        planner.reset()
        planner(start.clone())

    info: dict[int, Any] = {}

    def demos(n: int):
        return lambda: info.__setitem__(n, studies[n]._demonstrations(model, env)["info"])

    times = {}
    if not plan_only:
        times = interleaved_median_times(
            {n: demos(n) for n in studies}, repeats=repeats, warmup=0, device=device
        )
    return {
        "demonstrations": {
            str(n): {**times[n], **{k: float(v) for k, v in info[n].items()}} for n in times
        },
        "plan_s": median_time(plan, repeats=5),
        "planner": str(studies[1].cfg.planner),
        "mpc_episodes": studies[1].cfg.agent.mpc_episodes,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--side-by-side", type=int, default=15)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--plan-only", action="store_true")
    parser.add_argument("--out", default="demonstrations")
    args = parser.parse_args()
    if args.side_by_side < 2:
        raise SystemExit(f"--side-by-side: expected at least 2 envs, got {args.side_by_side}")
    if not (args.run_dir / "models" / "deterministic.pt").is_file():
        raise SystemExit(f"run_dir: expected a finished study run, got {str(args.run_dir)!r}")
    torch.set_num_threads(args.threads)
    device = benchmark_device(args.device)
    result = measure(args.run_dir, args.side_by_side, args.repeats, device, args.plan_only)
    payload = {
        "run_dir": str(args.run_dir),
        "repeats": args.repeats,
        "conditions": conditions(device),
    }
    if args.plan_only:
        print_table(
            "One plan, median of 5", ["planner", "s"], [[result["planner"], result["plan_s"]]]
        )
        write_json(args.out, {**payload, **result})
        return
    rows = [
        [
            "one at a time" if n == "1" else f"{n} side by side",
            r["wall_s"],
            r["cpu_s"],
            r["mpc_noisy_success_rate"],
            r["mpc_median_steps"],
            int(r["pairs"]),
        ]
        for n, r in result["demonstrations"].items()
    ]
    one, many = (result["demonstrations"][k]["wall_s"] for k in result["demonstrations"])
    print_table(
        f"MPC demonstrations ({result['mpc_episodes']} episodes), medians of {args.repeats} "
        f"interleaved rounds; one plan {result['plan_s']:.3f} s",
        ["demonstrations", "wall s", "CPU s", "success", "median steps", "pairs"],
        rows,
    )
    print(f"side by side / one at a time: {many / one:.2f}x the time")
    write_json(args.out, {**payload, "side_by_side_over_one_at_a_time": many / one, **result})


if __name__ == "__main__":
    main()

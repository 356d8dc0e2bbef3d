"""The MPC agent on the real Pusher: success, planning latency, and the stock TorchRL planner.

Uses (or trains, with the study's default data and model budgets) a deterministic-variant
ensemble, then measures:

- success within 30 s of our CEM planner at the default budget over ``--episodes`` in-distribution
  episodes, and over fewer stochastic and out-of-distribution episodes;
- planning latency per control step (median and 95th percentile) against the 0.05 s control step;
- TorchRL's stock ``CEMPlanner`` over the same model env at the same budget (candidates x
  iterations x horizon): time per plan on the same states (ratio from the same run) and success
  on the same ``--compare-episodes`` seeds.

    python benchmarks/planning.py [--episodes 50] [--compare-episodes 10] [--threads 1]

``--speed-only`` measures only the time per plan against the stock planner (ours eager and with
``compile=True``; C x I x H = 64 x 2 x 12 and 200 x 4 x 15, P = 1 and 5, no policy prior) and
the latency at the default budget, on the saved ``deterministic`` model of ``--work-dir``, and
merges them into the existing results as ``"speed"``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from pathlib import Path

import torch
from _report import RESULTS_DIR, print_table, write_json
from torchrl.modules.planners import CEMPlanner as StockCEMPlanner

from rcvae_torchrl.agent import PlannerConfig, run_episodes
from rcvae_torchrl.envs import CONTROL_TIMESTEP, make_pusher_env, pusher_reward, pusher_success
from rcvae_torchrl.model_env import make_rcvae_env
from rcvae_torchrl.training import load_ensemble
from recipes.pusher_competency.config import StudyConfig
from recipes.pusher_competency.pipeline import Study
from recipes.pusher_competency.pusher import MODEL_FUNCTIONS, make_planner

SPEED_BUDGETS = ((64, 2, 12), (200, 4, 15))  # candidates, iterations, horizon


class Timed:
    """Wraps a policy and records the wall time of every call."""

    def __init__(self, policy) -> None:
        self.policy, self.times = policy, []

    def reset(self) -> None:
        if hasattr(type(self.policy), "reset"):
            self.policy.reset()

    def __call__(self, td):
        start = time.perf_counter()
        out = self.policy(td)
        self.times.append(time.perf_counter() - start)
        return out


def _stock(model_env, config: PlannerConfig) -> StockCEMPlanner:
    return StockCEMPlanner(
        model_env,
        planning_horizon=config.horizon,
        optim_steps=config.iterations,
        num_candidates=config.num_candidates,
        top_k=config.top_k,
    )


def _episodes(env, policy, seeds, label):
    timed = Timed(policy)
    stats = run_episodes(env, timed, seeds=seeds, max_steps=600, progress=True, desc=label)
    times = sorted(timed.times)
    return {
        "episodes": len(seeds),
        "success_rate": stats.success_rate,
        "median_steps_to_success": stats.steps[stats.success].float().median().item()
        if stats.success.any()
        else float("nan"),
        "plan_s_median": statistics.median(times),
        "plan_s_p95": times[int(0.95 * (len(times) - 1))],
    }


def _plan_times(policy, states, repeats: int = 1) -> float:
    times = []
    for td in states:
        for _ in range(repeats):
            if hasattr(type(policy), "reset"):
                policy.reset()
            start = time.perf_counter()
            policy(td.clone())
            times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work-dir", type=Path, default=Path("outputs/benchmarks/study_default"))
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--other-episodes", type=int, default=20)
    parser.add_argument("--compare-episodes", type=int, default=10)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--speed-only", action="store_true")
    parser.add_argument("--rounds", type=int, default=3, help="speed: interleaved rounds")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.speed_only:
        speed(args)
        return
    if args.quick:
        args.episodes, args.other_episodes, args.compare_episodes = 4, 2, 2
    study = Study(StudyConfig(), args.work_dir, torch.device("cpu"), progress=True)
    study.data()
    study.models()
    model = study.load_model("deterministic")
    config = StudyConfig().planner
    results = {"planner_config": dataclasses.asdict(config), "control_step_s": CONTROL_TIMESTEP}

    env = make_pusher_env("deterministic")
    ours = make_planner(model, env, config)
    results["ours_deterministic"] = _episodes(env, ours, list(range(args.episodes)), "ours det")
    write_json("planning", {"partial": True, **results})
    for variant in ("stochastic", "ood"):
        results[f"ours_{variant}"] = _episodes(
            make_pusher_env(variant),
            make_planner(model, make_pusher_env(variant), config),
            list(range(1000, 1000 + args.other_episodes)),
            f"ours {variant}",
        )

    write_json("planning", {"partial": True, **results})
    model_env = make_rcvae_env(
        model, env, pusher_reward, pusher_success, terminate_on_success=True, seed=0
    )
    stock = _stock(model_env, config)
    ours_p1 = make_planner(model, env, dataclasses.replace(config, particles=1))
    seeds = list(range(args.compare_episodes))
    states = [env.reset() for _ in range(10)]
    t = {
        name: _plan_times(p, states)
        for name, p in [("ours", ours), ("ours_1_particle", ours_p1), ("stock", stock)]
    }
    results["plan_time_s"] = t
    results["speedup_vs_stock"] = {k: t["stock"] / t[k] for k in ("ours", "ours_1_particle")}
    results["stock_deterministic"] = _episodes(env, stock, seeds, "stock det")
    results["ours_same_episodes"] = _episodes(env, ours, seeds, "ours det (same)")

    print_table(
        "MPC agent in the real Pusher (success within 30 s)",
        ["planner", "variant", "episodes", "success", "plan s (median)", "plan s (p95)"],
        [
            [
                k.split("_")[0],
                k.split("_", 1)[1],
                r["episodes"],
                r["success_rate"],
                r["plan_s_median"],
                r["plan_s_p95"],
            ]
            for k, r in results.items()
            if isinstance(r, dict) and "success_rate" in r
        ],
    )
    print_table(
        "Time per plan on the same 10 states (same budget C x I x H)",
        ["planner", "s / plan", "stock / this"],
        [[k, v, t["stock"] / v] for k, v in t.items()],
    )
    write_json("planning", {"args": {k: str(v) for k, v in vars(args).items()}, **results})


def _interleaved(planners: dict, states, rounds: int) -> dict[str, float]:
    """Median time per plan of each planner, the best of ``rounds`` interleaved rounds (the
    machine is shared: interleaving exposes all planners to the same load)."""
    times: dict[str, list[float]] = {k: [] for k in planners}
    for _ in range(rounds):
        for name, policy in planners.items():
            times[name].append(_plan_times(policy, states, repeats=2))
    return {k: min(v) for k, v in times.items()}


def _latency(policy, states, calls: int = 5) -> dict[str, float]:
    """Plan latency over ``calls`` consecutive control steps (warm start) from each state."""
    times = []
    for td in states:
        policy.reset()
        for _ in range(calls):
            start = time.perf_counter()
            policy(td.clone())
            times.append(time.perf_counter() - start)
    times.sort()
    return {
        "median_s": statistics.median(times),
        "p95_s": times[int(0.95 * (len(times) - 1))],
        "calls": len(times),
    }


def speed(args) -> None:
    """Time per plan vs TorchRL's stock CEMPlanner, and the default budget's latency."""
    model = load_ensemble(args.work_dir / "models" / "deterministic.pt", functions=MODEL_FUNCTIONS)
    env = make_pusher_env("deterministic")
    torch.manual_seed(0)
    states = [env.reset() for _ in range(10)]
    rows, compile_s = [], {}
    for c, i, h in SPEED_BUDGETS:
        budget = PlannerConfig(
            horizon=h, num_candidates=c, iterations=i, top_k=8, policy_prior=False
        )
        model_env = make_rcvae_env(
            model, env, pusher_reward, pusher_success, terminate_on_success=True, seed=0
        )
        for p in (1, 5):
            config = dataclasses.replace(budget, particles=p)
            planners = {
                "stock": _stock(model_env, config),
                "ours": make_planner(model, env, config),
                "ours_compiled": make_planner(model, env, config, compile=True),
            }
            start = time.perf_counter()
            planners["ours_compiled"](states[0].clone())  # compiles
            compile_s[f"C{c}xI{i}xH{h}xP{p}"] = time.perf_counter() - start
            t = _interleaved(planners, states, args.rounds)
            rows.append(
                {
                    "candidates": c,
                    "iterations": i,
                    "horizon": h,
                    "particles": p,
                    **{f"{k}_s": v for k, v in t.items()},
                    "speedup": t["stock"] / t["ours"],
                    "speedup_compiled": t["stock"] / t["ours_compiled"],
                }
            )
            print(rows[-1], flush=True)
    latency = {}
    for compiled in (False, True):
        policy = make_planner(model, env, StudyConfig().planner, compile=compiled)
        policy(states[0].clone())  # warm-up (compiles)
        latency["compiled" if compiled else "eager"] = _latency(policy, states)
    print_table(
        "Time per plan vs stock CEMPlanner (same C x I x H; stock: one particle per candidate)",
        ["C x I x H", "P", "stock s", "ours s", "stock/ours", "compiled s", "stock/compiled"],
        [
            [
                f"{r['candidates']}x{r['iterations']}x{r['horizon']}",
                r["particles"],
                r["stock_s"],
                r["ours_s"],
                r["speedup"],
                r["ours_compiled_s"],
                r["speedup_compiled"],
            ]
            for r in rows
        ],
    )
    print_table(
        "Plan latency at the default budget (control step 0.05 s)",
        ["scoring", "median s", "p95 s"],
        [[k, v["median_s"], v["p95_s"]] for k, v in latency.items()],
    )
    path = RESULTS_DIR / "planning.json"
    old = json.loads(path.read_text()) if path.is_file() else {}
    old = {k: v for k, v in old.items() if k not in ("benchmark", "machine")}
    old["speed"] = {
        "note": "ours vs TorchRL's stock CEMPlanner over the same model env, same run, no policy "
        "prior; latency: default PlannerConfig (policy prior, P=5), 5 warm-started calls "
        "from each of 10 states",
        "vs_stock": rows,
        "compile_s": compile_s,
        "latency_default": latency,
        "args": {k: str(v) for k, v in vars(args).items()},
    }
    write_json("planning", old)


if __name__ == "__main__":
    main()

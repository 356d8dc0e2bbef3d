"""How much a Pusher task set lets a forecast show skill: the ceiling of the study's trust scores.

A forecast of P(success) per start state can only separate successes from failures as far as
the start states differ in their real chance. This script measures that ceiling for a task set
(start states drawn by the real env's reset) under the scripted pusher (a stand-in for the
agent: in the default study's stochastic condition it succeeds about as often as the agent),
for each setting of the stochastic env's randomness (per-step action-noise std and the range of
the episode's actuator strength) and each deadline:

- the per-start success rates over ``--runs`` real episodes per start (batched env);
- the *oracle* scores, those of the forecast that knows each start's rate: Brier skill against
  the episodes' own rate and AUROC over single episodes (in-sample, so a little optimistic);
- the between-start variance of the chance, corrected for the binomial noise of ``R`` runs,
  ``var(rates) - mean(rate (1 - rate)) / (R - 1)``, and its share of the outcome variance
  ``p (1 - p)``: the Brier skill the oracle would reach with infinitely many runs;
- ``pooled``: the oracle over the study's three conditions together, each weighted as the study
  weights it (``--runs`` episodes per start in the stochastic env, one in the deterministic
  envs, whose outcome per start is fixed): what "Brier skill against the overall base rate" and
  "AUROC over all episodes" can reach at best.

    python benchmarks/task_variation.py [--noise 0.5 1.0 1.5] [--strength 0.2,0.4 ...]
                                        [--deadlines 4 8 12] [--starts 40] [--runs 30] [--quick]
                                        [--agent RUN_DIR] [--out task_variation]

``--strength`` adds settings with an episode-level actuator strength uniform in ``low,high``
and no per-step noise (``low,high,std`` for both); each prints one table. ``--agent`` takes
the policy of a finished study run (its distilled agent, trained in the deterministic Pusher
and so the same whatever the stochastic setting) instead of the scripted pusher: the ceiling
the study's own agent leaves. Writes
``benchmarks/results/<out>.json`` (default ``task_variation``; ``<out>_quick`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import torch
from _report import conditions, print_table, write_json

from rcvae_torchrl.agent import make_policy_module, real_outcomes
from rcvae_torchrl.competency import pool_outcomes, validate_forecasts
from rcvae_torchrl.data import seed_env
from rcvae_torchrl.envs import (
    CONTROL_TIMESTEP,
    ball_to_target,
    make_batched_pusher_env,
    make_pusher_env,
    reset_to_state,
)
from rcvae_torchrl.envs.scripted import make_scripted_policy
from recipes.pusher_competency.pipeline import study_of_run

START_SEEDS = 1000  # start states of variant v: seeds START_SEEDS + 1000 v + i
REAL_SEEDS = 7
MAX_ENVS = 400


def draw(variant: str, count: int, index: int) -> torch.Tensor:
    """``count`` start observations ``[B, 14]`` of ``variant`` from its own seeded reset."""
    env = make_pusher_env(variant)
    rows = []
    for i in range(count):
        seed_env(env, START_SEEDS + 1000 * index + i)
        rows.append(env.reset()["observation"])
    return torch.stack(rows)


def first_steps(
    variant: str,
    starts: torch.Tensor,
    runs: int,
    noise: float,
    steps: int,
    strength: tuple[float, float] | None = None,
    policy: Callable | None = None,
):
    """First success step ``[B, R]`` of ``policy`` (a policy module; default the scripted
    pusher), ``steps`` when none."""
    stochastic = variant == "stochastic"
    env = make_batched_pusher_env(
        min(MAX_ENVS, len(starts) * runs),
        variant,
        action_noise_std=noise if stochastic else None,
        actuator_strength=strength if stochastic else None,
        time_limit=steps * CONTROL_TIMESTEP,
        terminate_on_success=False,
    )
    out = real_outcomes(
        env,
        make_scripted_policy() if policy is None else policy,
        starts,
        runs_per_start=runs,
        reset_to_state=reset_to_state,
        max_steps=steps,
        trace=ball_to_target,
        seed=REAL_SEEDS,
        progress=False,
    )
    return out.first_step


def agent_policy(run_dir: Path) -> Callable:
    """The agent of the finished study run ``run_dir`` as a policy module."""
    return make_policy_module(study_of_run(run_dir).load_policy())


def ceiling(success: torch.Tensor, mask: torch.Tensor | None = None) -> dict[str, float]:
    """The oracle's scores on outcomes ``[B, R]`` and the between-start share of the variance."""
    m = torch.ones_like(success) if mask is None else mask
    runs = m.sum(1).double()
    rates = (success & m).sum(1).double() / runs
    oracle = validate_forecasts(rates.float(), success, mask)
    p = float(success[m].double().mean())
    repeated = runs > 1  # the binomial correction applies where a start has several runs
    noise = torch.where(repeated, rates * (1 - rates) / (runs - 1).clamp_min(1), 0.0)
    between = max(0.0, float(rates.var(unbiased=False) - noise.mean()))
    return {
        "rate": p,
        "rate_sd": float(rates.std()),
        "rate_min": float(rates.min()),
        "rate_max": float(rates.max()),
        "oracle_brier_skill": oracle["brier_skill"],
        "oracle_auroc": oracle["auroc"],
        "between_share": between / (p * (1 - p)) if 0 < p < 1 else float("nan"),
    }


def _oracles(scores: dict[str, float]) -> tuple[float, float]:
    return scores["oracle_brier_skill"], scores["oracle_auroc"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--noise", type=float, nargs="+", default=[0.5, 1.0, 1.5])
    parser.add_argument(
        "--strength",
        nargs="*",
        default=[],
        help="low,high[,std]: an episode-level actuator strength range (and per-step noise std)",
    )
    parser.add_argument("--deadlines", type=float, nargs="+", default=[4.0, 8.0, 12.0])
    parser.add_argument("--starts", type=int, default=40)
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument(
        "--agent",
        type=Path,
        default=None,
        metavar="RUN_DIR",
        help="the distilled agent of a finished study run instead of the scripted pusher",
    )
    parser.add_argument("--quick", action="store_true", help="8 starts, 5 runs, one noise")
    parser.add_argument(
        "--out", default="task_variation", help="results/<out>.json (<out>_quick with --quick)"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.quick:
        args.starts, args.runs, args.noise = 8, 5, args.noise[-1:]
    settings = [(f"noise {n}", n, None) for n in args.noise]
    for text in args.strength:
        values = [float(v) for v in text.split(",")]
        if len(values) not in (2, 3):
            parser.error(f"--strength: expected low,high[,std], got {text!r}")
        noise = values[2] if len(values) == 3 else 0.0
        settings.append((f"strength {values[0]}-{values[1]} noise {noise}", noise, values[:2]))
    steps = round(max(args.deadlines) / CONTROL_TIMESTEP)
    deadlines = [round(d / CONTROL_TIMESTEP) for d in args.deadlines]
    policy = None if args.agent is None else agent_policy(args.agent)
    fixed = {  # the deterministic envs: one run per start (the outcome is fixed)
        v: first_steps(v, draw(v, args.starts, i), 1, 0.0, steps, policy=policy)
        for i, v in ((0, "deterministic"), (2, "ood"))
    }
    stochastic = draw("stochastic", args.starts, 1)
    results, started = {}, time.perf_counter()
    for name, noise, strength in settings:
        first = first_steps("stochastic", stochastic, args.runs, noise, steps, strength, policy)
        rows, per_deadline = [], {}
        for seconds, k in zip(args.deadlines, deadlines):
            won = first < k
            own = ceiling(won)
            both = ceiling(*pool_outcomes([fixed["deterministic"] < k, won, fixed["ood"] < k]))
            per_deadline[str(seconds)] = {"stochastic": own, "pooled": both}
            shown = ("rate", "rate_sd", "rate_min", "rate_max", "between_share")
            rows.append([seconds, *(own[k] for k in shown), *_oracles(own), *_oracles(both)])
        results[name if strength else str(noise)] = per_deadline
        print_table(
            f"{name if strength else f'action noise std {noise}'}: {args.starts} starts x "
            f"{args.runs} runs (stochastic); "
            f"pooled with {args.starts} deterministic and {args.starts} out-of-distribution starts",
            [
                "deadline s",
                "rate",
                "rate sd",
                "min",
                "max",
                "between share",
                "oracle BSS",
                "oracle AUROC",
                "pooled BSS",
                "pooled AUROC",
            ],
            rows,
        )
    write_json(
        f"{args.out}_quick" if args.quick else args.out,
        {
            "settings": {**vars(args), "agent": None if args.agent is None else str(args.agent)},
            "conditions": conditions(),
            "seconds": time.perf_counter() - started,
            "deterministic_rate": {
                str(s): float((fixed["deterministic"] < k).float().mean())
                for s, k in zip(args.deadlines, deadlines)
            },
            "ood_rate": {
                str(s): float((fixed["ood"] < k).float().mean())
                for s, k in zip(args.deadlines, deadlines)
            },
            "results": results,
        },
    )


if __name__ == "__main__":
    main()

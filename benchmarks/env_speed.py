"""Pusher speed and the scripted controller's success rate.

Measures control steps/s of the raw dm_control env, the TorchRL-wrapped env (one core) and a
2-worker ``ParallelEnv``, each as the median of repeats; then the scripted controller's success
rate and median time to success per variant over ``--episodes`` seeds.

    python benchmarks/env_speed.py [--steps 3000] [--repeats 3] [--episodes 100] [--quick]
"""

from __future__ import annotations

import argparse
import functools
import statistics

import numpy as np
import torch
from _report import median_time, print_table, write_json
from torchrl.envs import ParallelEnv

from rcvae_torchrl.envs import CONTROL_TIMESTEP, VARIANTS, make_pusher_env
from rcvae_torchrl.envs.pusher import make_environment
from rcvae_torchrl.envs.scripted import make_scripted_policy


def raw_steps(steps: int) -> None:
    env = make_environment(random=0)
    env.reset()
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(steps, 2))
    for a in actions:
        if env.step(a).last():
            env.reset()


def torchrl_steps(env, steps: int) -> None:
    """``steps`` rollout steps with random actions drawn up front (policy cost ~0)."""
    actions = torch.rand(steps, *env.action_spec.shape, generator=torch.Generator().manual_seed(0))
    actions = actions * 2 - 1
    counter = iter(range(steps))

    def policy(td):
        return td.set("action", actions[next(counter)].expand(*td.batch_size, -1))

    with torch.no_grad():
        env.rollout(steps, policy, break_when_any_done=False)


def scripted_success(variant: str, episodes: int) -> dict[str, float]:
    env = make_pusher_env(variant, seed=0)
    policy = make_scripted_policy()
    times = []
    for seed in range(episodes):
        env.set_seed(10_000 + seed)
        with torch.no_grad():
            td = env.rollout(600, policy, break_when_any_done=True)
        if td["next", "success"].any():
            times.append(td.shape[0] * CONTROL_TIMESTEP)
    return {
        "episodes": episodes,
        "success_rate": len(times) / episodes,
        "median_time_to_success_s": statistics.median(times) if times else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--quick", action="store_true", help="fewer steps and episodes")
    args = parser.parse_args()
    if args.quick:
        args.steps, args.repeats, args.episodes = 600, 2, 10
    torch.set_num_threads(1)

    wrapped = make_pusher_env(seed=0)
    parallel = ParallelEnv(2, functools.partial(make_pusher_env, "deterministic"))
    parallel.set_seed(0)
    try:
        t_raw = median_time(lambda: raw_steps(args.steps), args.repeats)
        t_wrapped = median_time(lambda: torchrl_steps(wrapped, args.steps), args.repeats)
        # A ParallelEnv rollout of n steps makes 2 n env steps.
        t_par = median_time(lambda: torchrl_steps(parallel, args.steps // 2), args.repeats)
    finally:
        parallel.close()
    speed = {
        "raw_dm_control": args.steps / t_raw,
        "torchrl_wrapped_1_core": args.steps / t_wrapped,
        "parallel_env_2_workers": 2 * (args.steps // 2) / t_par,
    }
    print_table(
        "Pusher control steps/s (random actions; median of repeats)",
        ["env", "steps/s", "ratio to raw"],
        [[k, v, v / speed["raw_dm_control"]] for k, v in speed.items()],
    )
    scripted = {v: scripted_success(v, args.episodes) for v in VARIANTS}
    print_table(
        f"Scripted pusher over {args.episodes} seeds",
        ["variant", "success rate", "median time to success (s)"],
        [[v, r["success_rate"], r["median_time_to_success_s"]] for v, r in scripted.items()],
    )
    write_json(
        "env_speed",
        {
            "steps": args.steps,
            "repeats": args.repeats,
            "steps_per_s": speed,
            "target_torchrl_steps_per_s": 3000,
            "scripted": scripted,
        },
    )


if __name__ == "__main__":
    main()

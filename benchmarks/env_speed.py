"""Pusher speed and the scripted controller's success rate.

Measures control steps/s (all envs together) of the raw dm_control env, the TorchRL-wrapped env
(one core), a 2-worker ``ParallelEnv`` and the batched env (``BatchedPusherEnv``: 16, 64, 256
envs), each as the median of repeats (every row timed once per repeat, in turn), with 1 torch
thread. Rows marked ``scripted`` call the
scripted pusher's batched torch policy once per control step (episodes end at success and the
envs restart: partial resets included); the others replay random actions drawn up front (policy
cost ~0). Then the scripted controller's success rate and median time to success per variant
over ``--episodes`` seeds.

    python benchmarks/env_speed.py [--steps 3000] [--batched-steps 100] [--repeats 3]
        [--episodes 100] [--quick]

Writes ``benchmarks/results/env_speed.json`` (``env_speed_quick.json`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
from collections.abc import Callable

import numpy as np
import torch
from _report import interleaved_median_times, print_table, write_json
from torchrl.envs import ParallelEnv

from rcvae_torchrl.envs import CONTROL_TIMESTEP, VARIANTS, make_batched_pusher_env, make_pusher_env
from rcvae_torchrl.envs.pusher import make_environment
from rcvae_torchrl.envs.scripted import make_scripted_policy
from rcvae_torchrl.threads import threads_kept


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


def scripted_steps(env, steps: int) -> None:
    """``steps`` rollout steps with the scripted pusher, one batched policy call per step."""
    with torch.no_grad():
        env.rollout(steps, make_scripted_policy(), break_when_any_done=False)


BATCHED_ROWS = [  # (envs, policy, MuJoCo threads)
    (16, "scripted", 1),
    (64, "scripted", 1),
    (256, "scripted", 1),
    (256, "random", 1),
    (256, "scripted", 2),
]


def batched_row_name(n: int, policy: str, threads: int) -> str:
    return f"batched_{n}_envs_{policy}" + (f"_{threads}_mujoco_threads" if threads > 1 else "")


def speed_rows(
    steps: int, batched_steps: int, wrapped, parallel
) -> dict[str, tuple[Callable[[], None], int]]:
    """Each row's run and the control steps (all envs together) one run makes."""
    rows = {
        "raw_dm_control": (lambda: raw_steps(steps), steps),
        "torchrl_wrapped_1_core": (lambda: torchrl_steps(wrapped, steps), steps),
        "torchrl_wrapped_1_core_scripted": (lambda: scripted_steps(wrapped, steps), steps),
        # A ParallelEnv rollout of n steps makes 2 n env steps.
        "parallel_env_2_workers": (lambda: torchrl_steps(parallel, steps // 2), 2 * (steps // 2)),
    }
    for n, policy, threads in BATCHED_ROWS:
        env = make_batched_pusher_env(n, seed=0, num_threads=threads)
        run = scripted_steps if policy == "scripted" else torchrl_steps
        call = functools.partial(run, env, batched_steps)
        rows[batched_row_name(n, policy, threads)] = (call, n * batched_steps)
    return rows


# Rows whose work runs in this process, so its CPU time is theirs (not the ParallelEnv's workers).
IN_PROCESS = {
    "raw_dm_control",
    "torchrl_wrapped_1_core",
    "torchrl_wrapped_1_core_scripted",
    *(
        f"batched_{n}_envs_{p}" + (f"_{t}_mujoco_threads" if t > 1 else "")
        for n, p, t in BATCHED_ROWS
    ),
}


def wrapped_baseline(speed: dict[str, float], row: str) -> float:
    """The TorchRL-wrapped env's speed with the policy of ``row`` (scripted or none)."""
    return speed["torchrl_wrapped_1_core" + ("_scripted" if "scripted" in row else "")]


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
    parser.add_argument(
        "--batched-steps", type=int, default=100, help="control steps per env, batched rows"
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--quick", action="store_true", help="fewer steps and episodes")
    args = parser.parse_args()
    if args.quick:
        args.steps, args.batched_steps, args.repeats, args.episodes = 600, 30, 2, 10
    torch.set_num_threads(1)
    load_before = os.getloadavg()

    wrapped = make_pusher_env(seed=0)
    with threads_kept():  # closing a ParallelEnv resets torch's thread count
        parallel = ParallelEnv(2, functools.partial(make_pusher_env, "deterministic"))
        parallel.set_seed(0)
        try:
            rows = speed_rows(args.steps, args.batched_steps, wrapped, parallel)
            times = interleaved_median_times({k: run for k, (run, _) in rows.items()}, args.repeats)
        finally:
            parallel.close()
    speed = {k: steps / times[k]["wall_s"] for k, (_, steps) in rows.items()}
    per_cpu = {k: steps / times[k]["cpu_s"] for k, (_, steps) in rows.items() if k in IN_PROCESS}
    load = {"before": load_before, "after": os.getloadavg()}
    print_table(
        f"Pusher control steps/s, all envs together (median of {args.repeats}; "
        f"{torch.get_num_threads()} torch thread; 1-min load {load_before[0]:.2f} before, "
        f"{load['after'][0]:.2f} after)",
        ["env", "steps/s", "steps per CPU-s", "ratio to raw", "ratio to wrapped (same policy)"],
        [
            [k, v, per_cpu.get(k, "-"), v / speed["raw_dm_control"], v / wrapped_baseline(speed, k)]
            for k, v in speed.items()
        ],
    )
    scripted = {v: scripted_success(v, args.episodes) for v in VARIANTS}
    print_table(
        f"Scripted pusher over {args.episodes} seeds",
        ["variant", "success rate", "median time to success (s)"],
        [[v, r["success_rate"], r["median_time_to_success_s"]] for v, r in scripted.items()],
    )
    write_json(
        "env_speed_quick" if args.quick else "env_speed",  # a smoke run keeps the record
        {
            "steps": args.steps,
            "batched_steps_per_env": args.batched_steps,
            "repeats": args.repeats,
            "torch_threads": torch.get_num_threads(),
            "loadavg": load,
            "steps_per_s": speed,
            "steps_per_cpu_s": per_cpu,
            "target_torchrl_steps_per_s": 3000,
            "target_batched_steps_per_s": 20000,
            "scripted": scripted,
        },
    )


if __name__ == "__main__":
    main()

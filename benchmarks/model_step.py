"""Model steps per second of plan scoring against the matmul peak, and compile time per shape.

At the planner's default budget (64 candidates x 5 particles x 12 steps, TS-inf: 64 trajectories
per member) on the study's ensemble (E = 5, H = MLP = 64, Z = 8, the Pusher's state constraint
and input features; untrained, normaliser fitted on random data: speed does not depend on the
weights), with the Pusher's reward and success:

- the FLOP of one model step (``FlopCounterMode`` on ``ensemble.step``) and the float32 matmul
  peak of this core (a [1024, 1024] x [1024, 1024] product);
- ``evaluate_action_sequences`` eager, and the model's own step alone over the same particles
  and horizon (no task, no rollout bookkeeping): model steps per second and percent of peak,
  interleaved rounds, one thread, with the load;
- with ``--stock``: time per plan of our CEM planner (eager and compiled, P = 1 and 5) against
  TorchRL's stock
  ``CEMPlanner`` over the same model env at the same budget (C x I x H = 64 x 2 x 12, no policy
  prior), interleaved on the same 5 real Pusher states;
- with ``--compile``: the library's compiled scoring rollout (``compile=True``: dynamic
  particle count), the seconds of its first call and of the first calls with new numbers of
  candidates (what a run waits for when a plan shape changes), the graphs compiled, then its
  steady speed;
- with ``--aot``: the scoring rollout compiled ahead of time (``compile="aot"``): the seconds
  of the first call of a fresh process with an empty package cache and an empty inductor
  cache, with an empty package cache but inductor's kernels cached, and with the package
  cached (what every later process pays); the same first call for ``torch.compile`` with its
  on-disk cache empty and warm; then its steady speed beside eager and ``compile=True``, and
  with ``--stock`` / ``--mbrl`` the AOT planners too. The package caches are temporary
  directories, removed afterwards;
- with ``--mbrl``: a peer, mbrl-lib 0.2.0's PETS CEM planning (an ensemble of 5 Gaussian MLPs,
  4 x 200, obs 14, act 2; population 200 x 20 particles x horizon 15 x 5 iterations), against our
  CEM planner at the same budget on the study's model, interleaved: seconds per plan, model
  steps/s and FLOP/s (each side's FLOP counted with ``FlopCounterMode``). mbrl-lib is not a
  dependency (it pins old packages); install it beside the project's torch without its
  dependencies and put it on the path::

      .venv/bin/pip install --no-deps --target /tmp/mbrl_target mbrl==0.2.0 termcolor \
          gymnasium farama-notifications
      PYTHONPATH=/tmp/mbrl_target .venv/bin/python benchmarks/model_step.py --mbrl

    python benchmarks/model_step.py [--repeats 7] [--stock] [--compile] [--aot] [--mbrl]
        [--out PATH]

``--out`` writes the results there instead of ``benchmarks/results/model_step.json`` (runs on a
busy machine).
"""

from __future__ import annotations

import argparse
import atexit
import dataclasses
import functools
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from _report import conditions, interleaved_median_times, machine_info, print_table, write_json
from torch.utils.flop_counter import FlopCounterMode

from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.io import write_json as write_json_to
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout import SCORING_CACHE_ENV, Task, evaluate_action_sequences, scoring
from recipes.pusher_competency.config import StudyConfig
from recipes.pusher_competency.pusher import MODEL_FUNCTIONS, rcvae_config

CANDIDATES, PARTICLES, HORIZON, MEMBERS = 64, 5, 12, 5


def study_ensemble() -> RCVAEEnsemble:
    """The study's model (its config and the Pusher's state constraint and input features)."""
    gen = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    config = rcvae_config(StudyConfig().model)
    model = RCVAEEnsemble(config, ensemble_size=MEMBERS, functions=MODEL_FUNCTIONS).eval()
    obs = torch.randn(2000, 14, generator=gen) * 0.1
    actions = torch.rand(2000, 2, generator=gen) * 2 - 1
    model.fit_normalizer(obs, actions, next_observations=obs + 0.01 * torch.randn_like(obs))
    return model


def matmul_peak_flops(size: int = 1024, repeats: int = 5) -> float:
    a, b = torch.randn(size, size), torch.randn(size, size)
    a @ b
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return 2.0 * size**3 / best


def step_flop(model: RCVAEEnsemble, per_member: int) -> float:
    """FLOP of one model step of one particle."""
    hidden = torch.zeros(MEMBERS, per_member, model.config.hidden_dim)
    obs, act = torch.zeros(MEMBERS, per_member, 14), torch.zeros(MEMBERS, per_member, 2)
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        model.step(hidden, obs, act, generator=torch.Generator())
    return counter.get_total_flops() / (MEMBERS * per_member)


def model_steps_alone(model: RCVAEEnsemble, per_member: int, horizon: int) -> None:
    gen = torch.Generator().manual_seed(0)
    hidden = torch.zeros(MEMBERS, per_member, model.config.hidden_dim)
    obs, act = torch.zeros(MEMBERS, per_member, 14), torch.zeros(MEMBERS, per_member, 2)
    with torch.no_grad():
        for _ in range(horizon):
            out = model.step(hidden, obs, act, generator=gen)
            hidden, obs = out.hidden, out.observation


def scoring_call(model, task, candidates: int, compile_=False, cache_dir=None) -> None:
    gen = torch.Generator().manual_seed(0)
    start = torch.randn(1, 14, generator=gen).expand(candidates, 14) * 0.1
    actions = torch.rand(candidates, HORIZON, 2, generator=gen) * 2 - 1
    with torch.no_grad():
        evaluate_action_sequences(
            model, start, actions, PARTICLES, task=task, generator=gen, compile=compile_,
            cache_dir=cache_dir,
        )  # fmt: skip


def first_call_here(mode: str, cache_dir: str) -> float:
    """Seconds of this process's first scoring call (``--first-call``, run by
    :func:`fresh_process_first_calls`)."""
    torch.set_num_threads(1)
    model = study_ensemble()
    task = Task(pusher_reward, pusher_success, terminate_on_success=True)
    start = time.perf_counter()
    scoring_call(model, task, CANDIDATES, {"compile": True, "aot": "aot"}[mode], cache_dir)
    return time.perf_counter() - start


def fresh_process_first_calls(root: Path, compile_too: bool) -> dict[str, float]:
    """The first scoring call of fresh processes (seconds), by the state of the caches: the
    ahead-of-time package cache (``aot``) and inductor's kernel cache (both paths)."""

    def first_call(mode: str, inductor: str, packages: str) -> float:
        env = {**os.environ, "OMP_NUM_THREADS": "1",
               "TORCHINDUCTOR_CACHE_DIR": str(root / inductor)}  # fmt: skip
        command = [sys.executable, __file__, "--first-call", mode, str(root / packages)]
        out = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
        return float(out.stdout.split()[-1])

    out = {
        "aot, empty package and inductor caches": first_call("aot", "inductor_aot", "a"),
        "aot, empty package cache, inductor cache warm": first_call("aot", "inductor_aot", "b"),
        "aot, package cached": first_call("aot", "inductor_aot", "b"),
    }
    if compile_too:
        out["compile=True, empty inductor cache"] = first_call("compile", "inductor", "-")
        out["compile=True, inductor cache warm"] = first_call("compile", "inductor", "-")
    return out


def compile_times(model, task) -> dict[str, float]:
    """The library's compiled scoring (``compile=True``): the first call, then calls with new
    numbers of candidates (what a run waits for when a plan shape changes), and the graphs
    Dynamo compiled. Run the script twice to see the first call with inductor's on-disk cache
    warm (as a later process finds it)."""
    from torch._dynamo.utils import counters

    scoring._COMPILED.clear()
    torch._dynamo.reset()
    out = {}
    for name, candidates in (
        ("first_call_s", CANDIDATES),
        ("new_shape_200_candidates_s", 200),
        ("new_shape_37_candidates_s", 37),
    ):
        start = time.perf_counter()
        scoring_call(model, task, candidates, compile_=True)
        out[name] = time.perf_counter() - start
    out["graphs_compiled"] = int(counters["stats"]["unique_graphs"])
    return out


def stock_comparison(model: RCVAEEnsemble, repeats: int, aot: bool = False) -> dict[str, Any]:
    """Seconds per plan: ours (P = 1, 5) vs the stock CEMPlanner, same model env and budget;
    with ``aot``, also ours with the ahead-of-time compiled scoring (its build, in the warm-up
    round, is not timed)."""
    from planning import _stock

    from rcvae_torchrl.agent import PlannerConfig
    from rcvae_torchrl.envs import make_pusher_env
    from rcvae_torchrl.model_env import make_rcvae_env
    from recipes.pusher_competency.pusher import make_planner

    env = make_pusher_env("deterministic")
    torch.manual_seed(0)
    states = [env.reset() for _ in range(5)]
    config = PlannerConfig(
        horizon=HORIZON, num_candidates=CANDIDATES, iterations=2, top_k=8, policy_prior=False
    )
    model_env = make_rcvae_env(
        model, env, pusher_reward, pusher_success, terminate_on_success=True, seed=0
    )
    planners = {
        "stock CEMPlanner": _stock(model_env, config),
        "ours P=1": make_planner(model, env, dataclasses.replace(config, particles=1)),
        "ours P=5": make_planner(model, env, config),
        "ours P=1, compile=True": make_planner(
            model, env, dataclasses.replace(config, particles=1), compile=True
        ),
        "ours P=5, compile=True": make_planner(model, env, config, compile=True),
    }
    if aot:
        planners["ours P=1, compile='aot'"] = make_planner(
            model, env, dataclasses.replace(config, particles=1), compile="aot"
        )
        planners["ours P=5, compile='aot'"] = make_planner(model, env, config, compile="aot")

    def plan_all(policy) -> None:
        for td in states:
            if hasattr(type(policy), "reset"):
                policy.reset()
            policy(td.clone())

    with torch.no_grad():
        times = interleaved_median_times(
            {k: functools.partial(plan_all, p) for k, p in planners.items()}, repeats
        )
    stock = times["stock CEMPlanner"]["wall_s"]
    return {k: {**v, "stock_over_this": stock / v["wall_s"]} for k, v in times.items()}


MBRL_BUDGET = {"population": 200, "particles": 20, "horizon": 15, "iterations": 5}


def _mbrl_plan():
    """mbrl-lib's PETS CEM plan at ``MBRL_BUDGET``, as a no-argument call (None without mbrl)."""
    try:
        import mbrl.models as mm
        import mbrl.planning as mp
        import numpy as np
        import omegaconf
    except ImportError:
        return None
    b = MBRL_BUDGET
    net = mm.GaussianMLP(
        16, 14, "cpu", num_layers=4, ensemble_size=MEMBERS, hid_size=200,
        propagation_method="fixed_model",
    )  # fmt: skip
    dynamics = mm.OneDTransitionRewardModel(
        net, target_is_delta=True, normalize=False, learned_rewards=False
    )

    class _Spaces:  # ModelEnv reads only these two attributes off the real env
        observation_space = action_space = None

    def reward(act, next_obs):
        return -next_obs[:, :2].norm(dim=-1, keepdim=True)

    def never_done(act, next_obs):
        return torch.zeros(next_obs.shape[0], 1, dtype=torch.bool)

    env = mm.ModelEnv(
        _Spaces(), dynamics, never_done, reward, generator=torch.Generator().manual_seed(0)
    )
    cfg = omegaconf.OmegaConf.create(
        {
            "_target_": "mbrl.planning.CEMOptimizer", "num_iterations": b["iterations"],
            "elite_ratio": 0.1, "population_size": b["population"], "alpha": 0.1,
            "device": "cpu", "lower_bound": "???", "upper_bound": "???",
            "return_mean_elites": True, "clipped_normal": False,
        }
    )  # fmt: skip
    optimizer = mp.TrajectoryOptimizer(cfg, -np.ones(2), np.ones(2), planning_horizon=b["horizon"])
    obs0 = np.zeros(14, dtype=np.float32)

    def evaluate(action_sequences):
        return env.evaluate_action_sequences(
            action_sequences, initial_state=obs0, num_particles=b["particles"]
        )

    return lambda: optimizer.optimize(evaluate)


def _flop_of(call) -> float:
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        call()
    return float(counter.get_total_flops())


def mbrl_comparison(model: RCVAEEnsemble, repeats: int, aot: bool = False) -> dict[str, Any]:
    """Ours against mbrl-lib's PETS CEM at its budget: s per plan, model steps/s, FLOP/s (with
    ``aot``, also ours with the ahead-of-time compiled scoring)."""
    peer = _mbrl_plan()
    if peer is None:
        return {}
    from rcvae_torchrl.agent import PlannerConfig
    from rcvae_torchrl.envs import make_pusher_env
    from recipes.pusher_competency.pusher import make_planner

    b = MBRL_BUDGET
    env = make_pusher_env("deterministic")
    torch.manual_seed(0)
    state = env.reset()
    config = PlannerConfig(
        horizon=b["horizon"], num_candidates=b["population"], iterations=b["iterations"],
        top_k=b["population"] // 10, particles=b["particles"], momentum=0.1,
        policy_prior=False,
    )  # fmt: skip
    planners = {
        "ours (CEMPlanner)": make_planner(model, env, config),
        "ours (CEMPlanner), compile=True": make_planner(model, env, config, compile=True),
    }
    if aot:
        planners["ours (CEMPlanner), compile='aot'"] = make_planner(
            model, env, config, compile="aot"
        )

    def plan(planner) -> None:
        planner.reset()
        planner(state.clone())

    calls = {"mbrl-lib PETS CEM": peer}
    calls.update({name: functools.partial(plan, p) for name, p in planners.items()})
    steps = b["population"] * b["particles"] * b["horizon"] * b["iterations"]
    # FLOP counted on the eager path (the compiled one does the same arithmetic)
    ours_flop = _flop_of(calls["ours (CEMPlanner)"])
    flop = {name: ours_flop for name in planners} | {"mbrl-lib PETS CEM": _flop_of(peer)}
    with torch.no_grad():
        times = interleaved_median_times(calls, repeats)
    out = {}
    for name, t in times.items():
        out[name] = {
            **t,
            "model_steps_per_s": steps / t["wall_s"],
            "flop_per_model_step": flop[name] / steps,
            "flop_per_s": flop[name] / t["wall_s"],
        }
    peer_row = out["mbrl-lib PETS CEM"]
    for row in out.values():
        row["steps_per_s_over_mbrl"] = row["model_steps_per_s"] / peer_row["model_steps_per_s"]
        row["flop_per_s_over_mbrl"] = row["flop_per_s"] / peer_row["flop_per_s"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--stock", action="store_true")
    parser.add_argument("--aot", action="store_true")
    parser.add_argument("--mbrl", action="store_true", help="compare with mbrl-lib (see above)")
    parser.add_argument("--out", type=Path, help="write the results here (default: results/)")
    parser.add_argument("--first-call", nargs=2, metavar=("MODE", "CACHE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.first_call:
        print(first_call_here(*args.first_call))
        return
    torch.set_num_threads(1)
    model = study_ensemble()
    task = Task(pusher_reward, pusher_success, terminate_on_success=True)
    per_member = CANDIDATES * PARTICLES // MEMBERS
    steps = CANDIDATES * PARTICLES * HORIZON
    flop, peak = step_flop(model, per_member), matmul_peak_flops()
    runs = {
        "evaluate_action_sequences, eager": functools.partial(
            scoring_call, model, task, CANDIDATES
        ),
        "model step alone (ensemble.step x H), eager": functools.partial(
            model_steps_alone, model, per_member, HORIZON
        ),
    }
    compiled, first_calls = {}, {}
    root = Path(tempfile.mkdtemp(prefix="model_step_"))
    if args.aot:  # first, while no compile of this process has filled a cache
        planners_cache = tempfile.mkdtemp(prefix="model_step_planners_")  # --stock, --mbrl
        atexit.register(shutil.rmtree, planners_cache, True)
        os.environ[SCORING_CACHE_ENV] = planners_cache
        first_calls = fresh_process_first_calls(root, compile_too=args.compile)
        runs["evaluate_action_sequences, compile='aot'"] = functools.partial(
            scoring_call, model, task, CANDIDATES, "aot", root / "b"
        )
    if args.compile:
        compiled = compile_times(model, task)
        runs["evaluate_action_sequences, compile=True"] = functools.partial(
            scoring_call, model, task, CANDIDATES, True
        )
    try:
        times = interleaved_median_times(runs, args.repeats)
    finally:
        shutil.rmtree(root)
    rows = []
    for name, t in times.items():
        rate = steps / t["wall_s"]
        rows.append(
            {
                "case": name,
                **t,
                "model_steps_per_s": rate,
                "model_steps_per_cpu_s": steps / t["cpu_s"],
                "percent_of_peak": 100.0 * rate * flop / peak,
            }
        )
    base = rows[1]["wall_s"]
    print_table(
        f"plan scoring at {CANDIDATES} candidates x {PARTICLES} particles x {HORIZON} steps "
        f"({per_member} trajectories per member); {flop / 1e3:.1f} kFLOP per model step; "
        f"matmul peak {peak / 1e9:.1f} GFLOP/s",
        ["case", "threads", "load", "s / call", "model steps/s", "% of peak", "x model alone"],
        [
            [
                r["case"], r["threads"], r["load_1min"], r["wall_s"], r["model_steps_per_s"],
                r["percent_of_peak"], r["wall_s"] / base,
            ]
            for r in rows
        ],
    )  # fmt: skip
    if compiled:
        print(f"\ncompile (dynamic particle count): {compiled}")
    if first_calls:
        print_table(
            "first scoring call of a fresh process (s), by cache state",
            ["path and caches", "s"],
            [[k, v] for k, v in first_calls.items()],
        )
    stock = stock_comparison(model, args.repeats, args.aot) if args.stock else {}
    if stock:
        print_table(
            f"seconds per plan of 5 states, C x I x H = {CANDIDATES} x 2 x {HORIZON}",
            ["planner", "threads", "load", "s", "stock / this"],
            [
                [k, v["threads"], v["load_1min"], v["wall_s"], v["stock_over_this"]]
                for k, v in stock.items()
            ],
        )
    peer = mbrl_comparison(model, args.repeats, args.aot) if args.mbrl else {}
    if args.mbrl and not peer:
        print("\nmbrl-lib is not importable: see this script's docstring to install it")
    if peer:
        print_table(
            "mbrl-lib PETS CEM vs ours, population 200 x 20 particles x horizon 15 x 5 iterations",
            ["planner", "threads", "load", "s / plan", "model steps/s", "kFLOP / step",
             "GFLOP/s", "steps/s / mbrl", "FLOP/s / mbrl"],
            [
                [k, v["threads"], v["load_1min"], v["wall_s"], v["model_steps_per_s"],
                 v["flop_per_model_step"] / 1e3, v["flop_per_s"] / 1e9,
                 v["steps_per_s_over_mbrl"], v["flop_per_s_over_mbrl"]]
                for k, v in peer.items()
            ],
        )  # fmt: skip
    results = {
        "budget": {"candidates": CANDIDATES, "particles": PARTICLES, "horizon": HORIZON},
        "flop_per_model_step": flop,
        "matmul_peak_flop_per_s": peak,
        "rows": rows,
        "compile_dynamic": compiled,
        "first_call_fresh_process_s": first_calls,
        "vs_stock_cem": stock,
        "vs_mbrl_lib": peer,
        **conditions(),
    }
    if args.out is None:
        write_json("model_step", results)
    else:
        write_json_to(args.out, {"benchmark": "model_step", "machine": machine_info(), **results})
        print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()

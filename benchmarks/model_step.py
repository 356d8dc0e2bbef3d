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
        [--scale N] [--device cpu|cuda|cuda:N] [--out PATH]

Where the goals of plan scoring stop (rows that explain a miss, same run):

- with ``--stock``: the plan's model and task calls alone (``ensemble.step``, the Pusher's
  reward and success, at the P = 1 plan's batch, I x H times per plan): every planner over this
  model env makes them, so stock / this is the most an eager planner can gain over the stock one
  without a cheaper step;
- with ``--mbrl``: each side's matrix products alone (the shapes recorded from one plan,
  replayed on random operands of the same shapes): their GFLOP/s bound what the whole plan can
  reach, whatever else it costs, and our bound over mbrl-lib's actual GFLOP/s is the most the
  FLOP/s ratio can be at these layer sizes.

``--scale N`` adds the same two eager rows (model step alone, ``evaluate_action_sequences``) at
N trajectories per member (imagination at a GPU's batch size). ``--device cuda`` (or
``cuda:N``) runs the model rows (scoring, model step alone, ``--scale``, ``--compile``) on a
GPU, timing each call until its kernels have run; ``--stock``, ``--mbrl`` and ``--aot`` (the
CPU package) stay CPU-only. The device's name is recorded with every figure.

``--out`` writes the results there instead of ``benchmarks/results/model_step.json`` (runs on a
busy machine).
"""

from __future__ import annotations

import argparse
import atexit
import dataclasses
import functools
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from _report import (
    benchmark_device,
    conditions,
    device_name,
    interleaved_median_times,
    machine_info,
    print_table,
    synchronize,
    write_json,
)
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.io import write_json as write_json_to
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout import SCORING_CACHE_ENV, Task, evaluate_action_sequences, scoring
from recipes.pusher_competency.config import StudyConfig
from recipes.pusher_competency.pusher import MODEL_FUNCTIONS, rcvae_config

CANDIDATES, PARTICLES, HORIZON, MEMBERS = 64, 5, 12, 5


def study_ensemble(device: torch.device | str = "cpu") -> RCVAEEnsemble:
    """The study's model (its config and the Pusher's state constraint and input features), on
    ``device``."""
    gen = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    config = rcvae_config(StudyConfig().model)
    model = RCVAEEnsemble(config, ensemble_size=MEMBERS, functions=MODEL_FUNCTIONS).eval()
    obs = torch.randn(2000, 14, generator=gen) * 0.1
    actions = torch.rand(2000, 2, generator=gen) * 2 - 1
    model.fit_normalizer(obs, actions, next_observations=obs + 0.01 * torch.randn_like(obs))
    return model.to(device)


def matmul_peak_flops(device: torch.device | str = "cpu", repeats: int = 5) -> float:
    """FLOP/s of a large float32 matrix product: [1024, 1024]² on a CPU core, [8192, 8192]² on
    a GPU (the best of ``repeats``)."""
    size = 8192 if torch.device(device).type == "cuda" else 1024
    a, b = torch.randn(size, size, device=device), torch.randn(size, size, device=device)
    a @ b
    best = float("inf")
    for _ in range(repeats):
        synchronize(device)
        start = time.perf_counter()
        a @ b
        synchronize(device)
        best = min(best, time.perf_counter() - start)
    return 2.0 * size**3 / best


def _step_inputs(model: RCVAEEnsemble, per_member: int) -> tuple[torch.Tensor, ...]:
    """The carried state (h and, with an episode latent, e), s and a of ``per_member``
    particles per member, zeros on the model's device."""
    device = model.device
    hidden = torch.zeros(MEMBERS, per_member, model.carry_dim, device=device)
    obs = torch.zeros(MEMBERS, per_member, 14, device=device)
    return hidden, obs, torch.zeros(MEMBERS, per_member, 2, device=device)


def step_flop(model: RCVAEEnsemble, per_member: int) -> float:
    """FLOP of one model step of one particle."""
    hidden, obs, act = _step_inputs(model, per_member)
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        model.step(hidden, obs, act, generator=torch.Generator(model.device))
    return counter.get_total_flops() / (MEMBERS * per_member)


def model_steps_alone(
    model: RCVAEEnsemble,
    per_member: int,
    horizon: int,
    task: Task | None = None,
    per_step: bool = True,
) -> None:
    """``horizon`` model steps of ``per_member`` particles per member, and with ``task`` its
    reward and success of every step: at every step (what a planner stepping the model env
    computes) or, with ``per_step=False``, once on all the steps' states (what this library's
    scoring computes)."""
    gen = torch.Generator(model.device).manual_seed(0)
    hidden, obs, act = _step_inputs(model, per_member)
    states = []
    with torch.no_grad():
        for _ in range(horizon):
            out = model.step(hidden, obs, act, generator=gen)
            hidden, obs = out.hidden, out.observation
            if task is not None and per_step:
                task.reward_fn(observation=obs, action=act), task.success_fn(observation=obs)
            elif task is not None:
                states.append(obs)
        if states:
            all_states = torch.stack(states)
            task.reward_fn(observation=all_states, action=act.expand_as(all_states[..., :2]))
            task.success_fn(observation=all_states)


def scoring_call(model, task, candidates: int, compile_=False, cache_dir=None) -> None:
    device = model.device
    gen = torch.Generator(device).manual_seed(0)
    start = torch.randn(1, 14, generator=gen, device=device).expand(candidates, 14) * 0.1
    actions = torch.rand(candidates, HORIZON, 2, generator=gen, device=device) * 2 - 1
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


MODEL_ALONE = "model step alone (ensemble.step x H), eager"


def model_rows(
    model: RCVAEEnsemble, task: Task, per_member: int, suffix: str = ""
) -> dict[str, tuple[Callable[[], None], int]]:
    """The eager rows at ``per_member`` trajectories per member (``PARTICLES`` particles of
    ``per_member * MEMBERS / PARTICLES`` candidates): ``evaluate_action_sequences`` and the
    model's own step alone; each with its number of candidates."""
    candidates = math.ceil(per_member * MEMBERS / PARTICLES)
    return {
        f"evaluate_action_sequences, eager{suffix}": (
            functools.partial(scoring_call, model, task, candidates),
            candidates,
        ),
        f"{MODEL_ALONE}{suffix}": (
            functools.partial(model_steps_alone, model, per_member, HORIZON),
            candidates,
        ),
    }


def _alone_of(case: str) -> str:
    """The model-alone row a row is compared with: the one of its batch size."""
    suffix = case.rsplit(", ", 1)[-1] if case.endswith("per member") else ""
    return f"{MODEL_ALONE}, {suffix}" if suffix else MODEL_ALONE


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


#: The row of :func:`stock_comparison` that bounds any eager planner stepping the model env
#: (the stock one calls the reward and success at every step).
CALLS_ALONE = "the P=1 plan's model and task calls alone"
#: The same model steps with the task called once on all of a scoring's steps, as this
#: library's scoring calls it: no eager planner with this model step can do without these.
MODEL_CALLS_ALONE = "the P=1 plan's model calls, its task calls once per scoring"


def stock_comparison(model: RCVAEEnsemble, repeats: int, aot: bool = False) -> dict[str, Any]:
    """Seconds per plan: ours (P = 1, 5) vs the stock CEMPlanner, same model env and budget;
    with ``aot``, also ours with the ahead-of-time compiled scoring (its build, in the warm-up
    round, is not timed). Also :data:`CALLS_ALONE`: the model steps with the Pusher's reward and
    success at every step that a P = 1 plan makes (64 candidates, padded to a multiple of the
    members, over I x H steps), with nothing around them: stock / that is the most a planner
    stepping the model env can gain over the stock one with this model step; and
    :data:`MODEL_CALLS_ALONE`: the same model steps with the task called once per scoring (I
    times per plan), as this library's scoring calls it: the most any eager planner can gain
    with this model step."""
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

    task = Task(pusher_reward, pusher_success, terminate_on_success=True)
    per_member = math.ceil(CANDIDATES / MEMBERS)

    def calls_alone(per_step: bool = True) -> None:
        for _ in states:
            for _ in range(config.iterations):
                model_steps_alone(model, per_member, config.horizon, task, per_step)

    runs = {k: functools.partial(plan_all, p) for k, p in planners.items()}
    with torch.no_grad():
        alone = {
            CALLS_ALONE: calls_alone,
            MODEL_CALLS_ALONE: functools.partial(calls_alone, per_step=False),
        }
        times = interleaved_median_times({**runs, **alone}, repeats)
    stock = times["stock CEMPlanner"]["wall_s"]
    return {k: {**v, "stock_over_this": stock / v["wall_s"]} for k, v in times.items()}


MBRL_BUDGET = {"population": 200, "particles": 20, "horizon": 15, "iterations": 5}
#: Rows of :func:`mbrl_comparison`: each plan's matrix products alone (:func:`matmuls_alone`).
MBRL_MATMULS = "mbrl-lib's matrix products alone"
OURS_MATMULS = "our matrix products alone"


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


_MATMULS = (torch.ops.aten.mm, torch.ops.aten.addmm, torch.ops.aten.bmm, torch.ops.aten.baddbmm)


class _Dispatched(TorchDispatchMode):
    """Every ATen call a call dispatches (views included), in order: the op, its operands
    (tensors by their shapes), its options, and the elements of its output."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple[Any, tuple, dict, int]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        shapes = tuple(torch.Size(a.shape) if isinstance(a, torch.Tensor) else a for a in args)
        elements = out.numel() if isinstance(out, torch.Tensor) else 0
        self.calls.append((func, shapes, dict(kwargs or {}), elements))
        return out


def dispatched(call) -> list[tuple[Any, tuple, dict, int]]:
    """The ATen calls of ``call()`` (no gradients), as :class:`_Dispatched` records them."""
    with _Dispatched() as recorder, torch.no_grad():
        call()
    return recorder.calls


def matmuls_alone(call) -> Callable[[], None]:
    """A call that makes the matrix products ``call()`` makes (recorded once), in order, on
    random contiguous operands of the same shapes (one set per shape), and nothing else: the
    time that arithmetic takes at those shapes when no other op stands between the products."""
    operands: dict[torch.Size, torch.Tensor] = {}

    def operand(a):
        if not isinstance(a, torch.Size):
            return a
        return operands.setdefault(a, torch.randn(a))

    replay = [
        (f, [operand(a) for a in shapes], kw)
        for f, shapes, kw, _ in dispatched(call)
        if f.overloadpacket in _MATMULS
    ]

    def run() -> None:
        for func, args, kwargs in replay:
            func(*args, **kwargs)

    return run


#: Elementwise functions that cost far more than a multiply-add per element (activations,
#: transcendental functions, normal draws); ReLU, a comparison, is not among them.
TRANSCENDENTAL = {
    "atan2", "cos", "erfinv", "exp", "linalg_vector_norm", "log", "normal", "normal_", "pow",
    "randn", "rsqrt", "sigmoid", "silu", "sin", "softplus", "sqrt", "tanh",
}  # fmt: skip


def transcendentals_of(call) -> int:
    """Elements produced by :data:`TRANSCENDENTAL` ops in ``call()`` (no gradients)."""
    calls = dispatched(call)
    return sum(n for f, _, _, n in calls if f.overloadpacket.__name__ in TRANSCENDENTAL)


def ops_of(call) -> int:
    """ATen calls dispatched by ``call()`` (no gradients), after a first call (which may fill
    caches: a second one is what every later step costs)."""
    with torch.no_grad():
        call()
    return len(dispatched(call))


def op_counts(model: RCVAEEnsemble, task: Task, per_member: int) -> dict[str, int]:
    """ATen calls of one eager model step with the task's reward and success, at
    ``per_member`` particles per member, and of the parts the model reads from its config (the
    input features and the state constraint, inside the step) and from the task."""
    hidden, obs, act = _step_inputs(model, per_member)
    gen = torch.Generator(model.device).manual_seed(0)
    out = {
        "model step": ops_of(lambda: model.step(hidden, obs, act, generator=gen)),
        "reward": ops_of(lambda: task.reward_fn(observation=obs, action=act)),
        "success": ops_of(lambda: task.success_fn(observation=obs)),
    }
    if model._features is not None:
        out["input features (in the step)"] = ops_of(lambda: model._features(obs))
    if model.state_constraint is not None:
        out["state constraint (in the step)"] = ops_of(lambda: model.state_constraint(obs, obs))
    return out


def _flop_of(call) -> float:
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        call()
    return float(counter.get_total_flops())


def mbrl_comparison(model: RCVAEEnsemble, repeats: int, aot: bool = False) -> dict[str, Any]:
    """Ours against mbrl-lib's PETS CEM at its budget: s per plan, model steps/s, FLOP/s (with
    ``aot``, also ours with the ahead-of-time compiled scoring); and each side's matrix
    products alone (:data:`MBRL_MATMULS`, :data:`OURS_MATMULS`): our products' FLOP/s over
    mbrl-lib's plan's is the most our plan's FLOP/s ratio can reach at these layer sizes."""
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
    alone = {
        MBRL_MATMULS: matmuls_alone(peer),
        OURS_MATMULS: matmuls_alone(calls["ours (CEMPlanner)"]),
    }
    steps = b["population"] * b["particles"] * b["horizon"] * b["iterations"]
    # FLOP counted on the eager path (the compiled one does the same arithmetic)
    ours_flop = _flop_of(calls["ours (CEMPlanner)"])
    flop = {name: ours_flop for name in planners} | {"mbrl-lib PETS CEM": _flop_of(peer)}
    flop |= {name: _flop_of(run) for name, run in alone.items()}
    transcendental = {
        "mbrl-lib PETS CEM": transcendentals_of(peer),
        "ours (CEMPlanner)": transcendentals_of(calls["ours (CEMPlanner)"]),
    }
    calls |= alone
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
    for name, count in transcendental.items():
        out[name]["transcendentals_per_model_step"] = count / steps
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
    parser.add_argument(
        "--scale", type=int, metavar="N", help="also the eager rows at N trajectories per member"
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (model rows)")
    parser.add_argument("--out", type=Path, help="write the results here (default: results/)")
    parser.add_argument("--first-call", nargs=2, metavar=("MODE", "CACHE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.first_call:
        print(first_call_here(*args.first_call))
        return
    device = benchmark_device(args.device)
    if device.type != "cpu" and (args.stock or args.mbrl or args.aot):
        raise SystemExit(
            f"--device {args.device}: --stock, --mbrl and --aot run on the CPU only (the real "
            "Pusher's states, mbrl-lib's CPU planner, the CPU package); run them without --device"
        )
    if args.scale is not None and args.scale < 1:
        raise SystemExit(f"--scale: expected trajectories per member >= 1, got {args.scale}")
    torch.set_num_threads(1)
    model = study_ensemble(device)
    task = Task(pusher_reward, pusher_success, terminate_on_success=True)
    per_member = CANDIDATES * PARTICLES // MEMBERS
    flop, peak = step_flop(model, per_member), matmul_peak_flops(device)
    runs = model_rows(model, task, per_member)
    if args.scale is not None:
        runs |= model_rows(model, task, args.scale, f", {args.scale} per member")
    compiled, first_calls = {}, {}
    root = Path(tempfile.mkdtemp(prefix="model_step_"))
    if args.aot:  # first, while no compile of this process has filled a cache
        planners_cache = tempfile.mkdtemp(prefix="model_step_planners_")  # --stock, --mbrl
        atexit.register(shutil.rmtree, planners_cache, True)
        os.environ[SCORING_CACHE_ENV] = planners_cache
        first_calls = fresh_process_first_calls(root, compile_too=args.compile)
        runs["evaluate_action_sequences, compile='aot'"] = (
            functools.partial(scoring_call, model, task, CANDIDATES, "aot", root / "b"),
            CANDIDATES,
        )
    if args.compile:
        compiled = compile_times(model, task)
        runs["evaluate_action_sequences, compile=True"] = (
            functools.partial(scoring_call, model, task, CANDIDATES, True),
            CANDIDATES,
        )
    try:
        calls = {name: call for name, (call, _) in runs.items()}
        times = interleaved_median_times(calls, args.repeats, device=device)
    finally:
        shutil.rmtree(root)
    rows = []
    for name, t in times.items():
        steps = runs[name][1] * PARTICLES * HORIZON
        rate = steps / t["wall_s"]
        rows.append(
            {
                "case": name,
                **t,
                "device": device_name(device),
                "model_steps_per_s": rate,
                "model_steps_per_cpu_s": steps / t["cpu_s"],
                "percent_of_peak": 100.0 * rate * flop / peak,
            }
        )
    base = {r["case"]: r["wall_s"] for r in rows if r["case"].startswith(MODEL_ALONE)}
    print_table(
        f"plan scoring, {PARTICLES} particles x {HORIZON} steps from {CANDIDATES} candidates "
        f"({per_member} trajectories per member) unless the row says; on "
        f"{device_name(device)}; {flop / 1e3:.1f} kFLOP per model step; matmul peak "
        f"{peak / 1e9:.1f} GFLOP/s",
        ["case", "threads", "load", "s / call", "model steps/s", "% of peak", "x model alone"],
        [
            [
                r["case"], r["threads"], r["load_1min"], r["wall_s"], r["model_steps_per_s"],
                r["percent_of_peak"], r["wall_s"] / base[_alone_of(r["case"])],
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
    ops = op_counts(model, task, per_member)
    total = ops["model step"] + ops["reward"] + ops["success"]
    print_table(
        f"ATen calls dispatched per imagined step (views included; {total} with the task)",
        ["part", "calls"],
        [[k, v] for k, v in ops.items()],
    )
    stock = stock_comparison(model, args.repeats, args.aot) if args.stock else {}
    if stock:
        print_table(
            f"seconds per plan of 5 states, C x I x H = {CANDIDATES} x 2 x {HORIZON} (the last "
            "rows: the model and task calls alone, the task at every step as a planner stepping "
            "the model env calls it, and once per scoring as this library's scoring does)",
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
            "mbrl-lib PETS CEM vs ours, population 200 x 20 particles x horizon 15 x 5 iterations "
            "(the last rows: each plan's matrix products alone)",
            ["planner", "threads", "load", "s / plan", "model steps/s", "kFLOP / step",
             "GFLOP/s", "steps/s / mbrl", "FLOP/s / mbrl"],
            [
                [k, v["threads"], v["load_1min"], v["wall_s"], v["model_steps_per_s"],
                 v["flop_per_model_step"] / 1e3, v["flop_per_s"] / 1e9,
                 v["steps_per_s_over_mbrl"], v["flop_per_s_over_mbrl"]]
                for k, v in peer.items()
            ],
        )  # fmt: skip
        print_table(
            "transcendental elements per model step (activations, exp/log/trigonometry, normal "
            "draws) against the step's FLOP",
            ["planner", "per model step", "per kFLOP"],
            [
                [k, v["transcendentals_per_model_step"],
                 1e3 * v["transcendentals_per_model_step"] / v["flop_per_model_step"]]
                for k, v in peer.items() if "transcendentals_per_model_step" in v
            ],
        )  # fmt: skip
    results = {
        "budget": {"candidates": CANDIDATES, "particles": PARTICLES, "horizon": HORIZON},
        "scale_per_member": args.scale,
        "flop_per_model_step": flop,
        "aten_calls_per_step": ops,
        "matmul_peak_flop_per_s": peak,
        "rows": rows,
        "compile_dynamic": compiled,
        "first_call_fresh_process_s": first_calls,
        "vs_stock_cem": stock,
        "vs_mbrl_lib": peer,
        **conditions(device),
    }
    if args.out is None:
        write_json("model_step", results)
    else:
        write_json_to(args.out, {"benchmark": "model_step", "machine": machine_info(), **results})
        print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()

"""Scaling over torch.distributed ranks: training, forecasting and real-rollout validation.

Each workload runs at 1 rank (one process, no process group) and at 2 gloo ranks (spawned
with ``torch.multiprocessing``), one intra-op thread per rank, in ``--repeats`` rounds of one
timed run per world size (each in freshly spawned processes, after one untimed warm-up run), so
that a drift of the machine's load hits both world sizes alike; the time of a run is rank 0's
wall clock from a barrier to the end of the gathered result. Workloads (Pusher-sized, the
study's default world model):

- training: ``train_ensemble`` of E = 4 members (2 per rank), 100 steps (``--training-steps``)
  of 32 windows x 32 steps, on synthetic 14-D episodes (``--compile``: the loss compiled, each
  process compiling in its untimed warm-up run); and the same in one process with 1, 2
  and 4 members, which splits its time into a fixed part (every rank pays it in full) and a
  part per member, and gives the split's ceiling (4 members over 2, alone) and what running
  side by side adds (the 2-rank time over 2 members alone);
- training_models: the study's models stage, two such ensembles of 5 members (its
  deterministic and stochastic world models), one per rank at 2 ranks
  (:func:`~rcvae_torchrl.distributed.parts`), one after the other at 1, their weights gathered;
  training_models_shared: the same two, one after the other, every rank sharing each one's
  members (3 and 2 at 2 ranks);
- training_data_parallel: the same training with ``TrainConfig(data_parallel=2)``: at 2 ranks
  both train all 4 members, each on 16 of every step's 32 windows, DDP all-reducing the
  gradients at every step (not in the gathered bytes); at 1 rank it is the training above;
- forecasting: ``CompetencyAssessor.assess`` closed loop, 16 start states in chunks of one
  (8 per rank), 20 samples per member of 5 members, a horizon of 100 steps;
- validation: ``real_outcomes`` of the scripted pusher in the real Pusher (one env per rank)
  from 16 start states, 200 steps; and the same in one process over 1 and 2 worker processes
  of a TorchRL ``ParallelEnv`` (``real_outcomes(..., workers=2)``), with the workers'
  start-up (built at each call) timed apart.

Printed and written to ``benchmarks/results/scaling.json``: median wall times, speed-up
(t1 / t2) and efficiency (speed-up / 2), the same from CPU seconds (the slowest rank's: what
the ranks would take on free cores, when other jobs hold the machine's cores); the bytes each
rank contributes to the gather and the gather's time; and a projection for 8 ranks on one
machine and 4 machines x 8 GPUs from the measured cost (see ``project`` for the model and its
assumptions). The machine's load average is recorded before and after: other jobs on a shared
2-core machine take cores away from the ranks.

    python benchmarks/scaling.py [--repeats 3] [--quick] [--only training ...] [--full-model]
                                 [--training-steps 100] [--compile] [--out scaling]
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import pickle
import resource
import socket
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
import torch.multiprocessing as mp
from _report import print_table, write_json

from rcvae_torchrl import distributed

WORLDS = (1, 2)
# members, members, chunks, episodes
UNITS = {
    "training": 4,
    "training_models": 10,
    "training_models_shared": 10,
    "training_data_parallel": 4,
    "forecasting": 16,
    "validation": 16,
}


# ---------------------------------------------------------------------- workloads
def _training(
    quick: bool,
    full_model: bool = False,
    steps: int = 100,
    members: int = 4,
    data_parallel: int = 1,
    compile: bool = False,
    seed: int = 0,
):
    from tensordict import TensorDict

    from rcvae_torchrl.data import TRAJ_KEY
    from rcvae_torchrl.models import RCVAEEnsemble
    from rcvae_torchrl.training import TrainConfig, train_ensemble
    from recipes.pusher_competency.config import ModelConfig
    from recipes.pusher_competency.pusher import MODEL_FUNCTIONS, rcvae_config

    g = torch.Generator().manual_seed(0)

    def episodes(n: int, first: int) -> TensorDict:
        obs = torch.randn(n, 64, 14, generator=g).cumsum(1) * 0.01
        obs[..., :4] = obs[..., :4].clamp(-1, 1)
        td = TensorDict(
            {
                "observation": obs[:, :-1],
                "action": torch.rand(n, 63, 2, generator=g) * 2 - 1,
                ("next", "observation"): obs[:, 1:],
                TRAJ_KEY: (torch.arange(n) + first)[:, None].expand(n, 63),
            },
            batch_size=[n, 63],
        )
        return td.reshape(-1)

    train, val = episodes(32, 0), episodes(8, 1000)
    steps = 10 if quick else steps
    windows = 64 if full_model else 32  # the full profile's batch and hidden size
    config = TrainConfig(
        max_steps=steps,
        batch_windows=windows,
        window=32,
        val_every=steps // 2,
        data_parallel=data_parallel,
        compile=compile,  # compiled in the warm-up run; the timed runs reuse it
    )
    model_config = rcvae_config(ModelConfig(hidden_dim=128 if full_model else 64))

    def run() -> dict[str, torch.Tensor]:
        torch.manual_seed(seed)
        model = RCVAEEnsemble(model_config, members, functions=MODEL_FUNCTIONS)
        # 8 validation episodes measure no dynamics check: none asked for (no warning)
        train_ensemble(model, train, val, config, progress=False, checks=False, dynamics=False)
        return model.state_dict()

    return run


def _training_models(quick: bool, steps: int = 100, parts: bool = True, **workload: Any):
    """The study's models stage: two ensembles of 5 members (its deterministic and stochastic
    world models; here the same synthetic episodes, drawn with seeds 0 and 1) trained with
    :func:`_training`'s budget, side by side over the ranks (:func:`distributed.parts`: one per
    rank at 2 ranks, one after the other at 1), every ensemble's weights then gathered; with
    ``parts=False`` one after the other, all ranks sharing each one's members (3 and 2 at 2
    ranks; the recipe's stage before it used parts)."""
    runs = [_training(quick, steps=steps, members=5, seed=job, **workload) for job in (0, 1)]

    def run() -> None:
        trained = {}
        n = min(len(runs), distributed.world_size()) if parts else 1
        with distributed.parts(n) as part:
            for job in range(part.index, len(runs), part.parts):
                trained[job] = runs[job]()
            leader = distributed.is_main()
        distributed.all_gather(trained if leader else {})

    return run


def _forecasting(quick: bool):
    from rcvae_torchrl.competency import CompetencyAssessor, SuccessBoundary
    from rcvae_torchrl.envs import resolution_tensor
    from rcvae_torchrl.model_env import RCVAEEnsembleEnv
    from rcvae_torchrl.models import RCVAEEnsemble
    from recipes.pusher_competency.config import ModelConfig
    from recipes.pusher_competency.pusher import MODEL_FUNCTIONS, rcvae_config

    torch.manual_seed(0)
    model = RCVAEEnsemble(rcvae_config(ModelConfig()), 5, functions=MODEL_FUNCTIONS)
    obs = torch.randn(500, 14) * 0.1
    model.fit_normalizer(obs, torch.rand(500, 2) * 2 - 1, next_observations=obs * 1.01)
    policy = torch.nn.Sequential(torch.nn.Linear(14, 64), torch.nn.Tanh(), torch.nn.Linear(64, 2))
    horizon = 20 if quick else 100
    env = RCVAEEnsembleEnv(
        model,
        lambda observation, action: -observation[..., :1],
        lambda observation: observation[..., 8] > 0.2,
    )
    assessor = CompetencyAssessor(
        env,
        SuccessBoundary(lambda s: s[..., 8] > 0.2, time_limit=horizon, dt=0.05),
        bin_width=resolution_tensor(),
        samples_per_member=20,
        start_chunk=1,
        bias_correction="shuffle",
    )
    starts = torch.randn(UNITS["forecasting"], 14, generator=torch.Generator().manual_seed(1))

    def run() -> None:
        with torch.no_grad():
            assessor.assess(starts * 0.1, policy=lambda o: policy(o).tanh(), seed=0)

    return run


def _scripted_outcomes(env, episodes: int, steps: int, workers: int):
    """A call of ``real_outcomes`` for the scripted pusher from ``episodes`` Pusher start
    states (seeds 0, 1, ...) in ``env`` (an env, or a function that makes one)."""
    from rcvae_torchrl.agent import make_policy_module, real_outcomes
    from rcvae_torchrl.envs import make_pusher_env, reset_to_state
    from rcvae_torchrl.envs.scripted import ScriptedPusher

    drawn = make_pusher_env("deterministic")
    starts = []
    for i in range(episodes):
        drawn.set_seed(i)
        starts.append(drawn.reset()["observation"])
    starts = torch.stack(starts)
    policy = make_policy_module(ScriptedPusher())

    def run() -> None:
        real_outcomes(
            env,
            policy,
            starts,
            runs_per_start=1,
            reset_to_state=reset_to_state,
            max_steps=steps,
            workers=workers,
            progress=False,
        )

    return run


def _validation(quick: bool, workers: int | None = None):
    """The validation workload: one env in this process (``workers=None``, a rank's), or the
    env built in each of ``workers`` TorchRL ``ParallelEnv`` worker processes."""
    from recipes.pusher_competency.config import DataConfig
    from recipes.pusher_competency.pusher import make_env

    make = functools.partial(make_env, "deterministic", DataConfig(), 0.03, time_limit=10.0)
    env = make() if workers is None else make
    return _scripted_outcomes(env, UNITS["validation"], 50 if quick else 200, workers or 1)


BATCHED_EPISODES = 256  # episodes of the batched-Pusher workers row


def _batched_validation(quick: bool, workers: int):
    """The recipe's validation: ``BATCHED_EPISODES`` episodes of the scripted pusher in
    batched Pushers, one of all the envs in this process (``workers=1``) or one of
    ``1/workers`` of them in each ``ParallelEnv`` worker."""
    from rcvae_torchrl.envs import make_batched_pusher_env

    episodes, steps = (16, 50) if quick else (BATCHED_EPISODES, 200)
    make = functools.partial(
        make_batched_pusher_env,
        episodes // workers,
        "deterministic",
        time_limit=10.0,
        terminate_on_success=False,
    )
    return _scripted_outcomes(make() if workers == 1 else make, episodes, steps, workers)


WORKLOADS = {
    "training": _training,
    "training_models": _training_models,
    "training_models_shared": functools.partial(_training_models, parts=False),
    # all 4 members on each of the 2 ranks, each computing half of every step's windows
    "training_data_parallel": functools.partial(_training, data_parallel=2),
    "forecasting": _forecasting,
    "validation": _validation,
}
#: Workloads whose ranks all-reduce at every step (DDP's gradients): the projection's model
#: (work shared once, one gather at the end) does not hold for them.
#: Nor for two whole ensembles, one per part of the ranks: 2 jobs do not split over 8 ranks.
NOT_PROJECTED = ("training_data_parallel", "training_models", "training_models_shared")


# ---------------------------------------------------------------------- one rank
def _rank(rank: int, world: int, port: int, name: str, args: dict, out: str) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        WORLD_SIZE=str(world),
        OMP_NUM_THREADS="1",
    )
    torch.set_num_threads(1)
    gathers: list[tuple[int, float]] = []
    gather = distributed.all_gather

    def measured_gather(obj: Any) -> list[Any]:  # bytes this rank sends, and the call's time
        start = time.perf_counter()
        result = gather(obj)
        gathers.append((len(pickle.dumps(obj)), time.perf_counter() - start))
        return result

    distributed.all_gather = measured_gather
    with distributed.session("gloo"):
        run = WORKLOADS[name](args["quick"], **args["workload"].get(name, {}))
        run()  # warm-up
        times, cpu = [], []
        for _ in range(args["repeats"]):
            gathers.clear()
            distributed.barrier()
            start, start_cpu = time.perf_counter(), time.process_time()
            run()
            cpu.append(time.process_time() - start_cpu)
            distributed.barrier()
            times.append(time.perf_counter() - start)
        sent, waited = sum(b for b, _ in gathers), sum(t for _, t in gathers)
        probe = _gather_probe(sent) if world > 1 else None
        cpu_by_rank = gather(cpu)
    if rank == 0:
        torch.save(
            {
                "times": times,
                "cpu_by_rank": cpu_by_rank,
                "gather_bytes": sent,
                "gather_s": waited,
                "probe": probe,
            },
            out,
        )


def _gather_probe(nbytes: int, repeats: int = 5) -> dict[str, float]:
    """The time of an all-gather of ``nbytes`` per rank with every rank ready (no waiting for a
    slower rank), and of an empty one (latency)."""
    payload = bytes(max(nbytes, 1))

    def timed(obj: Any) -> float:
        out = []
        for _ in range(repeats):
            distributed.barrier()
            start = time.perf_counter()
            distributed.all_gather(obj)
            out.append(time.perf_counter() - start)
        return statistics.median(out)

    return {"payload_s": timed(payload), "latency_s": timed(b"")}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def measure(name: str, world: int, args: dict) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "out.pt")
        mp.spawn(_rank, args=(world, _free_port(), name, args, out), nprocs=world, join=True)
        return torch.load(out)


def measure_interleaved(name: str, args: dict) -> dict[int, dict[str, Any]]:
    """``name`` at every world size, ``args["repeats"]`` rounds of one timed run per world size
    (each in its own processes, after their warm-up run): a drift of the machine's load hits
    every world size alike, as it would not if each ran all its repeats in a block."""
    rounds: dict[int, list[dict[str, Any]]] = {world: [] for world in WORLDS}
    for _ in range(args["repeats"]):
        for world in WORLDS:
            rounds[world].append(measure(name, world, {**args, "repeats": 1}))
    return {world: join_rounds(measured) for world, measured in rounds.items()}


def round_speedups(one: list[float], two: list[float]) -> list[float]:
    """Each round's speed-up: its 1-rank time over its 2-rank time (the rounds in order)."""
    if len(one) != len(two):
        raise ValueError(f"expected one 2-rank time per round, got {len(one)} and {len(two)}")
    return [a / b for a, b in zip(one, two)]


def join_rounds(measured: list[dict[str, Any]]) -> dict[str, Any]:
    """One result of several :func:`measure` calls: their times and each rank's CPU seconds in
    order, the gathered bytes (the same in every round), the median gather wait, and the
    gather probe's medians (``None`` at one rank)."""
    probes = [m["probe"] for m in measured if m["probe"] is not None]
    return {
        "times": [t for m in measured for t in m["times"]],
        "cpu_by_rank": [
            [t for m in measured for t in m["cpu_by_rank"][r]]
            for r in range(len(measured[0]["cpu_by_rank"]))
        ],
        "gather_bytes": measured[0]["gather_bytes"],
        "gather_s": statistics.median(m["gather_s"] for m in measured),
        "probe": {k: statistics.median(p[k] for p in probes) for k in probes[0]}
        if probes
        else None,
    }


# ---------------------------------------------------------------------- training by members
MEMBERS = (1, 2, 4)


def measure_members(args: dict) -> dict[int, list[float]]:
    """The training workload in this process (no process group) with 1, 2 and 4 members,
    interleaved: wall seconds per repeat. What a step costs whatever the members (the fixed
    part, which every rank pays in full) against what each member adds."""
    workload = args["workload"].get("training", {})
    runs = {m: _training(args["quick"], **workload, members=m) for m in MEMBERS}
    for run in runs.values():
        run()  # warm-up
    times: dict[int, list[float]] = {m: [] for m in MEMBERS}
    for _ in range(args["repeats"]):
        for m in MEMBERS:
            start = time.perf_counter()
            runs[m]()
            times[m].append(time.perf_counter() - start)
    return times


def members_summary(times: dict[int, list[float]], t1: float, t2: float) -> dict[str, Any]:
    """Fixed and per-member seconds (least squares of the medians over the members), what they
    allow at 2 ranks, and what the 2-rank run shows: ``t1``, ``t2`` are its 1- and 2-rank
    medians (4 members; 2 per rank)."""
    median = {m: statistics.median(v) for m, v in times.items()}
    xs, ys = list(median), list(median.values())
    mx, my = statistics.fmean(xs), statistics.fmean(ys)
    per_member = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)
    fixed = my - per_member * mx
    target = 1.7
    return {
        "median_s": {str(m): v for m, v in median.items()},
        "fixed_s": fixed,
        "per_member_s": per_member,
        # 4 members against 2 on one rank with the other rank idle: the split's own ceiling
        "speedup_ceiling_alone": median[4] / median[2],
        # the 2-rank run's rank against 2 members alone: other costs of running side by side
        # (the memory both ranks share, the gather)
        "side_by_side_over_alone": t2 / median[2],
        # fixed seconds to remove from every run for t1 / t2 to reach the target
        "fixed_to_remove_for_1.7x_s": max(0.0, (target * t2 - t1) / (target - 1)),
    }


# ---------------------------------------------------------------------- ParallelEnv workers
WORKERS = (1, 2)


def _cpu_s() -> float:
    """CPU seconds of this process and of its finished children (the env workers)."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def _worker_startup_s(repeats: int) -> float:
    """Median time to start 2 Pusher workers, reset them once and close them: the fixed cost
    of each ``real_outcomes(..., workers=2)`` call."""
    from rcvae_torchrl.agent import episode_workers
    from rcvae_torchrl.envs import make_pusher_env, reset_to_state

    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        pool = episode_workers(make_pusher_env, 2, reset_to_state)
        pool.reset()
        pool.close()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def measure_workers(args: dict, batched: bool = False) -> dict[str, Any]:
    """The validation workload in one process, at 1 worker (in process) and 2 ``ParallelEnv``
    workers (each call starting its workers), interleaved: wall and CPU seconds (this process
    and its workers) per repeat. ``batched``: the batched-Pusher workload
    (:func:`_batched_validation`) instead of one dm_control Pusher per worker."""
    workload = _batched_validation if batched else _validation
    runs = {k: workload(args["quick"], k) for k in WORKERS}
    times: dict[int, list[float]] = {k: [] for k in WORKERS}
    cpu: dict[int, list[float]] = {k: [] for k in WORKERS}
    for _ in range(args["repeats"]):
        for k in WORKERS:
            start, start_cpu = time.perf_counter(), _cpu_s()
            runs[k]()
            cpu[k].append(_cpu_s() - start_cpu)
            times[k].append(time.perf_counter() - start)
    return {"times": times, "cpu": cpu, "startup_s": _worker_startup_s(args["repeats"])}


# ---------------------------------------------------------------------- projection
# Assumed links of the projection (not measured here): 8 GPUs of one machine over NVLink /
# PCIe with NCCL, and 4 machines over a 100 Gb/s network.
INTRA_GPU = {"bandwidth_Bps": 50e9, "latency_s": 20e-6}
INTER_NODE = {"bandwidth_Bps": 12.5e9, "latency_s": 50e-6}


def project(
    t1: float, t2: float, gather_s: float, bytes_per_rank: int, units: int
) -> tuple[dict[str, float], Callable[[int, dict], dict[str, float]]]:
    """Projected times from the measured 1- and 2-rank runs (Amdahl's law plus a gather).

    ``t1``, ``t2``: the CPU seconds of one rank, and of the slowest of two (on a shared
    machine the CPU time is what a rank costs on a free core; wall time also holds the waits
    for cores that other jobs hold); ``gather_s``: an all-gather of the measured bytes with
    both ranks ready.

    - The serial part s (not shared: building the model and data, setting up, rank 0's
      extras) follows from t2 - gather = t1 (s + (1 - s) / 2); the shared part costs
      c = t1 (1 - s) / U per unit of work (member, chunk, episode) on one rank.
    - A workload of 32 units (enough for every rank) then takes
      s t1 + c ceil(32 / P) + gather(P), against s t1 + 32 c on one rank.
    - gather(P): an all-gather of P blocks, each the measured bytes per rank scaled to
      32 / P units: latency * ceil(log2 P) + (P - 1) / P * bytes / bandwidth, with the
      links assumed in INTRA_GPU / INTER_NODE (and, for 8 CPU ranks of one machine, the gloo
      bandwidth measured here). Each rank's per-unit cost is the one measured here (one CPU
      thread): a GPU rank computes faster, which shrinks c and so the speed-up.
    """
    serial = min(max(2 * (t2 - gather_s) / t1 - 1, 0.0), 1.0)
    per_unit = t1 * (1 - serial) / units
    bytes_per_unit = bytes_per_rank / (units / 2)
    projected_units = 32
    single = serial * t1 + per_unit * projected_units

    def at(ranks: int, link: dict) -> dict[str, float]:
        nbytes = bytes_per_unit * projected_units
        comm = link["latency_s"] * math.ceil(math.log2(ranks)) + (
            (ranks - 1) / ranks * nbytes / link["bandwidth_Bps"]
        )
        t = serial * t1 + per_unit * math.ceil(projected_units / ranks) + comm
        speedup = single / t
        return {"time_s": t, "gather_s": comm, "speedup": speedup, "efficiency": speedup / ranks}

    return {"serial_fraction": serial, "per_unit_s": per_unit, "single_rank_32_units_s": single}, at


def _workers_summary(
    measured: dict[str, Any], name: str, units: int
) -> tuple[list, dict[str, Any]]:
    """The table row and the JSON entry of :func:`measure_workers`' result."""
    wall = {k: statistics.median(v) for k, v in measured["times"].items()}
    cpu = {k: statistics.median(v) for k, v in measured["cpu"].items()}
    after_startup = wall[1] / max(wall[2] - measured["startup_s"], 1e-9)
    row = [name, units, wall[1], wall[2], wall[1] / wall[2], after_startup]
    row += [cpu[1], cpu[2], measured["startup_s"]]
    entry = {
        "units": units,
        "wall_s": {str(k): v for k, v in measured["times"].items()},
        "cpu_s": {str(k): v for k, v in measured["cpu"].items()},
        "median_wall_s": {str(k): v for k, v in wall.items()},
        "median_cpu_s": {str(k): v for k, v in cpu.items()},
        "speedup_wall": wall[1] / wall[2],
        "speedup_wall_after_startup": after_startup,
        "startup_2_workers_s": measured["startup_s"],
    }
    return row, entry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--only", choices=list(WORKLOADS), nargs="*", default=list(WORKLOADS))
    parser.add_argument(
        "--full-model",
        action="store_true",
        help="train the full profile's model (hidden 128, 64 windows per member)",
    )
    parser.add_argument(
        "--training-steps",
        type=int,
        default=100,
        help="training steps per run (the default profile trains up to 5000: with more steps "
        "the one-off set-up weighs less)",
    )
    parser.add_argument(
        "--compile",
        action="store_true",
        help="train with the loss compiled (TrainConfig(compile=True)); each process compiles "
        "in its warm-up run, which is not timed",
    )
    parser.add_argument("--out", default="scaling", help="results/<out>.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    settings = {
        "repeats": args.repeats,
        "quick": args.quick,
        "workload": {
            name: {
                "full_model": args.full_model,
                "steps": args.training_steps,
                "compile": args.compile,
            }
            for name in (
                "training",
                "training_models",
                "training_models_shared",
                "training_data_parallel",
            )
        },
    }
    results: dict[str, dict[int, dict]] = {name: {} for name in args.only}
    for name in args.only:
        print(f"{name}: 1 and 2 ranks, {args.repeats} interleaved rounds ...", flush=True)
        results[name] = measure_interleaved(name, settings)
    members = None
    if "training" in args.only:
        print("training: 1, 2 and 4 members in one process ...", flush=True)
        members = measure_members(settings)
    workers = {}
    if "validation" in args.only:
        print("validation: 1 and 2 ParallelEnv workers ...", flush=True)
        workers["validation (workers, one Pusher each)"] = (
            measure_workers(settings),
            UNITS["validation"],
            "validation_workers",
        )
        workers["validation (workers, batched Pushers)"] = (
            measure_workers(settings, batched=True),
            16 if args.quick else BATCHED_EPISODES,
            "validation_workers_batched",
        )
    load_after = os.getloadavg()
    rows, projections, payload = [], [], {}
    for name, by_world in results.items():
        one, two = by_world[1], by_world[2]
        t1, t2 = statistics.median(one["times"]), statistics.median(two["times"])
        c1 = statistics.median(one["cpu_by_rank"][0])
        c2 = statistics.median(max(r) for r in zip(*two["cpu_by_rank"]))
        probe = two["probe"]
        rounds = round_speedups(one["times"], two["times"])
        rows.append(
            [
                name,
                UNITS[name],
                t1,
                t2,
                t1 / t2,
                statistics.median(rounds),
                t1 / t2 / 2,
                c1,
                c2,
                c1 / c2,
                c1 / c2 / 2,
                two["gather_bytes"],
                probe["payload_s"],
            ]
        )
        gloo = {
            "latency_s": probe["latency_s"],
            "bandwidth_Bps": max(two["gather_bytes"], 1)
            / max(probe["payload_s"] - probe["latency_s"], 1e-9),
        }
        base, cases = None, {}
        if name not in NOT_PROJECTED:
            base, at = project(c1, c2, probe["payload_s"], two["gather_bytes"], UNITS[name])
            cases = {
                "8 ranks, 1 machine (gloo, as measured)": at(8, gloo),
                "8 GPUs, 1 machine (NCCL, assumed link)": at(8, INTRA_GPU),
                "4 machines x 8 GPUs (NCCL, assumed network)": at(32, INTER_NODE),
            }
        for case, p in cases.items():
            projections.append([name, case, p["time_s"], p["speedup"], p["efficiency"]])
        payload[name] = {
            "units": UNITS[name],
            "wall_s": {str(w): by_world[w]["times"] for w in WORLDS},
            "cpu_s_by_rank": {str(w): by_world[w]["cpu_by_rank"] for w in WORLDS},
            "median_wall_s": {"1": t1, "2": t2},
            "median_cpu_s": {"1": c1, "2 (slowest rank)": c2},
            "speedup_wall": t1 / t2,
            "speedup_wall_by_round": rounds,
            "speedup_wall_median_of_rounds": statistics.median(rounds),
            "efficiency_wall": t1 / t2 / 2,
            "speedup_cpu": c1 / c2,
            "efficiency_cpu": c1 / c2 / 2,
            "gather_bytes_per_rank": two["gather_bytes"],
            "gather_wait_s": two["gather_s"],
            "gather_probe": probe,
            "gloo_link": gloo,
            "model": base,
            "projection": cases,
        }
    print_table(
        "Scaling at 1 and 2 ranks (1 thread each, medians; CPU: the slowest rank's CPU seconds)",
        [
            "workload",
            "units",
            "wall 1",
            "wall 2",
            "speed-up",
            "rounds' median",
            "eff.",
            "CPU 1",
            "CPU 2",
            "CPU speed-up",
            "CPU eff.",
            "gathered B/rank",
            "gather s",
        ],
        rows,
    )
    if members is not None:
        by_world = results["training"]
        t1, t2 = (statistics.median(by_world[w]["times"]) for w in WORLDS)
        payload["training_members"] = summary = members_summary(members, t1, t2)
        print_table(
            "Training by members in one process (medians; fixed + per member, least squares)",
            [
                *(f"{m} member(s) s" for m in MEMBERS),
                "fixed s",
                "per member s",
                "4 / 2 alone",
                "2 ranks / 2 alone",
                "fixed to remove for 1.7x s",
            ],
            [
                [
                    *summary["median_s"].values(),
                    summary["fixed_s"],
                    summary["per_member_s"],
                    summary["speedup_ceiling_alone"],
                    summary["side_by_side_over_alone"],
                    summary["fixed_to_remove_for_1.7x_s"],
                ]
            ],
        )
    if projections:
        print_table(
            "Projection for 32 units of work (see project() for the model)",
            ["workload", "case", "time s", "speed-up", "efficiency"],
            projections,
        )
    if workers:
        worker_rows = []
        for name, (measured, units, key) in workers.items():
            row, payload[key] = _workers_summary(measured, name, units)
            worker_rows.append(row)
        print_table(
            "Validation in ParallelEnv workers (one process, medians; each call starts its "
            "workers; CPU: this process and its workers)",
            [
                "workload",
                "episodes",
                "wall 1",
                "wall 2",
                "speed-up",
                "after start-up",
                "CPU 1",
                "CPU 2",
                "start-up 2",
            ],
            worker_rows,
        )
    print(f"\nload average before {load_before}, after {load_after} on {os.cpu_count()} cores")
    write_json(
        args.out,
        {
            "settings": settings,
            "load_average_before": load_before,
            "load_average_after": load_after,
            "assumptions": {
                "intra_gpu_link": INTRA_GPU,
                "inter_node_link": INTER_NODE,
                "projected_units": 32,
                "model": project.__doc__,
            },
            "results": payload,
        },
    )


if __name__ == "__main__":
    main()

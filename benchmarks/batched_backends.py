"""How to step many Pushers at once: the backends ``BatchedPusherEnv`` was chosen from.

Physics only (no policy, no TorchRL), N envs from one start state, random controls held over each
control step's physics substeps, 1 torch thread; control steps per second and per CPU-second
of this process (what a free core would give, for one thread) as medians of repeats, the
backends timed in turn within each repeat:

* ``mujoco.batch.Batch`` (persistent rows, 1 and 2 MuJoCo threads): what the env uses;
* a Python loop over N ``MjData`` sharing one ``MjModel``, dm_control's own calls
  (``mj_step2``, ``mj_step`` for the other substeps, ``mj_step1``);
* ``mujoco.rollout`` called once per control step (1 and 2 threads), plus the per-env
  ``mj_kinematics`` it needs to read the fingertip.

Then the drift of each from the dm_control Pusher over a scripted episode with contacts:
``mujoco.rollout`` returns no ``qacc_warmstart``, so each call starts the contact solver cold.

    python benchmarks/batched_backends.py [--envs 256] [--steps 40] [--repeats 3]
"""

from __future__ import annotations

import argparse
import functools
import os

import mujoco
import numpy as np
import torch
from _report import interleaved_median_times, print_table, write_json
from mujoco import rollout as mj_rollout
from mujoco.batch import Batch

from rcvae_torchrl.envs.pusher import Physics, get_model_and_assets, make_environment
from rcvae_torchrl.envs.scripted import ScriptedPusher

_SUBSTEPS = 10
_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS.value
_VEL = mujoco.mjtStage.mjSTAGE_VEL.value


def _model_and_start() -> tuple[mujoco.MjModel, mujoco.MjData]:
    dm = make_environment(random=0)
    dm.reset()
    return Physics.from_xml_string(*get_model_and_assets()).model.ptr, dm.physics.data.ptr


class BatchBackend:
    def __init__(self, model, start, n: int, threads: int) -> None:
        self.n = n
        self.sim = Batch(model, n, nthread=threads, persistent=True)
        self.sim.reset()
        self.qpos, self.qvel = self.sim.bind("qpos"), self.sim.bind("qvel")
        self.ctrl, self.xpos = self.sim.bind("ctrl"), self.sim.bind("xpos")
        self.qpos[:], self.qvel[:] = start.qpos, start.qvel
        self.sim.forward()

    def step(self, ctrl: np.ndarray) -> np.ndarray:
        self.ctrl[:] = ctrl
        self.sim.step(nstep=_SUBSTEPS, stage=_VEL)
        return self.xpos


class LoopBackend:
    def __init__(self, model, start, n: int, threads: int = 1) -> None:
        self.model, self.n, self.datas = model, n, []
        for _ in range(n):
            d = mujoco.MjData(model)
            d.qpos[:], d.qvel[:] = start.qpos, start.qvel
            mujoco.mj_forward(model, d)
            self.datas.append(d)

    def step(self, ctrl: np.ndarray) -> np.ndarray:
        m = self.model
        for d, u in zip(self.datas, ctrl):
            d.ctrl[:] = u
            mujoco.mj_step2(m, d)
            mujoco.mj_step(m, d, _SUBSTEPS - 1)
            mujoco.mj_step1(m, d)
        return np.stack([d.xpos for d in self.datas])


class RolloutBackend:
    def __init__(self, model, start, n: int, threads: int) -> None:
        self.model, self.n = model, n
        self.pool = mj_rollout.Rollout(nthread=threads if threads > 1 else 0)
        self.datas = [mujoco.MjData(model) for _ in range(max(threads, 1))]
        self.kin = mujoco.MjData(model)
        row = np.empty(mujoco.mj_stateSize(model, _FULL))
        mujoco.mj_getState(model, start, row, _FULL)
        self.state = np.tile(row, (n, 1))

    def step(self, ctrl: np.ndarray) -> np.ndarray:
        control = np.repeat(ctrl[:, None, :], _SUBSTEPS, axis=1)
        states, _ = self.pool.rollout(self.model, self.datas, self.state, control)
        self.state = np.ascontiguousarray(states[:, -1])
        xpos = np.empty((self.n, self.model.nbody, 3))
        for i, row in enumerate(self.state):
            mujoco.mj_setState(self.model, self.kin, row, _FULL)
            mujoco.mj_kinematics(self.model, self.kin)
            xpos[i] = self.kin.xpos
        return xpos


BACKENDS = {
    "mujoco.batch, 1 thread": (BatchBackend, 1),
    "mujoco.batch, 2 threads": (BatchBackend, 2),
    "MjData loop": (LoopBackend, 1),
    "mujoco.rollout, 1 thread": (RolloutBackend, 1),
    "mujoco.rollout, 2 threads": (RolloutBackend, 2),
}


def _speeds(backends: dict, steps: int, repeats: int) -> dict[str, dict[str, float]]:
    """Control steps per second and per CPU-second (all threads) of each backend, the backends
    timed in turn within each repeat."""
    n = next(iter(backends.values())).n
    controls = np.random.default_rng(0).uniform(-1, 1, size=(steps, n, 2))
    runs = {name: functools.partial(_run, b, controls) for name, b in backends.items()}
    times = interleaved_median_times(runs, repeats)
    return {
        name: {"steps_per_s": steps * n / t["wall_s"], "steps_per_cpu_s": steps * n / t["cpu_s"]}
        for name, t in times.items()
    }


def _run(backend, controls: np.ndarray) -> None:
    for u in controls:
        backend.step(u)


def _drift(cls, threads: int, steps: int = 200) -> float:
    """Largest |fingertip and ball position| difference (m) from the dm_control Pusher over a
    scripted episode (deterministic, seed 3, no early termination)."""
    dm = make_environment(random=3, terminate_on_success=False)
    ts = dm.reset()
    model, _ = _model_and_start()
    backend = cls(model, dm.physics.data.ptr, 1, threads)
    policy, worst = ScriptedPusher(), 0.0
    for _ in range(steps):
        obs = torch.from_numpy(ts.observation["observation"])[None]
        with torch.no_grad():
            action = policy(obs).double().numpy()
        ts = dm.step(action[0])
        xpos = backend.step(np.asarray(dm.physics.data.ctrl)[None])[0]
        worst = max(worst, float(np.abs(xpos[2:6, :2] - dm.physics.data.xpos[2:6, :2]).max()))
    return worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=256)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    model, start = _model_and_start()
    n = args.envs
    backends = {k: cls(model, start, n, threads) for k, (cls, threads) in BACKENDS.items()}
    speed = _speeds(backends, args.steps, args.repeats)
    drift = {k: _drift(cls, threads) for k, (cls, threads) in BACKENDS.items()}
    load = os.getloadavg()
    print_table(
        f"Stepping {n} Pushers (physics only; control steps/s, median of {args.repeats}; "
        f"1 torch thread; load {load[0]:.2f})",
        ["backend", "steps/s", "steps per CPU-s", "drift from dm_control (m)"],
        [[k, speed[k]["steps_per_s"], speed[k]["steps_per_cpu_s"], drift[k]] for k in BACKENDS],
    )
    write_json(
        "batched_backends",
        {
            "envs": n,
            "steps": args.steps,
            "repeats": args.repeats,
            "loadavg": load,
            "speed": speed,
            "max_position_drift_m": drift,
        },
    )


if __name__ == "__main__":
    main()

"""``BatchedPusherEnv``: N Pushers stepped in C as one TorchRL env, equal to the dm_control Pusher.

Env ``i`` is the dm_control Pusher of :func:`make_pusher_env` with seed ``seed + i``, step for
step: the same MuJoCo model, the same calls (dm_control's step is ``mj_step2``, ``mj_step`` for
the other substeps, ``mj_step1``; here each control step is ``n`` ``mj_step`` substeps followed
by the position and velocity stages, and ``mj_step2`` after ``mj_step1`` is ``mj_step``), the
same ``numpy.random.RandomState`` draws in the same order (start states, the episode's actuator
strength where it varies, then action noise),
and the readout, reward and start sampling come from the functions the dm_control task calls
(:mod:`~rcvae_torchrl.envs.readout`, :func:`~rcvae_torchrl.envs.pusher.sample_start`). The tests
check float32-equal observations and equal rewards, success and done flags.

Backend, chosen by measurement (``benchmarks/batched_backends.py``: 256 envs, physics only,
random controls, 1 torch thread, medians of 7 interleaved repeats, on the shared 2-core
development machine while other jobs ran, load 3-6). Control steps per CPU-second, what a free
core gives: ``mujoco.batch.Batch`` (one persistent state row per simulation, stepped in C)
13,200, and 13,400 on two threads; a Python loop over 256 ``MjData`` sharing one ``MjModel``,
with dm_control's own calls, 11,600; ``mujoco.rollout`` once per control step 12,200.
Wall-clock rates moved with the load by a factor of two across four runs (``Batch``: 5,400 to
12,800); on one thread ``Batch`` was the fastest in all four, while two-thread rates followed
whatever the other jobs left of the second core. Speed hardly separates them, though:
all three are bound by MuJoCo itself, one ``mj_step`` of this model costing about 8 us here
(12 us while the fingertip pushes the ball), 80-120 us per control step, so a core gives at
most about 8,000-13,000 control steps/s. Exactness does: ``mujoco.rollout`` hands back no
``qacc_warmstart``, so every call starts the contact solver cold and the trajectories leave
dm_control's (6e-12 m after 200 scripted steps: not bit-equal), while ``Batch`` is
bit-identical to the ``MjData`` loop at any thread count, keeps Python out of the per-env loop,
and can step on several threads where cores are free.

The target is a geom position that takes part in no contact (``contype = conaffinity = 0``), so
the model is shared and each env keeps its target outside it (the simulations use a copy of a
scratch model whose own target is written only while a start state is drawn or loaded).
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np
import torch
from dm_control.rl.control import PhysicsError, compute_n_steps
from mujoco.batch import Batch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from rcvae_torchrl._checks import check_bool, check_device, check_positive

from .constraints import into_arena
from .factory import (
    _check_args,
    _variant_region,
    check_env_args,
    check_strength,
    check_strength_range,
)
from .functions import DEFAULT_SUCCESS_RADIUS
from .layout import OBSERVATION_DIM
from .pusher import (
    ARM_JOINTS,
    CONTROL_TIMESTEP,
    DEFAULT_TIME_LIMIT,
    IN_DISTRIBUTION,
    InitialStateRegion,
    Physics,
    check_region,
    clip_action,
    draw_action_noise,
    draw_strength,
    get_model_and_assets,
    noisy_control,
    sample_start,
)
from .readout import (
    PusherState,
    assemble_observation,
    planar_distance,
    shaped_reward,
    state_from_observation,
)

__all__ = ["BatchedPusherEnv", "episode_step_limit", "make_batched_pusher_env"]

_ACTION_DIM = 2
_MAX_SEED = 2**32  # numpy.random.RandomState takes seeds in [0, 2**32)
_STAGE_VEL = mujoco.mjtStage.mjSTAGE_VEL.value
_STAGE_NONE = mujoco.mjtStage.mjSTAGE_NONE.value
_WARNING_NAMES = list(mujoco.mjtWarning.__members__)


def episode_step_limit(time_limit: float, physics_timestep: float, n_sub_steps: int) -> float:
    """Episode length in control steps as dm_control's ``Environment`` computes it.

    A float: an episode is truncated at the first step count ``>=`` it (600 for 30 s at 0.05 s).
    """
    check_positive("time_limit", time_limit)
    check_positive("physics_timestep", physics_timestep)
    _check_count("n_sub_steps", n_sub_steps)
    return time_limit / (physics_timestep * n_sub_steps)


def _episode_end(
    steps: np.ndarray, step_limit: float, success: np.ndarray, terminate_on_success: bool
) -> tuple[np.ndarray, np.ndarray]:
    """``(terminated, truncated)`` after a step, dm_control's rule: the time limit ends the
    episode first (truncated, success or not); otherwise success terminates it if asked to."""
    truncated = steps >= step_limit
    terminated = success & ~truncated if terminate_on_success else np.zeros_like(truncated)
    return terminated, truncated


def _as_ids(envs: Sequence[int] | np.ndarray | torch.Tensor | None, n: int) -> np.ndarray:
    """Sorted env indices from indices or a boolean mask ``[n]``; all envs for None."""
    if envs is None:
        return np.arange(n)
    arr = envs.detach().cpu().numpy() if isinstance(envs, torch.Tensor) else np.asarray(envs)
    if arr.dtype == bool:
        if arr.size != n:
            raise ValueError(f"envs: expected a boolean mask of {n} envs, got shape {arr.shape}")
        return np.flatnonzero(arr.reshape(n))
    ids = arr.reshape(-1)
    if ids.size == 0:  # no env chosen (``[]`` reads as float64): nothing to do
        return np.zeros(0, dtype=np.int64)
    in_range = ids.min() >= 0 and ids.max() < n
    if not np.issubdtype(ids.dtype, np.integer) or not in_range:
        raise ValueError(f"envs: expected env indices in [0, {n}), got {arr.tolist()}")
    if np.unique(ids).size != ids.size:
        raise ValueError(f"envs: expected distinct env indices, got {arr.tolist()}")
    return np.sort(ids)


class BatchedPusherEnv(EnvBase):
    """``num_envs`` Pushers as one TorchRL env with ``batch_size=[num_envs]``.

    Build it with :func:`make_batched_pusher_env`. Keys and per-env specs are
    :func:`make_pusher_env`'s: ``"observation"`` float32 ``[N, 14]``, ``"success"`` bool
    ``[N, 1]``, ``"action"`` float32 ``[N, 2]`` in [-1, 1], ``"reward"`` float32 ``[N, 1]``,
    ``"done"``/``"terminated"``/``"truncated"`` bool ``[N, 1]``.

    Episodes:
        * ``set_seed(s)`` gives env ``i`` the stream ``RandomState(s + i)`` and, as the
          dm_control wrapper's ``set_seed`` does, resets every env once;
          :meth:`set_seeds` seeds (and resets) chosen envs with seeds of their own.
        * ``reset()`` starts every env; a ``"_reset"`` mask ``[N, 1]`` starts only those (as
          collectors and ``rollout(break_when_any_done=False)`` do).
        * ``reset(td, set_state=True)`` starts the reset envs from the states that
          ``td["observation"]`` describes, as :func:`~rcvae_torchrl.envs.state.reset_to_state`
          does for one env: a regular reset (which draws a start from the env's stream) and then
          the given state, so the stream continues exactly as the dm_control env's (a ball or
          target out of the ball's reach is moved into the arena, as there).
        * A step moves the envs that are not done. A done env is not simulated until it is
          reset: its observation stays, its reward is 0 and its done flags stay set. A
          ``"_step"`` mask (``rollout(break_when_all_done=True)``) skips envs likewise.

    ``num_threads`` MuJoCo threads step the simulations; results are bit-identical for any
    number. A MuJoCo warning (a state it rejects) raises dm_control's ``PhysicsError`` naming
    the envs, as the dm_control env does; a state loaded with ``set_state`` is checked when it is
    loaded, where dm_control finds it bad at the next step. Each env holds one ``MjData``
    (about 0.2 MB). Rendering is not supported (use :func:`make_pusher_env`).

    Example:
        >>> env = make_batched_pusher_env(64, "stochastic", seed=0)
        >>> td = env.rollout(100, break_when_any_done=False)
        >>> td["next", "observation"].shape
        torch.Size([64, 100, 14])
    """

    _supports_set_state = True

    def __init__(
        self,
        num_envs: int,
        *,
        region: InitialStateRegion = IN_DISTRIBUTION,
        success_radius: float = DEFAULT_SUCCESS_RADIUS,
        action_noise_std: float = 0.0,
        terminate_on_success: bool = True,
        time_limit: float = DEFAULT_TIME_LIMIT,
        control_timestep: float = CONTROL_TIMESTEP,
        num_threads: int = 1,
        device: torch.device | str | None = None,
        actuator_strength: tuple[float, float] | None = None,
    ) -> None:
        _check_count("num_envs", num_envs)
        _check_count("num_threads", num_threads)
        check_region(region)
        check_env_args(
            action_noise_std, time_limit, control_timestep, success_radius, noise_may_be_none=False
        )
        check_strength_range(actuator_strength)
        check_bool("terminate_on_success", terminate_on_success)
        check_device(device)
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.region = region
        self.success_radius = float(success_radius)
        self.action_noise_std = float(action_noise_std)
        self.actuator_strength = actuator_strength
        self.terminate_on_success = bool(terminate_on_success)
        self._scratch = Physics.from_xml_string(*get_model_and_assets())
        self._n_sub_steps = compute_n_steps(control_timestep, self._scratch.timestep())
        self._step_limit = episode_step_limit(
            time_limit, self._scratch.timestep(), self._n_sub_steps
        )
        self._sim = Batch(self._scratch.model.ptr, num_envs, nthread=num_threads, persistent=True)
        self._bind_fields()
        self._randoms = [np.random.RandomState() for _ in range(num_envs)]
        self._init_bookkeeping(num_envs)
        self._make_specs(num_envs)

    # ----------------------------------------------------------------------------- set-up

    def _bind_fields(self) -> None:
        sim, ids = self._sim, self._scratch.indices()
        self._qpos, self._qvel, self._ctrl = sim.bind("qpos"), sim.bind("qvel"), sim.bind("ctrl")
        self._xpos = sim.bind("xpos")
        self._finger, self._ball = ids["finger"], ids["ball"]
        self._ball_vel = slice(ids["ball_vx"], ids["ball_vx"] + 2)
        self._warnings = sim.warning[..., 1].copy()  # [N, mjNWARNING] counts

    def _init_bookkeeping(self, n: int) -> None:
        self._target = np.zeros((n, 2))
        self._strength = np.ones(n)  # each env's episode actuator strength
        self._steps = np.zeros(n, dtype=np.int64)
        self._obs = np.zeros((n, OBSERVATION_DIM), dtype=np.float32)
        self._success = np.zeros(n, dtype=bool)
        self._terminated = np.zeros(n, dtype=bool)
        self._truncated = np.zeros(n, dtype=bool)
        self._started = np.zeros(n, dtype=bool)

    def _make_specs(self, n: int) -> None:
        dev = self.device
        self.observation_spec = Composite(
            observation=Unbounded((n, OBSERVATION_DIM), dtype=torch.float32, device=dev),
            success=Unbounded((n, 1), dtype=torch.bool, device=dev),
            shape=(n,),
        )
        self.action_spec = Bounded(-1.0, 1.0, (n, _ACTION_DIM), dtype=torch.float32, device=dev)
        self.reward_spec = Unbounded((n, 1), dtype=torch.float32, device=dev)
        flag = Categorical(2, (n, 1), dtype=torch.bool, device=dev)
        self.done_spec = Composite(
            done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=(n,)
        )

    @property
    def num_envs(self) -> int:
        return self.batch_size[0]

    @property
    def strengths(self) -> np.ndarray:
        """Each env's actuator strength this episode ``[N]`` (1 where ``actuator_strength`` is
        None), a copy."""
        return self._strength.copy()

    @property
    def step_limit(self) -> float:
        """Episode length in control steps (see :func:`episode_step_limit`)."""
        return self._step_limit

    # ----------------------------------------------------------------------------- seeds

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            return
        if (
            isinstance(seed, bool)
            or not isinstance(seed, (int, np.integer))
            or not 0 <= seed <= _MAX_SEED - self.num_envs
        ):
            raise ValueError(
                f"seed: expected an integer in [0, 2**32 - num_envs] (env i gets seed + i), "
                f"got {seed!r}"
            )
        self.set_seeds(np.arange(self.num_envs) + int(seed))

    def set_seeds(
        self,
        seeds: Sequence[int] | np.ndarray | torch.Tensor,
        envs: Sequence[int] | np.ndarray | torch.Tensor | None = None,
    ) -> None:
        """Give each env of ``envs`` (all by default) its own stream ``RandomState(seed)``.

        As ``set_seed`` on a dm_control Pusher, each seeded env is reset once, so the next
        ``reset`` starts its stream's second episode, as a dm_control env seeded alike would.

        Args:
            seeds: one seed in [0, 2**32) per env of ``envs``, ``[k]``.
            envs: env indices ``[k]`` or a boolean mask ``[N]``; None: all, in order.

        Example:
            >>> from rcvae_torchrl.envs import make_pusher_env
            >>> env = BatchedPusherEnv(4)
            >>> env.set_seeds([7, 8], envs=[0, 3])  # env 0 as make_pusher_env(seed=7), ...
            >>> first = env.reset()["observation"]
            >>> bool((first[0] == make_pusher_env(seed=7).reset()["observation"]).all())
            True
        """
        ids = _as_ids(envs, self.num_envs)
        values = seeds.detach().cpu().numpy() if isinstance(seeds, torch.Tensor) else seeds
        values = np.asarray(values).reshape(-1)
        integers = values.size == 0 or np.issubdtype(values.dtype, np.integer)
        if values.shape != ids.shape or not integers:
            raise ValueError(
                f"seeds: expected {ids.size} integers (one per env), got {values.tolist()!r}"
            )
        if values.size and (values.min() < 0 or values.max() >= _MAX_SEED):
            raise ValueError(f"seeds: expected integers in [0, 2**32), got {values.tolist()}")
        for i, seed in zip(ids, values):
            self._randoms[i] = np.random.RandomState(int(seed))
        self._start_episodes(ids)

    # ----------------------------------------------------------------------------- reset

    def _reset(
        self, tensordict: TensorDictBase | None = None, set_state: bool = False, **kwargs
    ) -> TensorDictBase:
        ids = self._reset_ids(tensordict)
        given = None
        if set_state:
            given = self._given_observations(tensordict, ids)
        self._start_episodes(ids, given)
        return self._output(reward=None)

    def _reset_ids(self, tensordict: TensorDictBase | None) -> np.ndarray:
        reset = None if tensordict is None else tensordict.get("_reset", None)
        if reset is None:
            return np.arange(self.num_envs)
        return np.flatnonzero(reset.reshape(self.num_envs).cpu().numpy())

    def _given_observations(self, tensordict: TensorDictBase | None, ids: np.ndarray) -> np.ndarray:
        obs = None if tensordict is None else tensordict.get("observation", None)
        expected = (self.num_envs, OBSERVATION_DIM)
        if obs is None or tuple(obs.shape) != expected:
            got = None if obs is None else tuple(obs.shape)
            raise ValueError(
                f"observation: reset(..., set_state=True) expects the start states as "
                f"td['observation'] of shape {expected}, got {got}"
            )
        rows = obs.detach().cpu().double().numpy()[ids]
        bad = ids[~np.isfinite(rows).all(-1)]
        if bad.size:
            raise ValueError(f"observation: expected finite values, got NaN/inf for envs {bad}")
        return rows

    def _start_episodes(self, ids: np.ndarray, observations: np.ndarray | None = None) -> None:
        """Start an episode in each env of ``ids``: draw its start as the task does (or take the
        given state after drawing, as ``reset_to_state`` does), then load the rows."""
        if ids.size == 0:
            return
        data = self._scratch.data
        qpos = np.empty((ids.size, data.qpos.size))
        qvel = np.empty((ids.size, data.qvel.size))
        for k, i in enumerate(ids):
            state = sample_start(self._randoms[i], self.region, self._finger_to_ball)
            self._strength[i] = draw_strength(self._randoms[i], self.actuator_strength)
            if observations is not None:
                state = into_arena(state_from_observation(observations[k]))
            self._scratch.set_state(state)
            qpos[k], qvel[k], self._target[i] = data.qpos, data.qvel, state.target
        rows = ids.astype(np.int32)
        self._sim.reset(rows, stage=_STAGE_NONE)
        self._qpos[ids], self._qvel[ids] = qpos, qvel
        self._sim.forward(rows)
        self._check_warnings(ids)
        self._read(ids)
        self._steps[ids] = 0
        self._terminated[ids] = self._truncated[ids] = False
        self._started[ids] = True

    def _finger_to_ball(self, state: PusherState) -> float:
        """Fingertip-to-ball distance of a candidate start, by MuJoCo's kinematics on the
        scratch physics (what ``mj_forward`` computes for positions, without the rest)."""
        self._scratch.set_state(state)
        mujoco.mj_kinematics(self._scratch.model.ptr, self._scratch.data.ptr)
        return self._scratch.finger_to_ball()

    # ----------------------------------------------------------------------------- step

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        if not self._started.any():
            raise RuntimeError("BatchedPusherEnv: call reset() before step()")
        action = self._checked_action(tensordict.get("action", None))
        active = self._started & ~self._terminated & ~self._truncated
        partial = tensordict.get("_step", None)
        if partial is not None:
            active &= partial.reshape(self.num_envs).cpu().numpy()
        reward = np.zeros(self.num_envs, dtype=np.float32)
        if active.all():
            reward[:] = self._advance(action, slice(None))
        elif active.any():
            ids = np.flatnonzero(active)
            reward[ids] = self._advance(action[ids], ids)
        return self._output(reward)

    def _checked_action(self, action: torch.Tensor | None) -> np.ndarray:
        expected = (self.num_envs, _ACTION_DIM)
        if action is None or tuple(action.shape) != expected:
            got = None if action is None else tuple(action.shape)
            raise ValueError(f"action: expected shape {expected}, got {got}")
        values = action.detach().cpu().numpy()
        if not np.isfinite(values).all():
            bad = np.flatnonzero(~np.isfinite(values).all(-1))
            raise ValueError(f"action: expected finite values, got NaN/inf for envs {bad}")
        return values

    def _advance(self, action: np.ndarray, rows: slice | np.ndarray) -> np.ndarray:
        """One control step of the envs ``rows``; returns their rewards (float64)."""
        commanded = clip_action(action)
        applied = commanded
        if self.actuator_strength is not None:
            applied = self._strength[rows, None] * commanded
        if self.action_noise_std > 0:
            order = range(self.num_envs) if isinstance(rows, slice) else rows
            noise = [draw_action_noise(self._randoms[i], self.action_noise_std) for i in order]
            applied = noisy_control(applied, np.stack(noise))
        self._ctrl[rows] = applied
        ids = None if isinstance(rows, slice) else rows.astype(np.int32)
        self._sim.step(ids, nstep=self._n_sub_steps, stage=_STAGE_VEL)
        self._check_warnings(rows)
        ball_to_target, finger_to_ball = self._read(rows)
        self._steps[rows] += 1
        self._terminated[rows], self._truncated[rows] = _episode_end(
            self._steps[rows], self._step_limit, self._success[rows], self.terminate_on_success
        )
        return shaped_reward(ball_to_target, finger_to_ball, commanded)

    # ----------------------------------------------------------------------------- readout

    def _read(self, rows: slice | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Refresh observation and success of ``rows``; return (ball-target, finger-ball)."""
        qpos, qvel, xpos = self._qpos[rows], self._qvel[rows], self._xpos[rows]
        target = self._target[rows]
        finger, ball = xpos[:, self._finger, :2], xpos[:, self._ball, :2]
        self._obs[rows] = assemble_observation(
            qpos[:, ARM_JOINTS], qvel[:, ARM_JOINTS], finger, ball, qvel[:, self._ball_vel], target
        )
        ball_to_target = planar_distance(ball, target)
        self._success[rows] = ball_to_target <= self.success_radius
        return ball_to_target, planar_distance(finger, ball)

    def _check_warnings(self, rows: slice | np.ndarray) -> None:
        """Raise dm_control's ``PhysicsError`` where MuJoCo warned, as ``Physics.step`` does."""
        counts = self._sim.warning[..., 1]
        rose = counts[rows] > self._warnings[rows]
        self._warnings = counts.copy()
        if rose.any():
            envs = np.arange(self.num_envs)[rows][rose.any(-1)]
            names = sorted({_WARNING_NAMES[w] for w in np.flatnonzero(rose.any(0))})
            raise PhysicsError(f"physics state is invalid in envs {envs.tolist()}: {names}")

    def _output(self, reward: np.ndarray | None) -> TensorDictBase:
        terminated, truncated = self._terminated[:, None], self._truncated[:, None]
        out = {
            "observation": torch.from_numpy(self._obs.copy()),
            "success": torch.from_numpy(self._success[:, None].copy()),
            "terminated": torch.from_numpy(terminated.copy()),
            "truncated": torch.from_numpy(truncated.copy()),
            "done": torch.from_numpy(terminated | truncated),
        }
        if reward is not None:
            out["reward"] = torch.from_numpy(reward.astype(np.float32)[:, None])
        td = TensorDict(out, batch_size=self.batch_size)
        return td if self.device is None else td.to(self.device)


def _check_count(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")


def make_batched_pusher_env(
    num_envs: int,
    variant: str = "deterministic",
    *,
    seed: int | None = None,
    action_noise_std: float | None = None,
    time_limit: float = DEFAULT_TIME_LIMIT,
    control_timestep: float = CONTROL_TIMESTEP,
    success_radius: float = DEFAULT_SUCCESS_RADIUS,
    region: InitialStateRegion | None = None,
    terminate_on_success: bool = True,
    num_threads: int = 1,
    device: torch.device | str | None = None,
    actuator_strength: tuple[float, float] | None = None,
) -> BatchedPusherEnv:
    """``num_envs`` Pushers of ``variant`` as one batched TorchRL env (see
    :class:`BatchedPusherEnv`); env ``i`` equals ``make_pusher_env(variant, seed=seed + i, ...)``
    given the same actions.

    The arguments mean what :func:`make_pusher_env`'s mean; ``seed`` seeds env ``i`` with
    ``seed + i``, ``num_threads`` is the number of MuJoCo threads stepping the simulations
    (results do not depend on it). Pixels are not supported.

    Example:
        >>> from rcvae_torchrl.envs.scripted import make_scripted_policy
        >>> env = make_batched_pusher_env(256, "stochastic", seed=0)
        >>> td = env.rollout(600, make_scripted_policy(), break_when_any_done=False)
        >>> td["next", "success"].shape
        torch.Size([256, 600, 1])
    """
    noise = _check_args(variant, action_noise_std, time_limit, control_timestep, success_radius)
    env = BatchedPusherEnv(
        num_envs,
        region=_variant_region(variant, region),
        success_radius=success_radius,
        action_noise_std=noise,
        actuator_strength=check_strength(variant, actuator_strength),
        terminate_on_success=terminate_on_success,
        time_limit=time_limit,
        control_timestep=control_timestep,
        num_threads=num_threads,
        device=device,
    )
    if seed is not None:
        env.set_seed(seed)
    return env

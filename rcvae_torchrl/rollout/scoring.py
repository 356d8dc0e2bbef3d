"""Returns of candidate action sequences under the ensemble: the planner's fast path.

Mirrors mbrl-lib's ``ModelEnv.evaluate_action_sequences``: ``R = |B|·C`` rows (start state x
candidate), G particle groups per row, all G·R particles stepped together by the rollout loop;
every step's states kept, then the task's reward and success functions called once on all H
steps (not once per step: the task's ops are dispatched once per scoring) and the rewards summed
in time order; no TensorDict.

Particle layout (flat index i = g·R + r, so ``"ts_inf"`` is member-major without copies):

- ``"ts_inf"``: G = E·k with k = ⌈P / E⌉, so P is rounded **up** to a multiple of E and every
  member scores every candidate equally often; particle g = m·k + j follows member m. The
  tensors ``[G·R, ·]`` are viewed as ``[E, k·R, ·]``: one batched matmul per layer. With
  P = 1, G = 1: the rows (padded to a multiple of E) are split over the members in contiguous
  blocks, one particle each, as TorchRL's stock planners get from a round-robin reset.
- ``"ts1"``: G = P; every particle carries all members' hidden states ``[E, P·R, H]``.
- ``"mean"``: deterministic, so G = 1 and the result is repeated P times.

Three ways to run the ``"ts_inf"`` rollout (``compile``), one eager reference (``_score``):
``False`` runs it eagerly; ``True`` under ``torch.compile`` (:func:`compiled_scoring`: compiled
in each process, once); ``"aot"`` as a package compiled ahead of time and cached across
processes (:mod:`~rcvae_torchrl.rollout.aot`: built once per architecture, task and horizon,
then loaded in a fraction of a second).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Literal, NamedTuple

import torch

from rcvae_torchrl import _checks
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout.aot import aot_scoring
from rcvae_torchrl.rollout.loop import ActionBounds, check_action_bounds, rollout
from rcvae_torchrl.rollout.sampling import TRAJECTORY_SAMPLINGS, TrajectorySampling, initial_hidden
from rcvae_torchrl.rollout.task import Task
from rcvae_torchrl.threads import collection_paused

__all__ = [
    "COMPILE_MODES",
    "Compile",
    "SequenceReturns",
    "check_compile",
    "compiled_scoring",
    "evaluate_action_sequences",
    "particle_groups",
]


Compile = bool | Literal["aot"]
"""How the scoring rollout runs: eager (False), ``torch.compile`` (True), ahead of time ("aot")."""

COMPILE_MODES: tuple[bool | str, ...] = (False, True, "aot")


def check_compile(name: str, value: object) -> None:
    """Require one of :data:`COMPILE_MODES` (a bool, not a truthy number; the string "aot")."""
    if not (isinstance(value, bool) or (isinstance(value, str) and value == "aot")):
        raise ValueError(
            f"{name}: expected False (eager), True (torch.compile) or 'aot' (compiled ahead "
            f"of time, cached across processes), got {value!r}"
        )


class SequenceReturns(NamedTuple):
    """Per-particle outcome of each row's action sequence."""

    returns: torch.Tensor  #: sum of rewards up to and including the episode's end ``[R, P']``
    success: torch.Tensor  #: success reached within the horizon, bool ``[R, P']``


def particle_groups(
    trajectory_sampling: TrajectorySampling, particles: int, ensemble_size: int
) -> int:
    """G, the particles computed per row: ``E·⌈P/E⌉`` (``"ts_inf"``; 1 when P = 1), P
    (``"ts1"``), 1 (``"mean"``)."""
    _checks.check_choice("trajectory_sampling", trajectory_sampling, TRAJECTORY_SAMPLINGS)
    _checks.check_positive_int("particles", particles)
    if trajectory_sampling == "ts_inf":
        return 1 if particles == 1 else ensemble_size * math.ceil(particles / ensemble_size)
    return particles if trajectory_sampling == "ts1" else 1


def _scored(task: Task, states: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``(returns [n], success [n])`` of the steps ``(a_t, s_{t+1})``, ``[H, n, ·]`` each: one
    call of each task function for the whole horizon (the functions act on any batch), not one
    per step, so eager scoring dispatches the task's ops once instead of H times."""
    reward = task.checked_reward(task.reward_fn(observation=states, action=actions), states)
    success = task.checked_success(task.success_fn(observation=states), states)
    horizon, n = states.shape[:2]
    success = success.reshape(horizon, n)
    returns = task.returns(reward.reshape(horizon, n), success)
    return returns, success.any(0)  # the first success is always within the episode


def _score(ensemble, mode, task, hidden, obs, per_step, bounds, generator, noise):
    """All H steps of all particles, scored: ``(returns [n], success [n])``."""
    if bounds is not None:  # every step's actions clipped at once, as the loop would clip them
        per_step = torch.clamp(per_step, bounds.low, bounds.high)
    horizon, n = per_step.shape[:2]
    states: list[torch.Tensor] = []  # s_{t+1} of every step, scored together after the loop
    rows = per_step
    if mode == "ts_inf":  # member-major views of the flat particles, no copies
        e = ensemble.ensemble_size
        obs = obs.view(e, -1, obs.shape[-1])
        rows = per_step.view(horizon, e, -1, per_step.shape[-1])
    rollout(
        ensemble,
        mode,
        obs,
        hidden,
        horizon,
        lambda step: states.append(step.out.observation),
        actions=rows,
        generator=generator,
        noise=noise,
    )
    return _scored(task, torch.stack(states).view(horizon, n, -1), per_step)


def evaluate_action_sequences(
    ensemble: RCVAEEnsemble,
    start: torch.Tensor,
    actions: torch.Tensor,
    particles: int,
    *,
    task: Task,
    trajectory_sampling: TrajectorySampling = "ts_inf",
    bounds: ActionBounds | None = None,
    generator: torch.Generator | None = None,
    compile: Compile = False,
    cache_dir: str | Path | None = None,
) -> SequenceReturns:
    """Roll every row's action sequence out for its particles and score it.

    The return of a particle is Σ_t r_t over the steps up to and including its first success
    when the task terminates on success, else over all H steps; ``success`` says whether any
    step within the horizon succeeded. Non-finite states give non-finite rewards and returns;
    callers mask rows with non-finite starts themselves.

    Args:
        ensemble: the world model.
        start: s_0 of each row ``[R, S]`` (every particle starts from h_0 = 0).
        actions: a_0..a_{H-1} of each row ``[R, H, A]``.
        particles: P requested per row (see the module docstring for P').
        task: reward, success and whether success ends an episode.
        trajectory_sampling: ``"ts_inf"``, ``"ts1"`` or ``"mean"``.
        bounds: clip actions to these bounds.
        generator: source of all sampling noise.
        compile: run the ``"ts_inf"`` rollout as one ``torch.compile``-d function
            (``True``, :func:`compiled_scoring`) or as a package compiled ahead of time and
            cached across processes (``"aot"``, :func:`~rcvae_torchrl.rollout.aot_scoring`;
            no gradients); other modes ignore it. The same samples as the eager rollout up
            to float rounding.
        cache_dir: where ``"aot"`` packages are kept (default
            :func:`~rcvae_torchrl.rollout.default_cache_dir`).

    Returns:
        :class:`SequenceReturns`, each ``[R, P']``.
    """
    check_compile("compile", compile)
    _check_sequences(ensemble, start, actions, task)
    check_action_bounds(bounds, ensemble.config.action_dim)
    rows, horizon = actions.shape[0], actions.shape[1]
    e = ensemble.ensemble_size
    groups = particle_groups(trajectory_sampling, particles, e)
    pad = (-rows) % e if trajectory_sampling == "ts_inf" and groups == 1 else 0
    if pad:  # one particle per row: rows split over the members, padded to a multiple of E
        start = torch.cat([start, start[-1:].expand(pad, -1)])
        actions = torch.cat([actions, actions[-1:].expand(pad, -1, -1)])
        rows += pad
    n = groups * rows
    obs = start.expand(groups, *start.shape).reshape(n, start.shape[-1])
    # a_t of every particle, [H, n, A], one copy: each step reads a contiguous view
    per_step = actions.transpose(0, 1).unsqueeze(1).expand(horizon, groups, rows, -1)
    per_step = per_step.reshape(horizon, n, actions.shape[-1])
    ts_inf = trajectory_sampling == "ts_inf"
    hidden = initial_hidden(ensemble, n, obs, ts_inf, generator, mean=trajectory_sampling == "mean")
    args = (ensemble, trajectory_sampling, task, hidden, obs, per_step, bounds)
    if compile and ts_inf:  # the noise drawn here, as the steps would draw it
        noise = _ts_inf_noise(ensemble, hidden, horizon, generator)
        if compile == "aot":
            scoring = aot_scoring(_score, ensemble, task, horizon, cache_dir=cache_dir)
            returns, success = scoring(ensemble, hidden, obs, per_step, bounds, noise)
        else:
            _mark_particles_dynamic(hidden, obs, per_step, noise)
            returns, success = compiled_scoring()(*args, None, noise)
    else:
        returns, success = _score(*args, generator, None)
    out = SequenceReturns(returns.view(groups, rows).T, success.view(groups, rows).T)
    if pad:
        out = SequenceReturns(*(x[: rows - pad] for x in out))
    if trajectory_sampling == "mean":
        out = SequenceReturns(*(x.expand(rows, particles) for x in out))
    return out


def _check_sequences(ensemble: object, start: object, actions: object, task: object) -> None:
    """Shapes and kinds only (the planner's fast path: no pass over the values)."""
    if not isinstance(ensemble, RCVAEEnsemble):
        raise TypeError(f"ensemble: expected an RCVAEEnsemble, got {type(ensemble).__name__}")
    if not isinstance(task, Task):
        raise TypeError(f"task: expected a rollout.Task, got {type(task).__name__}")
    cfg = ensemble.config
    _checks.check_tensor("start", start)
    _checks.check_tensor("actions", actions)
    if start.ndim != 2 or start.shape[-1] != cfg.obs_dim or start.shape[0] < 1:
        raise ValueError(
            f"start: expected [R, S={cfg.obs_dim}] with R >= 1, got {tuple(start.shape)}"
        )
    rows = start.shape[0]
    if (
        actions.ndim != 3
        or actions.shape[0] != rows
        or actions.shape[1] < 1
        or (actions.shape[2] != cfg.action_dim)
    ):
        raise ValueError(
            f"actions: expected [R={rows}, H, A={cfg.action_dim}] with H >= 1 (R: the rows of "
            f"start), got {tuple(actions.shape)}"
        )


_COMPILED: list = []


def compiled_scoring() -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:
    """The scoring rollout under ``torch.compile`` (inductor, dynamic particle count), made once.

    One compiled call per scoring: the H steps unrolled into one graph (fused kernels and the
    matmuls instead of some sixty small ops per step, and one guard check instead of H). The
    number of particles (candidates x particles per candidate) is a symbolic size
    (:func:`evaluate_action_sequences` marks it dynamic), so one compile serves every number of
    candidates and particles; a new model, task function, horizon or dtype compiles again
    (tens of seconds on a CPU, a few seconds when inductor's on-disk cache, shared by later
    processes, already holds the kernels). The numbers agree with the eager rollout up to float
    rounding (fused kernels), not bit for bit.
    """
    if not _COMPILED:
        # no batched env's finalizer may change the threads while it traces (a new shape too)
        _COMPILED.append(collection_paused(torch.compile(_score, dynamic=True)))
    return _COMPILED[0]


def _mark_particles_dynamic(hidden, obs, per_step, noise) -> None:
    """Mark the particle dimension of the compiled rollout's inputs dynamic (sizes 0 and 1 are
    always specialised by the compiler, so those are left static)."""
    for tensor, dim in ((hidden, -2), (obs, 0), (per_step, 1), (noise[0], -2), (noise[1], -2)):
        if tensor.shape[dim] > 1:
            torch._dynamo.mark_dynamic(tensor, dim % tensor.dim())


def _ts_inf_noise(
    ensemble: RCVAEEnsemble, hidden: torch.Tensor, horizon: int, generator: torch.Generator | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """ε_z ``[H, E, n/E, Z]`` and ε_s ``[H, E, n/E, D]``: what ``ensemble.step`` would draw at
    each step (ε_z then ε_s), in the same order.

    On a CPU, ``normal_`` turns consecutive uniforms into normals in blocks of 16, so when every
    per-step draw is a multiple of 16 numbers one draw for the whole horizon gives the same
    numbers (and generator state) as the 2·H draws; otherwise the draws are made one by one.
    """
    batch, cfg = hidden.shape[:-1], ensemble.config
    latent, predicted = batch.numel() * cfg.latent_dim, batch.numel() * cfg.predicted_dim
    flat = hidden.new_empty(horizon, latent + predicted)
    if hidden.device.type == "cpu" and latent % 16 == 0 and predicted % 16 == 0:
        flat.normal_(generator=generator)
    else:
        for t in range(horizon):
            flat[t, :latent].normal_(generator=generator)
            flat[t, latent:].normal_(generator=generator)
    return (
        flat[:, :latent].view(horizon, *batch, cfg.latent_dim),
        flat[:, latent:].view(horizon, *batch, cfg.predicted_dim),
    )

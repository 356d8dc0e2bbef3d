"""Returns of candidate action sequences under the ensemble: the planner's fast path.

Mirrors mbrl-lib's ``ModelEnv.evaluate_action_sequences``: ``R = |B|·C`` rows (start state ×
candidate), G particle groups per row, all G·R particles stepped together, rewards accumulated
on the fly; no TensorDict, no per-step allocation beyond the model's own.

Particle layout (flat index i = g·R + r, so ``"ts_inf"`` is member-major without copies):

- ``"ts_inf"``: G = E·k with k = ⌈P / E⌉, so P is rounded **up** to a multiple of E and every
  member scores every candidate equally often; particle g = m·k + j follows member m. The
  tensors ``[G·R, ·]`` are viewed as ``[E, k·R, ·]``: one batched matmul per layer. With
  P = 1, G = 1: the rows (padded to a multiple of E) are split over the members in contiguous
  blocks, one particle each, as TorchRL's stock planners get from a round-robin reset.
- ``"ts1"``: G = P; every particle carries all members' hidden states ``[E, P·R, H]``.
- ``"mean"``: deterministic, so G = 1 and the result is repeated P times.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch

from rcvae_torchrl.model_env.propagation import Propagation, mean_step, ts1_step
from rcvae_torchrl.model_env.task import (
    RewardFn,
    SuccessFn,
    alive_mask,
    checked_reward,
    checked_success,
)
from rcvae_torchrl.models import RCVAEEnsemble

__all__ = ["SequenceScores", "compiled_rollout", "particle_groups", "score_action_sequences"]


class SequenceScores(NamedTuple):
    """Per-particle outcome of each row's action sequence."""

    returns: torch.Tensor  #: sum of rewards up to and including the first done ``[R, P']``
    success: torch.Tensor  #: success reached within the horizon, bool ``[R, P']``


def particle_groups(trajectory_sampling: Propagation, particles: int, ensemble_size: int) -> int:
    """G, the particles computed per row: ``E·⌈P/E⌉`` (``"ts_inf"``; 1 when P = 1), P
    (``"ts1"``), 1 (``"mean"``)."""
    if trajectory_sampling == "ts_inf":
        return 1 if particles == 1 else ensemble_size * math.ceil(particles / ensemble_size)
    return particles if trajectory_sampling == "ts1" else 1


def score_action_sequences(
    ensemble: RCVAEEnsemble,
    start: torch.Tensor,
    actions: torch.Tensor,
    particles: int,
    *,
    reward_fn: RewardFn,
    success_fn: SuccessFn,
    trajectory_sampling: Propagation = "ts_inf",
    terminate_on_success: bool = True,
    generator: torch.Generator | None = None,
    compile: bool = False,
) -> SequenceScores:
    """Roll every row's action sequence out for its particles and score it.

    The return of a particle is Σ_t r_t over the steps up to and including its first success
    when ``terminate_on_success`` (the real Pusher ends the episode there), else over all H
    steps; ``success`` says whether any step within the horizon succeeded. Non-finite states
    give non-finite rewards and returns; callers mask rows with non-finite starts themselves.

    Args:
        ensemble: the world model.
        start: s_0 of each row ``[R, S]`` (every particle starts from h_0 = 0).
        actions: a_0..a_{H−1} of each row ``[R, H, A]``.
        particles: P requested per row (see the module docstring for P').
        reward_fn: ``(s_{t+1} [M, S], a_t [M, A]) -> [M, 1]``.
        success_fn: ``s_{t+1} [M, S] -> [M]`` bool.
        trajectory_sampling: ``"ts_inf"``, ``"ts1"`` or ``"mean"``.
        terminate_on_success: success ends a particle's episode.
        generator: source of all sampling noise.
        compile: run each ``"ts_inf"`` step (model, state constraint, reward, success) as one
            ``torch.compile``-d function (see :func:`compiled_rollout`); other modes ignore it.

    Returns:
        :class:`SequenceScores`, each ``[R, P']``.
    """
    rows, horizon = actions.shape[0], actions.shape[1]
    groups = particle_groups(trajectory_sampling, particles, ensemble.ensemble_size)
    pad = (-rows) % ensemble.ensemble_size if trajectory_sampling == "ts_inf" and groups == 1 else 0
    if pad:  # one particle per row: rows split over the members, padded to a multiple of E
        start = torch.cat([start, start[-1:].expand(pad, -1)])
        actions = torch.cat([actions, actions[-1:].expand(pad, -1, -1)])
        rows += pad
    n = groups * rows
    obs = start.expand(groups, *start.shape).reshape(n, start.shape[-1])
    # a_t of every particle, [H, n, A], one copy: each step reads a contiguous view
    per_step = actions.transpose(0, 1).unsqueeze(1).expand(horizon, groups, rows, -1)
    per_step = per_step.reshape(horizon, n, actions.shape[-1])
    hidden = _initial_hidden(ensemble, trajectory_sampling, n, obs)
    if compile and trajectory_sampling == "ts_inf":  # the noise drawn here, as the steps would
        noise = _ts_inf_noise(ensemble, hidden, horizon, generator)
        returns, success = compiled_rollout()(
            ensemble, reward_fn, success_fn, hidden, obs, per_step, *noise, terminate_on_success
        )
    else:
        returns, success = _rollout(
            ensemble,
            trajectory_sampling,
            reward_fn,
            success_fn,
            hidden,
            obs,
            per_step,
            generator,
            terminate_on_success,
        )
    out = SequenceScores(returns.view(groups, rows).T, success.view(groups, rows).T)
    if pad:
        out = SequenceScores(*(x[: rows - pad] for x in out))
    if trajectory_sampling == "mean":
        out = SequenceScores(*(x.expand(rows, particles) for x in out))
    return out


def _rollout(
    ensemble: RCVAEEnsemble,
    trajectory_sampling: Propagation,
    reward_fn: RewardFn,
    success_fn: SuccessFn,
    hidden: torch.Tensor,
    obs: torch.Tensor,
    per_step: torch.Tensor,
    generator: torch.Generator | None,
    terminate_on_success: bool,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The eager rollout of all particles ``[n, ·]`` over ``per_step`` ``[H, n, A]``:
    ``(returns [n], success [n])``."""
    n = obs.shape[0]
    rewards, successes = [], []
    for t, action in enumerate(per_step.unbind(0)):
        obs, hidden = _propagate(ensemble, trajectory_sampling, hidden, obs, action, generator)
        reward, succeeded = reward_fn(obs, action), success_fn(obs)
        if t == 0:  # the task functions' outputs checked once: the shapes never change
            reward, succeeded = checked_reward(reward, obs), checked_success(succeeded, obs)
        rewards.append(reward.reshape(n))
        successes.append(succeeded.reshape(n))
    # the episode bookkeeping for all steps at once: [H, n]
    reward = torch.stack(rewards).to(obs.dtype)
    succeeded = torch.stack(successes).to(torch.bool)
    if terminate_on_success:  # rewards count up to and including the first success
        reward = reward.masked_fill(~alive_mask(succeeded, time_dim=0), 0.0)
    returns = obs.new_zeros(n)
    for r in reward.unbind(0):  # in time order, as the rewards come (not a pairwise sum)
        returns = returns + r
    return returns, succeeded.any(0)  # the first success is always within the episode


def _initial_hidden(
    ensemble: RCVAEEnsemble, trajectory_sampling: Propagation, n: int, like: torch.Tensor
) -> torch.Tensor:
    """h_0: ``[E, n/E, H]`` for TS-∞ (member-major), else every member's ``[E, n, H]``."""
    if trajectory_sampling == "ts_inf":
        return ensemble.initial_hidden((n // ensemble.ensemble_size,), like)
    return ensemble.initial_hidden((n,), like)


def _propagate(
    ensemble: RCVAEEnsemble,
    trajectory_sampling: Propagation,
    hidden: torch.Tensor,
    obs: torch.Tensor,
    action: torch.Tensor,
    generator: torch.Generator | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One step of all particles ``[n, ·]``: ``(s_{t+1} [n, S], hidden)``."""
    if trajectory_sampling == "ts_inf":
        e = ensemble.ensemble_size
        out = ensemble.step(
            hidden,
            obs.view(e, -1, obs.shape[-1]),
            action.view(e, -1, action.shape[-1]),
            generator=generator,
        )
        return out.observation.view(obs.shape), out.hidden
    if trajectory_sampling == "ts1":
        out = ts1_step(ensemble, hidden, obs, action, generator)
    else:
        out = mean_step(ensemble, hidden, obs, action)
    return out.observation, out.hidden


def ts_inf_rollout(
    ensemble: RCVAEEnsemble,
    reward_fn: RewardFn,
    success_fn: SuccessFn,
    hidden: torch.Tensor,
    obs: torch.Tensor,
    per_step: torch.Tensor,
    noise_latent: torch.Tensor,
    noise_obs: torch.Tensor,
    terminate_on_success: bool,
) -> tuple[torch.Tensor, torch.Tensor]:
    """All H TS-∞ steps of all particles ``[n, ·]`` (member-major) with the given noise
    (``[H, E, n/E, ·]``), scored: ``(returns [n], success [n])``.

    The same arithmetic as the eager rollout: each step's reward, zeroed after the first
    success when ``terminate_on_success``, added to the returns in time order.
    """
    e, n = ensemble.ensemble_size, obs.shape[0]
    returns = obs.new_zeros(n)
    alive = torch.ones(n, dtype=torch.bool, device=obs.device)
    success = torch.zeros(n, dtype=torch.bool, device=obs.device)
    for t in range(per_step.shape[0]):  # unrolled under torch.compile (static H)
        action = per_step[t]
        out = ensemble.step(
            hidden,
            obs.view(e, -1, obs.shape[-1]),
            action.view(e, -1, action.shape[-1]),
            noise_latent=noise_latent[t],
            noise_obs=noise_obs[t],
        )
        hidden, obs = out.hidden, out.observation.view(obs.shape)
        reward, succeeded = reward_fn(obs, action), success_fn(obs)
        if t == 0:  # checked while tracing: the shapes are static
            reward, succeeded = checked_reward(reward, obs), checked_success(succeeded, obs)
        reward, succeeded = reward.reshape(n).to(obs.dtype), succeeded.reshape(n).to(torch.bool)
        if terminate_on_success:  # rewards count up to and including the first success
            returns = returns + reward.masked_fill(~alive, 0.0)
            alive = alive & ~succeeded
        else:
            returns = returns + reward
        success = success | succeeded
    return returns, success


_COMPILED: list = []


def compiled_rollout() -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:
    """:func:`ts_inf_rollout` under ``torch.compile`` (inductor, static shapes), made once.

    One compiled call per scoring: the H steps unrolled into one graph (fused kernels and the
    matmuls instead of some sixty small ops per step, and one guard check instead of H). The
    first call for a new model, task function, horizon or batch size compiles it (seconds to
    tens of seconds on a CPU). The numbers agree with the eager rollout up to float rounding
    (fused kernels), not bit for bit. Dynamo recompiles for each new shape, up to its cache
    limit.
    """
    if not _COMPILED:
        _COMPILED.append(torch.compile(ts_inf_rollout, dynamic=False))
    return _COMPILED[0]


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

"""Imagined rollouts of an RCVAE ensemble, as a TensorDict ``[E, N, *B, T]``.

Samples x^{m,n}_t of member m, sample n, start state b and time t feed the uncertainty
decomposition of Acharya, Russell & Ahmed (2022), eq. 2–3 (DESIGN.md, "Uncertainty, in bits").
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDict

from rcvae_torchrl.models.validation import (
    check_batch_shapes,
    check_dtype,
    check_finite,
    check_trailing,
)

if TYPE_CHECKING:
    from rcvae_torchrl.models.rcvae import RCVAEEnsemble

__all__ = ["Policy", "generate"]

Policy = Callable[[torch.Tensor], torch.Tensor]
"""A closed-loop policy: observations ``[..., S]`` → actions ``[..., A]``."""


def generate(
    ensemble: RCVAEEnsemble,
    observation: torch.Tensor,
    actions: torch.Tensor | None = None,
    *,
    samples_per_member: int = 1,
    generator: torch.Generator | None = None,
    policy: Policy | None = None,
    horizon: int | None = None,
    requires_grad: bool = False,
    chunk_size: int | None = 1024,
) -> TensorDict:
    """Sample N trajectories per member from each start state, open or closed loop.

    Open loop: pass ``actions [*B, T, A]``. Closed loop: pass ``policy`` and ``horizon`` T; the
    policy is called once per step and chunk on the current states ``[E, R, S]`` and must
    return actions ``[E, R, A]`` (R = trajectories per member in the chunk).

    Args:
        ensemble: the world model (E members).
        observation: start states s_0 ``[*B, S]``.
        actions: a_0..a_{T−1} ``[*B, T, A]`` (open loop).
        samples_per_member: N.
        generator: torch generator for all sampling noise (same generator state and chunk
            size → same samples).
        policy: closed-loop policy (instead of ``actions``).
        horizon: number of steps T in closed loop.
        requires_grad: keep the autograd graph (off by default: rollouts are for evaluation).
        chunk_size: trajectories per member rolled out together (``None``: all ``N·|B|`` at
            once). Bounded chunks keep tensors in cache and below the allocator's mmap
            threshold; on 2 CPU cores one chunk of 5 × 4096 rows ran slower than a loop
            over members (``benchmarks/world_model_speed.py``).

    Returns:
        TensorDict with batch ``[E, N, *B, T]`` and entries ``"observation"`` s_1..s_T
        ``[..., S]``, ``"action"`` a_0..a_{T−1} ``[..., A]`` (the action that led to it),
        ``("rcvae", "loc")`` / ``("rcvae", "scale")`` ``[..., S]`` the decoder's Gaussian over s_t
        given the sampled z_t (passthrough dims: scale 0), and ``("rcvae", "latent")`` z_t.

    Raises:
        ValueError: non-finite or ill-shaped inputs, or non-finite states produced by the model.
    """
    _check_inputs(ensemble, observation, actions, samples_per_member, policy, horizon, chunk_size)
    n_steps = actions.shape[-2] if policy is None else int(horizon)
    grid = (ensemble.ensemble_size, samples_per_member, *observation.shape[:-1])
    starts = observation.reshape(-1, observation.shape[-1])
    plan = None if policy is not None else actions.reshape(starts.shape[0], n_steps, -1)
    rows = torch.arange(samples_per_member * starts.shape[0], device=observation.device)
    with torch.set_grad_enabled(requires_grad and torch.is_grad_enabled()):
        chunks = [
            _rollout(ensemble, starts, plan, chunk, n_steps, generator, policy)
            for chunk in rows.split(chunk_size or rows.numel())
        ]
    out = TensorDict(
        {k: torch.cat([c[k] for c in chunks], 1).reshape(*grid, n_steps, -1) for k in _KEYS},
        batch_size=[*grid, n_steps],
    )
    _check_output(out["observation"])
    return out


_KEYS = ("observation", "action", ("rcvae", "loc"), ("rcvae", "scale"), ("rcvae", "latent"))


def _rollout(
    ensemble: RCVAEEnsemble,
    starts: torch.Tensor,
    plan: torch.Tensor | None,
    rows: torch.Tensor,
    n_steps: int,
    generator: torch.Generator | None,
    policy: Policy | None,
) -> dict[str | tuple[str, str], torch.Tensor]:
    """Roll out trajectory rows (row r = sample r // P of start r % P) for all members.

    Args:
        starts: start states ``[P, S]``.
        plan: open-loop actions ``[P, T, A]`` (or ``None`` with a policy).
        rows: indices of the trajectories of this chunk ``[R]``.

    Returns:
        ``{key: [E, R, T, ·]}``.
    """
    e, start_of = ensemble.ensemble_size, rows % starts.shape[0]
    state = starts[start_of].expand(e, -1, -1)
    hidden = ensemble.initial_hidden(rows.shape, state)
    plan = None if plan is None else plan[start_of]
    steps: dict[str | tuple[str, str], list[torch.Tensor]] = {k: [] for k in _KEYS}
    for t in range(n_steps):
        if policy is None:
            action = plan[:, t].expand(e, -1, -1)
        else:
            action = _policy_action(policy, state, t, ensemble.config.action_dim)
        out = ensemble.step(hidden, state, action, generator=generator)
        loc, scale = ensemble.state_loc_scale(state, out.delta_mean, out.delta_std)
        for key, value in zip(_KEYS, (out.observation, action, loc, scale, out.latent)):
            steps[key].append(value)
        state, hidden = out.observation, out.hidden
    return {k: torch.stack(v, dim=-2) for k, v in steps.items()}


def _policy_action(policy: Policy, state: torch.Tensor, t: int, action_dim: int) -> torch.Tensor:
    """The policy's actions ``[E, R, A]`` for states ``[E, R, S]``, checked."""
    action = policy(state)
    want = (*state.shape[:-1], action_dim)
    if not isinstance(action, torch.Tensor) or tuple(action.shape) != want:
        got = tuple(action.shape) if isinstance(action, torch.Tensor) else type(action).__name__
        raise ValueError(f"policy: expected actions of shape {want}, got {got}.")
    check_finite(f"policy output at step {t}", action)
    return action


def _check_inputs(
    ensemble: RCVAEEnsemble,
    observation: torch.Tensor,
    actions: torch.Tensor | None,
    samples_per_member: int,
    policy: Policy | None,
    horizon: int | None,
    chunk_size: int | None,
) -> None:
    cfg = ensemble.config
    dtype = ensemble.dtype
    check_trailing("observation", observation, (cfg.obs_dim,), f"[*B, S={cfg.obs_dim}]")
    check_finite("observation", observation)
    check_dtype("observation", observation, dtype)
    if chunk_size is not None and (not isinstance(chunk_size, int) or chunk_size < 1):
        raise ValueError(f"chunk_size: expected a positive int or None, got {chunk_size!r}.")
    if not isinstance(samples_per_member, int) or samples_per_member < 1:
        raise ValueError(
            f"samples_per_member: expected a positive int, got {samples_per_member!r}."
        )
    if (actions is None) == (policy is None):
        raise ValueError(
            "generate: pass exactly one of actions (open loop) or policy (closed loop)."
        )
    if policy is not None:
        if not isinstance(horizon, int) or horizon < 1:
            raise ValueError(f"horizon: expected a positive int with a policy, got {horizon!r}.")
        return
    what = f"[*B, T, A={cfg.action_dim}]"
    check_trailing("actions", actions, (cfg.action_dim,), what)
    if actions.dim() < 2 or actions.shape[-2] < 1:
        raise ValueError(f"actions: expected shape {what} with T >= 1, got {tuple(actions.shape)}.")
    check_batch_shapes(("observation", "actions"), observation.shape[:-1], actions.shape[:-2])
    check_finite("actions", actions)
    check_dtype("actions", actions, dtype)


def _check_output(states: torch.Tensor) -> None:
    """Refuse to return non-finite imagined states silently."""
    bad = ~torch.isfinite(states).flatten(0, -3).all(0).all(-1)
    if bool(bad.any()):
        first = int(bad.nonzero()[0, 0])
        raise ValueError(
            f"generate: the model produced non-finite states from step {first + 1} on; "
            "check the normaliser statistics and the parameters for NaN/inf."
        )

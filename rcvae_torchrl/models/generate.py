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
) -> TensorDict:
    """Sample N trajectories per member from each start state, open or closed loop.

    Open loop: pass ``actions [*B, T, A]``. Closed loop: pass ``policy`` and ``horizon`` T; the
    policy is called once per step on the current states ``[E, N, *B, S]`` and must return
    actions ``[E, N, *B, A]``.

    Args:
        ensemble: the world model (E members).
        observation: start states s_0 ``[*B, S]``.
        actions: a_0..a_{T−1} ``[*B, T, A]`` (open loop).
        samples_per_member: N.
        generator: torch generator for all sampling noise (same generator state → same samples).
        policy: closed-loop policy (instead of ``actions``).
        horizon: number of steps T in closed loop.
        requires_grad: keep the autograd graph (off by default: rollouts are for evaluation).

    Returns:
        TensorDict with batch ``[E, N, *B, T]`` and entries ``"observation"`` s_1..s_T
        ``[..., S]``, ``"action"`` a_0..a_{T−1} ``[..., A]`` (the action that led to it),
        ``("rcvae", "loc")`` / ``("rcvae", "scale")`` ``[..., S]`` the decoder's Gaussian over s_t
        given the sampled z_t (passthrough dims: scale 0), and ``("rcvae", "latent")`` z_t.

    Raises:
        ValueError: non-finite or ill-shaped inputs, or non-finite states produced by the model.
    """
    _check_inputs(ensemble, observation, actions, samples_per_member, policy, horizon)
    n_steps = actions.shape[-2] if policy is None else int(horizon)
    grid = (ensemble.ensemble_size, samples_per_member, *observation.shape[:-1])
    with torch.set_grad_enabled(requires_grad and torch.is_grad_enabled()):
        steps = _rollout(ensemble, observation, actions, n_steps, grid, generator, policy)
    out = TensorDict(
        {k: torch.stack(v, dim=-2).reshape(*grid, n_steps, -1) for k, v in steps.items()},
        batch_size=[*grid, n_steps],
    )
    _check_output(out["observation"])
    return out


_KEYS = ("observation", "action", ("rcvae", "loc"), ("rcvae", "scale"), ("rcvae", "latent"))


def _rollout(
    ensemble: RCVAEEnsemble,
    observation: torch.Tensor,
    actions: torch.Tensor | None,
    n_steps: int,
    grid: tuple[int, ...],
    generator: torch.Generator | None,
    policy: Policy | None,
) -> dict[str | tuple[str, str], list[torch.Tensor]]:
    """The time loop in member-major layout ``[E, N·P, ...]`` (P = number of start states)."""
    e, s_dim = ensemble.ensemble_size, observation.shape[-1]
    state = observation.reshape(1, 1, -1, s_dim).expand(*grid[:2], -1, s_dim).reshape(e, -1, s_dim)
    hidden = ensemble.initial_hidden(state.shape[1:2], state)
    steps: dict[str | tuple[str, str], list[torch.Tensor]] = {k: [] for k in _KEYS}
    for t in range(n_steps):
        action = _action_at(t, state, grid, actions, policy, ensemble.config.action_dim)
        out = ensemble.step(hidden, state, action, generator=generator)
        loc, scale = ensemble.state_loc_scale(state, out.delta_mean, out.delta_std)
        for key, value in zip(_KEYS, (out.observation, action, loc, scale, out.latent)):
            steps[key].append(value)
        state, hidden = out.observation, out.hidden
    return steps


def _action_at(
    t: int,
    state: torch.Tensor,
    grid: tuple[int, ...],
    actions: torch.Tensor | None,
    policy: Policy | None,
    actions_dim: int,
) -> torch.Tensor:
    """a_t in member-major layout ``[E, N·P, A]``, from the open-loop plan or the policy."""
    e, n = grid[:2]
    if policy is None:
        a_t = actions[..., t, :].reshape(1, 1, -1, actions.shape[-1])
        return a_t.expand(e, n, -1, -1).reshape(e, state.shape[1], -1)
    action = policy(state.reshape(*grid, state.shape[-1]))
    want = (*grid, actions_dim)
    if not isinstance(action, torch.Tensor) or tuple(action.shape) != want:
        got = tuple(action.shape) if isinstance(action, torch.Tensor) else type(action).__name__
        raise ValueError(f"policy: expected actions of shape {want}, got {got}.")
    check_finite(f"policy output at step {t}", action)
    return action.reshape(e, state.shape[1], -1)


def _check_inputs(
    ensemble: RCVAEEnsemble,
    observation: torch.Tensor,
    actions: torch.Tensor | None,
    samples_per_member: int,
    policy: Policy | None,
    horizon: int | None,
) -> None:
    cfg = ensemble.config
    dtype = ensemble.embed.weight.dtype
    check_trailing("observation", observation, (cfg.obs_dim,), f"[*B, S={cfg.obs_dim}]")
    check_finite("observation", observation)
    check_dtype("observation", observation, dtype)
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

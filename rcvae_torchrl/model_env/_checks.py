"""Argument and input checks of the model env; errors name the argument, expectation and value."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase

from rcvae_torchrl._checks import check_dtype, check_finite, check_trailing
from rcvae_torchrl.model_env.specs import OBSERVATION_KEY
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout import TRAJECTORY_SAMPLINGS

MEMBER_ASSIGNMENTS = ("round_robin", "random")


def check_arguments(ensemble: object, trajectory_sampling: str, member_assignment: str) -> None:
    """The constructor arguments of :class:`~rcvae_torchrl.model_env.RCVAEEnsembleEnv` (the
    task functions are checked by :class:`~rcvae_torchrl.rollout.Task`)."""
    if not isinstance(ensemble, RCVAEEnsemble):
        raise TypeError(f"ensemble: expected an RCVAEEnsemble, got {type(ensemble).__name__}.")
    if trajectory_sampling not in TRAJECTORY_SAMPLINGS:
        raise ValueError(
            f"trajectory_sampling: expected one of {list(TRAJECTORY_SAMPLINGS)}, "
            f"got {trajectory_sampling!r}."
        )
    if member_assignment not in MEMBER_ASSIGNMENTS:
        raise ValueError(
            f"member_assignment: expected one of {list(MEMBER_ASSIGNMENTS)}, "
            f"got {member_assignment!r}."
        )


def check_start_states(ensemble: RCVAEEnsemble, start_states: torch.Tensor) -> None:
    """Start observations ``[K >= 1, S]``, finite, of the model's dtype."""
    cfg = ensemble.config
    check_trailing("start_states", start_states, (cfg.obs_dim,), f"[K, S={cfg.obs_dim}]")
    if start_states.dim() != 2 or start_states.shape[0] == 0:
        raise ValueError(
            f"start_states: expected shape [K >= 1, {cfg.obs_dim}], "
            f"got {tuple(start_states.shape)}."
        )
    check_finite("start_states", start_states)
    check_dtype("start_states", start_states, ensemble.dtype)


def check_observation(ensemble: RCVAEEnsemble, name: str, observation: torch.Tensor) -> None:
    """Start observations ``[*B, S]``, finite, of the model's dtype."""
    cfg = ensemble.config
    check_trailing(name, observation, (cfg.obs_dim,), f"[*B, S={cfg.obs_dim}]")
    check_finite(name, observation)
    check_dtype(name, observation, ensemble.dtype)


def check_batch_observation(name: str, observation: torch.Tensor, batch: Sequence[int]) -> None:
    """Require ``observation [*B, S]`` with ``[*B]`` its tensordict's ``batch`` (a tensordict
    built without its batch_size is the usual cause)."""
    if tuple(observation.shape[:-1]) != tuple(batch):
        raise ValueError(
            f"{name}: expected shape [*B, S={observation.shape[-1]}] with [*B] the tensordict's "
            f"batch_size {list(batch)}, got {tuple(observation.shape)}; build it with "
            f"TensorDict({{...}}, batch_size={list(observation.shape[:-1])})"
        )


def check_evaluation_inputs(
    ensemble: RCVAEEnsemble, td_start: TensorDictBase, actions: torch.Tensor, particles: object
) -> torch.Tensor:
    """Inputs of ``evaluate_action_sequences``; returns the start observations ``[*B, S]``.

    The start observations may be non-finite (they get NaN returns); actions may not.
    """
    cfg, batch, dtype = ensemble.config, tuple(td_start.batch_size), ensemble.dtype
    if isinstance(particles, bool) or not isinstance(particles, int) or particles < 1:
        raise ValueError(f"particles: expected an int >= 1, got {particles!r}.")
    if OBSERVATION_KEY not in td_start.keys():
        raise KeyError(f"td_start: expected an {OBSERVATION_KEY!r} entry [*B, S].")
    observation = td_start.get(OBSERVATION_KEY)
    check_trailing("td_start['observation']", observation, (cfg.obs_dim,), "[*B, S]")
    check_batch_observation("td_start['observation']", observation, batch)
    check_dtype("td_start['observation']", observation, dtype)
    what = f"[*B, C, H, A] with B = {batch}, A = {cfg.action_dim}"
    if (
        actions.dim() != len(batch) + 3
        or tuple(actions.shape[: len(batch)]) != batch
        or actions.shape[-1] != cfg.action_dim
    ):
        raise ValueError(f"actions: expected shape {what}, got {tuple(actions.shape)}.")
    if actions.shape[-3] < 1 or actions.shape[-2] < 1:
        raise ValueError(
            f"actions: expected C >= 1 candidates and a horizon H >= 1, got C = "
            f"{actions.shape[-3]}, H = {actions.shape[-2]} (shape {tuple(actions.shape)})."
        )
    check_finite("actions", actions)
    check_dtype("actions", actions, dtype)
    return observation

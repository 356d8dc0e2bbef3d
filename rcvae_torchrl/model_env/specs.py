"""Specs of the model env: the real env's task specs plus the model state.

Copied from the real env (when given): ``"observation"``, ``"success"`` (if it has one), the
action, reward and done specs. Other observation entries of the real env (pixels, step
counters added by transforms) are not modelled and are left out. Added: the model state
``("rcvae", "hidden")``, ``("rcvae", "latent")`` and ``"member"`` (not for ``"mean"``), declared
both as observations (so that ``step_mdp`` carries the new values) and as state (the inputs a
step reads), together with ``"observation"`` (so that ``reset`` can take start states from the
input tensordict, also through a ``TransformedEnv``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torchrl.data import Bounded, Categorical, Composite, TensorSpec, Unbounded
from torchrl.envs import EnvBase

from rcvae_torchrl._checks import check_choice, check_device
from rcvae_torchrl.data import ObservationLayout, control_step, observation_layout
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout import TRAJECTORY_SAMPLINGS, TrajectorySampling

__all__ = [
    "ACTION_KEY",
    "HIDDEN_KEY",
    "LATENT_KEY",
    "MEMBER_KEY",
    "OBSERVATION_KEY",
    "REWARD_KEY",
    "SUCCESS_KEY",
    "ModelEnvSpecs",
    "model_env_specs",
]

OBSERVATION_KEY = "observation"
ACTION_KEY = "action"
REWARD_KEY = "reward"
SUCCESS_KEY = "success"
HIDDEN_KEY = ("rcvae", "hidden")
LATENT_KEY = ("rcvae", "latent")
MEMBER_KEY = "member"


class ModelEnvSpecs(NamedTuple):
    """The specs of an :class:`~rcvae_torchrl.model_env.RCVAEEnsembleEnv` (unbatched)."""

    observation: Composite
    action: TensorSpec
    reward: TensorSpec
    done: Composite
    state: Composite


def model_env_specs(
    ensemble: RCVAEEnsemble,
    trajectory_sampling: TrajectorySampling,
    device: torch.device,
    real_env: EnvBase | None = None,
) -> ModelEnvSpecs:
    """Specs for the model env, from ``real_env`` or, without one, defaults.

    Defaults: observation unbounded ``[S]``, action bounded in [-1, 1] ``[A]``, reward
    unbounded ``[1]``, success bool ``[1]``, ``done`` / ``terminated`` / ``truncated`` bool
    ``[1]``. A batched real env contributes the spec of one of its elements.
    """
    if not isinstance(ensemble, RCVAEEnsemble):
        raise TypeError(f"ensemble: expected an RCVAEEnsemble, got {type(ensemble).__name__}")
    check_choice("trajectory_sampling", trajectory_sampling, TRAJECTORY_SAMPLINGS)
    check_device(device)
    if real_env is not None and not isinstance(real_env, EnvBase):
        raise TypeError(
            f"real_env: expected a TorchRL EnvBase or None, got {type(real_env).__name__}"
        )
    task = _real_specs(ensemble, real_env) if real_env is not None else _default_specs(ensemble)
    obs_spec, success_spec, action, reward, done = (s.clone().to(device) for s in task)
    model_state = _model_state_spec(ensemble, trajectory_sampling, obs_spec.dtype, device)
    observation = Composite(
        {OBSERVATION_KEY: obs_spec, SUCCESS_KEY: success_spec, **model_state}, device=device
    )
    state = Composite({OBSERVATION_KEY: obs_spec.clone(), **model_state}, device=device)
    return ModelEnvSpecs(observation, action, reward, done, state.clone())


def _model_state_spec(
    ensemble: RCVAEEnsemble, trajectory_sampling: TrajectorySampling, dtype: torch.dtype, device
) -> dict[str, TensorSpec]:
    cfg, e = ensemble.config, ensemble.ensemble_size
    carry = ensemble.carry_dim
    hidden = (carry,) if trajectory_sampling == "ts_inf" else (e, carry)
    out: dict[str, TensorSpec] = {
        "rcvae": Composite(
            hidden=Unbounded(hidden, dtype=dtype, device=device),
            latent=Unbounded((cfg.latent_dim,), dtype=dtype, device=device),
            device=device,
        )
    }
    if trajectory_sampling != "mean":
        out[MEMBER_KEY] = Categorical(e, shape=(), dtype=torch.int64, device=device)
    return out


def _default_specs(ensemble: RCVAEEnsemble) -> tuple[TensorSpec, ...]:
    cfg, dtype = ensemble.config, ensemble.dtype  # the model's dtype (float64 where cast)
    flag = Categorical(2, shape=(1,), dtype=torch.bool)
    return (
        Unbounded((cfg.obs_dim,), dtype=dtype),
        Unbounded((1,), dtype=torch.bool),
        Bounded(low=-1.0, high=1.0, shape=(cfg.action_dim,), dtype=dtype),
        Unbounded((1,), dtype=dtype),
        Composite(done=flag, terminated=flag.clone(), truncated=flag.clone()),
    )


def _unbatched(spec: Composite, batch_dims: int) -> Composite:
    for _ in range(batch_dims):
        spec = spec[0]
    return spec


def _real_specs(ensemble: RCVAEEnsemble, env: EnvBase) -> tuple[TensorSpec, ...]:
    """The real env's observation, success, action, reward and done specs, checked."""
    cfg, nb = ensemble.config, len(env.batch_size)
    observations = _unbatched(env.observation_spec, nb)
    name = type(env).__name__
    if OBSERVATION_KEY not in observations.keys():
        raise KeyError(
            f"real_env: {name} has no {OBSERVATION_KEY!r} observation to model (it has "
            f"{sorted(map(str, observations.keys()))}); concatenate the entries to model with "
            "rcvae_torchrl.data.prepare_env(env, observation_keys=[...]) (TorchRL's CatTensors)"
        )
    obs = observations[OBSERVATION_KEY]
    if obs.dtype != ensemble.dtype:
        narrower = obs.dtype.is_floating_point and obs.dtype.itemsize < ensemble.dtype.itemsize
        cast = (
            f"give the model the env's dtype (ensemble.to({obs.dtype})), or an env of the "
            f"model's (prepare_env casts every entry to float32)"
            if narrower
            else "cast with TorchRL's DoubleToFloat transform (prepare_env does)"
        )
        raise TypeError(
            f"real_env: {name}'s {OBSERVATION_KEY!r} has dtype {obs.dtype}, the ensemble's is "
            f"{ensemble.dtype}; {cast}"
        )
    success = observations[SUCCESS_KEY] if SUCCESS_KEY in observations.keys() else None
    if env.action_key != ACTION_KEY or env.reward_key != REWARD_KEY:
        raise ValueError(
            f"real_env: expected action and reward keys {ACTION_KEY!r} and {REWARD_KEY!r}, got "
            f"{env.action_key!r} and {env.reward_key!r}."
        )
    action = _unbatched(env.full_action_spec, nb)[ACTION_KEY]
    if not action.dtype.is_floating_point:
        raise TypeError(
            f"real_env: {name}'s {ACTION_KEY!r} spec is {type(action).__name__} of dtype "
            f"{action.dtype}; the world model, its planners and imagination take continuous "
            "actions (a floating vector, as the ensemble's action_dim), which a discrete "
            "action space is not"
        )
    reward = _unbatched(env.full_reward_spec, nb)[REWARD_KEY]
    _check_shape(f"real_env {OBSERVATION_KEY!r} spec", obs.shape, (cfg.obs_dim,))
    _check_layout(ensemble, env)
    _check_control_step(ensemble, env)
    _check_shape(f"real_env {ACTION_KEY!r} spec", action.shape, (cfg.action_dim,))
    _check_shape(f"real_env {REWARD_KEY!r} spec", reward.shape, (1,))
    defaults = _default_specs(ensemble)
    done = _unbatched(env.full_done_spec, nb).clone()
    if "truncated" not in done.keys() and "done" in done.keys():
        # the model env marks an imagined horizon's last step truncated, whether or not the
        # real env ever truncates (TorchRL's PendulumEnv has done and terminated alone)
        done["truncated"] = done["done"].clone()
    return (obs, defaults[1] if success is None else success, action, reward, done)


def _check_control_step(ensemble: RCVAEEnsemble, env: EnvBase) -> None:
    """Refuse ``env`` where one of its steps takes another time than a step of the episodes
    the ensemble was trained on (both where known): each imagined step would stand for a real
    step of another length, and every forecast in time would be off by their ratio."""
    trained = ensemble.config.control_step
    step = control_step(env) if trained is not None else None
    if step is None or math.isclose(step[0], trained, rel_tol=1e-6):
        return
    raise ValueError(
        f"real_env: one of its steps takes {step[0]:g} s ({step[1]}), where the ensemble was "
        f"trained on steps of {trained:g} s (its config's control_step): each imagined step "
        f"would stand for a real step {trained / step[0]:.3g}x its length; give the env the "
        "training episodes' step (a frame skip multiplies the simulator's: TorchRL's "
        "FrameSkipTransform), or train on episodes of its step"
    )


def _check_layout(ensemble: RCVAEEnsemble, env: EnvBase) -> None:
    """Refuse ``env`` where its ``"observation"`` puts a dimension the ensemble was trained on
    (by the name the ensemble records) at another place than the ensemble's: entries named in
    another order, or other entries of the same total size. Names the ensemble gave its
    dimensions itself, none of the env's entries', are not compared."""
    names = ensemble.config.observation_names
    layout = observation_layout(env)
    if names is None or layout is None or layout.dim != len(names):
        return
    ours = set(layout.names)
    moved = [i for i, name in enumerate(names) if name in ours and name != layout.names[i]]
    if moved:
        i = moved[0]
        trained = ObservationLayout.from_names(names)  # the entries the ensemble's names form
        raise ValueError(
            f"real_env: its {OBSERVATION_KEY!r} has {layout.names[i]!r} as dimension {i}, "
            f"where the ensemble was trained on {names[i]!r} ({len(moved)} of {len(names)} "
            f"dimensions differ): the env concatenates {list(layout.keys)}, the ensemble's "
            f"dimensions are {list(names)}; prepare the env with the entries in the ensemble's "
            f"order (prepare_env(env, observation_keys={list(trained.keys)}))"
        )


def _check_shape(name: str, got: torch.Size, want: tuple[int, ...]) -> None:
    if tuple(got) != want:
        raise ValueError(f"{name}: expected shape {want} (the ensemble's), got {tuple(got)}.")

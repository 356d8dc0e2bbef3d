"""Putting a Pusher env in a given state: the observation holds the whole simulator state.

Angles come back from their cos/sin, velocities and positions are read directly, so a real
episode can start from exactly the state a forecast started from (or from an imagined one).
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from .batched import BatchedPusherEnv
from .layout import OBSERVATION_DIM
from .readout import state_from_observation

__all__ = ["reset_to_state"]


def _dm_env(env: EnvBase):
    base = getattr(env, "base_env", env)
    dm = getattr(base, "_env", None)
    if dm is None or not hasattr(dm, "physics"):
        raise TypeError(
            f"env: expected a Pusher env from make_pusher_env, got {type(env).__name__}"
        )
    return dm


def reset_to_state(env: EnvBase, observation: torch.Tensor) -> TensorDictBase:
    """Reset ``env`` and move it to the state described by ``observation [*batch, 14]``.

    Returns the reset tensordict (observation and success of the new state), ready for
    ``env.rollout(T, policy, auto_reset=False, tensordict=td)``. The episode clock restarts;
    the task's random stream (action noise) continues from where it was, so seed first
    (``env.set_seed(s)``) for a reproducible noise sequence.

    ``env`` is a :func:`make_pusher_env` env (``observation [14]``) or a
    :class:`~rcvae_torchrl.envs.batched.BatchedPusherEnv` (``observation [N, 14]``: env ``i``
    restarts from row ``i``, as the single env would; a subset restarts with
    ``env.reset(TensorDict(observation=..., _reset=mask), set_state=True)``).

    Example:
        >>> env = make_pusher_env("stochastic", seed=3)
        >>> td = reset_to_state(env, start)  # start: an observation [14]
    """
    shape = (*env.batch_size, OBSERVATION_DIM)
    if observation.shape != shape or not torch.isfinite(observation).all():
        bad = int((~torch.isfinite(observation)).sum()) if observation.is_floating_point() else 0
        raise ValueError(
            f"observation: expected a finite tensor of shape {shape}, got shape "
            f"{tuple(observation.shape)}" + (f" with {bad} NaN or inf entries" if bad else "")
        )
    if isinstance(env, BatchedPusherEnv):
        td = TensorDict(observation=observation, batch_size=env.batch_size)
        return env.reset(td, set_state=True)
    td = env.reset()
    dm = _dm_env(env)
    physics = dm.physics
    with physics.reset_context():
        physics.set_state(state_from_observation(observation.double().numpy()))
    dm.task.after_step(physics)
    current = dm.task.get_observation(physics)
    td["observation"] = torch.as_tensor(current["observation"], dtype=torch.float32)
    td["success"] = torch.as_tensor(np.asarray(current["success"]))
    return td

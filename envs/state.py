"""Putting a Pusher env in a given state: the observation holds the whole simulator state.

Angles come back from their cos/sin, velocities and positions are read directly, so a real
episode can start from exactly the state a forecast started from (or from an imagined one).
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from .batched import BatchedPusherEnv
from .constraints import into_arena
from .layout import OBSERVATION_DIM, OBSERVATION_NAMES
from .readout import state_from_observation

__all__ = ["PROJECTION_TOLERANCE", "reset_to_state"]

#: Largest change of an observation entry that :func:`reset_to_state` makes silently. A real
#: observation comes back to within float32 rounding (about 1e-8); a larger change means the
#: observation was not a state the Pusher can be in (e.g. a cos/sin pair off the unit circle,
#: a fingertip away from where the joint angles put it).
PROJECTION_TOLERANCE = 1e-4


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

    The simulator state is read from the joint angles (their cos/sin), velocities and the ball
    and target positions; entries that the state determines (the fingertip) are recomputed. An
    observation that is not a state the Pusher can be in is moved to one it can, with a
    ``UserWarning`` naming the entry that moved most and by how much when any entry moves
    more than :data:`PROJECTION_TOLERANCE`; the returned ``td["observation"]`` is the state
    the episode starts from. That covers a ball outside the fence or inside the hub and a
    target out of the ball's reach: each is moved along its ray from the base to where the
    ball's centre can be (:func:`~rcvae_torchrl.envs.constraints.into_arena`).

    Example:
        >>> from rcvae_torchrl.envs import OBSERVATION_NAMES, make_pusher_env
        >>> env = make_pusher_env("stochastic", seed=3)
        >>> start = env.reset()["observation"].clone()  # an observation [14]
        >>> start[OBSERVATION_NAMES.index("ball_x")] = 0.1
        >>> td = reset_to_state(env, start)
        >>> bool(torch.allclose(td["observation"], start, atol=1e-5))
        True
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
        td = env.reset(td, set_state=True)
        _warn_if_moved(observation, td["observation"])
        return td
    td = env.reset()
    dm = _dm_env(env)
    physics = dm.physics
    with physics.reset_context():
        physics.set_state(into_arena(state_from_observation(observation.double().numpy())))
    dm.task.after_step(physics)
    current = dm.task.get_observation(physics)
    td["observation"] = torch.as_tensor(current["observation"], dtype=torch.float32)
    td["success"] = torch.as_tensor(np.asarray(current["success"]))
    _warn_if_moved(observation, td["observation"])
    return td


def _warn_if_moved(given: torch.Tensor, reached: torch.Tensor) -> None:
    """Warn when the state reached differs from the observation given by more than
    :data:`PROJECTION_TOLERANCE` in any entry."""
    gap = (reached.to(given.dtype) - given).abs().reshape(-1, OBSERVATION_DIM).amax(dim=0)
    worst = int(gap.argmax())
    if float(gap[worst]) > PROJECTION_TOLERANCE:
        warnings.warn(
            f"observation: not a state the Pusher can be in; the env starts from the nearest "
            f"one it can, {OBSERVATION_NAMES[worst]} (entry {worst}) moved by "
            f"{float(gap[worst]):.3g}",
            UserWarning,
            stacklevel=3,
        )

"""Putting a Pusher env in a given state: the observation holds the whole simulator state.

Angles come back from their cos/sin, velocities and positions are read directly, so a real
episode can start from exactly the state a forecast started from (or from an imagined one).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from .layout import OBSERVATION_DIM, obs_indices

__all__ = ["reset_to_state"]

_ANGLES = obs_indices("shoulder_cos", "shoulder_sin", "wrist_cos", "wrist_sin")
_QVEL = obs_indices("joint_vel")
_BALL, _BALL_VEL, _TARGET = obs_indices("ball"), obs_indices("ball_vel"), obs_indices("target")


def _dm_env(env: EnvBase):
    base = getattr(env, "base_env", env)
    dm = getattr(base, "_env", None)
    if dm is None or not hasattr(dm, "physics"):
        raise TypeError(
            f"env: expected a Pusher env from make_pusher_env, got {type(env).__name__}"
        )
    return dm


def reset_to_state(env: EnvBase, observation: torch.Tensor) -> TensorDictBase:
    """Reset ``env`` and move it to the state described by ``observation [14]``.

    Returns the reset tensordict (observation and success of the new state), ready for
    ``env.rollout(T, policy, auto_reset=False, tensordict=td)``. The episode clock restarts;
    the task's random stream (action noise) continues from where it was, so seed first
    (``env.set_seed(s)``) for a reproducible noise sequence.
    """
    if observation.shape != (OBSERVATION_DIM,) or not torch.isfinite(observation).all():
        raise ValueError(
            f"observation: expected a finite tensor of shape ({OBSERVATION_DIM},), "
            f"got {tuple(observation.shape)}"
        )
    td = env.reset()
    dm = _dm_env(env)
    physics, obs = dm.physics, observation.double().numpy()
    c1, s1, c2, s2 = obs[_ANGLES]
    with physics.reset_context():
        physics.data.qpos[:2] = [math.atan2(s1, c1), math.atan2(s2, c2)]
        physics.data.qvel[:2] = obs[_QVEL]
        physics.set_ball(obs[_BALL], obs[_BALL_VEL])
        physics.set_target(obs[_TARGET])
    dm.task.after_step(physics)
    current = dm.task.get_observation(physics)
    td["observation"] = torch.as_tensor(current["observation"], dtype=torch.float32)
    td["success"] = torch.as_tensor(np.asarray(current["success"]))
    return td

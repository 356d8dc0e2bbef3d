"""Env factories for the worker-process tests: module-level, so spawned workers can load them."""

from __future__ import annotations

from torchrl.envs import DMControlEnv, EnvBase

from rcvae_torchrl.data import ActionNoise, prepare_env


def noisy_point_mass(noise_std: float) -> EnvBase:
    """dm_control's point_mass with Gaussian action noise from a transform's own stream."""
    env, _ = prepare_env(DMControlEnv("point_mass", "easy"))
    env.append_transform(ActionNoise(noise_std))
    return env


def terminating_point_mass() -> EnvBase:
    """A deterministic point mass whose env ends an episode (``terminated``) at the origin."""
    from tests.planners.planner_envs import PointMassEnv

    env, _ = prepare_env(PointMassEnv(terminate_on_success=True))
    return env


def plain_reset(env: EnvBase, start: object) -> object:
    """A reset to the env's own start (for an env whose every reset gives the same state)."""
    return env.reset()

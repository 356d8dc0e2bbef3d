"""``make_rcvae_env``: the model env with the real env's specs, optionally with transforms."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from torchrl.envs import Compose, EnvBase, Transform, TransformedEnv

from rcvae_torchrl.model_env.env import RCVAEEnsembleEnv
from rcvae_torchrl.model_env.task import RewardFn, SuccessFn
from rcvae_torchrl.models import RCVAEEnsemble

__all__ = ["make_rcvae_env"]


def make_rcvae_env(
    ensemble: RCVAEEnsemble,
    real_env: EnvBase | None,
    reward_fn: RewardFn,
    success_fn: SuccessFn,
    *,
    transforms: Transform | Sequence[Transform] | None = None,
    **kwargs: Any,
) -> EnvBase:
    """Build an :class:`RCVAEEnsembleEnv` with the specs of ``real_env``.

    Args:
        ensemble: the trained world model.
        real_env: the env the agent acts in; its specs are copied, it is neither stepped nor
            reset (``None``: default specs).
        reward_fn: ``(observation_next, action) -> [..., 1]`` (Pusher: ``pusher_reward``).
        success_fn: ``observation -> [...]`` bool (Pusher: ``pusher_success``; use
            ``functools.partial(pusher_success, radius=r)`` to match a non-default radius).
        transforms: optional transforms; the env is then wrapped in a ``TransformedEnv``, whose
            class has no fast path, so planners score plans through ``step``.
        **kwargs: keyword arguments of :class:`RCVAEEnsembleEnv` (``trajectory_sampling``,
            ``start_states``, ``terminate_on_success``, ``seed``, ...).

    Example:
        >>> import torch
        >>> from rcvae_torchrl.envs import make_pusher_env, pusher_reward, pusher_success
        >>> from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
        >>> model = RCVAEEnsemble(RCVAEConfig(14, 2, hidden_dim=16, mlp_dim=16), ensemble_size=5)
        >>> real = make_pusher_env(seed=0)
        >>> env = make_rcvae_env(model, real, pusher_reward, pusher_success, seed=0)
        >>> env.action_spec == real.action_spec, env.trajectory_sampling
        (True, 'ts_inf')
    """
    env = RCVAEEnsembleEnv(ensemble, reward_fn, success_fn, real_env=real_env, **kwargs)
    if transforms is None:
        return env
    if isinstance(transforms, Transform):
        return TransformedEnv(env, transforms)
    return TransformedEnv(env, Compose(*transforms))

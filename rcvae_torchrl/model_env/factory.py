"""``make_rcvae_env``: the model env with the real env's specs, optionally with transforms."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from tensordict.utils import unravel_key
from torchrl.envs import Compose, EnvBase, FrameSkipTransform, Transform, TransformedEnv

from rcvae_torchrl.model_env.env import RCVAEEnsembleEnv
from rcvae_torchrl.model_env.specs import OBSERVATION_KEY
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout import RewardFn, SuccessFn

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
        real_env: the env the agent acts in; its specs are copied, and a reset of the model
            env that is given no start states (neither in the input nor ``start_states``) draws
            them by resetting it, which ends the episode it is in: act in another instance, or
            reset the model env from states (``None``: default specs). It is never stepped.
        reward_fn: ``reward_fn(observation=s_{t+1}, action=a_t) -> [..., 1]`` (or ``[...]``).
        success_fn: ``success_fn(observation=s) -> [...]`` bool (e.g. a
            ``functools.partial`` of a function with a radius argument).
        transforms: optional transforms; the env is then wrapped in a ``TransformedEnv``, whose
            class has no fast path, so planners score plans through ``step``. A transform that
            writes ``"observation"`` (an ``ObservationNorm`` or ``CatFrames`` on it) is
            refused: the model env reads its next state from that entry; write elsewhere. A
            ``FrameSkipTransform`` is refused too (skip frames in the real env instead). A
            :class:`~rcvae_torchrl.competency.CompetencyAssessor` imagines past the transforms
            (with the base env's ``imagine``), so it refuses a transform that changes the
            action: change the action in the policy.
        **kwargs: keyword arguments of :class:`RCVAEEnsembleEnv` (``trajectory_sampling``,
            ``start_states``, ``terminate_on_success``, ``seed``, ...).

    Example:
        >>> from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
        >>> model = RCVAEEnsemble(RCVAEConfig(2, 1, hidden_dim=16, mlp_dim=16), ensemble_size=5)
        >>> def reward(observation, action):
        ...     return -observation[..., :1].abs()
        >>> def success(observation):
        ...     return observation[..., 0].abs() < 0.1
        >>> env = make_rcvae_env(model, None, reward, success, seed=0)
        >>> env.action_spec.shape, env.trajectory_sampling
        (torch.Size([1]), 'ts_inf')
    """
    env = RCVAEEnsembleEnv(ensemble, reward_fn, success_fn, real_env=real_env, **kwargs)
    if transforms is None:
        return env
    compose = transforms if isinstance(transforms, Compose) else None
    if compose is None:
        compose = Compose(*([transforms] if isinstance(transforms, Transform) else transforms))
    transformed = TransformedEnv(env, compose)
    for transform in transformed.transform:  # with their parent: some (InitTracker) need one
        if isinstance(transform, FrameSkipTransform):
            raise ValueError(
                f"transforms: FrameSkipTransform({transform.frame_skip}) on the model env would "
                "step the world model's transition again from the same input (the model env "
                "keeps no simulator state to advance), summing the reward of the repeats while "
                "the state moves one step; skip frames in the real env before collecting the "
                "episodes (its step is then the model's step), not here"
            )
        if OBSERVATION_KEY in map(unravel_key, getattr(transform, "out_keys", None) or []):
            raise ValueError(
                f"transforms: {type(transform).__name__} writes {OBSERVATION_KEY!r}, the model's "
                "state: the model env reads its next state from it, so the transformed values "
                "would be fed back into the model (a normalised state taken for a raw one); "
                f"write to another key (out_keys=[...]), leaving {OBSERVATION_KEY!r} as it is"
            )
    return transformed

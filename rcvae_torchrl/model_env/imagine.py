"""Imagined rollouts with the task on top: :func:`~rcvae_torchrl.models.generate` + reward/done.

The layout is :func:`~rcvae_torchrl.models.generate`'s, batch ``[E, N, *B, T]`` (member,
sample per member, start state, time), propagated with TS-∞ (Chua et al. 2018, PETS): sample
``(m, n, b)`` follows member m throughout, which is what the uncertainty decomposition per
member needs. Entry t describes the transition s_t → s_{t+1}, i.e. what ``env.step`` writes
under ``"next"`` (``"action"`` is a_t, as at the root of a TorchRL rollout).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase

from rcvae_torchrl.model_env.task import (
    RewardFn,
    SuccessFn,
    alive_mask,
    task_reward,
    task_success,
)
from rcvae_torchrl.models import RCVAEEnsemble, generate

__all__ = ["ImaginePolicy", "as_tensor_policy", "imagine_rollouts"]

ImaginePolicy = TensorDictModuleBase | Callable[[torch.Tensor], torch.Tensor]
"""A TensorDict module (reads ``"observation"``, writes ``"action"``) or a tensor callable."""


def as_tensor_policy(
    policy: ImaginePolicy,
    observation_key: str = "observation",
    action_key: str = "action",
) -> Callable[[torch.Tensor], torch.Tensor]:
    """A tensor callable ``[..., S] -> [..., A]`` from either kind of policy.

    A TensorDict module is called on a TensorDict holding only ``observation_key``, with the
    observations' leading dims as its batch, and its ``action_key`` entry is returned.
    """
    if not isinstance(policy, TensorDictModuleBase):
        if not callable(policy):
            raise TypeError(f"policy: expected a callable, got {type(policy).__name__}.")
        return policy

    def call(observation: torch.Tensor) -> torch.Tensor:
        td = TensorDict({observation_key: observation}, batch_size=observation.shape[:-1])
        return policy(td).get(action_key)

    return call


def imagine_rollouts(
    ensemble: RCVAEEnsemble,
    observation: torch.Tensor,
    actions: torch.Tensor | None = None,
    *,
    reward_fn: RewardFn,
    success_fn: SuccessFn,
    policy: ImaginePolicy | None = None,
    horizon: int | None = None,
    samples_per_member: int = 1,
    terminate_on_success: bool = True,
    generator: torch.Generator | None = None,
    chunk_size: int | None = 1024,
) -> TensorDictBase:
    """N TS-∞ samples per member from each start state, open or closed loop, scored.

    Args:
        ensemble: the world model (E members).
        observation: start states s_0 ``[*B, S]``.
        actions: a_0..a_{T−1} ``[*B, T, A]`` (open loop), or ``None`` with ``policy``.
        reward_fn: ``(s_{t+1}, a_t) -> [..., 1]``.
        success_fn: ``s_{t+1} -> [...]`` bool.
        policy: closed-loop policy (see :data:`ImaginePolicy`), with ``horizon`` T.
        horizon: T in closed loop.
        samples_per_member: N.
        terminate_on_success: success ends an episode (sets ``"terminated"``/``"done"``).
        generator: source of all sampling noise.
        chunk_size: trajectories per member rolled out together (``None``: all ``N·|B|``), as in
            :func:`~rcvae_torchrl.models.generate`; the noise drawn depends on it.

    Returns:
        TensorDict ``[E, N, *B, T]`` with :func:`~rcvae_torchrl.models.generate`'s entries
        (``"observation"`` s_{t+1}, ``"action"`` a_t, ``("rcvae", "loc" | "scale" | "latent")``)
        plus ``"reward"`` ``[..., 1]``, ``"success"``, ``"terminated"``, ``"truncated"`` (always
        False) and ``"done"``, bool ``[..., 1]``, each as ``env.step`` would write it for that
        transition; ``"mask"`` bool ``[E, N, *B, T]``, True for the steps of the episode (up to
        and including the first done); ``"member"`` int64 ``[E, N, *B, T]``.
    """
    tensor_policy = None if policy is None else as_tensor_policy(policy)
    td = generate(
        ensemble,
        observation,
        actions,
        samples_per_member=samples_per_member,
        generator=generator,
        policy=tensor_policy,
        horizon=horizon,
        chunk_size=chunk_size,
    )
    return _add_task(td, ensemble.ensemble_size, reward_fn, success_fn, terminate_on_success)


def _add_task(
    td: TensorDictBase,
    ensemble_size: int,
    reward_fn: RewardFn,
    success_fn: SuccessFn,
    terminate_on_success: bool,
) -> TensorDictBase:
    obs = td.get("observation")
    success = task_success(success_fn, obs)
    terminated = success if terminate_on_success else torch.zeros_like(success)
    member = torch.arange(ensemble_size, device=obs.device)
    td.update(
        {
            "reward": task_reward(reward_fn, obs, td.get("action")),
            "success": success,
            "terminated": terminated,
            "truncated": torch.zeros_like(terminated),
            "done": terminated.clone(),
            "mask": alive_mask(terminated.squeeze(-1)),
            "member": member.view(-1, *([1] * (td.batch_dims - 1))).expand(td.batch_size).clone(),
        }
    )
    return td

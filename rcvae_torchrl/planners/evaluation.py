"""Scoring action sequences in an environment: the seam between the planner and the world model.

The planner sees the model only through one question: *what returns do these action sequences
get from these start states?* With ``td_start`` of batch ``[*B]`` and ``actions`` of shape
``[*B, C, H, *A]`` (C candidates, horizon H, action shape A) the answer is a
:class:`ParticleReturns`: ``returns`` ``[*B, C, P]`` over P particles and, when asked for, a
``success`` indicator of the same shape.

Two ways to answer it:

- **Rollout** (:func:`rollout_returns`, works with any TorchRL env that is not batch-locked): the
  start states are expanded to ``[*B, C, P]`` and stepped H times with ``env.step`` and
  ``env.step_mdp`` (no auto-reset); rewards are summed (optionally discounted) up to and including
  the first ``done`` of each particle.
- **Fast path** (:class:`ActionSequenceEvaluator`): an env that defines
  ``evaluate_action_sequences(td_start, actions, particles)`` answers by itself (mbrl-lib's
  ``ModelEnv.evaluate_action_sequences``). Envs that can also report success implement
  :class:`SuccessAwareEvaluator`: the keyword ``return_success=True`` makes the method return
  ``(returns, success)``.
"""

from __future__ import annotations

import inspect
from typing import Literal, NamedTuple, Protocol, overload, runtime_checkable

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key
from torch import Tensor
from torchrl.envs import EnvBase

from rcvae_torchrl.planners import _checks

__all__ = [
    "ActionSequenceEvaluator",
    "ParticleReturns",
    "SuccessAwareEvaluator",
    "env_returns",
    "has_fast_path",
    "rollout_returns",
    "supports_success",
]


class ParticleReturns(NamedTuple):
    """Returns of C candidate action sequences from each of ``[*B]`` start states.

    Attributes:
        returns: ``[*B, C, P]`` float, one return per particle.
        success: ``[*B, C, P]`` bool (or [0, 1] floats), or ``None`` when not computed.
    """

    returns: Tensor
    success: Tensor | None = None


@runtime_checkable
class ActionSequenceEvaluator(Protocol):
    """An environment that scores action sequences itself (the planner's fast path).

    ``evaluate_action_sequences(td_start, actions, particles)``:

    - ``td_start``: TensorDict of batch ``[*B]``, the current (model) state of each start.
    - ``actions``: ``[*B, C, H, *A]``, C candidate sequences of H actions per start.
    - ``particles``: P, the number of stochastic rollouts wanted per candidate.
    - returns: ``[*B, C, P]`` float returns (``[*B, C]`` is read as P = 1). The env may return
      another particle count P' (e.g. a multiple of its ensemble size); the planner reduces over
      whatever it gets. Non-finite returns are allowed and rank last.
    """

    def evaluate_action_sequences(
        self, td_start: TensorDictBase, actions: Tensor, particles: int
    ) -> Tensor: ...


@runtime_checkable
class SuccessAwareEvaluator(Protocol):
    """An :class:`ActionSequenceEvaluator` that can also say which particles succeed.

    With ``return_success=True`` the method returns ``(returns, success)``, both ``[*B, C, P]``;
    ``success`` is a bool indicator (or a probability in [0, 1]) per particle. With
    ``return_success=False`` it behaves as :class:`ActionSequenceEvaluator`.
    """

    @overload
    def evaluate_action_sequences(
        self,
        td_start: TensorDictBase,
        actions: Tensor,
        particles: int,
        *,
        return_success: Literal[False] = ...,
    ) -> Tensor: ...

    @overload
    def evaluate_action_sequences(
        self,
        td_start: TensorDictBase,
        actions: Tensor,
        particles: int,
        *,
        return_success: Literal[True],
    ) -> tuple[Tensor, Tensor]: ...


def has_fast_path(env: EnvBase) -> bool:
    """Whether ``env``'s own class defines ``evaluate_action_sequences``.

    The class is checked, not the instance: a ``TransformedEnv`` forwards unknown attributes to
    its base env, and scoring there would skip the transforms.
    """
    return callable(getattr(type(env), "evaluate_action_sequences", None))


def supports_success(env: object) -> bool:
    """Whether ``env.evaluate_action_sequences`` accepts ``return_success``."""
    method = getattr(env, "evaluate_action_sequences", None)
    if method is None:
        return False
    return "return_success" in inspect.signature(method).parameters


def _as_particles(name: str, x: Tensor, batch_shape: torch.Size, num_candidates: int) -> Tensor:
    """Validate ``[*B, C]`` or ``[*B, C, P]`` and return ``[*B, C, P]``."""
    prefix = (*batch_shape, num_candidates)
    if not isinstance(x, Tensor) or tuple(x.shape[: len(prefix)]) != prefix:
        got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"{name}: expected shape [*B, C, P] = {(*prefix, 'P')}, got {got}")
    if x.ndim == len(prefix):
        return x.unsqueeze(-1)
    if x.ndim != len(prefix) + 1:
        raise ValueError(
            f"{name}: expected shape [*B, C, P] = {(*prefix, 'P')}, got {tuple(x.shape)}"
        )
    return x


def env_returns(
    env: ActionSequenceEvaluator,
    td_start: TensorDictBase,
    actions: Tensor,
    particles: int,
    *,
    return_success: bool = False,
) -> ParticleReturns:
    """Score ``actions`` with ``env.evaluate_action_sequences`` and validate what comes back.

    Args:
        env: implements :class:`ActionSequenceEvaluator` (and :class:`SuccessAwareEvaluator`
            when ``return_success``).
        td_start: batch ``[*B]``.
        actions: ``[*B, C, H, *A]``.
        particles: P requested.

    Returns:
        :class:`ParticleReturns` with ``returns`` (and ``success``) ``[*B, C, P]``.
    """
    batch_shape, num_candidates = td_start.batch_size, actions.shape[td_start.batch_dims]
    name = f"{type(env).__name__}.evaluate_action_sequences"
    if not return_success:
        out = env.evaluate_action_sequences(td_start, actions, particles)
        return ParticleReturns(_as_particles(f"{name} result", out, batch_shape, num_candidates))
    out = env.evaluate_action_sequences(td_start, actions, particles, return_success=True)
    if not (isinstance(out, tuple) and len(out) == 2):
        raise ValueError(f"{name} result: expected (returns, success), got {type(out).__name__}")
    returns = _as_particles(f"{name} returns", out[0], batch_shape, num_candidates)
    success = _as_particles(f"{name} success", out[1], batch_shape, num_candidates)
    if success.shape != returns.shape:
        raise ValueError(
            f"{name} success: expected the shape of returns {tuple(returns.shape)}, "
            f"got {tuple(success.shape)}"
        )
    return ParticleReturns(returns, success)


def _expand_start(td_start: TensorDictBase, env: EnvBase, num_candidates: int, particles: int):
    """``[*B]`` -> ``[*B, C, P]`` copy holding only the env's observation, state and done keys."""
    keys = [
        *env.observation_spec.keys(True, True),
        *env.state_spec.keys(True, True),
        *env.done_keys,
    ]
    td = td_start.select(*keys, strict=False)
    batch_dims = td.batch_dims
    td = td.unsqueeze(batch_dims).unsqueeze(batch_dims + 1)
    return td.expand(*td_start.batch_size, num_candidates, particles).clone()


def _per_particle(x: Tensor, batch_dims: int) -> Tensor:
    """Flatten what follows the batch dims: ``[*B, C, P, ...] -> [*B, C, P, n]``."""
    return x.reshape(*x.shape[:batch_dims], -1)


def _done(td: TensorDictBase, env: EnvBase, batch_dims: int) -> Tensor:
    """Any ``("next", *done)`` flag raised, over the env's keys that end in ``"done"``."""
    flags = [
        _per_particle(td.get(("next", *_as_tuple(key))), batch_dims).any(-1)
        for key in env.done_keys
        if _as_tuple(key)[-1] == "done" and ("next", *_as_tuple(key)) in td.keys(True, True)
    ]
    if not flags:
        return torch.zeros(td.batch_size, dtype=torch.bool, device=td.device)
    return torch.stack(flags).any(0)


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    key = unravel_key(key)
    return (key,) if isinstance(key, str) else key


def rollout_returns(
    env: EnvBase,
    td_start: TensorDictBase,
    actions: Tensor,
    particles: int = 1,
    *,
    action_key: NestedKey = "action",
    reward_key: NestedKey = "reward",
    discount: float = 1.0,
    success_key: NestedKey | None = None,
) -> ParticleReturns:
    """Score action sequences by stepping ``env`` (generic path; any non-batch-locked env).

    Each start state is copied to ``C · P`` particles; particle ``(c, p)`` replays
    ``actions[..., c, t, :]`` for ``t = 0..H-1`` through ``env.step`` / ``env.step_mdp`` (no
    resets). Rewards after a particle's first ``done`` are ignored (the reward of the ``done``
    step counts), as in TorchRL's planners.

    Args:
        env: a TorchRL env accepting batch ``[*B, C, P]`` (``batch_locked=False``).
        td_start: batch ``[*B]``, holding the env's observation/state keys.
        actions: ``[*B, C, H, *A]``.
        particles: P copies of each candidate (useful when the env is stochastic).
        action_key, reward_key: the env's keys (reward read under ``"next"``).
        discount: γ, the reward of step t is weighted by γ^t.
        success_key: key under ``"next"`` of a success flag; a particle succeeds if the flag is
            raised at any step up to its first ``done``. ``None``: no success computed.

    Returns:
        :class:`ParticleReturns`, ``returns`` ``[*B, C, P]`` (and ``success`` bool, same shape).
    """
    _check_replay(td_start, actions, particles, discount)
    spec = env.full_action_spec.get(_as_tuple(action_key), None)
    if spec is None:
        raise KeyError(
            f"action_key: the env has no action {action_key!r}; its actions: "
            f"{', '.join(map(str, env.full_action_spec.keys(True, True)))}"
        )
    action_shape = tuple(spec.shape[len(env.batch_size) :])
    if tuple(actions.shape[actions.ndim - len(action_shape) :]) != action_shape or (
        actions.ndim != td_start.batch_dims + 2 + len(action_shape)
    ):
        raise ValueError(
            f"actions: expected [*B, C, H, *A] with *A = {action_shape} (the env's action "
            f"shape), got {tuple(actions.shape)}"
        )
    batch_dims = td_start.batch_dims + 2
    num_candidates, horizon = actions.shape[td_start.batch_dims : batch_dims]
    td = _expand_start(td_start, env, num_candidates, particles)
    replay = actions.unsqueeze(td_start.batch_dims + 1).expand(
        *td.batch_size, *actions.shape[batch_dims - 1 :]
    )
    returns = torch.zeros(td.batch_size, dtype=actions.dtype, device=actions.device)
    alive = torch.ones(td.batch_size, dtype=torch.bool, device=actions.device)
    success = torch.zeros_like(alive) if success_key is not None else None
    for t in range(horizon):
        td.set(action_key, replay.select(batch_dims, t).contiguous())
        td = env.step(td)
        reward = _per_particle(_entry(td, reward_key, "reward_key"), batch_dims).sum(-1)
        returns = returns + torch.where(alive, reward * discount**t, torch.zeros_like(reward))
        if success is not None:
            flag = _per_particle(_entry(td, success_key, "success_key"), batch_dims).any(-1)
            success = success | (alive & flag)
        alive = alive & ~_done(td, env, batch_dims)
        td = env.step_mdp(td)
    return ParticleReturns(returns, success)


def _check_replay(td_start: object, actions: object, particles: object, discount: object) -> None:
    """:func:`rollout_returns`' arguments, before any step."""
    if not isinstance(td_start, TensorDictBase):
        raise TypeError(f"td_start: expected a TensorDict, got {type(td_start).__name__}")
    _checks.check_positive_int("particles", particles)
    _checks.check_unit_interval("discount", discount, include_zero=False)
    if not isinstance(actions, Tensor) or actions.ndim < td_start.batch_dims + 2:
        got = tuple(actions.shape) if isinstance(actions, Tensor) else type(actions).__name__
        raise ValueError(
            f"actions: expected a tensor [*B, C, H, *A] with [*B] = {list(td_start.batch_size)}, "
            f"got {got}"
        )
    if tuple(actions.shape[: td_start.batch_dims]) != tuple(td_start.batch_size):
        raise ValueError(
            f"actions: expected [*B, C, H, *A] with the batch of td_start [*B] = "
            f"{list(td_start.batch_size)}, got {tuple(actions.shape)}"
        )
    _checks.check_finite("actions", actions)


def _entry(td: TensorDictBase, key: NestedKey, name: str) -> Tensor:
    """``td["next", key]``, or an error naming the argument ``name`` that gave the key."""
    value = td.get(("next", *_as_tuple(key)), None)
    if value is None:
        raise KeyError(
            f"{name}: the env's step wrote no {('next', *_as_tuple(key))!r} entry; its entries "
            f"under 'next': {', '.join(sorted(map(str, td.get('next').keys(True, True))))}"
        )
    return value

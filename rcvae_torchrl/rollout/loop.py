"""The rollout loop: H steps of particles through the ensemble, with a hook per step.

Every imagined rollout of the library runs here: :func:`~rcvae_torchrl.rollout.imagine`
(records every step), plan scoring (:func:`~rcvae_torchrl.rollout.evaluate_action_sequences`,
accumulates rewards), the policy's plan (:func:`~rcvae_torchrl.rollout.plan_actions`, records
actions). They differ only in where the actions come from and in what the hook keeps.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple, Protocol

import torch

from rcvae_torchrl._checks import check_bounds, check_finite
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout.sampling import Propagated, TrajectorySampling, propagate

__all__ = ["ActionBounds", "Policy", "RolloutHook", "StepRecord", "check_action_bounds", "rollout"]

Policy = Callable[[torch.Tensor], torch.Tensor]
"""A closed-loop policy on tensors: observations ``[..., S]`` -> actions ``[..., A]``."""


class ActionBounds(NamedTuple):
    """Bounds every action is clipped to, as the real env clips them (each ``[A]``)."""

    low: torch.Tensor
    high: torch.Tensor


def check_action_bounds(bounds: object, action_dim: int, name: str = "bounds") -> None:
    """Require ``None`` or :class:`ActionBounds` of tensors that broadcast to ``[A]``, with no
    NaN and ``low <= high`` (clipping to crossed bounds would put every action at one of them
    without a word)."""
    if bounds is None:
        return
    if not isinstance(bounds, ActionBounds):
        raise TypeError(
            f"{name}: expected ActionBounds(low, high) of tensors or None, got "
            f"{type(bounds).__name__} {bounds!r}"
        )
    for part in ("low", "high"):
        value = getattr(bounds, part)
        if (
            not isinstance(value, torch.Tensor)
            or value.ndim > 1
            or value.numel()
            not in (
                1,
                action_dim,
            )
        ):
            got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise ValueError(
                f"{name}.{part}: expected a tensor of shape [A={action_dim}] (or one value), "
                f"got {got}"
            )
    check_bounds(name, bounds.low, bounds.high)


class StepRecord(NamedTuple):
    """What a hook sees of step t: a_t applied in s_t, and the model's step to s_{t+1}."""

    t: int
    previous: torch.Tensor  #: s_t
    action: torch.Tensor  #: a_t (clipped to the bounds)
    out: Propagated  #: s_{t+1} and the model's internals


class RolloutHook(Protocol):
    """Called once per step with its :class:`StepRecord`."""

    def __call__(self, step: StepRecord) -> None: ...


def _policy_action(policy: Policy, state: torch.Tensor, t: int, action_dim: int) -> torch.Tensor:
    """The policy's actions ``[*P, A]`` for states ``[*P, S]``, checked."""
    action = policy(state)
    want = (*state.shape[:-1], action_dim)
    if not isinstance(action, torch.Tensor) or tuple(action.shape) != want:
        got = tuple(action.shape) if isinstance(action, torch.Tensor) else type(action).__name__
        raise ValueError(
            f"policy: expected actions of shape {want} (one action of A = {action_dim} entries "
            f"for each of the {list(state.shape[:-1])} imagined states it was given), got {got}"
            f" at step {t}"
        )
    if action.dtype != state.dtype:  # before the bounds' clamp casts an int or bool one
        raise TypeError(
            f"policy: expected actions of dtype {state.dtype} (the model's), got {action.dtype} "
            f"at step {t}"
        )
    return action


def _check_policy_actions(
    finite: list[torch.Tensor], actions: list[torch.Tensor], states: list[torch.Tensor]
) -> None:
    """Raise, naming the first step, if a policy action was NaN or inf: ``finite`` holds each
    step's "all finite" flag, read here once for the whole rollout (a read at every step would
    make an accelerator wait for the host at every step). Where the state the policy saw at
    that step was itself not finite, the model made it, and the error says so."""
    ok = torch.stack(finite)
    if not bool(ok.all()):
        t = int((~ok).nonzero()[0, 0])
        try:
            check_finite(f"the imagined states at step {t}", states[t])
        except ValueError as err:
            raise ValueError(
                f"{err}: the world model made them (the policy's actions were finite until "
                "then), and the policy's actions from them were not finite either (damaged "
                "weights, e.g. a checkpoint changed on disk, a training that diverged, or inputs "
                "far outside the model's training data)"
            ) from None
        check_finite(f"policy output at step {t}", actions[t])


def rollout(
    ensemble: RCVAEEnsemble,
    mode: TrajectorySampling,
    observation: torch.Tensor,
    hidden: torch.Tensor,
    horizon: int,
    hook: RolloutHook,
    *,
    actions: torch.Tensor | None = None,
    policy: Policy | None = None,
    bounds: ActionBounds | None = None,
    generator: torch.Generator | None = None,
    noise: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Step particles ``horizon`` times and call ``hook`` after each step.

    Args:
        ensemble: the world model.
        mode: trajectory sampling (:mod:`~rcvae_torchrl.rollout.sampling` gives the layouts).
        observation: s_0 of the particles.
        hidden: h_0 (``[E, M, H]``).
        horizon: H steps.
        hook: called with a :class:`StepRecord` after every step.
        actions: open loop: ``[H, *P, A]`` (index t gives a_t for every particle; a view of an
            expanded tensor is fine).
        policy: closed loop instead: called on s_t ``[*P, S]``, must return finite ``[*P, A]``
            (checked once, after the last step or when the policy raises: an error names the
            first bad step, and the model where the states it acted on were not finite).
        bounds: clip every action to these bounds (the real env's action spec).
        generator: source of the sampling noise.
        noise: pre-drawn ``(ε_z [H, ...], ε_s [H, ...])`` instead of ``generator``.

    Returns:
        ``(s_H, h_H)``.
    """
    action_dim = ensemble.config.action_dim
    finite: list[torch.Tensor] = []  # closed loop: each step's policy actions all finite
    taken: list[torch.Tensor] = []
    seen: list[torch.Tensor] = []  # closed loop: the states the policy acted on
    for t in range(horizon):
        if actions is not None:
            action = actions[t]
        else:
            try:
                action = _policy_action(policy, observation, t, action_dim)
            except Exception:
                if finite:  # a NaN action of an earlier step (read only now) can be why
                    _check_policy_actions(finite, taken, seen)
                raise
            finite.append(torch.isfinite(action).all())
            taken.append(action)
            seen.append(observation)
        if bounds is not None:
            action = torch.clamp(action, bounds.low, bounds.high)
        out = propagate(
            ensemble,
            mode,
            hidden,
            observation,
            action,
            noise=None if noise is None else (noise[0][t], noise[1][t]),
            generator=generator,
        )
        hook(StepRecord(t, observation, action, out))
        observation, hidden = out.observation, out.hidden
    if finite:
        _check_policy_actions(finite, taken, seen)
    return observation, hidden

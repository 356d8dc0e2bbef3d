"""Toy envs for the planner tests: a point mass driven towards the origin.

State: ``"position"`` and ``"velocity"`` of shape A (the action shape); ``v' = v + dt·a``,
``p' = p + dt·v'`` (``double=True``) or ``p' = p + dt·a``; reward ``−‖p'‖``; ``"success"`` when
``‖p'‖ < success_radius``. Not batch-locked, ``batch_size=()``: any leading batch works, as in a
``ModelBasedEnvBase``. :class:`AnalyticPointMassEnv` adds the planner's fast path with the same
arithmetic, so both paths give identical returns.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Binary, Bounded, Composite, Unbounded
from torchrl.envs import EnvBase


class PointMassEnv(EnvBase):
    """A deterministic point mass; ``start`` is the reset position (default: all 0.8)."""

    def __new__(cls, *args, **kwargs):
        return super().__new__(cls, *args, _batch_locked=False, **kwargs)

    def __init__(
        self,
        action_shape: Sequence[int] = (2,),
        low: float | Tensor = -1.0,
        high: float | Tensor = 1.0,
        *,
        start: Tensor | None = None,
        dt: float = 0.2,
        double: bool = True,
        success_radius: float = 0.1,
        terminate_on_success: bool = False,
        action_key: NestedKey = "action",
        device: str | torch.device | None = None,
    ) -> None:
        super().__init__(batch_size=(), device=device)
        self.action_shape = torch.Size(action_shape)
        self.dt, self.double, self.success_radius = dt, double, success_radius
        self.terminate_on_success = terminate_on_success
        self.start = torch.full(self.action_shape, 0.8) if start is None else start
        self.start = self.start.to(device)
        bounds = Bounded(low=low, high=high, shape=self.action_shape)
        self.full_action_spec = Composite({action_key: bounds})
        self.observation_spec = Composite(
            position=Unbounded(self.action_shape),
            velocity=Unbounded(self.action_shape),
            success=Binary(n=1, dtype=torch.bool),
        )
        self.reward_spec = Unbounded((1,))
        self._action_key = action_key

    def _distance(self, position: Tensor) -> Tensor:
        return position.flatten(-len(self.action_shape)).norm(dim=-1)

    def next_state(
        self, position: Tensor, velocity: Tensor, action: Tensor
    ) -> tuple[Tensor, Tensor]:
        """One step of the dynamics, on any leading batch."""
        velocity = velocity + self.dt * action if self.double else velocity
        step = velocity if self.double else action
        return position + self.dt * step, velocity

    def reward(self, position: Tensor, action: Tensor) -> Tensor:
        """``[*batch]`` reward of arriving at ``position`` with ``action``."""
        return -self._distance(position)

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDict:
        batch = self.batch_size if tensordict is None else tensordict.batch_size
        position = self.start.expand(*batch, *self.action_shape).clone()
        return TensorDict(
            position=position,
            velocity=torch.zeros_like(position),
            success=(self._distance(position) < self.success_radius).unsqueeze(-1),
            done=torch.zeros(*batch, 1, dtype=torch.bool, device=position.device),
            terminated=torch.zeros(*batch, 1, dtype=torch.bool, device=position.device),
            batch_size=batch,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        action = tensordict.get(self._action_key)
        position, velocity = self.next_state(
            tensordict.get("position"), tensordict.get("velocity"), action
        )
        success = (self._distance(position) < self.success_radius).unsqueeze(-1)
        done = success & self.terminate_on_success
        return TensorDict(
            position=position,
            velocity=velocity,
            success=success,
            reward=self.reward(position, action).unsqueeze(-1),
            done=done,
            terminated=done.clone(),
            batch_size=tensordict.batch_size,
        )

    def _set_seed(self, seed: int | None) -> None:
        return None


class AnalyticPointMassEnv(PointMassEnv):
    """:class:`PointMassEnv` that also scores action sequences itself (the planner's fast path)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.calls = 0

    def evaluate_action_sequences(
        self,
        td_start: TensorDictBase,
        actions: Tensor,
        particles: int,
        *,
        return_success: bool = False,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """``actions`` ``[*B, C, H, *A]`` -> returns ``[*B, C, P]`` (and success)."""
        self.calls += 1
        nb = td_start.batch_dims
        shape = (*actions.shape[: nb + 1], particles, *self.action_shape)

        def start(key: str) -> Tensor:
            value = td_start.get(key)
            return value.reshape(*td_start.batch_size, 1, 1, *self.action_shape).expand(shape)

        position, velocity = start("position"), start("velocity")
        returns = torch.zeros(shape[: nb + 2], device=actions.device)
        alive = torch.ones(shape[: nb + 2], dtype=torch.bool, device=actions.device)
        success = torch.zeros_like(alive)
        for t in range(actions.shape[nb + 1]):
            action = actions.select(nb + 1, t).unsqueeze(nb + 1).expand(shape)
            position, velocity = self.next_state(position, velocity, action)
            reward = self.reward(position, action)
            returns = returns + torch.where(alive, reward, torch.zeros_like(reward))
            reached = self._distance(position) < self.success_radius
            success = success | (alive & reached)
            if self.terminate_on_success:
                alive = alive & ~reached
        return (returns, success) if return_success else returns


class NaNPointMassEnv(PointMassEnv):
    """Rewards are NaN wherever the first action component is positive."""

    def reward(self, position: Tensor, action: Tensor) -> Tensor:
        reward = super().reward(position, action)
        first = action.flatten(-len(self.action_shape))[..., 0]
        return torch.where(first > 0, torch.full_like(reward, torch.nan), reward)


class NaNAnalyticPointMassEnv(AnalyticPointMassEnv, NaNPointMassEnv):
    """The NaN env with the fast path."""


class RiskyChoiceEnv(PointMassEnv):
    """Fast path only: the sign of the first action component picks a lottery.

    ``a_0 > 0``: returns ``1 + 3·z`` over particles (mean 1, high variance); otherwise a sure 0.5.
    The expected return prefers the lottery, risk-averse objectives the sure thing.
    """

    def evaluate_action_sequences(
        self, td_start: TensorDictBase, actions: Tensor, particles: int
    ) -> Tensor:
        nb = td_start.batch_dims
        z = torch.linspace(-1.0, 1.0, particles)
        z = (z - z.mean()) / z.std() if particles > 1 else z * 0
        first = actions.select(nb + 1, 0).flatten(nb + 1)[..., 0]
        risky = (first > 0).unsqueeze(-1)
        return torch.where(risky, 1.0 + 3.0 * z, torch.full_like(z, 0.5))

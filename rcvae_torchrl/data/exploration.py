"""Exploration policies for data collection: a base policy plus Gaussian noise, or uniform noise.

Actions stay inside the action bounds ``[low, high]`` (scalars or ``[A]``); take them from
your env's action spec with :func:`action_bounds`.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from rcvae_torchrl._checks import check_bounds, check_positive_int

__all__ = [
    "GaussianExploration",
    "UniformRandomPolicy",
    "action_bounds",
    "make_policy_module",
]

Bound = float | torch.Tensor


def action_bounds(env) -> tuple[torch.Tensor, torch.Tensor]:
    """``(low, high)`` ``[A]`` of a TorchRL env's bounded action spec."""
    space = getattr(env.action_spec, "space", None)
    low, high = getattr(space, "low", None), getattr(space, "high", None)
    if low is None or high is None:
        raise ValueError(
            f"env: expected a bounded continuous action spec, got {type(env.action_spec).__name__}"
        )
    shape = env.action_spec.shape[len(env.batch_size) :]
    return low.reshape(-1, *shape)[0].float(), high.reshape(-1, *shape)[0].float()


def _bounds(low: Bound, high: Bound) -> tuple[torch.Tensor, torch.Tensor]:
    low, high = (
        torch.as_tensor(low, dtype=torch.float32),
        torch.as_tensor(high, dtype=torch.float32),
    )
    check_bounds("low, high", low, high, finite=True)
    return low, high


class GaussianExploration(nn.Module):
    """``clip(policy(obs) + noise_std * eps, low, high)``, with noise from its own generator.

    Args:
        policy: a module mapping observations ``[..., S]`` to actions ``[..., A]``.
        noise_std: std of the added Gaussian noise (>= 0).
        seed: seed of the noise generator (reproducible collection).
        low, high: the action bounds (default [-1, 1]; see :func:`action_bounds`).
    """

    def __init__(
        self,
        policy: nn.Module,
        noise_std: float,
        seed: int = 0,
        *,
        low: Bound = -1.0,
        high: Bound = 1.0,
    ) -> None:
        super().__init__()
        if not noise_std >= 0:
            raise ValueError(f"noise_std: expected a non-negative std, got {noise_std!r}")
        self.policy, self.noise_std = policy, float(noise_std)
        self.low, self.high = _bounds(low, high)
        self.generator = torch.Generator().manual_seed(seed)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        action = self.policy(observation)
        if self.noise_std == 0:
            return action
        noise = torch.randn(action.shape, generator=self.generator, dtype=action.dtype)
        noisy = action + self.noise_std * noise.to(action.device)
        return torch.clamp(noisy, self.low.to(noisy), self.high.to(noisy))


class UniformRandomPolicy(nn.Module):
    """Actions uniform in ``[low, high]`` (default ``[-1, 1]^A``), held for ``hold`` consecutive
    calls (smoother exploration).

    Holding an action for a few steps moves a system further than white noise does, so random
    episodes cover more of its state space.
    """

    def __init__(
        self,
        action_dim: int,
        hold: int = 5,
        seed: int = 0,
        *,
        low: Bound = -1.0,
        high: Bound = 1.0,
    ) -> None:
        super().__init__()
        check_positive_int("action_dim", action_dim)
        check_positive_int("hold", hold)
        self.action_dim, self.hold = action_dim, hold
        self.low, self.high = _bounds(low, high)
        self.generator = torch.Generator().manual_seed(seed)
        self._calls, self._action = 0, None

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        shape = (*observation.shape[:-1], self.action_dim)
        if self._action is None or self._action.shape != shape or self._calls % self.hold == 0:
            unit = torch.rand(shape, generator=self.generator)
            self._action = self.low + unit * (self.high - self.low)
        self._calls += 1
        return self._action.to(observation.device, observation.dtype)


def make_policy_module(policy: nn.Module) -> TensorDictModule:
    """Wire a tensor policy (``observation -> action``, an exploration policy, an agent) to
    TorchRL keys: reads ``"observation"``, writes ``"action"``."""
    return TensorDictModule(policy, in_keys=["observation"], out_keys=["action"])

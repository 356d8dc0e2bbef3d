"""Exploration policies for data collection: a base policy plus Gaussian noise, or uniform noise."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn

__all__ = ["GaussianExploration", "UniformRandomPolicy", "make_exploration_policy"]


class GaussianExploration(nn.Module):
    """``clip(policy(obs) + noise_std * eps, -1, 1)``, with noise from its own generator.

    Args:
        policy: a module mapping observations ``[..., S]`` to actions ``[..., A]`` in [-1, 1].
        noise_std: std of the added Gaussian noise (>= 0).
        seed: seed of the noise generator (reproducible collection).
    """

    def __init__(self, policy: nn.Module, noise_std: float, seed: int = 0) -> None:
        super().__init__()
        if not noise_std >= 0:
            raise ValueError(f"noise_std: expected a non-negative std, got {noise_std!r}")
        self.policy, self.noise_std = policy, float(noise_std)
        self.generator = torch.Generator().manual_seed(seed)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        action = self.policy(observation)
        if self.noise_std == 0:
            return action
        noise = torch.randn(action.shape, generator=self.generator, dtype=action.dtype)
        return (action + self.noise_std * noise.to(action.device)).clamp(-1.0, 1.0)


class UniformRandomPolicy(nn.Module):
    """Actions uniform in [-1, 1]^A, held for ``hold`` consecutive calls (smoother exploration).

    Holding an action for a few steps moves the arm further than white noise does, so random
    episodes cover the arm's workspace and speeds, and now and then push the ball.
    """

    def __init__(self, action_dim: int, hold: int = 5, seed: int = 0) -> None:
        super().__init__()
        if hold < 1:
            raise ValueError(f"hold: expected >= 1 steps, got {hold}")
        self.action_dim, self.hold = action_dim, hold
        self.generator = torch.Generator().manual_seed(seed)
        self._calls, self._action = 0, None

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        shape = (*observation.shape[:-1], self.action_dim)
        if self._action is None or self._action.shape != shape or self._calls % self.hold == 0:
            self._action = torch.rand(shape, generator=self.generator) * 2 - 1
        self._calls += 1
        return self._action.to(observation.device, observation.dtype)


def make_exploration_policy(module: nn.Module) -> TensorDictModule:
    """Wire an observation -> action module to TorchRL keys (``"observation"`` -> ``"action"``)."""
    return TensorDictModule(module, in_keys=["observation"], out_keys=["action"])

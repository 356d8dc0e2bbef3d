"""An amortised policy: a small MLP that maps observations to actions in [-1, 1].

It stands in for the MPC planner where planning at every step is too slow: inside imagined
rollouts of thousands of particles (closed-loop competency forecasts) and as a real-time agent.
Observations are normalised with statistics fitted from data and saved with the weights.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn

__all__ = ["MLPPolicy", "ResidualPolicy", "make_policy_module"]


class MLPPolicy(nn.Module):
    """``a = tanh(MLP((s - mean) / std))``, ``[..., S] -> [..., A]``.

    Args:
        obs_dim: S.
        action_dim: A.
        hidden: width of the two hidden layers.
    """

    def __init__(self, obs_dim: int, action_dim: int, hidden: int = 256) -> None:
        super().__init__()
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.net = nn.Sequential(
            nn.Linear(obs_dim, hidden),
            nn.ELU(),
            nn.Linear(hidden, hidden),
            nn.ELU(),
            nn.Linear(hidden, action_dim),
        )
        self.register_buffer("obs_mean", torch.zeros(obs_dim))
        self.register_buffer("obs_std", torch.ones(obs_dim))

    def fit_normalizer(self, observations: torch.Tensor) -> None:
        """Set the input statistics from observations ``[..., S]`` (std floored at 1e-3)."""
        flat = observations.reshape(-1, self.obs_dim)
        self.obs_mean.copy_(flat.mean(0))
        self.obs_std.copy_(flat.std(0).clamp_min(1e-3))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        if observation.shape[-1] != self.obs_dim:
            raise ValueError(
                f"observation: expected shape [..., {self.obs_dim}], got {tuple(observation.shape)}"
            )
        return torch.tanh(self.net((observation - self.obs_mean) / self.obs_std))


class ResidualPolicy(nn.Module):
    """``a = clamp(base(s) + residual(s), -1, 1)``: a fixed prior policy plus a learned correction.

    Distilling a planner that refines a prior policy (policy-guided CEM) into the residual is far
    easier than into a whole policy: the correction is small and smooth where the prior switches
    modes abruptly (residual policy learning, Silver et al. 2018; Johannink et al. 2019).
    """

    def __init__(self, base: nn.Module, residual: MLPPolicy) -> None:
        super().__init__()
        self.base, self.residual = base, residual
        self.obs_dim, self.action_dim = residual.obs_dim, residual.action_dim

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return (self.base(observation) + self.residual(observation)).clamp(-1.0, 1.0)


def make_policy_module(policy: nn.Module) -> TensorDictModule:
    """Wire a policy to TorchRL keys: reads ``"observation"``, writes ``"action"``."""
    return TensorDictModule(policy, in_keys=["observation"], out_keys=["action"])

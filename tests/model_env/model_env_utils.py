"""Helpers shared by the model-env tests."""

from __future__ import annotations

import torch

from rcvae_torchrl.models import RCVAEConfig

E = 3  # ensemble size of the tiny test models
CONFIG = RCVAEConfig(14, 2, hidden_dim=16, latent_dim=4, mlp_dim=16, passthrough_dims=(12, 13))


def at_target(observation: torch.Tensor) -> torch.Tensor:
    """Copies of ``observation [..., 14]`` with the ball put on the target."""
    out = observation.clone()
    out[..., 8:10] = out[..., 12:14]
    return out


class Replay:
    """A policy writing ``actions[..., t, :]`` at its t-th call (``[*B, T, A]``)."""

    def __init__(self, actions: torch.Tensor) -> None:
        self.actions, self.t = actions, 0

    def __call__(self, td):
        td.set("action", self.actions[..., self.t, :])
        self.t += 1
        return td

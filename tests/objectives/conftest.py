"""Fixtures for the objective tests."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble


@pytest.fixture
def ensemble() -> RCVAEEnsemble:
    torch.manual_seed(0)
    cfg = RCVAEConfig(4, 2, hidden_dim=10, latent_dim=3, mlp_dim=12, passthrough_dims=(3,))
    return RCVAEEnsemble(cfg, ensemble_size=3)


def make_windows(batch: tuple[int, ...], seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        observation=torch.randn(*batch, 4, generator=g),
        action=torch.rand(*batch, 2, generator=g) * 2 - 1,
        batch_size=batch,
    )


@pytest.fixture
def windows_of():
    """A factory: windows of any batch shape ``[..., L]`` (S = 4, A = 2)."""
    return make_windows


@pytest.fixture
def windows() -> TensorDict:
    return make_windows((5, 8))

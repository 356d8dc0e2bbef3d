"""Shared test set-up: deterministic torch, one intra-op thread, small world models.

The fixtures here serve every test package; a package's own conftest overrides ``ensemble``
where it needs another model (the Pusher-sized one of the model-env tests, for instance).
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch

from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.rollout import SCORING_CACHE_ENV


@pytest.fixture(scope="session", autouse=True)
def aot_cache_dir(tmp_path_factory):
    """The cache of ahead-of-time compiled scoring packages for the whole session (never the
    user's): tests of one architecture, task and horizon share one build."""
    path = tmp_path_factory.mktemp("aot_scoring")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(SCORING_CACHE_ENV, str(path))
        yield path


@pytest.fixture(autouse=True)
def _seed_torch():
    torch.manual_seed(0)
    yield


@pytest.fixture(autouse=True)
def single_thread():
    """Tests run tiny tensor ops; one intra-op thread avoids OpenMP sync overhead on a shared
    2-core machine (a 5x slowdown was measured under load). Restored afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def compiled_calls_paused(monkeypatch) -> list[bool]:
    """``torch.compile`` replaced by a recorder (no compile): per call of a function it
    returned, whether Python's garbage collector was paused during the call."""
    import gc

    paused: list[bool] = []

    def recorded(fn, **_):
        def call(*args, **kwargs):
            paused.append(not gc.isenabled())
            return fn(*args, **kwargs)

        return call

    monkeypatch.setattr(torch, "compile", recorded)
    return paused


@pytest.fixture
def config() -> RCVAEConfig:
    return RCVAEConfig(
        obs_dim=5, action_dim=2, hidden_dim=12, latent_dim=3, mlp_dim=16, passthrough_dims=(3, 4)
    )


@pytest.fixture
def ensemble(config: RCVAEConfig) -> RCVAEEnsemble:
    torch.manual_seed(0)
    model = RCVAEEnsemble(config, ensemble_size=4)
    g = torch.Generator().manual_seed(1)
    model.fit_normalizer(torch.randn(8, 20, 5, generator=g), torch.rand(8, 20, 2, generator=g))
    return model


@dataclass
class LinearGaussian:
    """s_{t+1} = A s_t + B a_t + σ ε, ε ~ N(0, I); a stable A (spectral radius ≈ 0.92)."""

    A: torch.Tensor
    B: torch.Tensor
    sigma: float

    @property
    def obs_dim(self) -> int:
        return self.A.shape[0]

    def simulate(self, episodes: int, steps: int, g: torch.Generator):
        """Trajectories from s_0 ~ N(0, I) under uniform random actions in [-1, 1]."""
        s = torch.randn(episodes, self.obs_dim, generator=g)
        obs, acts = [], []
        for _ in range(steps):
            a = torch.rand(episodes, self.B.shape[1], generator=g) * 2 - 1
            obs.append(s)
            acts.append(a)
            s = s @ self.A.T + a @ self.B.T + self.sigma * torch.randn(s.shape, generator=g)
        return torch.stack(obs, 1), torch.stack(acts, 1)

    def open_loop_moments(self, s0: torch.Tensor, actions: torch.Tensor):
        """Mean and covariance of s_T from s0 ``[S]`` under actions ``[T, A]``."""
        mean, cov = s0.clone(), torch.zeros(self.obs_dim, self.obs_dim)
        for a in actions:
            mean = self.A @ mean + self.B @ a
            cov = self.A @ cov @ self.A.T + self.sigma**2 * torch.eye(self.obs_dim)
        return mean, cov


@pytest.fixture
def linear_system() -> LinearGaussian:
    A = torch.tensor([[0.9, 0.2, 0.0], [-0.2, 0.9, 0.0], [0.0, 0.1, 0.8]])
    B = torch.tensor([[0.0], [0.5], [0.2]])
    return LinearGaussian(A, B, sigma=0.1)

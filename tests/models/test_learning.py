"""It learns: aleatoric spread on a linear-Gaussian system, epistemic spread off-distribution.

Small models and short Adam loops on RCVAELoss; the full training loop lives in
rcvae_torchrl.training.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.objectives import RCVAELoss
from rcvae_torchrl.rollout import imagine


def _sample_windows(obs, act, shape, length, g):
    """Random windows ``[*shape, L]`` from trajectories ``[episodes, T, ·]``."""
    episodes, steps = obs.shape[:2]
    ep = torch.randint(episodes, shape, generator=g)[..., None]
    start = torch.randint(steps - length + 1, shape, generator=g)[..., None]
    idx = start + torch.arange(length)
    return TensorDict(observation=obs[ep, idx], action=act[ep, idx], batch_size=[*shape, length])


def _train(system, ensemble_size, steps, seed, windows=64, length=16, episodes=256, nll_beta=0.0):
    torch.manual_seed(seed)
    g = torch.Generator().manual_seed(seed)
    obs, act = system.simulate(episodes, 64, g)
    cfg = RCVAEConfig(system.obs_dim, 1, hidden_dim=32, latent_dim=2, mlp_dim=32)
    model = RCVAEEnsemble(cfg, ensemble_size)
    model.fit_normalizer(obs, act)
    loss_fn = RCVAELoss(model, nll_beta=nll_beta)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    shape = (windows,) if ensemble_size == 1 else (ensemble_size, windows)
    for _ in range(steps):
        out = loss_fn(_sample_windows(obs, act, shape, length, g))
        opt.zero_grad()
        (out["loss_reconstruction"] + out["loss_kl"]).backward()
        opt.step()
    return model


def _check_aleatoric(model, system, g, one_step_tol, spread_tol):
    with torch.no_grad():
        starts = torch.randn(32, system.obs_dim, generator=g)
        a = torch.rand(32, 1, 1, generator=g) * 2 - 1
        first = imagine(model, starts, a, samples_per_member=2000, generator=g)
        std = first["observation"][..., 0, :].std(dim=1)  # [E, 32, S]
        ratio = std.mean(dim=(1, 2)) / system.sigma
        assert ((ratio - 1).abs() < one_step_tol).all(), f"one-step std / sigma: {ratio}"

        actions = torch.rand(20, 1, generator=g) * 2 - 1
        s0 = torch.zeros(system.obs_dim)
        rollout = imagine(model, s0, actions, samples_per_member=4000, generator=g)
        final = rollout["observation"][:, :, -1]  # [E, N, S]
        _, cov = system.open_loop_moments(s0, actions)
        spread = final.std(dim=1) / cov.diagonal().sqrt()
        assert ((spread - 1).abs() < spread_tol).all(), f"20-step spread / analytic: {spread}"


@pytest.mark.parametrize("nll_beta", [0.0, 0.5])
def test_linear_gaussian_aleatoric_spread(linear_system, nll_beta):
    """One-step std within 15 % of σ; 20-step open-loop spread within 25 % of
    sqrt(diag Σ_k A^k σ²I A^kᵀ). About 3 s of training. β-NLL (the study's 0.5) reweights the
    gradient but keeps the variance's optimum, so the noise is learned as well."""
    model = _train(linear_system, ensemble_size=1, steps=400, seed=0, nll_beta=nll_beta)
    _check_aleatoric(model, linear_system, torch.Generator().manual_seed(10), 0.15, 0.25)


@pytest.mark.slow
def test_linear_gaussian_aleatoric_spread_every_member(linear_system):
    """All 5 members, longer training, tighter tolerances."""
    model = _train(linear_system, ensemble_size=5, steps=1500, seed=1)
    _check_aleatoric(model, linear_system, torch.Generator().manual_seed(11), 0.10, 0.15)


def test_epistemic_disagreement_off_distribution(linear_system):
    """Trained on s ~ N(0, I) (radius ≈ 1.6), members disagree ≥ 3x more at radius 8."""
    model = _train(linear_system, ensemble_size=5, steps=250, seed=2, windows=32, episodes=128)
    g = torch.Generator().manual_seed(12)
    direction = torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1)
    actions = torch.rand(64, 1, 1, generator=g) * 2 - 1

    def disagreement(starts):
        with torch.no_grad():
            td = imagine(model, starts, actions, samples_per_member=200, generator=g)
        member_means = td["observation"][:, :, :, 0].mean(dim=1)  # [E, 64, S]
        return member_means.std(dim=0).mean()

    inside = disagreement(torch.randn(64, 3, generator=g))
    outside = disagreement(8.0 * direction)
    assert outside > 3 * inside, f"inside {inside:.4f}, outside {outside:.4f}"

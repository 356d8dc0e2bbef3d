"""Kolchinsky–Tracey bounds on Gaussian-mixture entropy."""

import math

import pytest
import torch
from torch.distributions import Categorical, MixtureSameFamily, MultivariateNormal

from rcvae_torchrl.competency import (
    fit_gaussian_mixture_entropy_bounds,
    gaussian_entropy,
    gaussian_mixture_entropy_bounds,
)


def monte_carlo_entropy_bits(weights, means, covariances, n=200_000):
    mixture = MixtureSameFamily(Categorical(weights), MultivariateNormal(means, covariances))
    return (-mixture.log_prob(mixture.sample((n,))).mean() / math.log(2)).item()


@pytest.mark.parametrize("separation", [0.0, 0.5, 1.5, 4.0])
def test_bounds_sandwich_monte_carlo_entropy(separation):
    weights = torch.tensor([0.2, 0.5, 0.3], dtype=torch.float64)
    means = separation * torch.tensor([[0.0, 0.0], [1.0, 0.5], [-0.5, 1.0]], dtype=torch.float64)
    a = torch.tensor(
        [[[1.0, 0.3], [0.0, 0.6]], [[0.5, 0.0], [0.2, 1.2]], [[0.8, -0.4], [0.0, 0.7]]]
    )
    covariances = (a @ a.mT + 0.05 * torch.eye(2)).to(torch.float64)
    bounds = gaussian_mixture_entropy_bounds(weights, means, covariances)
    truth = monte_carlo_entropy_bits(weights, means, covariances)
    assert bounds.conditional.item() <= bounds.lower.item() + 1e-9
    assert bounds.lower.item() <= truth + 0.01
    assert truth <= bounds.upper.item() + 0.01
    assert (
        bounds.upper.item()
        <= bounds.conditional.item() + Categorical(weights).entropy().item() / math.log(2) + 1e-9
    )


def test_bounds_exact_for_single_component():
    cov = torch.tensor([[[2.0, 0.5], [0.5, 1.0]]], dtype=torch.float64)
    means = torch.zeros(1, 2, dtype=torch.float64)
    bounds = gaussian_mixture_entropy_bounds(torch.ones(1), means, cov)
    exact = 0.5 * (2 * math.log2(2 * math.pi * math.e) + math.log2(torch.linalg.det(cov[0]).item()))
    for value in bounds:
        assert value.item() == pytest.approx(exact, abs=1e-9)


def test_far_apart_components_add_log2_k():
    means = torch.tensor([[0.0], [1e3], [2e3], [3e3]])
    bounds = gaussian_mixture_entropy_bounds(torch.full((4,), 0.25), means, torch.ones(4, 1))
    assert bounds.lower.item() == pytest.approx(bounds.conditional.item() + 2.0, abs=1e-6)
    assert bounds.upper.item() == pytest.approx(bounds.conditional.item() + 2.0, abs=1e-6)


def test_diagonal_and_full_covariances_agree():
    weights = torch.rand(6, 3)
    means = torch.randn(6, 3, 4)
    variances = torch.rand(6, 3, 4) + 0.1
    diagonal = gaussian_mixture_entropy_bounds(weights, means, variances)
    full = gaussian_mixture_entropy_bounds(weights, means, torch.diag_embed(variances))
    for a, b in zip(diagonal, full):
        assert a.shape == (6,)
        assert torch.allclose(a, b, atol=1e-5)


def test_fit_from_samples_matches_member_gaussians():
    samples = torch.randn(3, 400, 5, 2) + torch.tensor([0.0, 3.0, 6.0]).view(3, 1, 1, 1)
    bounds = fit_gaussian_mixture_entropy_bounds(samples)
    member_entropy = gaussian_entropy(samples.transpose(0, 1), joint=True).mean(dim=0)
    assert bounds.lower.shape == (5,)
    # the diagonal fit of independent coordinates matches the joint Gaussian fit closely
    assert torch.allclose(bounds.conditional, member_entropy, atol=0.05)
    assert (bounds.lower <= bounds.upper + 1e-6).all()
    full = fit_gaussian_mixture_entropy_bounds(samples, full_covariance=True)
    assert torch.allclose(full.conditional, member_entropy, atol=1e-4)


def test_degenerate_components_stay_finite():
    bounds = fit_gaussian_mixture_entropy_bounds(torch.zeros(2, 10, 3))
    for value in bounds:
        assert torch.isfinite(value)

"""The ELBO's pure functions against torch.distributions."""

from __future__ import annotations

import pytest
import torch
from torch.distributions import Normal, kl_divergence

from rcvae_torchrl.objectives import free_bits, gaussian_kl, gaussian_nll, masked_mean


def test_gaussian_nll_matches_torch():
    g = torch.Generator().manual_seed(0)
    x, mean = torch.randn(2, 3, 4, generator=g), torch.randn(2, 3, 4, generator=g)
    std = torch.rand(2, 3, 4, generator=g) + 0.1
    torch.testing.assert_close(gaussian_nll(x, mean, std), -Normal(mean, std).log_prob(x))


def test_gaussian_kl_matches_torch_and_vanishes_on_equal_arguments():
    g = torch.Generator().manual_seed(1)
    mq, mp = torch.randn(5, 3, generator=g), torch.randn(5, 3, generator=g)
    sq, sp = torch.rand(5, 3, generator=g) + 0.1, torch.rand(5, 3, generator=g) + 0.1
    want = kl_divergence(Normal(mq, sq), Normal(mp, sp))
    torch.testing.assert_close(gaussian_kl(mq, sq, mp, sp), want)
    assert gaussian_kl(mq, sq, mq, sq).abs().max() < 1e-6


def test_free_bits_clamps_per_element_and_is_identity_at_zero():
    kl = torch.tensor([0.1, 0.5, 2.0], requires_grad=True)
    clamped = free_bits(kl, 1.0)
    assert clamped.tolist() == [1.0, 1.0, 2.0]
    clamped.sum().backward()
    assert kl.grad.tolist() == [0.0, 0.0, 1.0]  # no gradient below the free nats
    assert free_bits(kl, 0.0) is kl


def test_masked_mean_counts_only_valid_entries():
    x = torch.tensor([[1.0, 2.0, 100.0], [4.0, 100.0, 100.0]])
    mask = torch.tensor([[True, True, False], [True, False, False]])
    torch.testing.assert_close(masked_mean(x, mask, (1,)), torch.tensor([1.5, 4.0]))
    torch.testing.assert_close(masked_mean(x, None, (0, 1)), x.mean())
    empty = masked_mean(x, torch.zeros_like(mask), (1,))
    assert empty.tolist() == [0.0, 0.0]


@pytest.mark.parametrize("shape", [(2, 2), (3, 2), (1, 2, 3), (2,)])
def test_masked_mean_names_a_mask_that_does_not_broadcast(shape):
    x = torch.zeros(2, 3)
    with pytest.raises(
        ValueError,
        match=rf"mask: expected a shape that broadcasts to x's \(2, 3\), got \({shape[0]}",
    ):
        masked_mean(x, torch.ones(shape, dtype=torch.bool), (1,))
    row = masked_mean(torch.tensor([[1.0, 2.0, 3.0]] * 2), torch.tensor([True, False, True]), (1,))
    assert row.tolist() == [2.0, 2.0]  # a mask that broadcasts is taken as before

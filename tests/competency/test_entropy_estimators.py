"""Entropy estimators against closed-form truths (bits)."""

import math

import numpy as np
import pytest
import torch

from rcvae_torchrl.competency import _binning, gaussian_entropy, histogram_entropy, knn_entropy

LOG2_2PIE = math.log2(2 * math.pi * math.e)


def gaussian_bits(variance: float, dim: int = 1) -> float:
    """Differential entropy of an isotropic Gaussian, in bits."""
    return 0.5 * dim * (LOG2_2PIE + math.log2(variance))


def reference_histogram_entropy(x: np.ndarray, width: float) -> float:
    """Plug-in entropy of floor(x / width) for a 1-D sample, from np.unique."""
    _, counts = np.unique(np.floor(x / width), return_counts=True)
    p = counts / counts.sum()
    return float(-(p * np.log2(p)).sum())


def test_histogram_uniform_matches_log2_of_bin_count():
    x = torch.rand(100_000, 2, 3)
    h = histogram_entropy(x, 0.1)
    assert h.shape == (2, 3)
    assert torch.allclose(h, torch.full_like(h, math.log2(10)), atol=0.01)


def test_histogram_gaussian_matches_discretised_differential_entropy():
    sigma = torch.tensor([0.5, 1.0, 3.0])
    width = 0.1
    x = torch.randn(200_000, 3) * sigma
    expected = torch.tensor([gaussian_bits(s**2) - math.log2(width) for s in sigma.tolist()])
    assert torch.allclose(histogram_entropy(x, width), expected, atol=0.02)


def test_histogram_per_dimension_width():
    x = torch.rand(100_000, 2) * torch.tensor([1.0, 4.0])
    h = histogram_entropy(x, torch.tensor([0.25, 0.5]))
    assert torch.allclose(h, torch.tensor([2.0, 3.0]), atol=0.01)


def test_histogram_matches_numpy_reference_with_negative_values():
    x = torch.randn(500, 4, 2, dtype=torch.float64) * 3 - 1
    h = histogram_entropy(x, 0.7)
    for b in range(4):
        for d in range(2):
            ref = reference_histogram_entropy(x[:, b, d].numpy(), 0.7)
            assert h[b, d].item() == pytest.approx(ref, abs=1e-9)


def test_histogram_grid_is_anchored_at_zero():
    # 0.09 and 0.11 straddle the edge at 0.1: two bins, one bit. A grid anchored at the data's
    # minimum would put both into [0.09, 0.19) and give 0.
    assert histogram_entropy(torch.tensor([[0.09], [0.11]]), 0.1).item() == pytest.approx(1.0)
    assert histogram_entropy(torch.tensor([[0.11], [0.19]]), 0.1).item() == 0.0


def test_histogram_degenerate_samples_give_zero():
    h = histogram_entropy(torch.full((50, 3, 2), 1.2345), 0.1)
    assert torch.equal(h, torch.zeros(3, 2))


@pytest.mark.parametrize(
    "factors",
    [{"SORT_FACTOR": 0}, {"DENSE_FACTOR": 0}, {"DENSE_FACTOR": 10**9}],
    ids=["ranks by sorting", "occupied bins only", "every bin spanned"],
)
def test_histogram_chunking_and_counting_strategies_agree(monkeypatch, factors):
    x = torch.randn(300, 7, 5, 3)
    reference = histogram_entropy(x, 0.05)
    assert torch.equal(histogram_entropy(x, 0.05, chunk_elements=1), reference)
    for name, value in factors.items():
        monkeypatch.setattr(_binning, name, value)
    assert torch.allclose(histogram_entropy(x, 0.05), reference, atol=1e-6)


def test_gaussian_entropy_per_dimension_and_joint():
    cov = torch.tensor([[2.0, 0.8], [0.8, 1.0]], dtype=torch.float64)
    x = torch.distributions.MultivariateNormal(torch.zeros(2, dtype=torch.float64), cov).sample(
        (200_000,)
    )
    per_dim = gaussian_entropy(x)
    joint = gaussian_entropy(x, joint=True)
    expected_joint = 0.5 * (2 * LOG2_2PIE + math.log2(torch.linalg.det(cov).item()))
    assert per_dim.tolist() == pytest.approx([gaussian_bits(2.0), gaussian_bits(1.0)], abs=0.01)
    assert joint.item() == pytest.approx(expected_joint, abs=0.01)
    assert joint.item() < per_dim.sum().item() - 0.2  # correlation lowers the joint entropy


def test_gaussian_entropy_with_bin_width_matches_histogram():
    x = torch.randn(200_000, 2) * 2
    assert torch.allclose(gaussian_entropy(x, bin_width=0.1), histogram_entropy(x, 0.1), atol=0.02)


def test_gaussian_entropy_degenerate_is_finite():
    x = torch.full((40, 3), 2.0)
    h = gaussian_entropy(x, min_variance=1e-12)
    assert torch.allclose(h, torch.full((3,), gaussian_bits(1e-12)))
    assert torch.isfinite(gaussian_entropy(x, joint=True)).all()
    assert torch.equal(gaussian_entropy(x, bin_width=0.1), torch.zeros(3))
    assert torch.equal(gaussian_entropy(x, joint=True, bin_width=0.1), torch.tensor(0.0))


def test_knn_entropy_gaussian_and_uniform():
    gaussian = torch.randn(2000, 8, 2)
    assert knn_entropy(gaussian, k=3).mean().item() == pytest.approx(
        gaussian_bits(1.0, 2), abs=0.05
    )
    uniform = torch.rand(2000, 8, 1) * 2.0  # h = 1 bit
    assert knn_entropy(uniform, k=3).mean().item() == pytest.approx(1.0, abs=0.05)


def test_knn_bias_shrinks_with_sample_size():
    # Uniform on the unit square (h = 0 bits): the boundary bias is positive and decays with N.
    bias = [knn_entropy(torch.rand(n, 32, 2), k=3).mean().item() for n in (25, 1000)]
    assert bias[0] > 0.15
    assert abs(bias[1]) < bias[0] / 3


def test_knn_chunking_invariant():
    x = torch.randn(100, 6, 2)
    assert torch.allclose(knn_entropy(x, chunk_elements=1), knn_entropy(x))


def test_knn_duplicates_and_degenerate_stay_finite():
    x = torch.randn(200, 2)
    with_duplicates = torch.cat([x, x[:50]])
    assert torch.isfinite(knn_entropy(with_duplicates)).all()
    degenerate = torch.zeros(100, 3, 2)
    h = knn_entropy(degenerate)
    assert torch.isfinite(h).all() and (h < -50).all()
    assert torch.equal(knn_entropy(degenerate, bin_width=0.1), torch.zeros(3))


def test_a_python_number_width_is_taken_at_float64():
    """0.1 went through torch's default float32 (0.10000000149), and float64 samples on the
    bins' edges k * 0.1 fell a bin low: 0 and 0.1 shared a bin."""
    samples = (torch.arange(10, dtype=torch.float64) * 0.1)[:, None]
    got = histogram_entropy(samples, 0.1)
    assert got.item() == pytest.approx(math.log2(10), abs=1e-12)
    torch.testing.assert_close(
        got, histogram_entropy(samples, torch.tensor(0.1, dtype=torch.float64))
    )

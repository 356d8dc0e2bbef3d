"""Total / aleatoric / epistemic decompositions (paper equations 2 and 3)."""

import math

import pytest
import torch

from rcvae_torchrl.competency import (
    decompose_uncertainty,
    gaussian_entropy,
    histogram_entropy,
    knn_entropy,
    variance_decomposition,
)

E = 4
ESTIMATOR_CASES = [
    ("histogram", {"bin_width": 0.25}, (3, 2)),
    ("gaussian", {}, (3, 2)),
    ("gaussian", {"joint": True}, (3,)),
    ("knn", {"k": 3}, (3,)),
    ("mixture", {}, (3,)),
    ("mixture", {"bound": "lower"}, (3,)),
]


@pytest.mark.parametrize(("estimator", "args", "shape"), ESTIMATOR_CASES)
def test_identical_members_have_no_epistemic_uncertainty(estimator, args, shape):
    samples = torch.randn(E, 1000, 3, 2)
    u = decompose_uncertainty(samples, estimator, **args)
    assert u.total.shape == u.aleatoric.shape == u.epistemic.shape == shape
    tolerance = 0.1 if estimator == "knn" else 0.03
    assert u.epistemic.abs().max().item() < tolerance
    assert u.aleatoric.min().item() > 0.5  # the aleatoric part carries the entropy


MIXTURE_ESTIMATOR_CASES = [case for case in ESTIMATOR_CASES if case[0] != "gaussian"]


@pytest.mark.parametrize(("estimator", "args", "shape"), MIXTURE_ESTIMATOR_CASES)
def test_separated_members_have_log2_e_epistemic_bits(estimator, args, shape):
    offsets = 100.0 * torch.arange(E, dtype=torch.float32).view(E, 1, 1, 1)
    samples = 0.3 * torch.randn(E, 500, 3, 2) + offsets
    u = decompose_uncertainty(samples, estimator, **args)
    assert torch.allclose(u.epistemic, torch.full(shape, math.log2(E)), atol=0.01)


def test_gaussian_epistemic_is_half_log_variance_ratio():
    # Members N(μ_m, 1) with μ = (-1, 1): pooled variance 2, so epistemic = ½·log2(2) = ½ bit
    # (a moment-matched Gaussian, not the mixture entropy: it grows with the separation).
    samples = torch.randn(2, 50_000, 1, 3)
    samples = (samples - samples.mean(dim=1, keepdim=True)) / samples.std(dim=1, keepdim=True)
    samples = samples + torch.tensor([-1.0, 1.0]).view(2, 1, 1, 1)
    u = decompose_uncertainty(samples, "gaussian")
    assert torch.allclose(u.epistemic, torch.full((1, 3), 0.5), atol=1e-3)
    # Jointly the shift is along (1, 1, 1): pooled covariance I + 11ᵀ, det 4, so 1 bit.
    joint = decompose_uncertainty(samples, "gaussian", joint=True)
    assert joint.epistemic.item() == pytest.approx(1.0, abs=0.02)


def test_histogram_decomposition_matches_direct_entropies():
    samples = torch.randn(3, 200, 7, 4) * torch.tensor([1.0, 1.5, 2.0]).view(3, 1, 1, 1)
    u = decompose_uncertainty(samples, bin_width=torch.tensor([0.1, 0.2, 0.3, 0.4]))
    width = torch.tensor([0.1, 0.2, 0.3, 0.4])
    total = histogram_entropy(samples.reshape(600, 7, 4), width)
    aleatoric = torch.stack([histogram_entropy(s, width) for s in samples]).mean(dim=0)
    assert torch.allclose(u.total, total, atol=1e-5)
    assert torch.allclose(u.aleatoric, aleatoric, atol=1e-5)
    assert torch.allclose(u.epistemic, total - aleatoric, atol=1e-5)


def test_histogram_epistemic_is_a_bounded_jensen_shannon_divergence():
    samples = torch.randn(5, 50, 40, 3) * torch.rand(5, 1, 40, 3) * 3 + torch.randn(5, 1, 40, 3)
    u = decompose_uncertainty(samples, bin_width=0.3)
    assert (u.epistemic >= 0).all()
    assert (u.epistemic <= math.log2(5)).all()
    assert torch.equal(u.epistemic, (u.total - u.aleatoric).clamp(0, math.log2(5)))


def test_histogram_chunking_invariant():
    samples = torch.randn(3, 40, 11, 3)
    reference = decompose_uncertainty(samples, bin_width=0.2)
    chunked = decompose_uncertainty(samples, bin_width=0.2, chunk_elements=1)
    assert torch.equal(reference.total, chunked.total)
    assert torch.equal(reference.aleatoric, chunked.aleatoric)


def test_degenerate_samples_give_zero_and_never_nan():
    samples = torch.full((3, 20, 4, 2), 0.7)
    u = decompose_uncertainty(samples, bin_width=0.1)
    for value in u.as_dict().values():
        assert torch.equal(value, torch.zeros(4, 2))
    for estimator in ("gaussian", "knn", "mixture"):
        for value in decompose_uncertainty(samples, estimator).as_dict().values():
            assert torch.isfinite(value).all()


def test_variance_decomposition_adds_up_and_matches_construction():
    member_means = torch.tensor([-2.0, 0.0, 2.0]).view(3, 1, 1, 1)
    member_std = torch.tensor([0.5, 1.0, 1.5]).view(3, 1, 1, 1)
    samples = member_means + member_std * torch.randn(3, 20_000, 2, 1)
    v = variance_decomposition(samples)
    assert v.total.shape == (2, 1)
    assert torch.allclose(v.total, v.aleatoric + v.epistemic, atol=1e-5)
    assert torch.allclose(v.aleatoric, torch.full((2, 1), (0.25 + 1 + 2.25) / 3), atol=0.03)
    assert torch.allclose(v.epistemic, torch.full((2, 1), 8 / 3), atol=0.02)


def test_the_shuffle_correction_with_one_sample_per_member_is_refused():
    """A trial's study with one sample per member: the shuffle correction made every epistemic
    part 0 by construction, and nothing said so."""
    from rcvae_torchrl.competency.decomposition import check_shuffle_samples

    samples = torch.randn(3, 1, 4, 2, generator=torch.Generator().manual_seed(0))
    message = r"samples_per_member: the shuffle correction \(bias_correction='shuffle'\) needs"
    with pytest.raises(ValueError, match=message + r" at least 2 samples per member, got 1"):
        decompose_uncertainty(samples, "histogram", bin_width=0.1, bias_correction="shuffle")
    decompose_uncertainty(samples, "histogram", bin_width=0.1)  # no correction: as it is
    check_shuffle_samples("shuffle", 2)
    check_shuffle_samples("none", 1)


def test_knn_epistemic_stays_within_the_mutual_informations_bounds_in_many_dimensions():
    """A quadruped trial (78 dimensions): the knn estimator's bias differs between the E·N
    pooled samples and a member's N, and identical members read -14.7 epistemic bits. The
    split is clamped to [0, log2 E]: no negative doubt, no more than E members can hold."""
    g = torch.Generator().manual_seed(0)
    identical = torch.randn(E, 100, 2, 40, generator=g)
    raw = decompose_uncertainty(identical, "knn", k=3)
    members = torch.stack([knn_entropy(m, k=3) for m in identical]).mean(0)
    assert (raw.total - members).max() < -0.5  # the bias, as the trial met it
    assert torch.equal(raw.epistemic, torch.zeros(2))
    assert torch.equal(raw.aleatoric, raw.total)  # the pooled total kept, all of it aleatoric
    apart = identical + 50.0 * torch.arange(E, dtype=torch.float32).view(E, 1, 1, 1)
    far = decompose_uncertainty(apart, "knn", k=3)
    assert torch.allclose(far.epistemic, torch.full((2,), math.log2(E)), atol=0.05)


def test_variance_decomposition_needs_two_samples_per_member():
    """With one sample a member's variance is 0: aleatoric read 0 without a word."""
    from rcvae_torchrl.competency import variance_decomposition

    with pytest.raises(ValueError, match=r"samples: expected at least 2 samples per member"):
        variance_decomposition(torch.randn(3, 1, 2))
    assert variance_decomposition(torch.randn(3, 2, 2)).aleatoric.shape == (2,)


@pytest.mark.parametrize(
    ("estimator", "args"),
    [("gaussian", {"bin_width": 1.0}), ("gaussian", {"bin_width": 1.0, "joint": True})],
)
def test_a_clamped_epistemic_part_leaves_the_parts_adding_up_to_the_total(estimator, args):
    """With a bin width each member's discretised Gaussian entropy is clamped at 0, and their
    mean can exceed the pooled one's: a narrow member (entropy clamped up to 0) beside a wide
    one. The epistemic part is clamped at 0 and the pooled total kept, so aleatoric is what is
    left of it (it read 0.403 bits against a total of 0.305)."""
    g = torch.Generator().manual_seed(0)
    samples = torch.randn(2, 20_000, 1, generator=g, dtype=torch.float64)
    samples[0] *= 0.421
    samples[1] *= 1e-3
    u = decompose_uncertainty(samples, estimator, **args)
    pooled = gaussian_entropy(samples.reshape(-1, 1), **args)
    torch.testing.assert_close(u.total, pooled)
    assert float(u.total.sum()) > 0.25  # the pooled discretised entropy is not clamped
    assert (u.epistemic == 0).all()
    torch.testing.assert_close(u.aleatoric + u.epistemic, u.total)
    wide = decompose_uncertainty(samples, estimator, **{**args, "bin_width": 0.01})
    members = torch.stack([gaussian_entropy(m, **{**args, "bin_width": 0.01}) for m in samples])
    torch.testing.assert_close(wide.aleatoric, members.mean(0))  # unclamped: as before
    torch.testing.assert_close(wide.epistemic, wide.total - members.mean(0))


def test_a_clamped_knn_split_adds_up_to_the_total():
    samples = torch.randn(1, 300, 6, generator=torch.Generator().manual_seed(1)).expand(4, -1, -1)
    samples = samples + 1e-3 * torch.randn(4, 300, 6, generator=torch.Generator().manual_seed(2))
    u = decompose_uncertainty(samples, "knn")
    assert (u.epistemic >= 0).all() and (u.epistemic <= 2).all()
    torch.testing.assert_close(u.aleatoric + u.epistemic, u.total)

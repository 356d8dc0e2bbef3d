"""The vectorised histogram decomposition against a straightforward column-by-column reference.

The reference counts every column's bins with ``torch.unique``, puts ended samples in a bin of
their own and applies the shuffle correction to the same permutations (drawn from the same
generator in the same order), so the two must agree to float64 round-off on any input: ties,
values on bin edges, ended samples, columns spanning far more bins than they hold samples.
"""

import math

import pytest
import torch

from rcvae_torchrl.competency import _binning, decompose_uncertainty, histogram_entropy


def _entropy_bits(labels: torch.Tensor) -> float:
    """Plug-in entropy in bits of the discrete values in a 1-D tensor."""
    _, counts = torch.unique(labels, return_counts=True)
    p = counts.to(torch.float64) / labels.numel()
    return float(-(p * torch.log2(p)).sum())


def _reference(samples, width, ended, shuffles, generator):
    """Loop over columns: (total, aleatoric, epistemic) ``[*batch, D]`` in float64."""
    members, n, dim = samples.shape[0], samples.shape[1], samples.shape[-1]
    width = torch.as_tensor(width, dtype=samples.dtype).expand(dim)
    ids = torch.floor(samples / width).to(torch.int64).reshape(members * n, -1, dim)
    if ended is not None:
        # one bin below every bin the samples reach: the terminal bin of ended trajectories
        flat_ended = ended.reshape(members * n, -1, 1).expand_as(ids)
        ids = torch.where(flat_ended, ids.min() - 1, ids)
    perms = [torch.randperm(members * n, generator=generator) for _ in range(shuffles)]
    out = torch.zeros(3, ids.shape[1], dim, dtype=torch.float64)
    for b in range(ids.shape[1]):
        for d in range(dim):
            column = ids[:, b, d]
            total = _entropy_bits(column)
            mean_member = sum(_entropy_bits(m) for m in column.view(members, n)) / members
            epistemic = total - mean_member
            if perms:
                null = 0.0
                for perm in perms:
                    shuffled = column[perm].view(members, n)
                    null += total - sum(_entropy_bits(m) for m in shuffled) / members
                epistemic = min(max(epistemic - null / len(perms), 0.0), math.log2(members))
            out[:, b, d] = torch.tensor([total, total - epistemic, epistemic], dtype=torch.float64)
    return out.reshape(3, *samples.shape[2:])


def _tied_samples(shape, width, generator):
    """Values on a grid of half a bin: many ties, half of them exactly on bin edges.

    ``width`` is a power of two, so the edges are exact in binary floating point."""
    steps = torch.randint(-12, 12, shape, generator=generator).to(torch.float64)
    return steps * (width / 2)


@pytest.mark.parametrize("with_ended", [False, True])
@pytest.mark.parametrize("shuffles", [0, 3])
def test_histogram_decomposition_equals_column_by_column_reference(with_ended, shuffles):
    gen = torch.Generator().manual_seed(11)
    width = torch.tensor([0.5, 0.25, 0.125])
    samples = torch.cat(
        [
            _tied_samples((3, 20, 4, 2, 3), 0.5, gen),
            torch.randn(3, 20, 4, 2, 3, generator=gen, dtype=torch.float64),
        ],
        dim=2,
    )
    ended = torch.rand(3, 20, 8, 2, generator=gen) < 0.3 if with_ended else None
    ended_args = {} if ended is None else {"ended": ended}
    shuffle_args = {"bias_correction": "shuffle", "shuffles": shuffles} if shuffles else {}
    got = decompose_uncertainty(
        samples,
        bin_width=width,
        generator=torch.Generator().manual_seed(5),
        chunk_elements=97,  # several chunks of uneven size
        **ended_args,
        **shuffle_args,
    )
    want = _reference(samples, width, ended, shuffles, torch.Generator().manual_seed(5))
    for name, expected in zip(("total", "aleatoric", "epistemic"), want):
        torch.testing.assert_close(getattr(got, name), expected, atol=1e-12, rtol=0)


@pytest.mark.parametrize(
    "factors",
    [{"SORT_FACTOR": 0}, {"SORT_FACTOR": 10**9}, {"SORT_FACTOR": 10**9, "DENSE_FACTOR": 10**9}],
    ids=["ranks by sorting", "occupied bins only", "every bin spanned"],
)
@pytest.mark.parametrize("shuffles", [0, 2])
def test_every_counting_path_gives_the_reference(monkeypatch, factors, shuffles):
    # With shuffles the codes are reused, so they are never left spanning every bin.
    for name, value in factors.items():
        monkeypatch.setattr(_binning, name, value)
    gen = torch.Generator().manual_seed(2)
    samples = torch.randn(2, 15, 6, 2, generator=gen, dtype=torch.float64) * 50.0
    samples[:, :5] = samples[:, :1]  # a third of the samples tied
    ended = torch.rand(2, 15, 6, generator=gen) < 0.2
    got = decompose_uncertainty(
        samples,
        bin_width=1 / 128,  # thousands of bins spanned by 30 samples per column
        ended=ended,
        bias_correction="shuffle" if shuffles else "none",
        shuffles=max(shuffles, 1),
        generator=torch.Generator().manual_seed(0),
    )
    want = _reference(samples, 1 / 128, ended, shuffles, torch.Generator().manual_seed(0))
    torch.testing.assert_close(got.total, want[0], atol=1e-12, rtol=0)
    torch.testing.assert_close(got.epistemic, want[2], atol=1e-12, rtol=0)


def test_ended_samples_far_outside_the_live_range_do_not_widen_the_columns(monkeypatch):
    # Only the live samples decide how many cells a column owns: 1e9 on an ended sample must
    # not make the counting compress to ranks (the in-place path is forced to raise otherwise).
    def no_ranks(offsets):
        raise AssertionError("compressed to ranks although the live samples span few bins")

    monkeypatch.setattr(_binning, "_ranks", no_ranks)
    gen = torch.Generator().manual_seed(4)
    samples = torch.randn(3, 30, 5, 2, generator=gen)
    ended = torch.rand(3, 30, 5, generator=gen) < 0.4
    far = torch.where(ended.unsqueeze(-1), torch.full_like(samples, 1e9), samples)
    got = decompose_uncertainty(far, bin_width=0.5, ended=ended)
    want = _reference(samples.double(), 0.5, ended, 0, None)
    torch.testing.assert_close(got.total, want[0].float(), atol=1e-6, rtol=0)


def test_every_sample_ended_in_a_column_gives_zero_bits():
    samples = torch.randn(2, 10, 3, 1)
    ended = torch.zeros(2, 10, 3, dtype=torch.bool)
    ended[:, :, 1] = True
    u = decompose_uncertainty(samples, bin_width=0.1, ended=ended)
    assert float(u.total[1, 0]) == 0.0
    assert float(u.epistemic[1, 0]) == pytest.approx(0.0, abs=1e-6)
    assert float(u.total[0, 0]) > 0.0


def test_histogram_entropy_equals_reference_per_column():
    gen = torch.Generator().manual_seed(9)
    samples = _tied_samples((40, 3, 2), 0.25, gen)
    want = torch.tensor(
        [[_entropy_bits(torch.floor(samples[:, b, d] / 0.25)) for d in range(2)] for b in range(3)],
        dtype=torch.float64,
    )
    torch.testing.assert_close(histogram_entropy(samples, 0.25), want, atol=1e-12, rtol=0)


def test_shuffled_labels_put_each_permuted_block_in_one_group():
    perms = torch.stack([torch.tensor([4, 0, 5, 1, 3, 2]), torch.arange(6)])
    labels = _binning.shuffled_labels(perms, n=2)
    # perm [4, 0, 5, 1, 3, 2] cut into groups of 2: {4, 0} -> 0, {5, 1} -> 1, {3, 2} -> 2
    assert labels.tolist() == [[0, 1, 2, 2, 0, 1], [0, 0, 1, 1, 2, 2]]


@pytest.mark.parametrize("scale", [1e19, 1e25])
def test_samples_beyond_the_countable_bins_are_refused(scale):
    """Bin ids beyond int64 would put every sample in one bin: members that disagree
    completely would report 0 bits. Refused, naming bin_width."""
    samples = torch.cat([torch.rand(1, 50, 1, 1) + 1, -torch.rand(1, 50, 1, 1) - 1]) * scale
    with pytest.raises(ValueError, match=r"bin_width: expected samples within 2\*\*61 bin"):
        decompose_uncertainty(samples, bin_width=0.1)
    with pytest.raises(ValueError, match=r"bin_width: .* bin width down to 1e-30"):
        histogram_entropy(torch.randn(50, 1, 1), bin_width=1e-30)
    # the same layout with bins of its own scale: one bit of disagreement
    out = decompose_uncertainty(samples, bin_width=0.1 * scale)
    assert float(out.epistemic) == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize("correction", ["none", "shuffle"])
def test_samples_that_share_a_bin_give_no_bits_below_zero(correction):
    # log2 50 - 50·log2 50 / 50 rounds to -4.4e-16 in float64: an entropy never goes below 0
    samples = torch.full((5, 50, 3, 7, 2), 0.25, dtype=torch.float64)
    samples[..., 1] += torch.arange(5, dtype=torch.float64).view(5, 1, 1, 1)
    parts = decompose_uncertainty(samples, "histogram", bin_width=0.5, bias_correction=correction)
    assert bool((parts.aleatoric >= 0).all()) and bool((parts.total >= 0).all())
    torch.testing.assert_close(parts.aleatoric[..., 0], torch.zeros(3, 7, dtype=torch.float64))
    if correction == "none":  # (the shuffles' divergence is moved to the aleatoric part)
        torch.testing.assert_close(parts.aleatoric, torch.zeros_like(parts.aleatoric))
    torch.testing.assert_close(parts.total[..., 0], torch.zeros(3, 7, dtype=torch.float64))
    expected = torch.full((3, 7), math.log2(5), dtype=torch.float64)
    torch.testing.assert_close(parts.total[..., 1], expected)

"""The paired difference interval: a published table's figures, its coverage where a normal
interval has none, and refused inputs."""

from __future__ import annotations

import pytest
import torch

from rcvae_torchrl.competency import binomial_interval, paired_difference_interval


def _pairs(both: int, a_only: int, b_only: int, neither: int) -> tuple[torch.Tensor, ...]:
    a = [True] * (both + a_only) + [False] * (b_only + neither)
    b = [True] * both + [False] * a_only + [True] * b_only + [False] * neither
    return torch.tensor(a), torch.tensor(b)


def test_a_published_table():
    """The 2x2 paired table (59, 6; 16, 80): difference -0.0621, 95 % interval -0.1186 to
    -0.0046 (Newcombe's method 10, as statistics texts on contingency tables give it)."""
    low, high = paired_difference_interval(*_pairs(59, 6, 16, 80))
    assert (float(low), float(high)) == pytest.approx((-0.1186, -0.0046), abs=5e-5)
    # the pairs' order does not matter, nor do batch dimensions
    a, b = _pairs(59, 6, 16, 80)
    order = torch.randperm(len(a), generator=torch.Generator().manual_seed(0))
    batched = paired_difference_interval(torch.stack([a, a[order]]), torch.stack([b, b[order]]))
    torch.testing.assert_close(batched[0], low.expand(2))
    torch.testing.assert_close(batched[1], high.expand(2))


def test_swapping_the_agents_mirrors_it():
    a, b = _pairs(30, 9, 2, 19)
    low, high = paired_difference_interval(a, b)
    mirrored = paired_difference_interval(b, a)
    torch.testing.assert_close(mirrored[0], -high)
    torch.testing.assert_close(mirrored[1], -low)


def test_where_every_pair_agrees_it_keeps_a_width():
    """All successes: no difference seen, but 24 pairs cannot rule one out; the interval is
    the Wilson interval's gap from 1 on either side (no correlation term: margins are empty)."""
    a, b = _pairs(24, 0, 0, 0)
    low, high = paired_difference_interval(a, b)
    wilson_low, _ = binomial_interval(torch.tensor(24), 24, method="wilson")
    gap = 1 - float(wilson_low)
    assert (float(low), float(high)) == pytest.approx((-gap, gap), rel=1e-6)
    assert gap > 0.1


def test_independent_draws_are_covered_at_about_the_level():
    """Independent pairs with P(a) = 0.7, P(b) = 0.6: of 2000 draws of 50 pairs, the 95 %
    interval holds the true difference 0.1 in 93-97 %."""
    g = torch.Generator().manual_seed(1)
    a = torch.rand(2000, 50, generator=g) < 0.7
    b = torch.rand(2000, 50, generator=g) < 0.6
    low, high = paired_difference_interval(a, b)
    covered = float(((low <= 0.1) & (high >= 0.1)).double().mean())
    assert 0.93 <= covered <= 0.97


@pytest.mark.parametrize(
    ("a", "b", "match"),
    [
        (torch.ones(3), torch.ones(3, dtype=torch.bool), r"a: .* got a torch.float32 tensor"),
        (torch.ones(3, dtype=torch.bool), [True] * 3, "b: expected bool outcomes .* got list"),
        (torch.ones(3, dtype=torch.bool), torch.ones(4, dtype=torch.bool), "b: expected the shape"),
        (torch.ones(0, dtype=torch.bool), torch.ones(0, dtype=torch.bool), "n >= 1"),
    ],
)
def test_bad_outcomes_are_refused_by_name(a, b, match):
    with pytest.raises((TypeError, ValueError), match=match):
        paired_difference_interval(a, b)
    with pytest.raises(ValueError, match="confidence"):
        paired_difference_interval(
            torch.ones(3, dtype=torch.bool), torch.ones(3, dtype=torch.bool), 1.5
        )

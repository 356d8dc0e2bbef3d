"""The conformal level: a new draw stays at or below it with the probability asked for."""

import pytest
import torch

from rcvae_torchrl._conformal import conformal_level


def test_the_level_is_the_ceil_n_plus_1_q_th_smallest_and_too_few_values_keep_their_largest():
    values = torch.arange(20.0).flip(0)  # order does not matter
    assert conformal_level(values, 0.95) == (19.0, 0.95)  # ceil(21 x 0.95) = 20th
    assert conformal_level(values, 0.5) == (10.0, 0.5)  # ceil(10.5) = 11th
    level, kept = conformal_level(torch.arange(10.0), 0.95)  # 10 values cover at most 10/11
    assert level == 9.0 and kept == pytest.approx(10 / 11)
    with pytest.raises(ValueError, match=r"^values: expected at least one value, got none$"):
        conformal_level(torch.empty(0), 0.9)


def test_a_new_draw_exceeds_the_level_no_more_often_than_asked_where_a_quantile_would():
    g = torch.Generator().manual_seed(0)
    trials, n, q = 4000, 20, 0.95
    samples, new = torch.randn(trials, n, generator=g), torch.randn(trials, generator=g)
    conformal = torch.tensor([conformal_level(row, q)[0] for row in samples])
    interpolated = samples.quantile(q, dim=1)
    # expected 1 - 20/21 = 0.048 and about 0.09; binomial sd over 4000 trials about 0.004
    assert 0.035 < float((new > conformal).double().mean()) < 0.06
    assert float((new > interpolated).double().mean()) > 0.075


def test_a_quantile_outside_0_1_and_empty_spreads_are_named():
    """A quantile of 0 took the largest value (as if it were the highest); NaN reached ceil."""
    from rcvae_torchrl._spread import spread_steps

    values = torch.arange(10.0)
    for quantile in (0.0, -0.5, 1.5, float("nan")):
        with pytest.raises(ValueError, match=r"quantile: expected a float in \(0, 1\], got"):
            conformal_level(values, quantile)
    assert conformal_level(values, 1.0) == (9.0, 10 / 11)
    with pytest.raises(ValueError, match="length: expected a positive integer, got 0"):
        spread_steps(0, 5)
    with pytest.raises(ValueError, match="count: expected a positive integer, got 0"):
        spread_steps(10, 0)
    assert spread_steps(10, 3).tolist() == [0, 4, 9]

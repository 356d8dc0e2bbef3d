"""The ensemble's training pass and one-step predictions check their windows first."""

from __future__ import annotations

import math

import pytest
import torch

E, L = 4, 6  # the shared ``ensemble`` fixture: 4 members, obs_dim 5, action_dim 2


def _windows(b: int = 3, length: int = L):
    g = torch.Generator().manual_seed(0)
    return torch.randn(E, b, length, 5, generator=g), torch.rand(E, b, length, 2, generator=g)


@pytest.mark.parametrize("bad", [math.nan, math.inf])
@pytest.mark.parametrize("which", ["observations", "actions", "next_observations"])
def test_non_finite_windows_are_a_value_error(ensemble, bad, which):
    obs, act = _windows()
    args = {"observations": obs, "actions": act, "next_observations": obs.clone()}
    args[which][1, 2, 3, 0] = bad
    with pytest.raises(ValueError, match=rf"^{which}: expected finite values, got"):
        ensemble(args["observations"], args["actions"], next_observations=args["next_observations"])
    if which != "next_observations":
        with pytest.raises(ValueError, match=rf"^{which}: expected finite values"):
            ensemble.predict_next(args["observations"], args["actions"])


@pytest.mark.parametrize(
    ("obs_shape", "act_shape", "match"),
    [
        ((E, 3, L, 4), (E, 3, L, 2), r"^observations: expected shape \[E=4, \*B, L, 5\]"),
        ((E, 3, L, 5), (E, 3, L, 3), r"^actions: expected shape \[E=4, \*B, L, 2\]"),
        ((2, 3, L, 5), (2, 3, L, 2), r"^observations: expected shape \[E=4"),
        ((E, 3, L, 5), (E, 2, L, 2), r"^actions: expected the leading shape"),
        ((E, 3, 1, 5), (E, 3, 1, 2), r"^observations: expected windows of L >= 2 steps"),
        ((L, 5), (L, 2), r"^observations: expected shape .* \(at least 3 dims\)"),
    ],
)
def test_window_shapes_are_checked(ensemble, obs_shape, act_shape, match):
    with pytest.raises(ValueError, match=match):
        ensemble(torch.zeros(obs_shape), torch.zeros(act_shape))


def test_integer_windows_are_a_type_error(ensemble):
    obs, act = _windows()
    with pytest.raises(TypeError, match=r"^observations: expected a floating-point tensor"):
        ensemble(obs.long(), act)


def test_finite_windows_give_finite_outputs(ensemble):
    obs, act = _windows()
    out = ensemble(obs, act)
    assert out.decoder_mean.shape == (E, 3, L - 1, ensemble.config.predicted_dim)
    assert all(bool(torch.isfinite(x).all()) for x in out if x is not None)
    assert ensemble.predict_next(obs, act).shape == (E, 3, L - 1, 5)

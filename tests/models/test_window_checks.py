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


def test_masks_open_loop_steps_and_dtypes_are_taken_as_given_or_refused(ensemble):
    """Nothing is coerced: a float mask, a mask of another length, 2.7 or -3 open-loop
    steps and float64 windows are errors that name them."""
    obs, act = _windows()
    for mask, match in (
        (
            torch.ones(1, 3, L),
            r"^mask: expected a bool mask \[E=4 or 1, \*B, L\] = \[4 or 1, 3, 6\]",
        ),
        (torch.ones(1, 3, L - 1, dtype=torch.bool), r"^mask: expected a bool mask"),
        (torch.ones(2, 3, L, dtype=torch.bool), r"^mask: expected a bool mask"),
    ):
        with pytest.raises(ValueError, match=match):
            ensemble(obs, act, mask=mask)
    for steps in (2.7, -3, "2", True):
        with pytest.raises(ValueError, match=r"^open_loop_steps: expected an integer >= 0"):
            ensemble(obs, act, open_loop_steps=steps)
    with pytest.raises(TypeError, match=r"^observations: expected dtype torch.float32"):
        ensemble(obs.double(), act)
    ensemble(obs, act, mask=torch.ones(1, 3, L, dtype=torch.bool), open_loop_steps=2)


def test_a_step_of_another_layout_is_refused(ensemble):
    hidden = torch.zeros(E, 3, ensemble.carry_dim)
    obs, act = torch.zeros(E, 3, 5), torch.zeros(E, 3, 2)
    assert ensemble.step(hidden, obs, act).observation.shape == (E, 3, 5)
    layout = rf"expected \[E={E}, \*B, {ensemble.carry_dim}\], \[E={E}, \*B, S=5\] and "
    bad = {
        "action width": (hidden, obs, act[..., :1]),  # would broadcast over A = 2
        "members": (hidden[:1], obs[:1], act[:1]),
        "hidden batch": (torch.zeros(E, 2, ensemble.carry_dim), obs, act),
        "hidden width": (hidden[..., :-1], obs, act),
        "action batch": (hidden, obs, torch.zeros(E, 2, 2)),
    }
    for case, inputs in bad.items():
        with pytest.raises(ValueError, match=r"^hidden, obs_prev, action_prev: " + layout):
            ensemble.step(*inputs)
            pytest.fail(case)
    with pytest.raises(TypeError, match=r"^action_prev: expected dtype torch.float32"):
        ensemble.step(hidden, obs, act.double())
    with pytest.raises(TypeError, match=r"^hidden: expected dtype torch.float32"):
        ensemble.step(hidden.double(), obs, act)
    with pytest.raises(TypeError, match=r"^obs_prev: expected a torch.Tensor, got ndarray"):
        ensemble.step(hidden, obs.numpy(), act)


@pytest.mark.parametrize("indices", [[-1], [4], [0.5], [], [[0, 1]]])
def test_members_are_chosen_by_index(ensemble, indices):
    with pytest.raises(ValueError, match=r"^indices: expected"):
        ensemble.select_members(indices)


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

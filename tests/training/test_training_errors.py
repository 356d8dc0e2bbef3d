"""The self-checks, the novelty checks and the outcome check name a bad argument: what was
expected and what was given (not an error from deep inside, nor a wrong result)."""

from __future__ import annotations

import math

import pytest
import torch

from rcvae_torchrl.data import TRAJ_KEY
from rcvae_torchrl.training import StateNovelty, check_model, entry_groups
from rcvae_torchrl.training.checks import OutcomeCheck
from rcvae_torchrl.training.dynamics import DynamicsNovelty, check_dynamics


def _states(data):
    return torch.cat([data["observation"], data["next", "observation"]])


@pytest.fixture(scope="module")
def novelty(linear_data):
    train, val = linear_data
    return StateNovelty.fit(_states(train), _states(val))


def test_outcome_check_refuses_start_states_that_are_not_finite():
    """All-NaN start states were kept, and covers() then vouched for no start."""
    forecast = torch.full((12,), 0.5)
    real = torch.arange(24).reshape(12, 2) % 3 == 0
    nan = torch.full((12, 3), math.nan)
    with pytest.raises(ValueError, match="start_states: expected finite values, got 36 NaN"):
        OutcomeCheck.from_outcomes(forecast, real, start_states=nan)
    with pytest.raises(ValueError, match="state_scale: expected finite values"):
        OutcomeCheck.from_outcomes(
            forecast, real, start_states=torch.randn(12, 3), state_scale=torch.full((3,), math.inf)
        )
    starts = torch.randn(12, 3, generator=torch.Generator().manual_seed(0))
    check = OutcomeCheck.from_outcomes(forecast, real, start_states=starts)
    assert bool(check.covers(starts).all())


def test_describe_checks_top_and_names(novelty):
    """top=-1 said "and 4 more" of 3 dimensions, top=0 listed none; "abc" was read letter by
    letter as three names."""
    far = torch.tensor([10.0, 10.0, 10.0])
    for top in (-1, 0, 1.5, True):
        with pytest.raises(ValueError, match=f"top: expected a positive integer .*got {top!r}"):
            novelty.describe(far, top=top)
    with pytest.raises(TypeError, match="names: expected None or a sequence of 3 dimension names"):
        novelty.describe(far, names="abc")
    with pytest.raises(TypeError, match="names: expected None or a sequence of 3"):
        novelty.describe(far, names=["a", "b", 3])
    with pytest.raises(ValueError, match="names: expected 3 names, got 2"):
        novelty.describe(far, names=["a", "b"])
    with pytest.raises(TypeError, match="start: expected True or False, got 'yes'"):
        novelty.describe(far, start="yes")
    text = novelty.describe(far, names=("a", "b", "c"), top=2)
    assert "and 1 more" in text and text.count("(training") == 2


def test_entry_groups_names_a_string_or_no_names():
    """A string was read letter by letter (no groups); no names at all got another function's
    error."""
    with pytest.raises(TypeError, match=r"names: expected None or a non-empty sequence .*'ab'"):
        entry_groups("ab")
    with pytest.raises(TypeError, match=r"names: expected .*got \['a', 3\]"):
        entry_groups(["a", 3])
    with pytest.raises(ValueError, match=r"names: expected None or a non-empty .*got \[\]"):
        entry_groups([])
    assert entry_groups(["x[0]", "x[1]", "y"]) == ((0, 1),)


def test_levels_of_1_are_refused(linear_data, small_ensemble):
    """A test at level 1 always rejects; a quantile of 1 covers every held-out episode, as
    StateNovelty.fit already refused."""
    train, val = linear_data
    model = small_ensemble(2)
    level = r"alpha: expected a level in \(0, 1\) \(a test at level 1 always rejects\), got 1.0"
    with pytest.raises(ValueError, match=level):
        check_model(model, val, alpha=1.0, warn=False)
    with pytest.raises(ValueError, match=level):
        check_dynamics(model, val, alpha=1.0)
    with pytest.raises(ValueError, match=r"quantile: expected a share in \(0, 1\), got 1.0"):
        DynamicsNovelty.fit(model, train, val, quantile=1.0)


@pytest.mark.parametrize(
    ("kwargs", "error", "words"),
    [
        ({"k": 0}, ValueError, "k: expected a positive integer (open-loop steps), got 0"),
        ({"k": 2.5}, ValueError, "k: expected a positive integer (open-loop steps), got 2.5"),
        ({"windows": 0}, ValueError, "windows: expected a positive integer, got 0"),
        ({"seed": 1.5}, ValueError, "seed: expected an integer seed >= 0, got 1.5"),
        ({"seed": -1}, ValueError, "seed: expected an integer seed >= 0, got -1"),
    ],
)
def test_check_model_names_k_windows_and_seed(linear_data, small_ensemble, kwargs, error, words):
    """k=0 was reported as a window of 1 step; k=2.5 and seed=1.5 got torch's errors."""
    _, val = linear_data
    with pytest.raises(error) as info:
        check_model(small_ensemble(2), val, warn=False, **kwargs)
    assert str(info.value).startswith(words)  # windows, not sample_windows' num_windows


def test_the_checks_name_an_ensemble_or_data_of_another_kind(linear_data, small_ensemble):
    """A string for the ensemble, a tensor for the data, gave AttributeErrors."""
    train, val = linear_data
    model = small_ensemble(2)
    for bad in ("x", torch.zeros(3)):
        name = type(bad).__name__
        with pytest.raises(TypeError, match=f"ensemble: expected an RCVAEEnsemble, got {name}"):
            check_model(bad, val, warn=False)
        with pytest.raises(TypeError, match=f"ensemble: expected an RCVAEEnsemble, got {name}"):
            DynamicsNovelty.fit(bad, train, val)
        with pytest.raises(TypeError, match=f"ensemble: expected an RCVAEEnsemble, got {name}"):
            check_dynamics(bad, val)
    with pytest.raises(TypeError, match=r"data: expected a flat TensorDict .*got Tensor"):
        check_model(model, torch.zeros(3), warn=False)


def test_state_novelty_fit_names_no_held_out_states_and_a_bad_seed(linear_data):
    """No held-out states failed in zip(); seed=1.5 got torch's manual_seed error."""
    train, val = linear_data
    states, held = _states(train), _states(val)
    with pytest.raises(ValueError, match=r"held_out: expected at least one held-out state"):
        StateNovelty.fit(states, held[:0])
    for seed in (1.5, -1, "0"):
        with pytest.raises(ValueError, match=f"seed: expected an integer seed >= 0, got {seed!r}"):
            StateNovelty.fit(states, held, seed=seed)
    # an empty batch of states has an empty distance, as any other batch its own
    assert StateNovelty.fit(states, held).distance(states[:0]).shape == (0,)


def test_from_episodes_names_data_without_episode_ids(linear_data):
    """val_data without episode ids gave "'NoneType' object has no attribute 'reshape'"."""
    train, val = linear_data
    no_ids = val.exclude(TRAJ_KEY)
    with pytest.raises(KeyError, match=r"val_data: expected episode ids under .*traj_ids"):
        StateNovelty.from_episodes(train, no_ids)
    with pytest.raises(KeyError, match=r"train_data: expected episode ids under .*traj_ids"):
        StateNovelty.from_episodes(train.exclude(TRAJ_KEY), val)

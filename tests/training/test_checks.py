"""The model's self-checks: an unlearnable dimension is named, learnt ones are not."""

from __future__ import annotations

import dataclasses
import math
import warnings

import pytest
import torch

from rcvae_torchrl.data import TRAJ_KEY
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.training import (
    ModelChecks,
    ModelCheckWarning,
    TrainConfig,
    check_model,
    load_ensemble,
    save_ensemble,
    train_ensemble,
)
from tests.training.conftest import linear_episodes

NAMES = ("x", "y", "z", "noise")


def _with_noise_dim(data, seed):
    """The linear system plus a fourth dimension drawn afresh at every step (unlearnable)."""
    g = torch.Generator().manual_seed(seed)
    frames = data.shape[0]
    noise = torch.rand(frames + 1, 1, generator=g)
    ids = data[TRAJ_KEY]
    same = torch.cat([ids[1:] == ids[:-1], torch.tensor([False])])
    nxt = torch.where(same[:, None], noise[1 : frames + 1], torch.rand(frames, 1, generator=g))
    out = data.clone()
    out["observation"] = torch.cat([data["observation"], noise[:frames]], -1)
    out["next", "observation"] = torch.cat([data["next", "observation"], nxt], -1)
    return out


def _noisy_system():
    """Episodes of a linear system with a fourth, unlearnable noise dimension, and a model."""
    train = _with_noise_dim(linear_episodes(24, 40, seed=0), 0)
    val = _with_noise_dim(linear_episodes(8, 40, seed=1), 1)
    val[TRAJ_KEY] += 100
    torch.manual_seed(0)
    config = RCVAEConfig(4, 1, hidden_dim=16, latent_dim=2, mlp_dim=32, observation_names=NAMES)
    return train, val, config


@pytest.fixture(scope="module")
def trained():
    train, val, config = _noisy_system()
    budget = TrainConfig(max_steps=400, batch_windows=16, window=8, val_every=100, lr=3e-3)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = train_ensemble(RCVAEEnsemble(config, 3), train, val, budget, progress=False)
    return result, val, caught


def test_the_unlearnable_dimension_is_flagged_by_name(trained):
    result, _, caught = trained
    checks = result.checks
    assert result.ensemble.checks is checks and checks.names == NAMES
    assert [checks.names[d] for d in checks.flagged] == ["noise"]
    messages = [str(w.message) for w in caught if issubclass(w.category, ModelCheckWarning)]
    assert len(messages) == 1 and "noise" in messages[0] and "x (" not in messages[0]
    # the learnt dimensions beat both baselines (x and y change little per step next to the
    # system's noise, so copying them is nearly as good); the noise one does not beat its spread
    for d in range(3):
        assert checks.one_step[d] < 0.9 * torch.minimum(checks.copy_one_step[d], checks.spread[d])
    assert checks.one_step[3] > 0.9 * checks.spread[3]
    assert (checks.k_step[:3] < checks.copy_k_step[:3]).all()


def test_coverage_of_a_calibrated_model_and_of_a_harsher_reality(trained):
    """20 steps into 60 held-out episodes of the system it learned, the real state lies in
    the model's 90 % interval about as often as it should; in a system with 5 times the noise
    it lies there far too rarely, and every dimension the noise drives is named."""
    result, _, _ = trained
    same = _with_noise_dim(linear_episodes(60, 40, seed=2), 2)
    harsh = _with_noise_dim(linear_episodes(60, 40, seed=2, sigma=0.25), 2)
    checks = check_model(result.ensemble, same, samples_per_member=20, warn=False)
    assert checks.episodes == 60 and checks.coverage_steps == 20
    assert checks.interval == pytest.approx(55 / 61)  # order statistics 3 and 58 of 60 samples
    assert checks.overconfident == ()
    assert (checks.coverage[:3] > 0.8).all(), checks.coverage
    with pytest.warns(ModelCheckWarning, match="overconfident") as caught:
        worse = check_model(result.ensemble, harsh, samples_per_member=20)
    assert set(worse.overconfident) >= {0, 1, 2} and (worse.coverage[:3] < 0.6).all()
    assert set(worse.flagged) >= set(worse.overconfident)
    assert "x (" in str(caught[0].message) and "of 60)" in str(caught[0].message)
    restored = ModelChecks.from_dict(worse.as_dict())
    assert restored.overconfident == worse.overconfident
    few = check_model(result.ensemble, same, min_episodes=61, warn=False)
    assert few.coverage is None and few.overconfident == ()
    # an unchecked spread is not a pass: the message says why, and it travels with the model
    assert not few.passed and few.episodes == 60
    assert "spread is unchecked: 60 held-out episodes last over 20 steps, the coverage " in (
        few.message()
    )
    assert ModelChecks.from_dict(few.as_dict()).message() == few.message()
    one = dataclasses.replace(few, episodes=1)
    assert "spread is unchecked: 1 held-out episode lasts over 20 steps" in one.message()
    with pytest.warns(ModelCheckWarning, match="spread is unchecked"):
        check_model(result.ensemble, same, min_episodes=61)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"coverage_steps": 0}, r"coverage_steps: expected a positive integer, got 0"),
        ({"min_episodes": -1}, r"min_episodes: expected a positive integer, got -1"),
        ({"interval": 0.0}, r"interval: expected a float in \(0, 1\], got 0.0"),
        (
            {"alpha": 1.5},
            r"alpha: expected a level in \(0, 1\) \(a test at level 1 always rejects\), got 1.5",
        ),
    ],
)
def test_bad_coverage_settings_are_named(trained, kwargs, match):
    result, val, _ = trained
    with pytest.raises(ValueError, match=match):
        check_model(result.ensemble, val, warn=False, **kwargs)


def test_the_coverage_test_is_a_binomial_test():
    """32 episodes, a 0.9 interval, 4 dimensions (level 0.01 / 4): 23 covered is within
    chance (P(X <= 23) = 0.0033 > 0.0025), 22 is not (0.0008)."""
    zeros = torch.zeros(4, dtype=torch.float64)
    checks = ModelChecks(
        ("a", "b", "c", "d"), zeros, zeros + 1, zeros + 1, zeros, zeros + 1, 5, (0, 1, 2, 3),
        0.05, covered=torch.tensor([32.0, 29.0, 23.0, 22.0]), episodes=32, coverage_steps=20,
        interval=0.9, alpha=0.01,
    )  # fmt: skip
    assert checks.overconfident == (3,) and checks.unlearned == () and checks.flagged == (3,)
    assert "d (22 of 32)" in checks.message() and "not learned" not in checks.message()
    assert checks.describe() == checks.message()  # a miss: the same sentence
    passing = dataclasses.replace(checks, covered=torch.tensor([32.0, 29.0, 23.0, 30.0]))
    assert passing.passed and passing.message() == ""
    assert passing.describe() == (
        "the world model passed its self-checks: each of the 4 dimensions checked it predicts "
        "one step ahead at least 5% better than copying the previous state or guessing its "
        "mean; 20 steps into 32 held-out episodes the real state lay inside its 90% interval "
        "in 23 to 32 of them, dimension by dimension, not too rarely for any. The checks do "
        "not name a spread that is too wide: a model too unsure of its states passes them, "
        "and only a check of its forecasts against real episodes finds it"
    )


def test_checks_travel_with_the_checkpoint(trained, tmp_path):
    result, _, _ = trained
    save_ensemble(result.ensemble, tmp_path / "m.pt")
    loaded = load_ensemble(tmp_path / "m.pt")
    assert isinstance(loaded.checks, ModelChecks)
    assert loaded.checks.flagged == result.checks.flagged
    torch.testing.assert_close(loaded.checks.one_step, result.checks.one_step)
    assert ModelChecks.from_dict(result.checks.as_dict()).as_dict() == result.checks.as_dict()


def test_a_constant_or_passthrough_dimension_is_not_checked(trained):
    _, val, _ = trained
    val = val.clone()
    val["observation"][:, 2] = 1.0
    val["next", "observation"][:, 2] = 1.0
    config = RCVAEConfig(4, 1, hidden_dim=8, mlp_dim=8, passthrough_dims=(1,))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ModelCheckWarning)
        checks = check_model(RCVAEEnsemble(config, 2), val)
    assert 1 not in checks.checked and 2 not in checks.checked
    assert checks.names == ("obs[0]", "obs[1]", "obs[2]", "obs[3]")


@pytest.mark.slow  # collects 30 reacher episodes and trains 3 members for 1500 steps (~1 min)
def test_reacher_goal_relative_dimensions_are_flagged():
    """dm_control reacher as a new user models it: the goal-relative ``to_target`` vector,
    which the ensemble does not learn from exploration data (its error equals copying the
    previous state), is named by the check; the arm's own dimensions are not."""
    from torch import nn
    from torchrl.envs import DMControlEnv

    from rcvae_torchrl.data import (
        GaussianExploration,
        action_bounds,
        collect_episodes,
        make_policy_module,
        prepare_env,
        split_episodes,
    )

    torch.manual_seed(0)
    env, layout = prepare_env(DMControlEnv("reacher", "easy"))

    class Still(nn.Module):
        def forward(self, observation):
            return torch.zeros(*observation.shape[:-1], 2)

    low, high = action_bounds(env)
    behaviour = make_policy_module(GaussianExploration(Still(), 0.7, low=low, high=high))
    data = collect_episodes(
        lambda: prepare_env(DMControlEnv("reacher", "easy"))[0],
        behaviour,
        num_episodes=30,
        seed=0,
        progress=False,
    )
    train, val = split_episodes(data, val_fraction=0.2, seed=0)
    config = RCVAEConfig(
        layout.dim, 2, hidden_dim=64, mlp_dim=64, latent_dim=8, observation_names=layout.names
    )
    budget = TrainConfig(max_steps=1500, batch_windows=32, window=32, val_every=250)
    with pytest.warns(ModelCheckWarning, match="to_target"):
        result = train_ensemble(RCVAEEnsemble(config, 3), train, val, budget, progress=False)
    flagged = {layout.names[i] for i in result.checks.flagged}
    assert {"to_target[0]", "to_target[1]"} <= flagged
    assert not flagged & {"position[0]", "position[1]", "velocity[0]", "velocity[1]"}


def test_a_warning_of_members_that_stopped_early_says_so():
    train, val, config = _noisy_system()
    # a patience of one validation stops members at their first step back
    budget = TrainConfig(max_steps=400, batch_windows=16, window=8, val_every=10, patience=1)
    with pytest.warns(ModelCheckWarning, match=r"has not learned noise") as caught:
        result = train_ensemble(RCVAEEnsemble(config, 2), train, val, budget, progress=False)
    early = result.member_steps[result.member_steps < 400]
    assert early.numel() > 0
    message = [str(w.message) for w in caught if issubclass(w.category, ModelCheckWarning)][-1]
    assert (
        f"{early.numel()} of 2 members stopped early, after {int(early.min())}–"
        f"{int(early.max())} of max_steps=400 steps (patience=1 validations" in message
    )
    assert "a larger patience, more steps or more data" in message


def test_the_spread_too_wide_is_the_other_tail_of_a_binomial_test():
    """32 episodes, a central half of exact coverage 0.5, 4 dimensions (level 0.01 / 4):
    27 of 32 strictly inside is beyond chance (P(X >= 27) = 0.00011), 23 is not (0.010)."""
    zeros = torch.zeros(4, dtype=torch.float64)
    checks = ModelChecks(
        ("a", "b", "c", "d"), zeros, zeros + 1, zeros + 1, zeros, zeros + 1, 5, (0, 1, 2, 3),
        0.05, covered=torch.tensor([30.0, 29.0, 31.0, 30.0]), episodes=32, coverage_steps=20,
        interval=0.9, alpha=0.01, covered_half=torch.tensor([16.0, 27.0, 23.0, 0.0]),
        half_interval=0.5,
    )  # fmt: skip
    assert checks.underconfident == (1,) and checks.passed  # it does not fail the checks
    assert checks.wide_sentence() == (
        "the world model's spread is too wide for b (27 of 32): 20 steps into held-out "
        "episodes the real state lay inside its central 50% too often, so its aleatoric bits "
        "there overstate the env's noise"
    )
    assert checks.describe().endswith(
        "not too rarely for any. But the world model's spread is too wide for b (27 of 32): "
        "20 steps into held-out episodes the real state lay inside its central 50% too often, "
        "so its aleatoric bits there overstate the env's noise"
    )
    restored = ModelChecks.from_dict(checks.as_dict())
    assert restored.underconfident == (1,) and checks.as_dict()["underconfident"] == ["b"]
    fine = dataclasses.replace(checks, covered_half=torch.tensor([16.0, 23.0, 20.0, 0.0]))
    assert fine.underconfident == () and fine.wide_sentence() == ""
    assert fine.describe().endswith(
        "not too rarely for any, nor too often inside its central 50% (a spread too wide)"
    )


def test_a_model_whose_spread_is_wider_than_reality_is_named_underconfident(trained):
    """The model learned a system's noise; in one with a fifth of it the real state lies in
    the middle of its samples far too often: its aleatoric bits overstate that system's noise
    (an acrobot trial: 19-22 'aleatoric' bits from a model of noise-free episodes)."""
    result, _, _ = trained
    same = _with_noise_dim(linear_episodes(60, 40, seed=2), 2)
    calm = _with_noise_dim(linear_episodes(60, 40, seed=2, sigma=0.01), 2)
    assert (
        check_model(result.ensemble, same, samples_per_member=20, warn=False).underconfident == ()
    )
    wide = check_model(result.ensemble, calm, samples_per_member=20, warn=False)
    assert set(wide.underconfident) >= {0, 1, 2} and 3 not in wide.underconfident
    assert "x (" in wide.wide_sentence() and "noise (" not in wide.wide_sentence()


def test_a_dimension_the_model_gets_exactly_is_covered():
    """A clock the model advances exactly (a state constraint rotating the previous phase) has
    an interval of width 0 that the real phase, computed in another order, misses by float
    rounding: that counts as inside, not as overconfident."""
    from tensordict import TensorDict

    from rcvae_torchrl.models import ModelFunctions

    step = 0.37

    def rotate(previous, state):
        cos, sin = previous[..., 0], previous[..., 1]
        c, s = math.cos(step), math.sin(step)
        turned = torch.stack([cos * c - sin * s, sin * c + cos * s], dim=-1)
        return torch.cat([turned, state[..., 2:]], dim=-1)

    episodes, steps = 12, 30
    g = torch.Generator().manual_seed(0)
    phase0 = torch.rand(episodes, 1, generator=g, dtype=torch.float64) * 6.28
    angle = phase0 + step * torch.arange(steps + 1, dtype=torch.float64)  # float64, then cast
    clock = torch.stack([angle.cos(), angle.sin()], -1).float()
    other = torch.randn(episodes, steps + 1, 1, generator=g)
    states = torch.cat([clock, other], -1)
    data = TensorDict(
        {
            "observation": states[:, :-1],
            "action": torch.zeros(episodes, steps, 1),
            ("next", "observation"): states[:, 1:],
            TRAJ_KEY: torch.arange(episodes)[:, None].expand(episodes, steps),
        },
        batch_size=[episodes, steps],
    ).reshape(-1)
    config = RCVAEConfig(3, 1, hidden_dim=8, mlp_dim=8, state_constraint="clock")
    model = RCVAEEnsemble(config, 2, functions=ModelFunctions(state_constraints={"clock": rotate}))
    checks = check_model(model, data, samples_per_member=20, min_episodes=10, warn=False)
    assert checks.covered[:2].tolist() == [episodes, episodes]
    assert not {0, 1} & set(checks.overconfident)
    # nor is its interval of width 0 a spread too wide: nothing lies strictly inside it
    assert checks.covered_half[:2].tolist() == [0, 0] and not {0, 1} & set(checks.underconfident)


def _right_and_biased_p(offset: float, seed: int) -> torch.Tensor:
    """p-values of the drift test for windows of 16 episodes (4 each) of an unpredictable
    dimension: the truth is N(0, 1), the baseline its mean, the forecast the mean of 8 draws
    of the truth's law, shifted by ``offset``."""
    from rcvae_torchrl.training.checks import _drift_p_values

    g = torch.Generator().manual_seed(seed)
    truth = torch.randn(64, 1, generator=g, dtype=torch.float64)
    forecast = torch.randn(64, 8, generator=g, dtype=torch.float64).mean(1, keepdim=True)
    episodes = torch.arange(16).repeat_interleave(4)
    return _drift_p_values(forecast + offset, truth, torch.zeros_like(truth), 8, episodes)


def test_the_drift_test_holds_its_level_where_a_right_model_only_ties_the_baseline():
    """Where nothing is predictable, a right model's mean of 8 samples errs by (1 + 1/8) times
    the baseline's square: the test's boundary, rejected about as often as its level; a mean
    off by a whole spread is found almost every time."""
    right = torch.cat([_right_and_biased_p(0.0, s) for s in range(400)])
    biased = torch.cat([_right_and_biased_p(1.0, s) for s in range(100)])
    assert float((right < 0.05).double().mean()) <= 0.085
    assert float((right < 0.05).double().mean()) >= 0.02  # not a test that never rejects
    assert float((biased < 0.05).double().mean()) >= 0.9


def test_the_drift_test_takes_episodes_as_its_units():
    """The same excess in every window of an episode counts once per episode: 2 episodes are
    too few to test, and copies of each window do not make it more sure."""
    from rcvae_torchrl.training.checks import _drift_p_values

    truth = torch.tensor([[0.0], [0.1], [0.3], [-0.2], [0.2], [0.05]], dtype=torch.float64)
    forecast, base = truth + 1.0, torch.zeros_like(truth)
    two = _drift_p_values(forecast, truth, base, 8, torch.tensor([0, 0, 0, 1, 1, 1]))
    assert two is None
    six = _drift_p_values(forecast, truth, base, 8, torch.arange(6))
    doubled = _drift_p_values(
        forecast.repeat_interleave(2, 0),
        truth.repeat_interleave(2, 0),
        base.repeat_interleave(2, 0),
        8,
        torch.arange(6).repeat_interleave(2),
    )
    assert float(six[0]) < 0.01 and torch.allclose(six, doubled)


def test_a_model_off_course_after_k_steps_is_named_drifting(trained):
    """The model checked on the system it learned drifts on no dimension; on the same system
    with the third dimension's decay (0.8) gone, its mean forecast 10 steps ahead is further
    off than copying the start, and it is named, with both errors."""
    result, _, _ = trained
    assert result.checks.drifting == () and result.checks.k_samples == 3 * 8
    assert result.checks.k_step_p is not None and (result.checks.k_step_p > 0.01).all()
    g = torch.Generator().manual_seed(3)
    a_mat = torch.tensor([[0.9, 0.1, 0.0], [0.0, 0.9, 0.1], [0.0, 0.0, 1.0]])
    s, obs, act, nxt = torch.randn(60, 3, generator=g), [], [], []
    for _ in range(40):
        a = torch.rand(60, 1, generator=g) * 2 - 1
        s_next = s @ a_mat.T + a * torch.tensor([0.0, 0.0, 0.5])
        s_next = s_next + 0.05 * torch.randn(60, 3, generator=g)
        obs.append(s), act.append(a), nxt.append(s_next)
        s = s_next
    episodes = linear_episodes(60, 40, seed=3).reshape(60, 40).clone()
    episodes["observation"], episodes["action"] = torch.stack(obs, 1), torch.stack(act, 1)
    episodes["next", "observation"] = torch.stack(nxt, 1)
    changed = _with_noise_dim(episodes.reshape(-1), 3)
    with pytest.warns(ModelCheckWarning, match="the world model drifts: 10 steps into") as caught:
        checks = check_model(result.ensemble, changed, samples_per_member=20)
    assert 2 in checks.drifting and 2 in checks.flagged and not checks.passed
    assert float(checks.k_step[2]) > float(checks.copy_k_step[2])
    assert f"z (error {float(checks.k_step[2]):.3g} vs " in str(caught[0].message)
    restored = ModelChecks.from_dict(checks.as_dict())
    assert restored.drifting == checks.drifting and checks.as_dict()["drifting"][0] == "z"
    # checks saved before the drift test carry no p-values: nothing is named drifting
    old = {k: v for k, v in checks.as_dict().items() if k not in ("k_step_p", "k_samples")}
    assert ModelChecks.from_dict(old).drifting == ()


def test_the_dimensions_a_forecast_hangs_on_can_be_checked_alone(trained):
    """The coverage test's level is shared over the dimensions checked (a quadruped's torso
    uprightness, inside its interval in 49 of 60 episodes, p = 0.0007, went unnamed among 78
    dimensions, its forecasts 0.28 off): ``dims`` checks those a forecast hangs on alone."""
    zeros = torch.zeros(4, dtype=torch.float64)
    covered = torch.tensor([32.0, 29.0, 23.0, 30.0])  # P(X <= 23) = 0.0033 for 32 at 0.9
    args = dict(covered=covered, episodes=32, coverage_steps=20, interval=0.9, alpha=0.01)
    names = ("a", "b", "c", "d")
    every = ModelChecks(names, zeros, zeros + 1, zeros + 1, zeros, zeros + 1, 5, (0, 1, 2, 3),
                        0.05, **args)  # fmt: skip
    alone = dataclasses.replace(every, checked=(2,))
    assert every.overconfident == () and alone.overconfident == (2,)
    result, val, _ = trained
    checks = check_model(result.ensemble, val, dims=["z", 0, "z"], warn=False)
    assert checks.checked == (0, 2)
    for dims, match in [
        (["w"], r"dims: 'w' is not a dimension's name \(x, y, z, noise\)"),
        ([7], r"dims: expected dimensions in \[0, 4\) or their names, got 7"),
        ([], r"dims: expected a non-empty sequence of dimensions, got \[\]"),
    ]:
        with pytest.raises((ValueError, TypeError), match=match):
            check_model(result.ensemble, val, dims=dims, warn=False)


def test_a_message_names_eight_dimensions_and_counts_the_rest():
    """A 78-dimensional model's warning named 30 dimensions in 2,500 characters."""
    n = 20
    zeros = torch.zeros(n, dtype=torch.float64)
    names = tuple(f"d{i}" for i in range(n))
    checks = ModelChecks(names, zeros + 1, zeros + 1, zeros + 1, zeros, zeros + 1, 5,
                         tuple(range(n)), 0.05, covered=zeros + 32, episodes=32,
                         coverage_steps=20, interval=0.9)  # fmt: skip
    assert len(checks.unlearned) == n
    message = checks.message()
    assert "d7 (one-step error" in message and "d8 (" not in message
    assert "d7 (one-step error 1 vs 1 for a trivial baseline) and 12 more:" in message


def test_a_dimension_forecast_to_float_rounding_does_not_drift():
    """A cheetah trial: a gait clock set by a state constraint, its period exactly k steps, so
    that copying the start state was exact (error 4.5e-14) and the model's float32 forecast off
    by 2.4e-7: named drifting, and the model failed its checks."""
    from rcvae_torchrl.training.checks import _drift_p_values

    g = torch.Generator().manual_seed(0)
    phase = torch.rand(24, 1, generator=g, dtype=torch.float64) * 2 - 1
    forecast = phase.float().double() + 2.4e-7 * torch.randn(24, 1, generator=g).double()
    episodes = torch.arange(6).repeat_interleave(4)
    assert float(_drift_p_values(forecast, phase, phase.clone(), 8, episodes)[0]) == 1.0
    # beyond rounding it is still an error: off by 1e-3 where the copy is exact
    off = _drift_p_values(phase + 1e-3, phase, phase.clone(), 8, episodes)
    assert float(off[0]) == 0.0

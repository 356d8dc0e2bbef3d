"""train_ensemble checks all of its data before it uses any, and a resumed run continues only
the run it was: the same data and the same model."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from rcvae_torchrl.data import TRAJ_KEY
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.training import CheckpointError, TrainConfig, train_ensemble
from tests.training.conftest import linear_episodes

BUDGET = TrainConfig(max_steps=4, batch_windows=4, window=8, val_every=2, val_windows=4)


def _train(ensemble, train, val, **kwargs):
    # the self-checks and the dynamics check (4 validation episodes: it would warn that it
    # measured none) are not this file's
    return train_ensemble(
        ensemble, train, val, BUDGET, progress=False, checks=False, dynamics=False, **kwargs
    )


def test_a_nan_no_window_would_draw_is_refused_and_the_model_left_as_it_was(
    linear_data, small_ensemble
):
    """A NaN in an episode shorter than the window is never in a training window, but it is in
    the normaliser's statistics: refused by name before anything is fitted."""
    train, val = linear_data
    short = linear_episodes(1, 5, seed=3)
    short[TRAJ_KEY] = short[TRAJ_KEY] + 500
    short["observation"][2, 1] = math.nan
    model = small_ensemble(2)
    with pytest.raises(ValueError, match=r"train_data\['observation'\]: expected finite values"):
        _train(model, torch.cat([train, short]), val)
    assert not model.normalizer.fitted
    bad_val = val.clone()
    bad_val["next", "observation"][0, 0] = math.inf
    with pytest.raises(ValueError, match=r"val_data\[\('next', 'observation'\)\]: .* 1 inf"):
        _train(model, train, bad_val)
    result = _train(model, train, val)  # the same model then trains on clean data
    assert torch.isfinite(result.best_val).all() and model.normalizer.fitted


def test_data_of_another_layout_and_a_wrong_config_are_named(linear_data, small_ensemble):
    train, val = linear_data
    model = small_ensemble(2)
    with pytest.raises(ValueError, match=r"train_data\['action'\]: expected shape \[frames, A=1\]"):
        _train(model, train.clone().set("action", torch.zeros(train.shape[0], 2)), val)
    with pytest.raises(ValueError, match=r"val_data: expected an entry 'action'"):
        _train(model, train, val.exclude("action"))
    with pytest.raises(TypeError, match=r"train_data: expected a flat TensorDict .*, got list"):
        _train(model, [train], val)
    with pytest.raises(
        ValueError, match=r"val_data: expected .* at least one frame, got batch \(0,\)"
    ):
        _train(model, train, val[:0])
    with pytest.raises(ValueError, match=r"train_data: expected a flat .*, got batch \(2, \d+\)"):
        _train(model, train.reshape(2, -1), val)
    with pytest.raises(TypeError, match="config: expected a TrainConfig, got dict"):
        train_ensemble(model, train, val, {"max_steps": 4}, progress=False)
    for name, bad in (("max_steps", 2.5), ("window", 3.5), ("lr", math.inf), ("patience", True)):
        with pytest.raises(ValueError, match=f"{name}: expected a positive"):
            TrainConfig(**{name: bad})


def test_resume_refuses_other_data_and_another_model(tmp_path, linear_data, small_ensemble):
    train, val = linear_data
    path = tmp_path / "run.pt"
    _train(small_ensemble(2), train, val, checkpoint_path=path)
    scaled = train.clone()
    scaled["observation"] *= 100
    scaled["next", "observation"] *= 100  # other data, still episodes in time order
    with pytest.raises(  # and how to go on from its weights on other data
        CheckpointError, match=r"was written by a training on other data .* pass load_ensemble"
    ):
        _train(small_ensemble(2), scaled, val, checkpoint_path=path, resume=True)
    with pytest.raises(CheckpointError, match=r"holds members 0\.\.1, this run trains 0\.\.2"):
        _train(small_ensemble(3), train, val, checkpoint_path=path, resume=True)
    wide = RCVAEEnsemble(RCVAEConfig(3, 1, hidden_dim=32, latent_dim=2, mlp_dim=16), 2)
    with pytest.raises(  # one line naming the fields, not a list of every tensor
        CheckpointError,
        match=r"was written for a model of another config \(hidden_dim=\d+ there, 32 now.*\); "
        r"resume with the same model config or a new path",
    ):
        _train(wide, train, val, checkpoint_path=path, resume=True)
    # another config whose weights have the same shapes would load and take its bounds
    config = small_ensemble(2).config
    bounded = RCVAEEnsemble(dataclasses.replace(config, max_log_std=config.max_log_std - 1), 2)
    with pytest.raises(CheckpointError, match=r"\(max_log_std=\S+ there, \S+ now\)"):
        _train(bounded, train, val, checkpoint_path=path, resume=True)
    again = _train(small_ensemble(2), train, val, checkpoint_path=path, resume=True)
    assert again.steps == BUDGET.max_steps  # the finished run, returned as it was


def test_resume_with_other_settings_names_only_the_settings_that_differ(
    tmp_path, linear_data, small_ensemble
):
    train, val = linear_data
    path = tmp_path / "run.pt"
    _train(small_ensemble(2), train, val, checkpoint_path=path)
    other = TrainConfig(max_steps=6, batch_windows=4, window=8, val_every=2, val_windows=4, lr=3e-3)
    with pytest.raises(
        CheckpointError,
        match=r"was written with another TrainConfig \(lr=0\.001 there, 0\.003 now, max_steps=4 "
        r"there, 6 now\); resume with the same config or a new path",
    ):
        train_ensemble(
            small_ensemble(2),
            train,
            val,
            other,
            progress=False,
            checks=False,
            checkpoint_path=path,
            resume=True,
        )


def test_training_never_writes_over_what_is_not_a_training_checkpoint(
    tmp_path, linear_data, small_ensemble
):
    """A user's episodes, a saved model or a folder at ``checkpoint_path`` is refused before
    any step, and left as it was; a training checkpoint is overwritten (a new run)."""
    from rcvae_torchrl.data import load_episodes, save_episodes
    from rcvae_torchrl.training import save_ensemble

    train, val = linear_data
    episodes = save_episodes(train, tmp_path / "episodes.pt")
    before = episodes.read_bytes()
    with pytest.raises(ValueError, match=r"checkpoint_path: .*episodes.pt' exists and is not a tr"):
        _train(small_ensemble(2), train, val, checkpoint_path=episodes)
    assert episodes.read_bytes() == before
    assert (load_episodes(episodes) == train).all()
    model = save_ensemble(small_ensemble(2), tmp_path / "model.pt")
    with pytest.raises(ValueError, match=r"no training state: a model saved with save_ensemble"):
        _train(small_ensemble(2), train, val, checkpoint_path=model)
    junk = tmp_path / "notes.pt"
    junk.write_bytes(b"my notes")
    with pytest.raises(ValueError, match=r"notes.pt' exists and is not a training checkpoint"):
        _train(small_ensemble(2), train, val, checkpoint_path=junk)
    assert junk.read_bytes() == b"my notes"
    with pytest.raises(ValueError, match=r"checkpoint_path: .* is a directory; expected the pat"):
        _train(small_ensemble(2), train, val, checkpoint_path=tmp_path)
    assert not (tmp_path.parent / "logs").exists()
    run = tmp_path / "run.pt"
    _train(small_ensemble(2), train, val, checkpoint_path=run)
    again = _train(small_ensemble(2, seed=1), train, val, checkpoint_path=run)  # a new run
    assert again.steps == BUDGET.max_steps


def test_data_of_the_wrong_rank_or_too_short_for_a_window_names_the_dataset(
    linear_data, small_ensemble
):
    train, val = linear_data
    model = small_ensemble(2)
    extra_dim = train.clone()
    extra_dim["observation"] = extra_dim["observation"].unsqueeze(1)
    with pytest.raises(
        ValueError,
        match=r"^train_data\['observation'\]: expected shape \[frames, S=3\], got \(\d+, 1, 3\)",
    ):
        _train(model, extra_dim, val)
    short = linear_episodes(4, 5, seed=2)  # 5 steps each, the window is 8
    with pytest.raises(
        ValueError,
        match=r"^val_data: expected an episode of at least TrainConfig.window = 8 steps, got "
        r"episodes of at most 5",
    ):
        _train(model, train, short)
    with pytest.raises(ValueError, match=r"^train_data: expected episode ids under \('collector'"):
        _train(model, train.exclude(TRAJ_KEY), val)


def test_a_model_that_is_not_an_ensemble_is_named(linear_data):
    with pytest.raises(TypeError, match=r"^ensemble: expected an RCVAEEnsemble, got NoneType"):
        _train(None, *linear_data)


def test_fractions_that_are_not_numbers_are_named():
    for name, bad in (("episode_start_fraction", "a"), ("lr_final_fraction", None)):
        with pytest.raises(TypeError, match=rf"^{name}: expected a float in .*, got {bad!r}"):
            TrainConfig(**{name: bad})


def test_episodes_too_short_for_a_window_are_named_with_the_terminations_lost(
    linear_data, small_ensemble
):
    train, val = linear_data
    short = linear_episodes(3, 5, seed=4)  # 5 steps, the window is 8
    short[TRAJ_KEY] = short[TRAJ_KEY] + 500
    short["next", "terminated"] = short["next", "done"].clone()
    short["next", "terminated"][:5] = False  # the first of them ran out, the others ended
    long = train.clone().set(("next", "terminated"), torch.zeros_like(train["next", "done"]))
    train = torch.cat([long, short])
    with pytest.warns(
        UserWarning,
        match=r"^train_data: 3 of \d+ episodes \(15 frames\) are shorter than the window "
        r"\(TrainConfig.window = 8 steps\) and are never drawn; 2 of them \(of the 2 episodes "
        r"the env terminated\) end in a termination",
    ):
        _train(small_ensemble(2), train, val)


def test_a_member_that_kept_its_first_validation_is_named():
    from rcvae_torchrl.data import split_episodes

    train, val = split_episodes(linear_episodes(40, 30, seed=0), 0.25, seed=0)
    torch.manual_seed(0)
    model = RCVAEEnsemble(RCVAEConfig(3, 1, hidden_dim=16, latent_dim=2, mlp_dim=16), 3)
    budget = TrainConfig(
        max_steps=40, batch_windows=4, window=8, val_every=2, val_windows=4, patience=2, lr=3.0
    )  # a learning rate that throws the weights away at once
    with pytest.warns(
        UserWarning,
        match=r"^train_ensemble: member\(s\) \[0, 2\] kept the weights of their first validation "
        r"\(step 2, .*so they are barely trained \(stopped at step\(s\) \[6, 6\], patience=2\)",
    ):
        result = train_ensemble(model, train, val, budget, progress=False, checks=False)
    # they stopped after patience validations without improvement on the first
    assert result.member_steps[[0, 2]].tolist() == [6, 6] and result.member_steps[1] > 6


def test_the_self_checks_take_check_model_s_arguments(linear_data, small_ensemble):
    train, val = linear_data
    result = train_ensemble(
        small_ensemble(2), train, val, BUDGET, progress=False, checks={"coverage_steps": 5}
    )
    assert result.checks.coverage_steps == 5
    default = train_ensemble(small_ensemble(2), train, val, BUDGET, progress=False, checks={})
    assert default.checks.coverage_steps == 20
    with pytest.raises(TypeError, match=r"^checks: unknown check_model arguments \['horizon'\]"):
        train_ensemble(small_ensemble(2), train, val, BUDGET, progress=False, checks={"horizon": 5})
    with pytest.raises(TypeError, match=r"^checks: expected True, False or a mapping .*, got str"):
        train_ensemble(small_ensemble(2), train, val, BUDGET, progress=False, checks="yes")


def test_validating_on_the_training_episodes_is_warned(linear_data, small_ensemble):
    train, _ = linear_data
    with pytest.warns(UserWarning, match=r"^val_data: the same episodes as train_data"):
        _train(small_ensemble(2), train, train)


def test_only_flat_episodes_are_saved(tmp_path, linear_data):
    from rcvae_torchrl.data import save_episodes

    train, _ = linear_data
    with pytest.raises(TypeError, match=r"^data: expected a flat TensorDict \[frames\], got dict"):
        save_episodes(train.to_dict(), tmp_path / "episodes.pt")
    with pytest.raises(ValueError, match=r"^data: expected a flat TensorDict \[frames\], got \(2,"):
        save_episodes(train.reshape(2, -1), tmp_path / "episodes.pt")
    assert not (tmp_path / "episodes.pt").exists()


def test_a_fitted_normaliser_far_from_new_data_is_named(linear_data, small_ensemble):
    """A point-mass trial fine-tuned a trained model on data of the other half of the arena:
    the old normaliser was kept (the new states about 4 of its stds out), with nothing said.
    Training again on data like the first says nothing; on data elsewhere, it names the
    dimension and how to refit."""
    import warnings

    train, val = linear_data
    model = small_ensemble(2)
    _train(model, train, val)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _train(model, train, val)  # the data it was fitted on: nothing to say
    moved = train.clone()
    moved["observation"] += 50
    moved["next", "observation"] += 50  # the same episodes, elsewhere
    with pytest.warns(
        UserWarning,
        match=r"^train_data: the ensemble's normaliser was fitted before, and is kept, but these "
        r"data lie elsewhere: observation\[0\] has mean 50 and std .* refit them first \(ensemble",
    ):
        _train(model, moved, val)


@pytest.mark.parametrize(
    ("kwargs", "error", "words"),
    [
        ({"progress": "no"}, TypeError, "progress: expected True or False, got 'no'"),
        ({"log_prefix": 5}, TypeError, "log_prefix: expected a str, got int"),
        ({"logger": "csv"}, TypeError, "logger: expected a TorchRL Logger or None"),
        ({"checkpoint_path": 5}, TypeError, "checkpoint_path: expected a str, a path or None"),
    ],
)
def test_train_ensemble_refuses_arguments_of_another_type_by_name(
    linear_data, small_ensemble, kwargs, error, words
):
    """A string is not a flag ('no' would read as True) and not a logger."""
    train, val = linear_data
    args = {"progress": False, "checks": False, "dynamics": False, **kwargs}
    with pytest.raises(error) as info:
        train_ensemble(small_ensemble(2), train, val, BUDGET, **args)
    assert words in str(info.value)


def test_resume_is_a_flag(linear_data, small_ensemble, tmp_path):
    train, val = linear_data
    with pytest.raises(TypeError, match="resume: expected True or False, got 'no'"):
        _train(small_ensemble(2), train, val, resume="no", checkpoint_path=tmp_path / "c.pt")


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"window": 8, "open_loop_steps": 8}, "open_loop_steps: expected fewer than the window"),
        ({"seed": 2**70}, "seed: expected an integer in [0, 2**63)"),
    ],
)
def test_train_config_refuses_what_training_would_clamp_or_overflow(kwargs, words):
    with pytest.raises(ValueError) as info:
        TrainConfig(**kwargs)
    assert words in str(info.value)
    assert TrainConfig(window=8, open_loop_steps=7).open_loop_steps == 7


def test_the_checks_name_their_thresholds_and_inputs(linear_data, small_ensemble):
    """A NaN or negative min_gain passed a model that fails; a NaN action was judged seen; a
    reference smaller than k; a NaN tolerance or a dimension out of range in rank_p_values."""
    from rcvae_torchrl.training import StateNovelty, check_model
    from rcvae_torchrl.training.dynamics import rank_p_values

    _, val = linear_data
    model = small_ensemble(2)
    for bad in (math.nan, -1.0, "0.1"):
        with pytest.raises(ValueError, match="min_gain: expected a finite number >= 0"):
            check_model(model, val, windows=4, min_gain=bad, warn=False)
    with pytest.raises(TypeError, match="warn: expected True or False, got 'no'"):
        check_model(model, val, windows=4, warn="no")
    states, held = torch.randn(200, 3), torch.randn(50, 3)
    with pytest.raises(ValueError, match="max_states: expected more than k = 5"):
        StateNovelty.fit(states, held, k=5, max_states=2)
    novelty = StateNovelty.fit(states, held).with_actions(
        torch.rand(200, 1), torch.rand(50, 1), torch.arange(50) // 10
    )
    with pytest.raises(ValueError, match="actions: expected finite values"):
        novelty.unseen_actions(torch.tensor([[math.nan]]))
    scores, held_out = torch.rand(8, 3), torch.rand(12, 3)
    for tolerance in (math.nan, -1.0, 0.5):
        with pytest.raises(ValueError, match="tolerance: expected a finite factor >= 1"):
            rank_p_values(scores, held_out, (0,), tolerance=tolerance)
    with pytest.raises(ValueError, match=r"dims: expected dimensions in 0..2, got \(-1,\)"):
        rank_p_values(scores, held_out, (-1,))
    with pytest.raises(ValueError, match=r"scores \(in dims\): expected finite values"):
        rank_p_values(torch.full((8, 3), math.nan), held_out, (0,))
    nan_elsewhere = scores.clone()
    nan_elsewhere[:, 2] = math.nan  # a dimension not tested may hold NaN
    assert rank_p_values(nan_elsewhere, held_out, (0,))[0].isfinite()

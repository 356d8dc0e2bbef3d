"""The study's typed configuration: ``from_mapping`` errors, nested configs, the recipe's YAML."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from rcvae_torchrl.agent import DistillConfig, PlannerConfig
from rcvae_torchrl.study import (
    AgentStudyConfig,
    AssessConfig,
    DataConfig,
    ModelConfig,
    StudyConfig,
    from_mapping,
)
from rcvae_torchrl.training import TrainConfig

ROOT = Path(__file__).resolve().parents[2]
CONFIG_DIR = ROOT / "recipes" / "config"


def _recipe():
    spec = importlib.util.spec_from_file_location(
        "pusher_competency", ROOT / "recipes" / "pusher_competency.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _profile(name: str, *overrides: str) -> dict:
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(config_name="pusher_competency", overrides=[f"profile={name}", *overrides])
    return OmegaConf.to_container(cfg, resolve=True)


# --------------------------------------------------------------------------- unknown keys
def test_unknown_top_level_key_names_it_and_the_allowed_keys():
    with pytest.raises(ValueError) as info:
        from_mapping(StudyConfig, {"trian": {"max_steps": 3}})
    message = str(info.value)
    assert message.startswith("config: unknown key(s) ['trian']")
    for allowed in ("agent", "assess", "data", "model", "planner", "seed", "train"):
        assert repr(allowed) in message


def test_unknown_nested_keys_give_their_path():
    with pytest.raises(ValueError, match=r"config\.train: unknown key\(s\) \['max_step'\]") as info:
        from_mapping(StudyConfig, {"train": {"max_step": 3}})
    assert "'max_steps'" in str(info.value)
    with pytest.raises(ValueError, match=r"config\.agent\.distill: unknown key\(s\) \['epoch'\]"):
        from_mapping(StudyConfig, {"agent": {"distill": {"epoch": 3}}})


def test_every_unknown_key_is_reported_sorted():
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['modle', 'trian'\]"):
        from_mapping(StudyConfig, {"trian": {}, "modle": {}, "seed": 1})


def test_where_prefixes_the_message():
    with pytest.raises(ValueError, match=r"^train: unknown key\(s\) \['lr_'\]"):
        from_mapping(TrainConfig, {"lr_": 0.1}, where="train")


# --------------------------------------------------------------------------- nested configs
def test_nested_mappings_build_the_nested_dataclasses():
    config = from_mapping(
        StudyConfig,
        {
            "data": {"scripted_episodes": 4},
            "model": {"ensemble_size": 2},
            "train": {"max_steps": 7, "batch_windows": 8, "window": 16},
            "planner": {"horizon": 5, "objective": "cvar"},
            "agent": {"mpc_episodes": 3, "distill": {"epochs": 2}},
            "assess": {"start_states": 4, "open_loop": True},
            "seed": 3,
        },
    )
    assert isinstance(config.data, DataConfig) and config.data.scripted_episodes == 4
    assert isinstance(config.model, ModelConfig) and config.model.ensemble_size == 2
    assert isinstance(config.train, TrainConfig) and config.train.max_steps == 7
    assert isinstance(config.planner, PlannerConfig) and config.planner.objective == "cvar"
    assert isinstance(config.agent, AgentStudyConfig) and config.agent.mpc_episodes == 3
    assert isinstance(config.agent.distill, DistillConfig) and config.agent.distill.epochs == 2
    assert isinstance(config.assess, AssessConfig) and config.assess.open_loop is True
    assert config.seed == 3
    # keys left out keep the defaults of their own config
    assert config.data.random_episodes == DataConfig().random_episodes
    assert config.agent.distill.patience == DistillConfig().patience


@pytest.mark.parametrize("values", [None, {}])
def test_empty_mapping_gives_the_defaults(values):
    assert from_mapping(StudyConfig, values) == StudyConfig()


def test_round_trip_through_asdict():
    config = from_mapping(
        StudyConfig, {"train": {"max_steps": 9, "window": 8}, "agent": {"distill": {"lr": 0.01}}}
    )
    assert from_mapping(StudyConfig, dataclasses.asdict(config)) == config


def test_configs_are_frozen():
    config = from_mapping(StudyConfig, {})
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.seed = 1  # type: ignore[misc]


# --------------------------------------------------------------------------- invalid values
@pytest.mark.parametrize(
    ("values", "match"),
    [
        ({"train": {"max_steps": 0}}, r"config\.train: max_steps: expected >= 1, got 0"),
        ({"train": {"window": 1}}, r"config\.train: window: expected >= 2 steps, got 1"),
        ({"train": {"lr": -1.0}}, r"config\.train: lr, grad_clip: expected > 0"),
        ({"train": {"max_steps": "ten"}}, r"config\.train\.max_steps: expected int"),
        (
            {"assess": {"bias_correction": "jackknife"}},
            r"config\.assess: bias_correction: expected 'none' or 'shuffle', got 'jackknife'",
        ),
        ({"assess": {"episode_end": "yes"}}, r"config\.assess\.episode_end: expected bool"),
    ],
)
def test_invalid_values_are_rejected_with_their_path(values, match):
    with pytest.raises(ValueError, match=match):
        from_mapping(StudyConfig, values)


@pytest.mark.parametrize(
    "values",
    [
        pytest.param({"train": 5}, id="scalar-for-a-section"),
        pytest.param({"data": {"scripted_episodes": -1}}, id="negative-episodes"),
        pytest.param({"model": {"ensemble_size": 0}}, id="empty-ensemble"),
        pytest.param({"planner": {"top_k": 500}}, id="top_k-above-candidates"),
        pytest.param({"planner": {"objective": "best"}}, id="unknown-objective"),
        pytest.param({"assess": {"horizon_s": 2.03}}, id="horizon-not-whole-steps"),
        pytest.param({"assess": {"start_states": "ten"}}, id="string-for-int"),
    ],
)
def test_invalid_values_fail_before_any_stage_runs(values):
    try:
        from_mapping(StudyConfig, values)
    except (TypeError, ValueError):
        return
    raise AssertionError(f"accepted: {values}")


def test_partial_section_keeps_the_study_defaults():
    config = from_mapping(StudyConfig, {"train": {"max_steps": 7}})
    assert config.train.batch_windows == StudyConfig().train.batch_windows


# --------------------------------------------------------------------------- the recipe's YAML
@pytest.mark.parametrize("profile", ["quick", "default", "full"])
def test_every_profile_builds_a_study_config(profile):
    values = _profile(profile)
    recipe = _recipe()
    settings = {k: values.pop(k) for k in recipe._RECIPE_KEYS if k in values}
    assert settings["profile"] == profile
    assert settings["run_dir"] == f"outputs/pusher_competency/{profile}"
    assert settings["device"] == "auto"
    config = from_mapping(StudyConfig, values)
    assert config.model.ensemble_size >= 2
    assert config.train.window <= config.data.time_limit / 0.05


def test_profiles_scale_up():
    budgets = {}
    for profile in ("quick", "default", "full"):
        values = _profile(profile)
        values = {k: v for k, v in values.items() if k not in _recipe()._RECIPE_KEYS}
        budgets[profile] = from_mapping(StudyConfig, values)
    quick, default, full = budgets["quick"], budgets["default"], budgets["full"]
    assert quick.train.max_steps < default.train.max_steps < full.train.max_steps
    assert quick.assess.start_states < default.assess.start_states < full.assess.start_states
    assert quick.data.scripted_episodes < default.data.scripted_episodes
    assert default.data.scripted_episodes < full.data.scripted_episodes
    assert default == StudyConfig()  # the default profile is the typed config's default


def test_command_line_overrides_reach_the_config():
    values = _profile("quick", "assess.start_states=7", "+train.lr=3e-4")
    values = {k: v for k, v in values.items() if k not in _recipe()._RECIPE_KEYS}
    config = from_mapping(StudyConfig, values)
    assert config.assess.start_states == 7 and config.train.lr == pytest.approx(3e-4)


def test_device_option():
    recipe = _recipe()
    assert recipe._device("cpu") == "cpu"
    assert recipe._device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            recipe._device("cuda:0")


def test_stochastic_open_loop_steps_apply_to_the_stochastic_ensemble_only(tmp_path):
    import torch

    from rcvae_torchrl.study.pipeline import _Study

    config = from_mapping(StudyConfig, {"model": {"stochastic_open_loop_steps": 8}})
    study = _Study(config, tmp_path, torch.device("cpu"), progress=False)
    assert study._train_config("stochastic").open_loop_steps == 8
    assert study._train_config("deterministic") == config.train
    assert study._train_config("deterministic").open_loop_steps == 0
    values = {"model": {"stochastic_open_loop_steps": None}, "train": {"open_loop_steps": 2}}
    shared = from_mapping(StudyConfig, values)
    study = _Study(shared, tmp_path, torch.device("cpu"), progress=False)
    assert study._train_config("stochastic").open_loop_steps == 2
    with pytest.raises(ValueError, match="stochastic_open_loop_steps: expected a number >= 0"):
        from_mapping(StudyConfig, {"model": {"stochastic_open_loop_steps": -1}})

"""The study's typed configuration: Hydra structured configs, profiles, checks up front."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from rcvae_torchrl.io import StoredFileError, write_json
from recipes._settings import SEED_MAX, check_override_keys, resolve_device, set_threads
from recipes.pusher_competency.config import (
    MAX_SEED,
    RecipeConfig,
    StudyConfig,
    register_configs,
    study_config,
)
from recipes.pusher_competency.pipeline import Study, study_of_run, study_settings

CONF = Path(__file__).resolve().parents[2] / "recipes" / "pusher_competency" / "conf"
register_configs()


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="pusher_competency", overrides=list(overrides))


def _config(*overrides: str) -> RecipeConfig:
    return study_config(_compose(*overrides))


# --------------------------------------------------------------------------- one source of defaults
def test_the_default_profile_is_the_dataclass_defaults():
    config = _config()
    assert config == dataclasses.replace(RecipeConfig(), run_dir=config.run_dir)
    assert config.run_dir == "outputs/pusher_competency/default"
    study = {f.name: getattr(config, f.name) for f in dataclasses.fields(StudyConfig)}
    assert StudyConfig(**study) == StudyConfig()


@pytest.mark.parametrize("profile", ["quick", "full", "weak_arm", "action_noise"])
def test_profiles_hold_only_their_differences(profile):
    """Every value a profile file sets differs from the dataclass default (one home per number)."""
    values = yaml.safe_load((CONF / "profile" / f"{profile}.yaml").read_text())
    defaults = OmegaConf.to_container(OmegaConf.structured(RecipeConfig))

    def walk(node, default, path):
        for key, value in node.items():
            assert key in default, f"{path}{key}: not a setting"
            if isinstance(value, dict):
                walk(value, default[key], f"{path}{key}.")
            else:
                assert value != default[key], f"{path}{key}: equals the default {value!r}"

    walk(values, defaults, "")


def test_the_default_forecast_check_finds_the_largest_bias_the_targets_allow():
    """375 real episodes per condition name a bias of 0.10 (the per-condition tolerance of the
    study's targets) at the check's level with power 0.9, whatever the success rate."""
    from rcvae_torchrl.training import OutcomeCheck
    from recipes.pusher_competency.config import AssessConfig

    assert AssessConfig().check_episodes >= OutcomeCheck.episodes_to_find(0.10) > 100


def test_profiles_scale_up():
    quick, default, full = (_config(f"profile={p}") for p in ("quick", "default", "full"))
    assert quick.train.max_steps < default.train.max_steps <= full.train.max_steps
    assert quick.assess.start_states < default.assess.start_states < full.assess.start_states
    assert quick.data.scripted_episodes < default.data.scripted_episodes
    assert default.data.scripted_episodes < full.data.scripted_episodes
    assert quick.run_dir == "outputs/pusher_competency/quick"
    # a GPU's imagination is launch-bound at the default chunk: the full profile's are bigger
    assert full.assess.start_chunk > default.assess.start_chunk


def test_default_stochastic_design_is_a_weak_arm_with_a_little_per_step_noise():
    """The default stochastic condition: the arm's strength drawn once per episode in 0.2-0.4
    and action noise std 0.1 at every step; models with an episode latent, a quarter of their
    windows at episode starts, 10,000 training steps."""
    config = _config()
    assert config.data.stochastic_strength == [0.2, 0.4]
    assert config.data.stochastic_noise_std == pytest.approx(0.1)
    assert config.model.episode_latent_dim == 4 and config.train.episode_start_fraction == 0.25
    assert config.train.max_steps == 10000


def test_weak_arm_profile_is_the_default_without_per_step_noise():
    """Every setting of the weak-arm profile is the default's but the per-step noise, and a
    command-line override still wins over the profile."""
    default, weak = _config(), _config("profile=weak_arm")
    assert weak.data.stochastic_noise_std == 0 and weak.run_dir.endswith("/weak_arm")
    same = dataclasses.replace(
        weak,
        profile=default.profile,
        run_dir=default.run_dir,
        data=dataclasses.replace(weak.data, stochastic_noise_std=default.data.stochastic_noise_std),
    )
    assert same == default
    override = _config("profile=weak_arm", "data.stochastic_noise_std=0.2")
    assert override.data.stochastic_noise_std == pytest.approx(0.2)


def test_action_noise_profile_changes_only_the_stochastic_design():
    """The first design: a full-strength arm with per-step noise std 1.5, no episode latent, no
    start windows and half the training steps; every other setting is the default's."""
    default, noisy = _config(), _config("profile=action_noise")
    assert noisy.data.stochastic_strength is None and noisy.data.stochastic_noise_std == 1.5
    assert noisy.model.episode_latent_dim == 0 and noisy.train.episode_start_fraction == 0
    assert 2 * noisy.train.max_steps == default.train.max_steps
    assert noisy.run_dir == "outputs/pusher_competency/action_noise"
    for section in ("planner", "agent", "assess"):
        assert getattr(noisy, section) == getattr(default, section), section
    assert dataclasses.replace(noisy.model, episode_latent_dim=4) == default.model
    assert dataclasses.replace(noisy.train, max_steps=1, episode_start_fraction=0) == (
        dataclasses.replace(default.train, max_steps=1, episode_start_fraction=0)
    )


# --------------------------------------------------------------------------- overrides
def test_every_setting_can_be_overridden_without_plus():
    config = _config("profile=quick", "train.lr=0.01", "agent.distill.epochs=3", "seed=4")
    assert config.train.lr == pytest.approx(0.01)
    assert config.agent.distill.epochs == 3 and config.seed == 4
    assert config.train.max_steps == 60  # the profile's value stays


@pytest.mark.parametrize(
    "override",
    ["trian.max_steps=3", "train.max_step=3", "agent.distill.epoch=3", "bogus=1"],
)
def test_unknown_keys_are_rejected(override):
    with pytest.raises(ConfigCompositionException) as info:
        _compose(override)
    message = str(info.value.__cause__ or info.value)
    assert any(part in message for part in ("trian", "max_step", "epoch", "bogus"))


@pytest.mark.parametrize(
    "override",
    [
        "train.max_steps=ten",
        "progress=maybe",
        "seed=1.5",
        "assess.episode_end=perhaps",
    ],
)
def test_values_of_the_wrong_type_are_rejected(override):
    """Hydra refuses them while composing; the message names the key and the value."""
    key, _, value = override.partition("=")
    with pytest.raises(ConfigCompositionException) as info:
        _compose(override)
    message = str(info.value.__cause__)
    assert f"full_key: {key}" in message and repr(value) in message


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"threads": "abc"}, r"threads"),
        ({"progress": "maybe"}, r"progress"),
        ({"seed": 1.5}, r"seed"),
        ({"train": {"lr": "fast"}}, r"train\.lr"),
        ({"bogus": 1}, r"bogus"),
    ],
)
def test_a_plain_mapping_is_checked_the_same_way(overrides, match):
    """study_config on a mapping (no Hydra) names the setting of a wrong type."""
    with pytest.raises(ValueError, match=match):
        study_config(overrides)


def test_the_schema_is_the_base_of_every_profile():
    """Keys absent from a profile's YAML are overridable (the schema is the first default)."""
    config = _config("profile=quick", "train.lr=0.01", "train.beta=0.5", "assess.open_loop=true")
    assert (config.train.lr, config.train.beta, config.assess.open_loop) == (0.01, 0.5, True)
    full = _config("profile=full", "model.latent_dim=6", "data.time_limit=10.0")
    assert (full.model.latent_dim, full.data.time_limit, full.model.hidden_dim) == (6, 10.0, 128)


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("train.max_steps=0", r"^train\.max_steps: expected a positive integer, got 0"),
        ("train.window=1", r"^train\.window: expected >= 2 steps"),
        ("train.lr=-1", r"^train\.lr: expected a positive number, got -1"),
        ("assess.bias_correction=jackknife", r"^assess\.bias_correction: expected 'none'"),
        ("assess.horizon_s=2.03", r"^assess\.horizon_s: expected a positive whole number"),
        ("assess.horizon_s=inf", r"^assess\.horizon_s: expected a positive whole number"),
        ("data.scripted_episodes=-1", r"^data\.scripted_episodes: expected an integer >= 0"),
        ("data.exploration_std=-1", r"^data\.exploration_std: expected a finite number >= 0"),
        (
            "data.stochastic_strength=[0.4,0.2]",
            r"^data\.stochastic_strength: expected \(low, high\) with 0 < low <= high <= 1",
        ),
        (
            "data.stochastic_strength=[0.2]",
            r"^data\.stochastic_strength: expected \(low, high\), two numbers",
        ),
        ("model.ensemble_size=1", r"^model\.ensemble_size: expected an integer >= 2"),
        (
            "assess.samples_per_member=1",
            r"^assess\.samples_per_member: expected an integer >= 2, got 1",
        ),
        ("model.state_constraint=bogus", r"^model\.state_constraint: expected 'pusher' or None"),
        ("planner.top_k=500", r"^planner\.top_k: expected at most num_candidates"),
        ("planner.objective=best", r"^planner\.objective: expected one of"),
        ("seed=-1", r"^seed: expected an integer in \[0, 3000\] \(the study's real episodes"),
        (f"seed={MAX_SEED + 1}", rf"^seed: expected an integer in .*, got {MAX_SEED + 1}"),
        ("device=3", r"^device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got '3'"),
        ("device=tpu", r"^device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got 'tpu'"),
        ("device=meta", r"^device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got 'meta'"),
        ("device=cuda:99", r"^device: 'cuda:99' asked for, but"),
        ("train.beta=-1", r"^train\.beta: expected a positive number, got -1"),
        ("train.beta=0", r"^train\.beta: expected a positive number, got 0"),
        ("train.free_nats=-2", r"^train\.free_nats: expected a finite number >= 0, got -2"),
        ("train.open_loop_steps=-3", r"^train\.open_loop_steps: expected an integer >= 0"),
        ("train.nll_beta=2", r"^train\.nll_beta: expected a float in \[0, 1\]"),
        ("assess.horizon_s=-5", r"^assess\.horizon_s: expected a positive whole number"),
        ("assess.real_workers=0", r"^assess\.real_workers: expected an integer >= 1, got 0"),
        ("assess.check_episodes=0", r"^assess\.check_episodes: expected an integer >= 1, got 0"),
        (
            "assess.check_samples_per_member=1",
            r"^assess\.check_samples_per_member: expected an integer >= 2, got 1",
        ),
        (
            "assess.spread_runs=32",
            r"^assess\.spread_runs: expected None or samples_per_member=50 \(the real spread",
        ),
        ("data.time_limit=inf", r"^data\.time_limit: expected a positive whole number"),
        ("model.input_features=bogus", r"^model\.input_features: expected 'pusher' or None"),
        ("threads=0", r"^threads: expected a positive integer, 'auto' or null, got 0"),
        ("threads=-1", r"^threads: expected a positive integer, 'auto' or null, got -1"),
        ("threads=abc", r"^threads: expected a positive integer, 'auto' or null, got 'abc'"),
        ("threads=1.5", r"^threads: expected a positive integer, 'auto' or null, got 1.5"),
        ("run_dir=''", r"^run_dir: expected a directory path"),
        ("run_dir=' '", r"^run_dir: expected a directory path"),
        (
            "run_dir=/proc/x",
            r"^run_dir: expected a writable directory, got '/proc/x' \(no directory can be "
            r"created in its parent '/proc'",
        ),
        ("train.window=100000", r"train\.window: expected at most the longest data episode"),
        (
            "model.stochastic_open_loop_steps=-1",
            r"^model\.stochastic_open_loop_steps: expected an integer >= 0",
        ),
        ("model.episode_latent_dim=-1", r"^model\.episode_latent_dim: expected an integer >= 0"),
        (
            "train.episode_start_fraction=1.5",
            r"^train\.episode_start_fraction: expected a float in \[0, 1\]",
        ),
    ],
)
def test_out_of_range_values_name_their_setting(override, match):
    cfg = _compose(override)
    with pytest.raises(ValueError, match=match):
        study_config(cfg)


# --------------------------------------------------------------------------- run settings
def test_device_option():
    assert resolve_device("cpu") == "cpu"
    assert resolve_device("auto") == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            resolve_device("cuda:0")
        with pytest.raises(ValueError, match=r"^device: 'cuda' asked for"):
            study_config(_compose("device=cuda"))
    else:
        count = torch.cuda.device_count()
        assert resolve_device(f"cuda:{count - 1}") == f"cuda:{count - 1}"
        with pytest.raises(ValueError, match=rf"has {count} CUDA device"):
            resolve_device(f"cuda:{count}")
    for bad in (3, None, "tpu", "meta", "cuda:x", "CPU"):
        with pytest.raises(ValueError, match=rf"^device: expected .*got {bad!r}"):
            resolve_device(bad)


def test_the_largest_seed_is_accepted_and_seeds_every_real_episode_within_2_to_the_32():
    """Each recipe's largest seed keeps its real episodes' seeds (``seed·100_003 + episode``
    in ``real_outcomes``, up to 100_003 episodes a call) below 2**32; one more is refused up
    front, not after the study's training."""
    from recipes.point_mass_competency import config as point_mass_config
    from recipes.point_mass_competency import pipeline as point_mass
    from recipes.pusher_competency import pipeline as pusher

    assert _config(f"seed={MAX_SEED}").seed == MAX_SEED
    bases = (pusher.REAL_SEEDS, pusher.SPREAD_SEEDS, pusher.SHARE_SEEDS, pusher.HELD_OUT_SEEDS)
    largest = max(bases) + 10 * MAX_SEED + len(pusher.CONDITIONS) - 1
    assert (largest + 1) * 100_003 <= 2**32
    limit = point_mass_config.MAX_SEED
    assert point_mass_config.StudyConfig(seed=limit).seed == limit
    largest = point_mass.REAL_SEEDS + point_mass.CHECK_REAL_SEEDS + 100 * limit + 2
    assert (largest + 1) * 100_003 <= 2**32
    with pytest.raises(ValueError, match=rf"^seed: expected an integer in \[0, {limit}\]"):
        point_mass_config.StudyConfig(seed=limit + 1)
    assert SEED_MAX > MAX_SEED  # what a seed of any generator allows, more than a study does


def test_threads_are_set_and_checked():
    before = torch.get_num_threads()
    set_threads(None)
    assert torch.get_num_threads() == before
    set_threads(1)
    assert torch.get_num_threads() == 1
    assert set_threads("auto", op_flop=1.0) == 1  # a tiny op: one thread, whatever the machine
    assert _config().threads == "auto"  # the default
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match=rf"^threads: expected .*got {bad!r}"):
            set_threads(bad)


def test_run_dir_is_checked_before_anything_is_written(tmp_path):
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(
        ValueError,
        match=r"^run_dir: expected a writable directory.*no directory can be created in its "
        r"parent '.*file': Not a directory",
    ):
        study_config(_compose(f"run_dir={a_file}/run"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    with pytest.raises(ValueError, match=r"^run_dir: expected a directory, got .*existing file"):
        study_config(_compose(f"run_dir={a_file}"))
    fresh = tmp_path / "new" / "run"
    assert study_config(_compose(f"run_dir={fresh}")).run_dir == str(fresh)
    assert not fresh.parent.exists()  # checking creates nothing


def test_stochastic_open_loop_steps_apply_to_the_stochastic_ensemble_only(tmp_path):
    config = _config("model.stochastic_open_loop_steps=8")
    study = Study(config, tmp_path, torch.device("cpu"), progress=False)
    assert study._train_config("stochastic").open_loop_steps == 8
    assert study._train_config("deterministic") == config.train
    assert study._train_config("deterministic").open_loop_steps == 0
    shared = _config("train.open_loop_steps=2")
    study = Study(shared, tmp_path, torch.device("cpu"), progress=False)
    assert study._train_config("stochastic").open_loop_steps == 2


def test_the_stochastic_variant_takes_the_studys_randomness():
    """The study's envs of the stochastic variant draw the configured strength range and
    noise; ``data.stochastic_strength=null`` gives the full-strength arm."""
    from recipes.pusher_competency.pusher import make_env

    config = _config("data.stochastic_strength=[0.3,0.5]", "data.stochastic_noise_std=0.25")
    env = make_env("stochastic", config.data, 0.03)
    env.reset()
    task = env.base_env._env.task
    assert (task.actuator_strength, task.action_noise_std) == ((0.3, 0.5), 0.25)
    assert 0.3 <= task.strength <= 0.5
    plain = make_env("deterministic", config.data, 0.03).base_env._env.task
    assert (plain.actuator_strength, plain.action_noise_std) == (None, 0.0)
    config = _config("data.stochastic_strength=null")
    assert make_env("stochastic", config.data, 0.03).base_env._env.task.actuator_strength is None


def test_the_episode_latent_reaches_both_models():
    """``model.episode_latent_dim`` sizes the models' latent drawn once per episode (4 by
    default, 0 leaves them without one); the models carry the Pusher's dimension names."""
    from recipes.pusher_competency.pusher import rcvae_config

    assert rcvae_config(_config().model).episode_latent_dim == 4
    assert rcvae_config(_config("model.episode_latent_dim=0").model).episode_latent_dim == 0
    config = rcvae_config(_config("model.episode_latent_dim=3").model)
    assert config.episode_latent_dim == 3
    assert config.observation_names[:2] == ("shoulder_cos", "shoulder_sin")
    assert _config("train.episode_start_fraction=0.5").train.episode_start_fraction == 0.5


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ({"foo": 1}, r"^foo: not a setting of the recipe \(expected one of: agent, "),
        ({"train": {"max_step": 3}}, r"^train\.max_step: not a setting of train \(expected "),
        ({"agent": {"distill": {"epoch": 3}}}, r"^agent\.distill\.epoch: not a setting of"),
    ],
)
def test_keys_added_with_plus_are_checked_too(override, expected):
    """Hydra lets ``+key=value`` past its own check: the schema refuses it by name."""
    with pytest.raises(ValueError, match=expected):
        study_config(override)


def test_a_mistyped_key_on_the_command_line_is_named_before_hydra_runs():
    """Hydra's own message for an unknown key suggests ``+key=...``, which the schema then
    refuses: the command line is checked first, with the recipe's message; what is Hydra's
    (flags, groups, its own settings, ``+``/``~`` overrides) is left to it."""
    from recipes.pusher_competency.config import RecipeConfig

    fine = ["-m", "seed=0,1", "profile=quick", "assess.horizon_s=5", "hydra/launcher=local"]
    check_override_keys(RecipeConfig, [*fine, "hydra.job.chdir=false", "+x=1", "~seed"])
    check_override_keys(RecipeConfig, ["run_dir=a=b", "agent.distill.epochs=2", "--help"])
    with pytest.raises(SystemExit, match=r"^error: assess\.horizn_s: not a setting of assess \("):
        check_override_keys(RecipeConfig, [*fine, "assess.horizn_s=5"])
    with pytest.raises(SystemExit, match=r"^error: trian: not a setting of the recipe"):
        check_override_keys(RecipeConfig, ["trian.max_steps=3"])
    with pytest.raises(SystemExit, match=r"^error: agent\.distill\.epoch: not a setting of"):
        check_override_keys(RecipeConfig, ["agent.distill.epoch=3"])


def test_a_run_dir_under_home_is_the_folder_that_was_checked(monkeypatch, tmp_path):
    monkeypatch.setenv("HOME", str(tmp_path))
    assert study_config({"run_dir": "~/study"}).run_dir == str(tmp_path / "study")


def test_reuse_from_under_home_is_the_run_that_was_checked(monkeypatch, tmp_path):
    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "study_config.json").write_text("{}")
    config = study_config({"run_dir": "~/new", "reuse_from": "~/old"})
    assert config.reuse_from == str(tmp_path / "old")
    with pytest.raises(ValueError, match="reuse_from: expected another directory than run_dir"):
        study_config({"run_dir": "~/old", "reuse_from": str(tmp_path / "old")})
    with pytest.raises(ValueError, match=r"reuse_from: expected a run directory \(with its"):
        study_config({"run_dir": "~/new", "reuse_from": "~/missing"})


def test_a_nested_setting_is_named_by_its_whole_path():
    with pytest.raises(ValueError, match=r"^agent\.distill\.epochs: expected an int >= 1, got 0"):
        study_config({"agent": {"distill": {"epochs": 0}}})


def test_a_finished_run_is_opened_with_the_settings_it_recorded(tmp_path):
    """``study_of_run``: a run's recorded settings, a section's keys changed on request, or
    the settings of another run; a run that recorded none is named."""
    recorded = dataclasses.replace(_config("seed=3", "assess.start_states=7"), run_dir="x")
    write_json(tmp_path / "study_config.json", study_settings(recorded))
    study = study_of_run(tmp_path, changes={"agent": {"demo_envs": 4}})
    assert study.dir == tmp_path and study.cfg.run_dir == str(tmp_path)
    assert (study.cfg.seed, study.cfg.assess.start_states, study.cfg.agent.demo_envs) == (3, 7, 4)
    assert study.cfg.agent.mpc_episodes == recorded.agent.mpc_episodes  # the other keys kept
    elsewhere = tmp_path / "work"
    elsewhere.mkdir()
    assert study_of_run(elsewhere, settings_from=tmp_path).cfg.seed == 3
    with pytest.raises(StoredFileError, match=r"run config .*work/study_config.json"):
        study_of_run(elsewhere)
    with pytest.raises(ValueError, match="agnt: not a setting of the recipe"):
        study_of_run(tmp_path, changes={"agnt": {"demo_envs": 4}})


def test_sections_and_flags_built_in_python_are_of_their_types():
    """Hydra types them; built by hand, a dict for a section would skip its own checks and
    'no' for a flag would read as True."""
    from recipes.pusher_competency.config import RecipeConfig, StudyConfig

    with pytest.raises(TypeError, match=r"assess: expected AssessConfig settings .* got dict"):
        StudyConfig(assess={"start_states": -1})
    with pytest.raises(TypeError, match=r"data: expected DataConfig settings .* got NoneType"):
        StudyConfig(data=None)
    with pytest.raises(TypeError, match="progress: expected true or false, got 'no'"):
        RecipeConfig(progress="no")


def test_lists_built_in_python_are_lists():
    """A scalar where a section takes a list is named (it failed as "'float' object is not
    iterable"), in both recipes."""
    from recipes.point_mass_competency.config import AssessConfig as PointMassAssess
    from recipes.point_mass_competency.config import DataConfig as PointMassData
    from recipes.pusher_competency.config import AssessConfig

    with pytest.raises(ValueError, match=r"surface_radii: expected a list of values, got 0\.03"):
        AssessConfig(surface_radii=0.03)
    with pytest.raises(ValueError, match=r"surface_deadlines_s: expected a list .* got 12\.0"):
        AssessConfig(surface_deadlines_s=12.0)
    with pytest.raises(ValueError, match=r"exploration_std: expected a list of values, got 0\.3"):
        PointMassData(exploration_std=0.3)
    with pytest.raises(ValueError, match=r"bins: expected a list of values, got 0\.01"):
        PointMassAssess(bins=0.01)
    assert PointMassData(exploration_std=[0.3]).exploration_std == [0.3]


@pytest.mark.parametrize("recipe", ["pusher_competency", "point_mass_competency"])
def test_a_profile_named_in_a_mapping_brings_its_settings(recipe, tmp_path):
    """``{"profile": "quick"}`` is the quick profile as Hydra composes it, not the defaults
    under its name; an unknown profile is refused, built either way."""
    import importlib

    config = importlib.import_module(f"recipes.{recipe}.config")
    config.register_configs()
    run_dir = str(tmp_path / "run")
    with initialize_config_dir(config_dir=str(config.PROFILES.parent), version_base="1.3"):
        composed = config.study_config(
            compose(config_name=recipe, overrides=["profile=quick", f"run_dir={run_dir}"])
        )
    mapped = config.study_config({"profile": "quick", "run_dir": run_dir})
    assert mapped == composed
    assert mapped.train.max_steps != config.study_config({"run_dir": run_dir}).train.max_steps
    overridden = config.study_config({"profile": "quick", "run_dir": run_dir, "seed": 3})
    assert overridden == dataclasses.replace(composed, seed=3)
    with pytest.raises(
        ValueError, match=r"profile: expected one of \[.*'quick'.*\] \(.*\), got 'qiuck'"
    ):
        config.study_config({"profile": "qiuck", "run_dir": run_dir})
    with pytest.raises(ValueError, match=r"profile: expected one of .* got 'qiuck'"):
        config.RecipeConfig(profile="qiuck")


def test_a_printed_config_is_checked_like_a_run():
    """``--cfg job`` prints the composed config without calling the recipe: a setting out of
    range ends it with the recipe's message instead of being printed as if it ran; the machine
    (device, run_dir) is not judged, nor what Hydra itself refuses or prints."""
    from recipes._settings import check_printed_config
    from recipes.pusher_competency.config import PROFILES

    def check(*argv: str) -> None:
        check_printed_config(RecipeConfig, argv, CONF, "pusher_competency", PROFILES)

    with pytest.raises(SystemExit, match=r"^error: assess\.start_states: expected an integer >= 1"):
        check("--cfg", "job", "assess.start_states=-1")
    with pytest.raises(SystemExit, match=r"^error: train\.max_steps: expected a positive"):
        check("-c", "all", "profile=quick", "train.max_steps=0", "hydra.job.chdir=false")
    with pytest.raises(SystemExit, match=r"^error: data\.scripted_episodes: expected an integ"):
        check("--cfg", "job", "profile=quick", "data.scripted_episodes=-3")
    check("--cfg", "job", "device=cuda:7", "run_dir=/proc/x")  # another machine's config
    check("--cfg", "hydra", "assess.start_states=-1")  # Hydra's settings only
    check("assess.start_states=-1")  # a run: refused when it starts
    check("--cfg", "job", "assess.start_states=x")  # a wrong type: Hydra's own message

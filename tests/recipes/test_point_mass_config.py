"""The point-mass study's settings: the same up-front checks as the Pusher study's."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException

from recipes.point_mass_competency.config import register_configs, study_config

CONF = Path(__file__).resolve().parents[2] / "recipes" / "point_mass_competency" / "conf"
register_configs()


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(config_name="point_mass_competency", overrides=list(overrides))


def test_keys_missing_from_the_profile_are_overridable_without_plus():
    config = study_config(_compose("profile=quick", "train.lr=0.01", "task.kp=5.0", "seed=3"))
    assert (config.train.lr, config.task.kp, config.seed) == (0.01, 5.0, 3)
    assert config.train.max_steps == 40  # the quick profile's value stays


@pytest.mark.parametrize("override", ["progress=maybe", "seed=x"])
def test_values_of_the_wrong_type_name_their_key(override):
    key, _, value = override.partition("=")
    with pytest.raises(ConfigCompositionException) as info:
        _compose(override)
    message = str(info.value.__cause__)
    assert f"full_key: {key}" in message and repr(value) in message


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ("threads=0", r"^threads: expected a positive integer, 'auto' or null, got 0"),
        ("threads=abc", r"^threads: expected a positive integer, 'auto' or null, got 'abc'"),
        ("threads=1.5", r"^threads: expected a positive integer, 'auto' or null, got 1.5"),
        ("seed=-1", r"^seed: expected an integer in \[0, 200\] \(the study.s real episodes"),
        ("seed=201", r"^seed: expected an integer in \[0, 200\] .*got 201"),
        ("seed=4294967296", r"^seed: expected an integer in .*got 4294967296"),
        ("train.beta=-1", r"^train\.beta: expected a positive number"),
        ("train.free_nats=-2", r"^train\.free_nats: expected a finite number >= 0"),
        ("train.open_loop_steps=-3", r"^train\.open_loop_steps: expected an integer >= 0"),
        ("task.deadline_s=inf", r"^task\.deadline_s: expected a positive whole number"),
        ("data.episodes=2", r"^data\.episodes: expected an integer >= 3, got 2"),
        (
            "assess.samples_per_member=1",
            r"^assess\.samples_per_member: expected an integer >= 2, got 1",
        ),
        ("task.outer=0.29", r"^task\.inner, outer: expected inner <= outer < 0\.29 m"),
        (
            "data.exploration_std=[]",
            r"^data\.exploration_std: expected at least one std .*got \[\]",
        ),
        ("assess.real_workers=0", r"^assess\.real_workers: expected an integer >= 1, got 0"),
        ("run_dir=''", r"^run_dir: expected a directory path"),
        ("run_dir=/proc/x", r"^run_dir: expected a writable directory"),
        ("train.window=1000", r"^train\.window: expected at most the data episodes"),
    ],
)
def test_out_of_range_values_name_their_setting(override, match):
    with pytest.raises(ValueError, match=match):
        study_config(_compose(override))

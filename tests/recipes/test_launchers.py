"""The recipe's Hydra launchers: parallel local jobs (joblib) and Slurm (submitit, optional)."""

from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir

from recipes.point_mass_competency.config import register_configs as register_point_mass
from recipes.pusher_competency.config import register_configs

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
CONF = RECIPES / "pusher_competency" / "conf"
register_configs()
register_point_mass()


@pytest.mark.parametrize("recipe", ["pusher_competency", "point_mass_competency"])
def test_local_launcher_runs_jobs_in_parallel_processes(recipe):
    with initialize_config_dir(config_dir=str(RECIPES / recipe / "conf"), version_base="1.3"):
        cfg = compose(
            recipe,
            overrides=["hydra/launcher=local", "hydra.launcher.n_jobs=3"],
            return_hydra_config=True,
        )
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("joblib_launcher.JoblibLauncher")
    assert (launcher.n_jobs, launcher.backend, launcher.prefer) == (3, "loky", "processes")


def test_slurm_launcher_builds_on_submitit():
    text = (CONF / "hydra" / "launcher" / "slurm.yaml").read_text()
    assert text.startswith("# @package hydra.launcher")
    config = yaml.safe_load(text)
    assert config["defaults"] == ["submitit_slurm"]
    assert config["tasks_per_node"] == 1 and config["timeout_min"] > 0

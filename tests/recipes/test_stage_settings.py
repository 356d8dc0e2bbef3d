"""The settings each stage of a recipe declares (``STAGE_SETTINGS``) are all it reads.

A stage is reused from another run when the settings it declares are the same there; one it
reads without declaring would let a stale result through. The declared stages of a micro run of
each recipe (the Pusher's data, models and agent; the point mass's data and models) are run here
with a config that records every setting they read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch
from hydra import compose, initialize_config_dir
from micro import MICRO, POINT_MASS_MICRO

from recipes.point_mass_competency import config as point_mass_config
from recipes.point_mass_competency import pipeline as point_mass
from recipes.pusher_competency import config as pusher_config
from recipes.pusher_competency import pipeline as pusher

RECIPES = Path(__file__).resolve().parents[2] / "recipes"
pusher_config.register_configs()
point_mass_config.register_configs()
# a micro run's models are too small to learn: their checks warn, as they should
pytestmark = pytest.mark.filterwarnings("ignore::rcvae_torchrl.training.ModelCheckWarning")


class _Recorded:
    """Attribute reads of ``obj`` go into ``seen`` (as ``prefix + name``); the sections named
    in ``by_key`` are recorded key by key (the others as a whole: code may copy them)."""

    def __init__(self, obj: Any, seen: set[str], prefix: str = "", by_key: frozenset = frozenset()):
        self._obj, self._seen, self._prefix, self._by_key = obj, seen, prefix, by_key

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._obj, name)
        if not self._prefix and name in self._by_key:
            return _Recorded(value, self._seen, f"{name}.")
        self._seen.add(self._prefix + name)
        return value


def _study(recipe: str, run_dir: Path, config: Any) -> Any:
    if recipe == "pusher":
        return pusher.Study(config, run_dir, torch.device("cpu"), False)
    return point_mass.Study(config, run_dir, False)


@pytest.mark.parametrize("recipe", ["pusher", "point_mass"])
def test_the_early_stages_read_only_the_settings_they_declare(recipe, tmp_path):
    module, configs = (
        (pusher, pusher_config) if recipe == "pusher" else (point_mass, point_mass_config)
    )
    name = "pusher_competency" if recipe == "pusher" else "point_mass_competency"
    micro = MICRO if recipe == "pusher" else POINT_MASS_MICRO
    with initialize_config_dir(config_dir=str(RECIPES / name / "conf"), version_base="1.3"):
        cfg = compose(config_name=name, overrides=[*micro, f"run_dir={tmp_path}"])
    config = configs.study_config(cfg)
    settings = module.study_settings(config)
    keys = [k for declared in module.STAGE_SETTINGS.values() for k in declared]
    partly = frozenset(k.split(".")[0] for k in keys if "." in k)
    stages = list(module.STAGES)
    assert list(module.STAGE_SETTINGS) == stages[: len(module.STAGE_SETTINGS)]  # the first ones
    for stage, declared in module.STAGE_SETTINGS.items():
        seen: set[str] = set()
        getattr(_study(recipe, tmp_path, _Recorded(config, seen, by_key=partly)), stage)()
        # only study settings count (not how the recipe runs: run_dir, threads, ...)
        read = {k for k in seen if k.split(".")[0] in settings}
        undeclared = {k for k in read if k not in declared and k.split(".")[0] not in declared}
        assert not undeclared, f"stage {stage!r} reads {sorted(undeclared)} undeclared"
        assert read, f"stage {stage!r}: no setting read was recorded"


@pytest.mark.parametrize("recipe", ["pusher", "point mass"])
def test_every_stage_declares_the_code_of_its_env(recipe, tmp_path, monkeypatch):
    """A run resumed after the env's code changed runs its stages again (the runner's side is
    tested in tests/test_stages.py): every stage declares a digest of the env's files, which
    follows them (here a copy, edited)."""
    import shutil

    module = pusher if recipe == "pusher" else point_mass
    code = module.stage_code()
    assert set(code) == set(module.STAGES) and len(set(code.values())) == 1
    source = Path(
        pusher.pusher_domain.__file__ if recipe == "pusher" else point_mass.task_module.__file__
    )
    if recipe == "pusher":
        shutil.copytree(source.parent, tmp_path / "envs")
        copy = tmp_path / "envs" / "__init__.py"
        edited = tmp_path / "envs" / "pusher.xml"  # the MJCF model counts, not only Python
        monkeypatch.setattr(pusher.pusher_domain, "__file__", str(copy))
    else:
        edited = tmp_path / "task.py"
        shutil.copy(source, edited)
        monkeypatch.setattr(point_mass.task_module, "__file__", str(edited))
    assert module.stage_code() == code  # the same files, elsewhere
    edited.write_text(edited.read_text().replace("0", "1", 1))
    assert set(module.stage_code().values()).isdisjoint(code.values())

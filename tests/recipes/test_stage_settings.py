"""The settings each stage of the Pusher recipe declares (``STAGE_SETTINGS``) are all it reads.

A stage is reused from another run when the settings it declares are the same there; one it
reads without declaring would let a stale result through. The data, models and agent stages of
a micro run are run here with a config that records every setting they read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch
from hydra import compose, initialize_config_dir
from micro import MICRO

from recipes.pusher_competency.config import register_configs, study_config
from recipes.pusher_competency.pipeline import STAGE_SETTINGS, STAGES, Study, study_settings

CONF = Path(__file__).resolve().parents[2] / "recipes" / "pusher_competency" / "conf"
register_configs()
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


def test_the_early_stages_read_only_the_settings_they_declare(tmp_path):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="pusher_competency", overrides=[*MICRO, f"run_dir={tmp_path}"])
    config = study_config(cfg)
    settings = study_settings(config)
    partly = frozenset(
        k.split(".")[0] for keys in STAGE_SETTINGS.values() for k in keys if "." in k
    )
    assert list(STAGE_SETTINGS) == list(STAGES)[: len(STAGE_SETTINGS)]  # the first stages
    for stage, declared in STAGE_SETTINGS.items():
        seen: set[str] = set()
        study = Study(_Recorded(config, seen, by_key=partly), tmp_path, torch.device("cpu"), False)
        getattr(study, stage)()
        # only study settings count (not how the recipe runs: run_dir, threads, ...)
        read = {k for k in seen if k.split(".")[0] in settings}
        undeclared = {k for k in read if k not in declared and k.split(".")[0] not in declared}
        assert not undeclared, f"stage {stage!r} reads {sorted(undeclared)} undeclared"
        assert read, f"stage {stage!r}: no setting read was recorded"

"""The models stage with its world models trained side by side in worker processes: the same
models as one after the other, and the training curves in the run's logger."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from micro import MICRO

from recipes.pusher_competency.config import register_configs, study_config
from recipes.pusher_competency.pipeline import Study
from recipes.pusher_competency.pusher import WORLD_MODELS

CONF = Path(__file__).resolve().parents[2] / "recipes" / "pusher_competency" / "conf"
register_configs()
# micro budgets: the models learn little, which their self-checks say
pytestmark = pytest.mark.filterwarnings("ignore::rcvae_torchrl.training.ModelCheckWarning")


class RecordingLogger:
    """The logger interface the trainer uses (``log_scalar``), recording every call."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, float, int]] = []

    def log_scalar(self, name: str, value: float, step: int) -> None:
        self.calls.append((name, value, step))


def _config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="pusher_competency", overrides=[*MICRO, *overrides])
    return study_config(cfg)


def test_world_models_trained_in_two_workers_equal_those_trained_in_turn(tmp_path):
    config = _config("train_workers=2")
    assert config.train_workers == 2
    serial, parallel = tmp_path / "serial", tmp_path / "parallel"
    Study(config, serial, torch.device("cpu"), progress=False).data()
    shutil.copytree(serial / "data", parallel / "data")
    loggers, said = [RecordingLogger(), RecordingLogger()], []
    for run_dir, workers, logger in zip((serial, parallel), (1, 2), loggers, strict=True):
        study = Study(
            config, run_dir, torch.device("cpu"), False, logger, workers=workers, log=said.append
        )
        summary = study.models()
        assert set(summary) == set(WORLD_MODELS)
    assert said == [f"[models] training {', '.join(WORLD_MODELS)} in 2 worker processes"]
    for name in WORLD_MODELS:
        a = torch.load(serial / "models" / f"{name}.pt", weights_only=False)
        b = torch.load(parallel / "models" / f"{name}.pt", weights_only=False)
        assert a["extra"] == b["extra"]
        for key, value in a["state_dict"].items():
            assert torch.equal(value, b["state_dict"][key]), (name, key)
    # the workers' curves reach the run's logger when they finish: the same records
    assert loggers[0].calls and sorted(loggers[0].calls) == sorted(loggers[1].calls)
    assert {c[0].split("/")[1] for c in loggers[1].calls} == set(WORLD_MODELS)

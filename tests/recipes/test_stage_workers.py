"""A stage's independent jobs side by side in worker processes (``stage_workers``): the data of
both variants, both world models and the three conditions' forecasts equal those of one process
bit for bit, and the workers' training curves reach the run's logger."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from micro import MICRO
from tensordict import TensorDictBase

from recipes.pusher_competency.config import register_configs, study_config
from recipes.pusher_competency.pipeline import Study
from recipes.pusher_competency.pusher import CONDITIONS, WORLD_MODELS

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


def _assert_same(a, b, where: str) -> None:
    """Equal nested dicts / TensorDicts / tensors / plain values, tensors bit for bit."""
    if isinstance(a, TensorDictBase):
        a, b = a.to_dict(), b.to_dict()
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _assert_same(a[key], b[key], f"{where}/{key}")
    elif isinstance(a, torch.Tensor):
        assert torch.equal(a, b), where
    elif isinstance(a, tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, where


def _same_files(one: Path, other: Path, stage: str, names) -> None:
    for name in names:
        path = f"{stage}/{name}.pt"
        _assert_same(
            torch.load(one / path, weights_only=False),
            torch.load(other / path, weights_only=False),
            path,
        )


def test_stage_jobs_in_two_workers_equal_one_process(tmp_path):
    config = _config("stage_workers=2")
    assert config.stage_workers == 2
    serial, parallel = tmp_path / "serial", tmp_path / "parallel"
    loggers, said = [RecordingLogger(), RecordingLogger()], []
    studies = [
        Study(config, d, torch.device("cpu"), False, log_, workers=w, log=said.append)
        for d, w, log_ in zip((serial, parallel), (1, 2), loggers, strict=True)
    ]
    for study in studies:
        study.data()
    _same_files(serial, parallel, "data", WORLD_MODELS)
    for study in studies:
        assert set(study.models()) == set(WORLD_MODELS)
    _same_files(serial, parallel, "models", WORLD_MODELS)
    # the workers' curves reach the run's logger when they finish: the same records
    assert loggers[0].calls and sorted(loggers[0].calls) == sorted(loggers[1].calls)
    studies[0].agent()
    shutil.copytree(serial / "agent", parallel / "agent")
    forecasts = [study.forecast() for study in studies]
    assert forecasts[0] == forecasts[1]
    _same_files(serial, parallel, "forecast", CONDITIONS)
    # the report's forecast checks (forecasts and real episodes from unscored starts)
    checks = [s.side_by_side("report", list(CONDITIONS), "held_out_outcomes") for s in studies]
    assert [elsewhere for _, elsewhere in checks] == [False, True]
    _assert_same(checks[0][0], checks[1][0], "held_out_outcomes")
    assert said == [
        f"[data] {', '.join(WORLD_MODELS)} in 2 worker processes",
        f"[models] {', '.join(WORLD_MODELS)} in 2 worker processes",
        f"[forecast] {', '.join(CONDITIONS)} in 2 worker processes",
        f"[report] {', '.join(CONDITIONS)} in 2 worker processes",
    ]


@pytest.mark.parametrize("bad", ["0", "-1", "two", "1.5"])
def test_a_bad_stage_workers_setting_names_it(bad):
    with pytest.raises(ValueError, match=r"stage_workers: expected a positive integer or 'auto'"):
        _config(f"stage_workers={bad}")


def test_on_a_gpu_auto_runs_only_the_host_jobs_side_by_side(tmp_path, monkeypatch):
    """On a GPU, ``"auto"`` collects the data (the real env alone) in workers and runs the
    device's jobs (models, forecasts) one after the other; a count applies to every stage."""
    import recipes.pusher_competency.pipeline as pipeline

    monkeypatch.setattr(pipeline, "choose_workers", lambda jobs, setting: 2)
    config, gpu = _config(), torch.device("cuda")
    auto = Study(config, tmp_path, gpu, False, workers="auto")
    assert (auto.workers, auto.device_workers) == (2, 1)
    asked = Study(config, tmp_path, gpu, False, workers=2)
    assert (asked.workers, asked.device_workers) == (2, 2)
    cpu = Study(config, tmp_path, torch.device("cpu"), False, workers="auto")
    assert (cpu.workers, cpu.device_workers) == (2, 2)
    ran = []
    monkeypatch.setattr(
        pipeline, "map_in_processes", lambda fn, jobs, workers: ran.append(workers) or jobs
    )
    auto.side_by_side("data", WORLD_MODELS, "collect", host=True)
    assert ran == [2]
    monkeypatch.setattr(Study, "train_world_model", lambda self, name: ran.append(name))
    auto.side_by_side("models", WORLD_MODELS, "train_world_model")
    assert ran == [2, *WORLD_MODELS]  # here, one after the other

"""A stage's independent jobs side by side in worker processes (``stage_workers``): the data of
both variants, both world models, the three conditions' forecasts, the real outcomes, spreads
and shares of the truth stage and the report's checks equal those of one process bit for bit,
and the workers' training curves reach the run's logger."""

from __future__ import annotations

import dataclasses
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


def _config(*overrides: str, micro: bool = True):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        micro_overrides = MICRO if micro else ()
        cfg = compose(config_name="pusher_competency", overrides=[*micro_overrides, *overrides])
    return study_config(cfg)


def _assert_same(a, b, where: str) -> None:
    """Equal nested dicts / TensorDicts / tensors / plain values, tensors bit for bit."""
    if isinstance(a, TensorDictBase):
        a, b = a.to_dict(), b.to_dict()
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _assert_same(a[key], b[key], f"{where}/{key}")
    elif isinstance(a, torch.Tensor):  # bit for bit, NaN where NaN
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True, msg=where)
    elif dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        _assert_same(dataclasses.asdict(a), dataclasses.asdict(b), where)
    elif isinstance(a, (tuple, list)):
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
    config = _config("stage_workers=2", "assess.start_chunk=1")  # 2 chunks of start states
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
    # in two workers each condition's forecast in two parts, put together; a part of a run
    # stopped with another split is removed
    (parallel / "forecast").mkdir()
    torch.save({}, parallel / "forecast" / "stochastic.chunks0-7.pt")
    forecasts = [study.forecast() for study in studies]
    assert forecasts[0] == forecasts[1]
    _same_files(serial, parallel, "forecast", CONDITIONS)
    assert sorted(p.name for p in (parallel / "forecast").iterdir()) == sorted(
        f"{c}.pt" for c in CONDITIONS
    )
    parts = [f"{c}.chunks{k}-{k + 1}" for c in CONDITIONS for k in range(2)]
    truths = [study.truth() for study in studies]
    assert truths[0] == truths[1]
    jobs = studies[0].truth_jobs()  # the truth stage's files, each written by one job
    assert sorted(jobs) == sorted(p.stem for p in (serial / "truth").glob("*.pt"))
    _same_files(serial, parallel, "truth", jobs)
    # the report's forecast checks (forecasts and real episodes from unscored starts) and the
    # world models' far self-checks and dynamics checks
    report_jobs = list(studies[0].report_jobs())
    checks = [s.side_by_side("report", report_jobs, "report_job") for s in studies]
    assert [elsewhere for _, elsewhere in checks] == [False, True]
    assert list(checks[0][0]) == report_jobs
    _assert_same(checks[0][0], checks[1][0], "report jobs")
    assert said == [
        f"[data] {', '.join(WORLD_MODELS)} in 2 worker processes",
        f"[models] {', '.join(WORLD_MODELS)} in 2 worker processes",
        f"[forecast] {', '.join(parts)} in 2 worker processes",
        f"[truth] {', '.join(jobs)} in 2 worker processes",
        f"[report] {', '.join(report_jobs)} in 2 worker processes",
    ]


def test_the_truth_stage_jobs_come_longest_first(tmp_path):
    """The default profile's truth jobs, by the real episodes each runs: the stochastic
    condition's 100 starts x 30 runs, then the calibrations of the split (12 starts x 50 runs
    and a forecast), the spreads (12 x 50), the deterministic envs' outcomes (100 x 1); each
    the method that writes its file. Without spread starts, the outcomes alone."""
    config = _config(micro=False)
    jobs = Study(config, tmp_path, torch.device("cpu"), False).truth_jobs()
    assert jobs == {
        "stochastic": ("real_truth", "stochastic"),
        "deterministic_share": ("aleatoric_share", "deterministic"),
        "stochastic_share": ("aleatoric_share", "stochastic"),
        "deterministic_spread": ("real_spread", "deterministic"),
        "stochastic_spread": ("real_spread", "stochastic"),
        "out-of-distribution_spread": ("real_spread", "out-of-distribution"),
        "deterministic": ("real_truth", "deterministic"),
        "out-of-distribution": ("real_truth", "out-of-distribution"),
    }
    config = _config("assess.spread_starts=0", micro=False)
    jobs = Study(config, tmp_path, torch.device("cpu"), False).truth_jobs()
    assert list(jobs) == ["stochastic", "deterministic", "out-of-distribution"]


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

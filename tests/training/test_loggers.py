"""Training curves and stage summaries through TorchRL's loggers: csv, TensorBoard, W&B, MLflow.

Each backend is read back from what it wrote on disk. A backend whose package is not installed
is skipped with the reason (they are the package's extras: ``pip install .[tensorboard]``...).
"""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from rcvae_torchrl.loggers import LOGGER_BACKENDS, check_logger_backend, log_scalars, make_logger
from rcvae_torchrl.stages import StageRunner
from rcvae_torchrl.training import TrainConfig, train_ensemble

CONFIG = TrainConfig(max_steps=30, batch_windows=8, window=8, val_every=10, val_windows=16)
NAMES = ("train_loss", "val_loss", "best_val_loss", "members_improved")

pytestmark = pytest.mark.filterwarnings("ignore::rcvae_torchrl.training.ModelCheckWarning")


def _csv(root: Path) -> dict[str, list[tuple[int, float]]]:
    out = {}
    for path in root.rglob("scalars/**/*.csv"):
        name = path.relative_to(next(p for p in path.parents if p.name == "scalars"))
        rows = [line.split(",") for line in path.read_text().split()]
        out[str(name.with_suffix(""))] = [(int(s), float(v)) for s, v in rows]
    return out


def _tensorboard(root: Path) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = {}
    for events in root.rglob("events.out.tfevents.*"):
        acc = EventAccumulator(str(events.parent))
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            out[tag] = [(e.step, e.value) for e in acc.Scalars(tag)]
    return out


def _mlflow(root: Path) -> dict[str, list[tuple[int, float]]]:
    out = {}
    for path in root.rglob("metrics/**/*"):
        if path.is_file():
            name = path.relative_to(next(p for p in path.parents if p.name == "metrics"))
            rows = [line.split() for line in path.read_text().splitlines()]
            out[str(name)] = [(int(step), float(value)) for _, value, step in rows]
    return out


READERS = {"csv": _csv, "tensorboard": _tensorboard, "mlflow": _mlflow}


def _installed(backend: str) -> None:
    module = LOGGER_BACKENDS[backend]
    if module is not None and importlib.util.find_spec(module) is None:
        pytest.skip(f"{module} is not installed (the optional extra rcvae_torchrl[{backend}])")


@pytest.mark.parametrize("backend", ["csv", "tensorboard", "mlflow"])
def test_training_curves_reach_the_backend(backend, linear_data, small_ensemble, tmp_path):
    _installed(backend)
    train, val = linear_data
    logger = make_logger(backend, tmp_path / "logs", "trial")
    result = train_ensemble(
        small_ensemble(),
        train,
        val,
        CONFIG,
        logger=logger,
        log_prefix="models/linear/",
        progress=False,
    )
    logger.close()
    assert (tmp_path / "logs" / backend).is_dir()
    scalars = READERS[backend](tmp_path / "logs" / backend)
    for name in NAMES:
        logged = scalars[f"models/linear/{name}"]
        assert [s for s, _ in logged] == [int(r["step"]) for r in result.history]
        assert [v for _, v in logged] == pytest.approx([r[name] for r in result.history])


def test_wandb_runs_offline_and_keeps_the_curves(linear_data, small_ensemble, tmp_path):
    _installed("wandb")
    train, val = linear_data
    logger = make_logger("wandb", tmp_path / "logs", "trial")
    result = train_ensemble(
        small_ensemble(), train, val, CONFIG, logger=logger, log_prefix="models/x/", progress=False
    )
    logger.close()
    runs = list((tmp_path / "logs" / "wandb").rglob("offline-run-*/*.wandb"))
    assert len(runs) == 1, "one offline run, nothing synced"
    expected = [f"models/x/{name}".encode() for name in NAMES]
    expected.append(repr(result.history[-1]["val_loss"]).encode())
    data = _written(runs[0], expected)  # protobuf records: keys and JSON values as plain bytes
    assert [e for e in expected if e not in data] == []


def _written(path: Path, expected: list[bytes], timeout: float = 60.0) -> bytes:
    """The file once it holds every ``expected`` piece: W&B's service process writes an offline
    run's records on its own, a moment after ``finish`` returned (longer on a busy machine)."""
    deadline = time.monotonic() + timeout
    while True:
        data = path.read_bytes()
        if all(e in data for e in expected) or time.monotonic() > deadline:
            return data
        time.sleep(0.2)


def test_stage_summaries_are_logged(tmp_path):
    logger = make_logger("csv", tmp_path / "logs", "trial")
    runner = StageRunner(tmp_path / "run", log=lambda line: None, logger=logger)
    runner.run("data", lambda: {"frames": 120, "variant": "noisy", "rates": {"ok": 0.75}})
    runner.run("models", lambda: {"loss": 1.5})
    scalars = _csv(tmp_path / "logs" / "csv")
    assert scalars["stages/data/frames"] == [(0, 120.0)]
    assert scalars["stages/data/rates/ok"] == [(0, 0.75)]
    assert scalars["stages/models/loss"] == [(1, 1.5)]
    assert "stages/data/variant" not in scalars  # strings are not scalars
    again = StageRunner(tmp_path / "run", log=lambda line: None, logger=logger)
    again.run("data", lambda: pytest.fail("a finished stage runs again"))
    assert _csv(tmp_path / "logs" / "csv")["stages/data/frames"] == [(0, 120.0), (0, 120.0)]


@pytest.mark.parametrize("backend", ["csv", "mlflow"])
def test_check_names_become_names_every_backend_takes(backend, tmp_path):
    """A report's checks are named in words and symbols (``|``, ``<=``, ``/``): MLflow refused
    them (every run with logger=mlflow failed) and the CSV logger made folders of the ``/``."""
    _installed(backend)
    logger = make_logger(backend, tmp_path / "logs", "trial")
    checks = {
        "aleatoric stochastic / deterministic >= 1.5": {"value": 2.1},
        "|forecast - real| <= 0.10 (deterministic)": {"value": 0.03},
    }
    names = log_scalars(logger, {"checks": checks}, step=0, prefix="stages/report/")
    logger.close()
    assert names == [
        "stages/report/checks/aleatoric_stochastic_over_deterministic_ge_1.5/value",
        "stages/report/checks/forecast_-_real_le_0.10_deterministic/value",
    ]
    if backend == "csv":
        assert _csv(tmp_path / "logs" / "csv")[names[1]] == [(0, 0.03)]


def test_log_scalars_flattens_and_keeps_finite_numbers():
    logged = []

    class Recorder:
        def log_scalar(self, name, value, step=None):
            logged.append((name, value, step))

    names = log_scalars(
        Recorder(), {"a": 1, "b": {"c": 2.5, "d": "text"}, "e": float("nan"), "f": True}, 7, "p/"
    )
    assert names == ["p/a", "p/b/c", "p/f"]
    assert logged == [("p/a", 1.0, 7), ("p/b/c", 2.5, 7), ("p/f", 1.0, 7)]
    assert log_scalars(None, {"a": 1}, 0) == []


def test_none_and_bad_backends(tmp_path):
    assert make_logger("none", tmp_path, "x") is None
    with pytest.raises(ValueError, match=r"logger: expected one of .*'tensorboard'.* got 'tb'"):
        make_logger("tb", tmp_path, "x")
    with pytest.raises(ValueError, match=r"settings\.logger: expected one of"):
        check_logger_backend("csvv", name="settings.logger")


def test_a_missing_backend_names_its_extra(tmp_path, monkeypatch):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ImportError, match=r"pip install 'rcvae_torchrl\[wandb\]'"):
        make_logger("wandb", tmp_path, "x")


def test_tensors_and_numpy_scalars_are_logged_as_floats(tmp_path):
    """A 0-d tensor (a loss) and a NumPy scalar were left out silently, though every finite
    number is logged."""
    logger = make_logger("csv", tmp_path / "logs", "trial")
    values = {
        "loss": torch.tensor(0.5),
        "acc": np.float32(0.25),
        "count": np.int64(4),
        "one": torch.tensor([1.5]),
        "array": np.array([2.0]),
        "n": 3,
        "vector": torch.ones(2),  # not one number: left out as before
        "nan": torch.tensor(float("nan")),
    }
    names = log_scalars(logger, values, np.int64(2))
    assert names == ["loss", "acc", "count", "one", "array", "n"]
    scalars = _csv(tmp_path / "logs" / "csv")
    assert {name: scalars[name] for name in names} == {
        "loss": [(2, 0.5)], "acc": [(2, 0.25)], "count": [(2, 4.0)], "one": [(2, 1.5)],
        "array": [(2, 2.0)], "n": [(2, 3.0)],
    }  # fmt: skip


def test_keys_that_become_one_name_are_refused_naming_both(tmp_path):
    logger = make_logger("csv", tmp_path / "logs", "trial")
    with pytest.raises(ValueError, match=r"^values: the keys 'a>b' and 'a_gt_b' both become"):
        log_scalars(logger, {"a>b": 1.0, "a_gt_b": 2.0}, 0)
    with pytest.raises(ValueError, match=r"'x' / 'a>b' and 'x ' / 'a_gt_b' .* 'p/x/a_gt_b'"):
        log_scalars(logger, {"x": {"a>b": 1.0}, "x ": {"a_gt_b": 2.0}}, 0, prefix="p/")
    # a key whose value is not logged takes no name
    assert log_scalars(logger, {"a>b": "text", "a_gt_b": 2.0}, 0) == ["a_gt_b"]


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"step": "x"}, TypeError, r"^step: expected an integer >= 0, got str 'x'"),
        ({"step": 1.0}, TypeError, r"^step: expected an integer >= 0, got float 1\.0"),
        ({"step": True}, TypeError, r"^step: expected an integer >= 0, got bool True"),
        ({"step": -1}, ValueError, r"^step: expected an integer >= 0, got -1"),
        ({"prefix": None}, TypeError, r"^prefix: expected a str .* got NoneType None"),
        ({"values": [1, 2]}, TypeError, r"^values: expected a mapping .* got list \[1, 2\]"),
        ({"logger": "csv"}, TypeError, r"^logger: expected a TorchRL Logger .* got str 'csv'"),
    ],
)
def test_bad_log_scalars_arguments_are_named(kwargs, error, match, tmp_path):
    arguments = {"logger": make_logger("csv", tmp_path, "x"), "values": {"a": 1.0}, "step": 0}
    with pytest.raises(error, match=match):
        log_scalars(**{**arguments, **kwargs})


@pytest.mark.parametrize("name", ["../../escape", "a/b", "..", ".", "", "a\\b"])
def test_an_exp_name_that_is_not_a_plain_name_is_refused(name, tmp_path):
    with pytest.raises(ValueError, match=r"^exp_name: expected a plain name"):
        make_logger("csv", tmp_path / "logs", name)
    assert not tmp_path.exists() or list(tmp_path.iterdir()) == []  # nothing written


def test_bad_make_logger_arguments_are_named(tmp_path):
    with pytest.raises(ValueError, match=r"^logger: expected one of .* got \['csv'\]"):
        make_logger(["csv"], tmp_path, "x")
    with pytest.raises(TypeError, match=r"^log_dir: expected a folder's path .* got NoneType"):
        make_logger("csv", None, "x")
    with pytest.raises(TypeError, match=r"^exp_name: expected the experiment's name .* None"):
        make_logger("csv", tmp_path, None)

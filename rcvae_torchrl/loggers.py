"""Experiment loggers of the user's choice, through TorchRL's logger factory.

- :func:`make_logger`: a TorchRL :class:`~torchrl.record.loggers.Logger` of one of
  :data:`LOGGER_BACKENDS` (``"csv"``, ``"tensorboard"``, ``"wandb"``, ``"mlflow"``) or ``None``
  for ``"none"``. Everything stays on the local disk: Weights & Biases runs offline (``wandb
  sync`` uploads a run later) and MLflow writes a local file store. The optional backends are
  the package's extras (``pip install rcvae_torchrl[tensorboard]``, ``[wandb]``, ``[mlflow]``).
- :func:`log_scalars`: a (nested) mapping of numbers logged as scalars under one prefix, the one
  way training records and stage summaries reach a logger.
"""

from __future__ import annotations

import importlib.util
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from torchrl.record.loggers import Logger, get_logger

__all__ = ["LOGGER_BACKENDS", "check_logger_backend", "log_scalars", "make_logger"]

#: The loggers :func:`make_logger` builds, and the module each one needs.
LOGGER_BACKENDS = {
    "csv": None,
    "tensorboard": "tensorboard",
    "wandb": "wandb",
    "mlflow": "mlflow",
    "none": None,
}


def check_logger_backend(backend: str, name: str = "logger") -> str:
    """``backend`` if it is one of :data:`LOGGER_BACKENDS`; else a ValueError naming ``name``."""
    if backend not in LOGGER_BACKENDS:
        raise ValueError(f"{name}: expected one of {sorted(LOGGER_BACKENDS)}, got {backend!r}")
    return backend


def make_logger(
    backend: str, log_dir: str | Path, exp_name: str, *, project: str = "rcvae_torchrl"
) -> Logger | None:
    """A TorchRL logger writing under ``log_dir/<backend>`` (``None`` for ``"none"``).

    Args:
        backend: one of :data:`LOGGER_BACKENDS`.
        log_dir: the folder of all loggers of a run (e.g. ``<run dir>/logs``).
        exp_name: the experiment's name (e.g. from
            :func:`torchrl.record.loggers.generate_exp_name`).
        project: the Weights & Biases project.

    Raises:
        ValueError: an unknown backend.
        ImportError: the backend's package is not installed (the message names the extra).

    Example:
        >>> import tempfile
        >>> logger = make_logger("csv", tempfile.mkdtemp(), "demo")
        >>> log_scalars(logger, {"loss": 0.5, "info": {"steps": 3}}, step=0, prefix="train/")
        ['train/loss', 'train/info/steps']
    """
    check_logger_backend(backend)
    if backend == "none":
        return None
    module = LOGGER_BACKENDS[backend]
    if module is not None and importlib.util.find_spec(module) is None:
        raise ImportError(
            f"logger={backend!r} needs the {module!r} package: "
            f"pip install 'rcvae_torchrl[{backend}]'"
        )
    kwargs: dict[str, Any] = {}
    if backend == "wandb":
        kwargs["wandb_kwargs"] = {"offline": True, "project": project}
    if backend == "mlflow":
        # MLflow 3 refuses a file store unless asked; a local store is what this logger is for
        os.environ.setdefault("MLFLOW_ALLOW_FILE_STORE", "true")
    logger = get_logger(backend, str(Path(log_dir) / backend), exp_name, **kwargs)
    if backend == "mlflow":
        _end_run_on_close(logger.experiment)
    return logger


def _end_run_on_close(run: Any) -> None:
    """TorchRL's MLflow logger starts a run that its ``close`` leaves active, so the next
    logger of the process cannot start one ("Run ... is already active"): ``close`` ends it."""
    import mlflow

    def close() -> None:
        active = mlflow.active_run()
        if active is not None and active.info.run_id == run.info.run_id:
            mlflow.end_run()

    run.close = close


_WORDS = {">=": "_ge_", "<=": "_le_", ">": "_gt_", "<": "_lt_", "/": "_over_", "±": "_pm_"}


def scalar_name(key: object) -> str:
    """``key`` as one segment of a scalar's name that every backend takes: letters, digits,
    ``_``, ``-`` and ``.`` only (MLflow refuses ``|`` or ``>``, and a ``/`` would make a
    folder of the CSV and TensorBoard loggers); comparisons become words.

    Example:
        >>> scalar_name("|forecast - real| <= 0.10 (deterministic)")
        'forecast_-_real_le_0.10_deterministic'
    """
    text = str(key)
    for symbol, word in _WORDS.items():
        text = text.replace(symbol, word)
    text = re.sub(r"[^A-Za-z0-9_.-]+", "_", text)
    return re.sub(r"_+", "_", text).strip("_") or "_"


def _numbers(values: Mapping[str, Any], prefix: str) -> dict[str, float]:
    out = {}
    for key, value in values.items():
        if isinstance(value, Mapping):
            out.update(_numbers(value, f"{prefix}{scalar_name(key)}/"))
        elif isinstance(value, (bool, int, float)) and math.isfinite(value):
            out[f"{prefix}{scalar_name(key)}"] = float(value)
    return out


def log_scalars(
    logger: Logger | None, values: Mapping[str, Any], step: int, prefix: str = ""
) -> list[str]:
    """Log every finite number in ``values`` (nested mappings joined with ``/``) at ``step``.

    Values that are not numbers (strings, lists) are left out. Returns the names logged
    (none when ``logger`` is None).
    """
    if logger is None:
        return []
    scalars = _numbers(values, prefix)
    for name, value in scalars.items():
        logger.log_scalar(name, value, step=step)
    return list(scalars)

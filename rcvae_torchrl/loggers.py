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
import numbers
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torchrl.record.loggers import Logger, get_logger

from rcvae_torchrl._checks import check_choice

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
    check_choice(name, backend, list(LOGGER_BACKENDS))
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
        ValueError: an unknown backend, or an ``exp_name`` that is not a plain name (empty,
            ``.`` or ``..``, or holding a path separator: the logs would go elsewhere than
            under ``log_dir``).
        TypeError: a ``log_dir`` that is not a path, or an ``exp_name`` that is not a str.
        ImportError: the backend's package is not installed (the message names the extra).

    Example:
        >>> import tempfile
        >>> logger = make_logger("csv", tempfile.mkdtemp(), "demo")
        >>> log_scalars(logger, {"loss": 0.5, "info": {"steps": 3}}, step=0, prefix="train/")
        ['train/loss', 'train/info/steps']
    """
    check_logger_backend(backend)
    if not isinstance(log_dir, (str, os.PathLike)):
        raise TypeError(
            f"log_dir: expected a folder's path (a str or Path), got {type(log_dir).__name__} "
            f"{log_dir!r}"
        )
    _check_exp_name(exp_name)
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


def _check_exp_name(exp_name: object) -> None:
    """Require a plain name: one folder under ``log_dir``, not a path leading out of it."""
    if not isinstance(exp_name, str):
        raise TypeError(
            f"exp_name: expected the experiment's name (a str), got {type(exp_name).__name__} "
            f"{exp_name!r}"
        )
    separators = {"/", "\\", os.sep, os.altsep} - {None}
    if exp_name in ("", ".", "..") or any(sep in exp_name for sep in separators):
        raise ValueError(
            "exp_name: expected a plain name (not empty, '.' or '..', and no path separator: "
            f"the logs are written to a folder of that name under log_dir), got {exp_name!r}"
        )


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


def _number(value: object) -> float | None:
    """``value`` as a float where it is a real number (Python's, a NumPy scalar, or a tensor
    or NumPy array of one element), else ``None``."""
    if isinstance(value, (bool, int, float, np.bool_, np.integer, np.floating)):
        return float(value)
    if isinstance(value, torch.Tensor) and value.numel() == 1 and not value.dtype.is_complex:
        return float(value.item())
    if isinstance(value, np.ndarray) and value.size == 1 and value.dtype.kind in "biuf":
        return float(value.item())
    return None


def _numbers(
    values: Mapping[str, Any], prefix: str, path: tuple[object, ...], keys: dict[str, tuple]
) -> dict[str, float]:
    out = {}
    for key, value in values.items():
        if isinstance(value, Mapping):
            out.update(_numbers(value, f"{prefix}{scalar_name(key)}/", (*path, key), keys))
            continue
        number = _number(value)
        if number is None or not math.isfinite(number):
            continue
        name = f"{prefix}{scalar_name(key)}"
        if name in keys:
            raise ValueError(
                f"values: the keys {_key_path(keys[name])} and {_key_path((*path, key))} both "
                f"become the scalar name {name!r} (one would overwrite the other); rename one"
            )
        keys[name] = (*path, key)
        out[name] = number
    return out


def _key_path(path: tuple[object, ...]) -> str:
    """Where a value is in the nested mapping, as its keys joined: ``'a' / 'b>c'``."""
    return " / ".join(repr(key) for key in path)


def log_scalars(
    logger: Logger | None, values: Mapping[str, Any], step: int, prefix: str = ""
) -> list[str]:
    """Log every finite number in ``values`` (nested mappings joined with ``/``) at ``step``.

    Numbers are Python's, NumPy's scalars, and tensors or NumPy arrays of one element (logged
    as floats). Values that are not numbers (strings, lists) are left out. Returns the names
    logged (none when ``logger`` is None).

    Raises:
        TypeError: ``logger`` is neither None nor a logger (an object with ``log_scalar``),
            ``values`` is not a mapping, ``step`` is not an integer or ``prefix`` not a str.
        ValueError: ``step`` is negative, or two keys become the same scalar name (``a>b``
            and ``a_gt_b``: one would overwrite the other).
    """
    if logger is not None and not callable(getattr(logger, "log_scalar", None)):
        raise TypeError(
            "logger: expected a TorchRL Logger (from make_logger) or None, got "
            f"{type(logger).__name__} {logger!r}"
        )
    if not isinstance(values, Mapping):
        raise TypeError(
            f"values: expected a mapping of names to numbers, got {type(values).__name__} "
            f"{values!r}"
        )
    if isinstance(step, bool) or not isinstance(step, numbers.Integral):
        raise TypeError(f"step: expected an integer >= 0, got {type(step).__name__} {step!r}")
    if step < 0:
        raise ValueError(f"step: expected an integer >= 0, got {step!r}")
    if not isinstance(prefix, str):
        kind = type(prefix).__name__
        raise TypeError(f"prefix: expected a str (e.g. 'train/' or ''), got {kind} {prefix!r}")
    if logger is None:
        return []
    scalars = _numbers(values, prefix, (), {})
    for name, value in scalars.items():
        logger.log_scalar(name, value, step=int(step))
    return list(scalars)

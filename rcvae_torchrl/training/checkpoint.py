"""One-file ensemble checkpoints: weights, normalisation, config and a format version.

``save_ensemble`` writes atomically; ``load_ensemble`` rebuilds the ensemble and raises
:class:`CheckpointError` with a clear message for a missing, corrupt, truncated, foreign or
mismatched file.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch

from rcvae_torchrl.io import StoredFileError, atomic_write, load_torch
from rcvae_torchrl.models import ModelFunctions, RCVAEConfig, RCVAEEnsemble

from .checks import ModelChecks

__all__ = ["FORMAT_VERSION", "CheckpointError", "load_ensemble", "save_ensemble"]

FORMAT_VERSION = 1
_KIND = "rcvae_torchrl.RCVAEEnsemble"


class CheckpointError(StoredFileError):
    """A checkpoint file cannot be used: missing, corrupt, truncated, foreign or mismatched."""


def ensemble_payload(ensemble: RCVAEEnsemble, extra: dict[str, Any] | None = None) -> dict:
    """The checkpoint content of ``ensemble`` (CPU tensors), as written by :func:`save_ensemble`."""
    return {
        "kind": _KIND,
        "format_version": FORMAT_VERSION,
        "config": dataclasses.asdict(ensemble.config),
        "ensemble_size": ensemble.ensemble_size,
        "state_dict": {k: v.detach().cpu() for k, v in ensemble.state_dict().items()},
        "extra": extra or {},
        "checks": None if getattr(ensemble, "checks", None) is None else ensemble.checks.as_dict(),
    }


def save_ensemble(
    ensemble: RCVAEEnsemble, path: str | Path, extra: dict[str, Any] | None = None
) -> Path:
    """Write ``ensemble`` (weights, normalisation, config, format version) to ``path`` atomically.

    Args:
        ensemble: the trained ensemble.
        path: destination file (parent folders are created).
        extra: small picklable metadata stored beside (e.g. the data it was trained on).
    """
    payload = ensemble_payload(ensemble, extra)
    return atomic_write(path, lambda f: torch.save(payload, f))


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a checkpoint dict from ``path`` with clear errors (no model is built)."""
    path = Path(path)
    try:
        payload = load_torch(path, "checkpoint")
    except StoredFileError as err:
        raise CheckpointError(str(err), path) from err.__cause__
    if not isinstance(payload, dict) or "kind" not in payload:
        raise CheckpointError(
            f"checkpoint {str(path)!r}: expected an rcvae_torchrl checkpoint", path
        )
    return payload


def load_ensemble(
    path: str | Path,
    *,
    map_location: str | torch.device = "cpu",
    expected_config: RCVAEConfig | None = None,
    functions: ModelFunctions | None = None,
) -> RCVAEEnsemble:
    """Rebuild the ensemble saved by :func:`save_ensemble`.

    Args:
        path: the checkpoint file.
        map_location: device of the returned ensemble.
        expected_config: if given, the saved config must equal it.
        functions: the state constraint and input features the saved config names (a
            :class:`~rcvae_torchrl.models.ModelFunctions`); needed when it names any.

    Raises:
        CheckpointError: missing, corrupt or truncated file; another kind of file; an unknown
            format version; a config or weights that do not match.
    """
    payload = read_checkpoint(path)
    ensemble = ensemble_from_payload(payload, str(path), expected_config, functions)
    return ensemble.to(map_location)


def ensemble_from_payload(
    payload: dict[str, Any],
    source: str,
    expected_config: RCVAEConfig | None = None,
    functions: ModelFunctions | None = None,
) -> RCVAEEnsemble:
    """Build an ensemble from a checkpoint dict, checking kind, version, config and weights."""
    if payload.get("kind") != _KIND:
        raise CheckpointError(
            f"checkpoint {source!r}: expected kind {_KIND!r}, got {payload.get('kind')!r}", source
        )
    version = payload.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            f"checkpoint {source!r}: expected format version {FORMAT_VERSION}, got {version!r}",
            source,
        )
    try:
        config = RCVAEConfig(**payload["config"])
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"checkpoint {source!r}: invalid config: {err}", source) from err
    if expected_config is not None and config != expected_config:
        raise CheckpointError(
            f"checkpoint {source!r}: config mismatch: expected {expected_config}, got {config}",
            source,
        )
    try:
        ensemble = RCVAEEnsemble(config, int(payload["ensemble_size"]), functions=functions)
    except KeyError as err:
        raise CheckpointError(f"checkpoint {source!r}: {err.args[0]}", source) from err
    try:
        ensemble.load_state_dict(payload["state_dict"], strict=True)
    except RuntimeError as err:
        raise CheckpointError(
            f"checkpoint {source!r}: weights do not match: {err}", source
        ) from err
    if payload.get("checks") is not None:
        ensemble.checks = ModelChecks.from_dict(payload["checks"])
    return ensemble

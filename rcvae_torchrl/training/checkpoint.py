"""One-file ensemble checkpoints: weights, normalisation, config and a format version.

``save_ensemble`` writes atomically, with a checksum of the content; ``load_ensemble`` rebuilds
the ensemble and raises :class:`CheckpointError` with a clear message for a missing, corrupt
(a changed byte included), truncated, foreign or mismatched file.
"""

from __future__ import annotations

import dataclasses
import io
import pickle
from pathlib import Path
from typing import Any

import torch

from rcvae_torchrl.io import StoredFileError, load_torch, save_torch
from rcvae_torchrl.models import ModelFunctions, RCVAEConfig, RCVAEEnsemble

from .checks import ModelChecks
from .dynamics import DynamicsNovelty
from .novelty import StateNovelty

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
        "novelty": None
        if getattr(ensemble, "novelty", None) is None
        else ensemble.novelty.as_dict(),
        "dynamics": None
        if getattr(ensemble, "dynamics", None) is None
        else ensemble.dynamics.as_dict(),
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
    if not isinstance(ensemble, RCVAEEnsemble):
        raise TypeError(f"ensemble: expected an RCVAEEnsemble, got {type(ensemble).__name__}")
    _check_extra(extra)
    payload = ensemble_payload(ensemble, extra)
    for name, value in payload["state_dict"].items():  # load_ensemble refuses them
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ValueError(
                f"ensemble: {name!r} holds NaN or infinite values (its training diverged?), "
                "and load_ensemble refuses such a model: nothing was written"
            )
    return save_torch(path, payload)


def _check_extra(extra: object) -> None:
    """Refuse metadata that :func:`load_ensemble` could not read back (it loads with
    ``weights_only=True``, which takes tensors, numbers, strings and their containers only), so
    that no checkpoint is written that then reads as corrupt."""
    if extra is None:
        return
    if not isinstance(extra, dict):
        raise TypeError(f"extra: expected a dict of metadata or None, got {type(extra).__name__}")
    buffer = io.BytesIO()
    try:
        torch.save(extra, buffer)
        buffer.seek(0)
        torch.load(buffer, weights_only=True)
    except (pickle.PicklingError, pickle.UnpicklingError, TypeError, AttributeError) as err:
        raise TypeError(
            "extra: expected tensors, numbers, strings, None and lists, tuples or dicts of "
            "them (what a checkpoint loads back with weights_only=True; e.g. str() a Path), "
            f"got {extra!r}: {str(err).splitlines()[0]}"
        ) from err


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a checkpoint dict from ``path`` with clear errors (no model is built)."""
    try:
        payload = load_torch(path, "checkpoint")
    except StoredFileError as err:
        raise CheckpointError(str(err), err.path) from err.__cause__
    path = Path(path)
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
    if expected_config is not None and not isinstance(expected_config, RCVAEConfig):
        raise TypeError(
            "expected_config: expected an RCVAEConfig or None, got "
            f"{type(expected_config).__name__}"
        )
    device = _device(map_location)
    payload = read_checkpoint(path)
    if "training" in payload:  # train_ensemble's checkpoint_path: for resuming, not a model
        raise CheckpointError(
            f"checkpoint {str(path)!r}: expected a model saved by save_ensemble, got a training "
            "checkpoint (train_ensemble's checkpoint_path: the weights of its last validation, "
            "without the best weights training keeps or the model's self-checks); load the "
            "model save_ensemble wrote after training, or continue training from this file with "
            "train_ensemble(..., checkpoint_path=it, resume=True)",
            path,
        )
    ensemble = ensemble_from_payload(payload, str(path), expected_config, functions)
    return ensemble.to(device)


def _device(map_location: object) -> torch.device:
    """``map_location`` as a device this machine has."""
    try:
        device = torch.device(map_location)  # type: ignore[arg-type]
    except (RuntimeError, TypeError) as err:
        raise ValueError(
            f"map_location: expected a device (e.g. 'cpu' or 'cuda:0'), got {map_location!r}"
        ) from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(
            f"map_location: {map_location!r} asked for, but CUDA is not available here"
        )
    return device


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
    for key in ("config", "ensemble_size", "state_dict"):
        if key not in payload:
            raise CheckpointError(f"checkpoint {source!r}: no {key!r} entry", source)
    try:
        config = RCVAEConfig(**payload["config"])
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"checkpoint {source!r}: invalid config: {err}", source) from err
    if expected_config is not None and config != expected_config:
        theirs, ours = dataclasses.asdict(config), dataclasses.asdict(expected_config)
        differ = "; ".join(
            f"{k}: expected {ours.get(k)!r}, got {theirs.get(k)!r}"
            for k in sorted(ours.keys() | theirs.keys())
            if ours.get(k) != theirs.get(k)
        )
        raise CheckpointError(
            f"checkpoint {source!r}: config mismatch ({differ}): expected {expected_config}, "
            f"got {config}",
            source,
        )
    size = payload["ensemble_size"]
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise CheckpointError(
            f"checkpoint {source!r}: ensemble_size: expected a positive int, got {size!r}", source
        )
    try:
        # seeded: its weights are the checkpoint's, and torch's generator is left as it was
        ensemble = RCVAEEnsemble(config, size, functions=functions, seed=0)
    except KeyError as err:
        raise CheckpointError(f"checkpoint {source!r}: {err.args[0]}", source) from err
    state = payload["state_dict"]
    if not isinstance(state, dict):
        raise CheckpointError(
            f"checkpoint {source!r}: state_dict: expected a dict of tensors, got "
            f"{type(state).__name__}",
            source,
        )
    # in the weights' own precision: load_state_dict copies into the new model's (float32)
    # tensors, which would round a float64 model's weights silently
    tensors = [v for v in state.values() if isinstance(v, torch.Tensor)]
    saved = {v.dtype for v in tensors if v.is_floating_point()}
    if len(saved) == 1:
        ensemble = ensemble.to(saved.pop())
    try:
        ensemble.load_state_dict(state, strict=True)
    except RuntimeError as err:
        raise CheckpointError(
            f"checkpoint {source!r}: weights do not match: {err}", source
        ) from err
    for name, value in ensemble.state_dict().items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise CheckpointError(
                f"checkpoint {source!r}: {name!r} holds NaN or infinite values (a model "
                "saved after its training diverged?)",
                source,
            )
    if payload.get("checks") is not None:
        ensemble.checks = _record(payload, "checks", ModelChecks, "self-check results", source)
    if payload.get("novelty") is not None:
        novelty = _record(payload, "novelty", StateNovelty, "training states (novelty)", source)
        if novelty.dim != ensemble.config.obs_dim:
            raise CheckpointError(
                f"checkpoint {source!r}: its training states (novelty) have {novelty.dim} "
                f"dimensions, the model's observations {ensemble.config.obs_dim}",
                source,
            )
        ensemble.novelty = novelty
    if payload.get("dynamics") is not None:
        dynamics = _record(
            payload, "dynamics", DynamicsNovelty, "one-step errors (dynamics check)", source
        )
        if len(dynamics.names) != ensemble.config.obs_dim:
            raise CheckpointError(
                f"checkpoint {source!r}: its one-step errors (dynamics check) have "
                f"{len(dynamics.names)} dimensions, the model's observations "
                f"{ensemble.config.obs_dim}",
                source,
            )
        ensemble.dynamics = dynamics
    return ensemble


def _record(payload: dict, key: str, kind: Any, what: str, source: str) -> Any:
    """``kind.from_dict(payload[key])``, a corrupt record a :class:`CheckpointError`."""
    try:
        return kind.from_dict(payload[key])
    except (KeyError, TypeError, ValueError) as err:
        raise CheckpointError(
            f"checkpoint {source!r}: its {what} are corrupt: {type(err).__name__}: {err}",
            source,
        ) from err

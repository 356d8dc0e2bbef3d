"""Saving collected episodes (flat TensorDicts) atomically, and loading them back."""

from __future__ import annotations

from pathlib import Path

from tensordict import TensorDict, TensorDictBase

from rcvae_torchrl.io import StoredFileError, load_torch, save_torch

__all__ = ["load_episodes", "save_episodes"]


def save_episodes(data: TensorDictBase, path: str | Path) -> Path:
    """Write a flat TensorDict ``[frames]`` of tensors to ``path`` (atomic, tensors only)."""
    if not isinstance(data, TensorDictBase):
        raise TypeError(f"data: expected a flat TensorDict [frames], got {type(data).__name__}")
    if data.ndim != 1:
        raise ValueError(f"data: expected a flat TensorDict [frames], got {tuple(data.shape)}")
    payload = {"batch_size": list(data.shape), "data": data.to_dict()}
    return save_torch(path, payload)


def load_episodes(path: str | Path) -> TensorDict:
    """Load what :func:`save_episodes` wrote; a missing, truncated or corrupt file is a
    :class:`~rcvae_torchrl.io.StoredFileError` naming it."""
    payload = load_torch(path, "episodes file")
    if not isinstance(payload, dict) or not {"data", "batch_size"} <= payload.keys():
        found = (
            f"a dict of {sorted(map(str, payload))}"
            if isinstance(payload, dict)
            else f"a {type(payload).__name__}"
        )
        kind = (
            f" (a {payload['kind']!r} file)"
            if isinstance(payload, dict) and "kind" in payload
            else ""
        )
        raise StoredFileError(
            f"episodes file {str(path)!r}: expected what save_episodes writes, a dict of "
            f"'batch_size' and 'data', got {found}{kind}",
            path,
        )
    try:
        return TensorDict(payload["data"], batch_size=payload["batch_size"])
    except Exception as err:
        raise StoredFileError(
            f"episodes file {str(path)!r}: expected what save_episodes writes: {err}", path
        ) from err

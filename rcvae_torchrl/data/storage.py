"""Saving collected episodes (flat TensorDicts) atomically, and loading them back."""

from __future__ import annotations

import io
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase

from rcvae_torchrl.training.atomic import atomic_write

__all__ = ["load_episodes", "save_episodes"]


def save_episodes(data: TensorDictBase, path: str | Path) -> Path:
    """Write a flat TensorDict ``[frames]`` of tensors to ``path`` (atomic, tensors only)."""
    if data.ndim != 1:
        raise ValueError(f"data: expected a flat TensorDict [frames], got {tuple(data.shape)}")
    payload = {"batch_size": list(data.shape), "data": data.to_dict()}
    return atomic_write(path, lambda f: torch.save(payload, f))


def load_episodes(path: str | Path) -> TensorDict:
    """Load what :func:`save_episodes` wrote, with a clear error for a damaged file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: expected an episodes file, got {str(path)!r}")
    try:
        payload = torch.load(io.BytesIO(path.read_bytes()), weights_only=True)
        return TensorDict(payload["data"], batch_size=payload["batch_size"])
    except Exception as err:
        raise ValueError(f"episodes file {str(path)!r} is corrupt or truncated: {err}") from err

"""What each spawned rank runs (importable by name in the spawned processes)."""

from __future__ import annotations

import importlib.util
import os
import signal
from pathlib import Path

import torch

from rcvae_torchrl import distributed
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.training import TrainConfig, train_ensemble

_spec = importlib.util.spec_from_file_location(
    "training_fixtures", Path(__file__).resolve().parents[1] / "training" / "conftest.py"
)
fixtures = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fixtures)

CONFIG = TrainConfig(max_steps=40, batch_windows=16, window=8, val_every=10, val_windows=32)


def linear_data():
    train = fixtures.linear_episodes(12, 40, seed=0)
    val = fixtures.linear_episodes(4, 40, seed=1)
    val[fixtures.TRAJ_KEY] += 100
    return train, val


def small_ensemble(members: int = 4, seed: int = 0) -> RCVAEEnsemble:
    torch.manual_seed(seed)
    return RCVAEEnsemble(RCVAEConfig(3, 1, hidden_dim=16, latent_dim=2, mlp_dim=16), members)


def train(out: str, ckpt: str | None = None, kill_rank: int = -1, kill_at: int = -1) -> None:
    """Train the 4-member ensemble; rank ``kill_rank`` kills itself (SIGKILL) at step
    ``kill_at`` (before that validation's checkpoint); rank 0 saves the result to ``out``."""

    class KillAt:
        def log_scalar(self, name, value, step):
            if distributed.rank() == kill_rank and step == kill_at:
                os.kill(os.getpid(), signal.SIGKILL)

    train_data, val_data = linear_data()
    result = train_ensemble(
        small_ensemble(),
        train_data,
        val_data,
        CONFIG,
        checkpoint_path=ckpt,
        resume=ckpt is not None,
        logger=KillAt(),
        progress=False,
        checks=False,
    )
    if distributed.is_main():
        torch.save(
            {
                "weights": result.ensemble.state_dict(),
                "steps": result.steps,
                "best_val": result.best_val,
                "history": result.history,
            },
            out,
        )

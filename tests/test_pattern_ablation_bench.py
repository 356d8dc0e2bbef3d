"""``benchmarks/pattern_ablation.py``: the aleatoric ratio second by second."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import pattern_ablation

from rcvae_torchrl.envs import CONTROL_TIMESTEP


def test_per_second_reads_every_whole_second_of_both_conditions():
    steps_per_s = round(1.0 / CONTROL_TIMESTEP)
    steps = 3 * steps_per_s
    t = torch.arange(steps, dtype=torch.float32)
    det = {"aleatoric": 1.0 + t, "running": 1.0 - t / steps}
    ood = {"aleatoric": 2.0 * (1.0 + t), "running": torch.full((steps,), 0.5)}
    rows = pattern_ablation._per_second(det, ood)
    assert [r["second"] for r in rows] == [0, 1, 2]
    for r in rows:
        step = r["second"] * steps_per_s
        assert r["ratio"] == pytest.approx(2.0)
        assert r["running_det"] == pytest.approx(1.0 - step / steps)
        assert r["running_ood"] == pytest.approx(0.5)

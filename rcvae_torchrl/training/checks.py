"""Has the model learned what it must? Per-dimension self-checks on held-out episodes.

A falling validation loss does not say that every state dimension was learned: a dimension the
model predicts no better than copying the previous state (or than guessing its mean) makes a
forecast that looks confident and is wrong. :func:`check_model` measures, per state
dimension, on held-out episodes:

- the one-step error (teacher forced: the true history, the model's point prediction of the
  next state) against two baselines: copying the previous state, and the dimension's spread in
  the data (the error of predicting its mean);
- the open-loop error after ``k`` steps (the mean of imagined rollouts driven by the episode's
  own actions) against the same baselines (copying the start state).

A predicted dimension whose one-step error is not at least ``min_gain`` below the better of the
two baselines is flagged: the model has not learned it. :func:`train_ensemble
<rcvae_torchrl.training.train_ensemble>` runs the checks after training, warns naming the
flagged dimensions, and stores them with the model; the competency assessor flags a forecast
made with a model that failed them.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase

from rcvae_torchrl.data import TRAJ_KEY, make_window_buffer, sample_windows
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout import imagine

__all__ = ["ModelCheckWarning", "ModelChecks", "check_model"]


class ModelCheckWarning(UserWarning):
    """A state dimension the model predicts no better than a trivial baseline."""


@dataclass(frozen=True)
class ModelChecks:
    """Per-dimension errors of a model on held-out episodes (RMSE, state units, ``[S]``)."""

    names: tuple[str, ...]
    one_step: torch.Tensor  #: the model's one-step error
    copy_one_step: torch.Tensor  #: copying the previous state
    spread: torch.Tensor  #: the dimension's std in the data (predicting its mean)
    k_step: torch.Tensor  #: the mean open-loop forecast's error after ``k`` steps
    copy_k_step: torch.Tensor  #: copying the start state
    k: int
    checked: tuple[int, ...]  #: the dimensions checked (predicted and not constant)
    min_gain: float

    @property
    def flagged(self) -> tuple[int, ...]:
        """Checked dimensions whose one-step error is not ``min_gain`` below both baselines."""
        best = torch.minimum(self.copy_one_step, self.spread)
        bad = self.one_step >= (1.0 - self.min_gain) * best
        return tuple(d for d in self.checked if bool(bad[d]))

    @property
    def passed(self) -> bool:
        return not self.flagged

    def message(self) -> str:
        """One sentence naming the flagged dimensions and their errors ('' when none)."""
        if self.passed:
            return ""
        parts = [
            f"{self.names[d]} (one-step error {float(self.one_step[d]):.3g} vs "
            f"{float(torch.minimum(self.copy_one_step[d], self.spread[d])):.3g} for a trivial "
            "baseline)"
            for d in self.flagged
        ]
        return (
            "the world model has not learned "
            + ", ".join(parts)
            + ": it predicts these dimensions no better than copying the previous state or "
            "guessing their mean, so forecasts that depend on them are not trustworthy"
        )

    def as_dict(self) -> dict[str, Any]:
        """Plain values (for checkpoints and JSON)."""
        out: dict[str, Any] = {
            "names": list(self.names),
            "k": self.k,
            "checked": list(self.checked),
            "min_gain": self.min_gain,
            "flagged": [self.names[d] for d in self.flagged],
        }
        for key in ("one_step", "copy_one_step", "spread", "k_step", "copy_k_step"):
            out[key] = getattr(self, key).tolist()
        return out

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ModelChecks:
        tensors = {
            k: torch.tensor(values[k], dtype=torch.float64)
            for k in ("one_step", "copy_one_step", "spread", "k_step", "copy_k_step")
        }
        return cls(
            tuple(values["names"]),
            k=int(values["k"]),
            checked=tuple(values["checked"]),
            min_gain=float(values["min_gain"]),
            **tensors,
        )


def _rmse(error: torch.Tensor) -> torch.Tensor:
    """Root mean square over every axis but the last: ``[..., S] -> [S]`` (float64)."""
    return error.to(torch.float64).square().reshape(-1, error.shape[-1]).mean(0).sqrt()


def _longest_episode(data: TensorDictBase) -> int:
    return int(torch.unique_consecutive(data.get(TRAJ_KEY), return_counts=True)[1].max())


def _windows(data: TensorDictBase, length: int, count: int, seed: int) -> TensorDictBase:
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        return sample_windows(make_window_buffer(data, length), count, length)


@torch.no_grad()
def check_model(
    ensemble: RCVAEEnsemble,
    data: TensorDictBase,
    *,
    k: int = 10,
    window: int = 16,
    windows: int = 256,
    samples_per_member: int = 8,
    min_gain: float = 0.05,
    seed: int = 0,
    warn: bool = True,
) -> ModelChecks:
    """The self-checks of the module docstring on held-out episodes ``data`` ``[frames]``.

    Args:
        ensemble: the trained model (its config's ``names`` name the dimensions).
        data: held-out whole episodes (``split_episodes``' validation part).
        k: open-loop steps (windows of ``k + 1`` frames).
        window: length of the one-step windows.
        windows: windows drawn for each check.
        samples_per_member: imagined samples per member for the open-loop mean.
        min_gain: how far below the better baseline a dimension's one-step error must be.
        seed: the windows and the samples are drawn from it.
        warn: emit a :class:`ModelCheckWarning` naming the flagged dimensions.
    """
    cfg, e = ensemble.config, ensemble.ensemble_size
    device = ensemble.device
    longest = _longest_episode(data)
    if longest < 2:
        raise ValueError(f"data: expected episodes of at least 2 steps, got at most {longest}")
    window, k = min(window, longest), min(k, longest - 1)
    one = _windows(data, window, windows, seed).to(device)
    obs, act = one.get("observation"), one.get("action")
    predicted = ensemble.predict_next(obs.expand(e, *obs.shape), act.expand(e, *act.shape))
    truth = obs[..., 1:, :]
    one_step = _rmse(predicted.mean(0) - truth)
    copy_one_step = _rmse(truth - obs[..., :-1, :])
    spread = data.get("observation").to(torch.float64).std(0, correction=0)
    many = _windows(data, k + 1, windows, seed + 1).to(device)
    starts, truth_k = many.get("observation")[:, 0], many.get(("next", "observation"))[:, k - 1]
    generator = torch.Generator(device=device).manual_seed(seed)
    rollouts = imagine(
        ensemble,
        starts,
        many.get("action")[:, :k],
        samples_per_member=samples_per_member,
        generator=generator,
    )
    forecast = rollouts.get("observation")[..., k - 1, :].mean((0, 1))
    k_step, copy_k_step = _rmse(forecast - truth_k), _rmse(truth_k - starts)
    changing = (copy_one_step > 0) | (spread > 0)
    checked = tuple(d for d in cfg.predicted_dims if bool(changing[d]))
    checks = ModelChecks(
        cfg.names,
        one_step.cpu(),
        copy_one_step.cpu(),
        spread.cpu(),
        k_step.cpu(),
        copy_k_step.cpu(),
        k,
        checked,
        float(min_gain),
    )
    if warn and not checks.passed:
        warnings.warn(checks.message(), ModelCheckWarning, stacklevel=2)
    return checks

"""How close imagined trajectories come to what really happened: errors, bands, spread.

Pure tensor functions over imagined samples ``[E, N, *B, T, D]`` (member, sample, start state,
time, dimension) and the real trajectories ``[*B, T, D]`` from the same start states and actions;
the state-level counterpart of :mod:`~rcvae_torchrl.competency.calibration` (which scores
outcome forecasts).
"""

from __future__ import annotations

import torch

__all__ = ["band_coverage", "constant_baseline_error", "forecast_error", "forecast_spread"]


def _pooled(samples: torch.Tensor) -> torch.Tensor:
    """``[E, N, *B, T, D]`` -> ``[E·N, *B, T, D]``: the ensemble mixture's samples."""
    if samples.ndim < 4:
        raise ValueError(
            f"samples: expected [E, N, *B, T, D] (>= 4 dims), got {tuple(samples.shape)}"
        )
    return samples.flatten(0, 1)


def _check_truth(samples: torch.Tensor, truth: torch.Tensor) -> None:
    if samples.shape[2:] != truth.shape:
        raise ValueError(
            f"truth: expected shape {tuple(samples.shape[2:])} (samples without [E, N]), "
            f"got {tuple(truth.shape)}"
        )


def forecast_error(samples: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Euclidean distance ``[*B, T]`` between the pooled median forecast and the truth.

    Distances are taken over the last dimension, so pass only the dimensions that matter
    (e.g. an object's x, y).
    """
    _check_truth(samples, truth)
    median = _pooled(samples).median(dim=0).values
    return torch.linalg.vector_norm(median - truth, dim=-1)


def band_coverage(
    samples: torch.Tensor, truth: torch.Tensor, low: float = 0.05, high: float = 0.95
) -> torch.Tensor:
    """Whether the truth lies inside the pooled ``[low, high]`` quantile band, ``[*B, T]`` bool.

    A step counts as covered when every dimension of the truth is inside its band.
    """
    _check_truth(samples, truth)
    if not 0.0 <= low < high <= 1.0:
        raise ValueError(f"low, high: expected 0 <= low < high <= 1, got {low}, {high}")
    q = torch.quantile(_pooled(samples), torch.tensor([low, high], dtype=samples.dtype), dim=0)
    return ((truth >= q[0]) & (truth <= q[1])).all(dim=-1)


def forecast_spread(samples: torch.Tensor) -> torch.Tensor:
    """Root of the summed per-dimension variance of the pooled samples, ``[*B, T]``."""
    return _pooled(samples).var(dim=0).sum(-1).sqrt()


def constant_baseline_error(truth: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    """Error ``[*B, T]`` of forecasting that nothing moves: ``|truth_t - start|``."""
    if start.shape != truth.shape[:-2] + truth.shape[-1:]:
        raise ValueError(
            f"start: expected shape {tuple(truth.shape[:-2] + truth.shape[-1:])}, "
            f"got {tuple(start.shape)}"
        )
    return torch.linalg.vector_norm(truth - start.unsqueeze(-2), dim=-1)

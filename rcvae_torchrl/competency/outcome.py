"""Forecast task outcomes from imagined trajectories: P(success), its uncertainty, time to success.

Outcome tensors have the ensemble layout ``[E, N, *batch]`` (member, sample, batch), or
``[E, N, *batch, T]`` over time. P(success) is the mean over all ``E·N`` trajectories, and the
binary entropy of the outcome splits like the state entropy of the paper's equations 2 and 3:
``H2(p) = mean_m H2(p_m) + epistemic`` (Acharya, Russell & Ahmed, 2022, Table 1).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from rcvae_torchrl.competency import _checks
from rcvae_torchrl.competency._binning import LN2
from rcvae_torchrl.competency.decomposition import UncertaintyDecomposition

__all__ = [
    "TimeToSuccess",
    "binary_entropy",
    "first_success_step",
    "outcome_uncertainty",
    "success_on_grid",
    "success_probability",
    "time_to_success",
]

_LAYOUT = "[E, N, *batch]"


def _as_probability(name: str, x: Tensor) -> Tensor:
    """Bool or [0, 1] tensor -> float tensor, validated."""
    if x.dtype == torch.bool:
        return x.float()
    _checks.check_probability(name, x)
    return x if x.is_floating_point() else x.float()


def success_probability(success: Tensor) -> tuple[Tensor, Tensor]:
    """P(success) over all trajectories and per ensemble member.

    Args:
        success: ``[E, N, *batch]`` bool, or floats in [0, 1] (soft outcomes).

    Returns:
        ``p`` ``[*batch]`` (mean over ``E·N``) and ``p_member`` ``[E, *batch]`` (mean over ``N``).

    Example:
        >>> p, p_m = success_probability(torch.tensor([[True, True], [True, False]]))
        >>> float(p), p_m.tolist()
        (0.75, [1.0, 0.5])
    """
    _checks.check_min_rank("success", success, 2, _LAYOUT)
    x = _as_probability("success", success)
    p_member = x.mean(dim=1)
    return p_member.mean(dim=0), p_member


def binary_entropy(p: Tensor) -> Tensor:
    """``H2(p) = -p·log2 p - (1-p)·log2(1-p)`` in bits, elementwise; 0 at p in {0, 1}.

    Example:
        >>> binary_entropy(torch.tensor([0.0, 0.5, 1.0])).tolist()
        [0.0, 1.0, 0.0]
    """
    p = _as_probability("p", torch.as_tensor(p))
    nats = torch.special.xlogy(p, p) + torch.special.xlogy(1 - p, 1 - p)
    return -nats / LN2 + 0.0  # + 0.0 turns -0.0 into 0.0


def outcome_uncertainty(success: Tensor) -> UncertaintyDecomposition:
    """Binary-entropy decomposition of the forecast outcome, in bits.

    total = ``H2(p)``, aleatoric = ``mean_m H2(p_m)``, epistemic = total - aleatoric, in
    ``[0, 1]`` (concavity of ``H2``; float round-off clamped).

    Args:
        success: ``[E, N, *batch]`` bool or floats in [0, 1], ``E >= 2``.

    Returns:
        :class:`~rcvae_torchrl.competency.UncertaintyDecomposition` of ``[*batch]`` tensors.

    Example:
        >>> u = outcome_uncertainty(torch.tensor([[True] * 4, [False] * 4]))
        >>> float(u.total), float(u.aleatoric), float(u.epistemic)
        (1.0, 0.0, 1.0)
    """
    _checks.check_min_rank("success", success, 2, _LAYOUT)
    _checks.check_members("success", success, _LAYOUT)
    p, p_member = success_probability(success)
    total = binary_entropy(p)
    aleatoric = binary_entropy(p_member).mean(dim=0)
    return UncertaintyDecomposition(total, aleatoric, (total - aleatoric).clamp(0.0, 1.0))


def first_success_step(success_over_time: Tensor) -> Tensor:
    """Index of the first step with success along the last axis; ``T`` when never.

    Args:
        success_over_time: bool ``[..., T]``.

    Returns:
        int64 ``[...]`` in ``[0, T]``.

    Example:
        >>> first_success_step(torch.tensor([[False, True, True], [False, False, False]])).tolist()
        [1, 3]
    """
    _checks.check_min_rank("success_over_time", success_over_time, 1, "[..., T]")
    if success_over_time.dtype != torch.bool:
        raise TypeError(
            f"success_over_time: expected a bool tensor, got dtype {success_over_time.dtype}"
        )
    horizon = success_over_time.shape[-1]
    first = success_over_time.to(torch.uint8).argmax(dim=-1)
    return torch.where(success_over_time.any(dim=-1), first, horizon)


class TimeToSuccess(NamedTuple):
    """Distribution of the first-success step (see :func:`time_to_success`)."""

    first_step: Tensor  #: int64 ``[E, N, *batch]``, ``T`` for trajectories that never succeed
    step_probability: Tensor  #: ``[*batch, T]`` P(first success at step t)
    success_by_step: Tensor  #: ``[*batch, T]`` P(success at or before step t), non-decreasing
    mean_steps: Tensor  #: ``[*batch]`` mean first-success step among successes (inf if none)
    #: ``[*batch]`` median first-success step among successes, the lower one of an even count
    #: (inf if none)
    median_steps: Tensor


def time_to_success(success_over_time: Tensor) -> TimeToSuccess:
    """Distribution over time of the first success, pooled over members and samples.

    Args:
        success_over_time: bool ``[E, N, *batch, T]``, true where the trajectory is in the success
            region at step ``t``.

    Returns:
        :class:`TimeToSuccess`; its last ``success_by_step`` entry equals P(success).

    Example:
        >>> s = torch.zeros(2, 2, 4, dtype=torch.bool)
        >>> s[0, 0, 1:] = True; s[1, 1, 3] = True
        >>> tts = time_to_success(s)
        >>> tts.success_by_step.tolist(), float(tts.mean_steps)
        ([0.0, 0.25, 0.25, 0.5], 2.0)
    """
    _checks.check_min_rank("success_over_time", success_over_time, 3, "[E, N, *batch, T]")
    first = first_success_step(success_over_time)
    horizon = success_over_time.shape[-1]
    trajectories = first.flatten(0, 1).movedim(0, -1)  # [*batch, E·N]
    counts = torch.zeros(
        (*trajectories.shape[:-1], horizon + 1), dtype=torch.float64, device=first.device
    )
    counts.scatter_add_(-1, trajectories, torch.ones_like(trajectories, dtype=torch.float64))
    step_probability = counts[..., :horizon] / trajectories.shape[-1]
    success_by_step = step_probability.cumsum(dim=-1)
    steps = torch.arange(horizon, dtype=torch.float64, device=first.device)
    p = success_by_step[..., -1]
    mean = (step_probability * steps).sum(dim=-1) / p
    # the lower median, from whole counts: with the probabilities' float sums, rounding decided
    # a tie at exactly half the successes (10 successes gave the 5th, 100 the 51st)
    by_step = counts[..., :horizon].cumsum(dim=-1)
    median = (2 * by_step < by_step[..., -1:]).sum(dim=-1).double()
    never = p == 0
    inf = torch.full_like(p, float("inf"))
    return TimeToSuccess(
        first,
        step_probability.float(),
        success_by_step.float(),
        torch.where(never, inf, mean).float(),
        torch.where(never, inf, median).float(),
    )


def success_on_grid(distance: Tensor, radii: Tensor, deadlines: Tensor) -> Tensor:
    """Success on a grid of boundaries, from a per-step distance to the goal.

    A trajectory succeeds for radius ``r`` and deadline ``d`` (in steps) when its distance is
    at most ``r`` at some step ``t < d``: one set of trajectories (imagined or real) answers
    every boundary of the grid. NaN distances (steps after an episode ended without success)
    never count.

    Args:
        distance: ``[..., T]``.
        radii: ``[R]`` positive.
        deadlines: ``[D]`` integers in ``[1, T]``.

    Returns:
        bool ``[..., R, D]``.

    Example:
        >>> d = torch.tensor([0.5, 0.2, 0.05])
        >>> success_on_grid(d, torch.tensor([0.1, 0.3]), torch.tensor([2, 3])).tolist()
        [[False, True], [True, True]]
    """
    _checks.check_min_rank("distance", distance, 1, "[..., T]")
    horizon = distance.shape[-1]
    deadlines = torch.as_tensor(deadlines, dtype=torch.int64, device=distance.device)
    radii = torch.as_tensor(radii, dtype=distance.dtype, device=distance.device)
    if deadlines.numel() and (int(deadlines.min()) < 1 or int(deadlines.max()) > horizon):
        raise ValueError(f"deadlines: expected steps in [1, T={horizon}], got {deadlines.tolist()}")
    if not bool((radii > 0).all()):
        raise ValueError(f"radii: expected positive radii, got {radii.tolist()}")
    inside = distance.unsqueeze(-2) <= radii.unsqueeze(-1)  # [..., R, T]; NaN compares False
    reached = inside.cummax(dim=-1).values  # success at or before step t
    return reached[..., deadlines - 1]

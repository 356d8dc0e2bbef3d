"""Forecasts of an agent's success held against its real episodes, start state by start state.

A forecast gives each start state ``b`` a probability ``f_b`` of success (and a distribution of
the time to success); the real agent ran ``R`` episodes from the same state, with outcomes
``o_{b,r}``. These pure functions score the forecasts on what a person relies on:

- per start: the mean absolute error between ``f_b`` and the real success rate, and Spearman's
  rank correlation between them (does the forecast rank the tasks?);
- per episode: the Brier score (every episode counts, so repeated runs weigh as they should),
  the Brier skill score against a reference forecast (e.g. the base rate), and the AUROC of
  ``f_b`` as a score of single-episode outcomes;
- reliability over start states, with binomial intervals on each bin's observed frequency;
- time to success: the CRPS of the forecast distribution of the first-success time against
  the real times, and that of a reference (climatological) distribution.

Layouts: forecasts ``[B]``; outcomes ``[B, R]`` bool (``runs`` may differ per start through a
``mask`` ``[B, R]``, True for the runs that exist).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from rcvae_torchrl.competency import _checks
from rcvae_torchrl.competency.intervals import binomial_interval, mean_interval

__all__ = [
    "StartReliability",
    "auroc",
    "brier_skill_score",
    "chance_brier_skill",
    "crps_samples",
    "episode_brier",
    "members_brier_skill",
    "per_start_rates",
    "pool_outcomes",
    "rank_correlation",
    "rate_reliability",
    "same_chance_p_value",
    "start_reliability",
    "time_to_success_scores",
    "validate_forecasts",
]


def _outcomes(forecast: Tensor, outcome: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """Checked forecasts ``[B]`` (float64) and outcomes ``[B, R]`` with their mask."""
    _checks.check_rank("forecast", forecast, 1, "[B]")
    _checks.check_floating("forecast", forecast)
    _checks.check_probability("forecast", forecast)
    if forecast.shape[0] == 0:
        raise ValueError("forecast: expected at least one start state, got none")
    _checks.check_rank("outcome", outcome, 2, "[B, R]")
    if outcome.shape[0] != forecast.shape[0]:
        raise ValueError(
            f"outcome: expected one row of runs per forecast ({forecast.shape[0]}), got shape "
            f"{tuple(outcome.shape)}"
        )
    if outcome.dtype != torch.bool:
        raise TypeError(f"outcome: expected bool outcomes of single episodes, got {outcome.dtype}")
    return forecast.to(torch.float64), _runs_mask(mask, outcome, "the outcomes'")


def _runs_mask(mask: Tensor | None, runs: Tensor, whose: str) -> Tensor:
    """The bool mask ``[B, R]`` of the runs that exist (all without one), at least one per
    start state."""
    if mask is None:
        return torch.ones_like(runs, dtype=torch.bool)
    if mask.shape != runs.shape or mask.dtype != torch.bool:
        raise ValueError(
            f"mask: expected a bool tensor of {whose} shape {tuple(runs.shape)}, got "
            f"{mask.dtype} {tuple(mask.shape)}"
        )
    if not bool(mask.any(1).all()):
        raise ValueError("mask: expected at least one run per start state")
    return mask


def per_start_rates(outcome: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Real success rate ``[B]`` and number of runs ``[B]`` of outcomes ``[B, R]``."""
    _checks.check_tensor("outcome", outcome)
    if outcome.dtype != torch.bool or outcome.dim() != 2:
        raise ValueError(
            f"outcome: expected bool outcomes [B, R] (starts, runs), got dtype {outcome.dtype} "
            f"and shape {tuple(outcome.shape)}"
        )
    runs = outcome.shape[1] * torch.ones(outcome.shape[0]) if mask is None else mask.sum(1)
    hits = outcome.sum(1) if mask is None else (outcome & mask).sum(1)
    return hits.to(torch.float64) / runs.to(torch.float64), runs.to(torch.int64)


def pool_outcomes(parts: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
    """Outcomes of several sets of start states, ``[B_i, R_i]`` bool each (e.g. the conditions
    of a study, one run per start where the outcome is fixed, many where it varies), stacked
    into ``[sum B_i, max R_i]`` with the mask of the runs that exist: the layout in which the
    scores pool them, every episode counting once. A row's missing runs repeat its first run
    (masked out, so never counted).

    Example:
        >>> fixed = torch.tensor([[True], [False]])
        >>> varied = torch.tensor([[True, False, True]])
        >>> outcome, mask = pool_outcomes([fixed, varied])
        >>> outcome.shape, mask.sum(1).tolist()
        (torch.Size([3, 3]), [1, 1, 3])
    """
    if not parts:
        raise ValueError("parts: expected at least one [B, R] tensor of outcomes, got none")
    for i, part in enumerate(parts):
        _checks.check_rank(f"parts[{i}]", part, 2, "[B, R]")
        if part.dtype != torch.bool:
            raise TypeError(
                f"parts[{i}]: expected bool outcomes of single episodes, got {part.dtype}"
            )
        if part.shape[1] == 0:
            raise ValueError(
                f"parts[{i}]: expected at least one run per start state, got shape "
                f"{tuple(part.shape)}"
            )
    runs = max(part.shape[1] for part in parts)
    rows, masks = [], []
    for part in parts:
        pad = runs - part.shape[1]
        rows.append(torch.cat([part, part[:, :1].expand(-1, pad)], 1) if pad else part)
        mask = torch.zeros(part.shape[0], runs, dtype=torch.bool, device=part.device)
        mask[:, : part.shape[1]] = True
        masks.append(mask)
    return torch.cat(rows), torch.cat(masks)


def rate_reliability(outcome: Tensor, mask: Tensor | None = None) -> float:
    """Split-half reliability of the per-start success rates of outcomes ``[B, R]``: how much
    of their spread over the start states is the starts' own and how much the runs' noise.

    Each start's runs (those in ``mask``) are dealt alternately into two halves; the rank
    correlation r between the two halves' rates is stepped up to all the runs by the
    Spearman-Brown formula, 2r / (1 + r). Its square root is about the rank correlation
    between the true chances and the rates of R runs, the most that any forecast can reach
    against those rates on average: the ceiling that the runs' noise leaves to a per-start
    Spearman. A split-half estimate: with few start states it is noisy itself. NaN where fewer
    than 2 start states have 2 runs or more, or where a half's rates do not vary.

    In the example every start first succeeds in all its runs or in none (no noise: all the
    spread is the starts' own), then in one of its two runs each (none of it is).

    Example:
        >>> sure = torch.tensor([[True] * 4, [False] * 4, [True] * 4, [False] * 4])
        >>> rate_reliability(sure)
        1.0
        >>> rate_reliability(torch.tensor([[True, False], [False, True], [True, False]]))
        nan
    """
    _checks.check_rank("outcome", outcome, 2, "[B, R]")
    if outcome.dtype != torch.bool:
        raise TypeError(f"outcome: expected bool outcomes of single episodes, got {outcome.dtype}")
    mask = _runs_mask(mask, outcome, "the outcomes'")
    position = mask.cumsum(1) - 1  # each run's index among its start's runs
    first = mask & (position % 2 == 0)
    second = mask & (position % 2 == 1)
    both = second.any(1)  # starts with two runs or more
    if int(both.sum()) < 2:
        return math.nan

    halves = (per_start_rates(outcome[both], half[both])[0] for half in (first, second))
    r = float(rank_correlation(*halves))
    return 2 * r / (1 + r) if math.isfinite(r) and r > -1 else math.nan


def episode_brier(forecast: Tensor, outcome: Tensor, mask: Tensor | None = None) -> Tensor:
    """The Brier score over single episodes: ``mean_{b,r} (f_b - o_{b,r})²``.

    Example:
        >>> episode_brier(torch.tensor([0.5, 1.0]), torch.tensor([[True, False], [True, True]]))
        tensor(0.1250, dtype=torch.float64)
    """
    f, mask = _outcomes(forecast, outcome, mask)
    errors = (f[:, None] - outcome.to(torch.float64)).square()
    return errors[mask].mean()


def brier_skill_score(brier: Tensor | float, reference: Tensor | float) -> Tensor:
    """``1 - brier / reference``: 1 is perfect, 0 no better than the reference, NaN when the
    reference is itself perfect (a reference Brier of 0 leaves nothing to improve on)."""
    brier, reference = (
        torch.as_tensor(brier, dtype=torch.float64),
        torch.as_tensor(reference, dtype=torch.float64),
    )
    for name, value in (("brier", brier), ("reference", reference)):
        if bool((value < 0).any()):  # NaN (nothing scored) gives NaN
            raise ValueError(f"{name}: expected Brier scores >= 0, got {value.tolist()}")
    return torch.where(reference > 0, 1.0 - brier / reference.clamp_min(1e-300), math.nan)


def chance_brier_skill(outcome: Tensor, mask: Tensor | None = None) -> float:
    """The Brier skill, against the outcomes' overall rate, that the forecast of every start's
    true chance of success has in expectation: the ceiling that the outcomes' own randomness
    leaves to any forecast, without the optimism of the oracle that forecasts each start's
    observed rate (fitted to the very runs it is scored on).

    Under its true chance ``p`` a start's episodes have an expected Brier of ``p (1 - p)``,
    estimated without bias from its ``R >= 2`` runs with rate ``q`` as ``q (1 - q) R / (R - 1)``.
    A start run once is taken as fixed (its outcome does not vary, as in a deterministic env):
    nothing is left to its Brier. NaN where every outcome is the same. An estimate: with few
    runs per start it is noisy, and can fall below 0 (the second example: two runs each).

    Example:
        >>> fixed = torch.tensor([[True, True], [False, False]])
        >>> chance_brier_skill(fixed)
        1.0
        >>> chance_brier_skill(torch.tensor([[True, False], [False, True]]))
        -1.0
    """
    _checks.check_rank("outcome", outcome, 2, "[B, R]")
    if outcome.dtype != torch.bool:
        raise TypeError(f"outcome: expected bool outcomes of single episodes, got {outcome.dtype}")
    mask = _runs_mask(mask, outcome, "the outcomes'")
    rate, runs = per_start_rates(outcome, mask)
    runs = runs.to(torch.float64)
    per_episode = torch.where(runs > 1, rate * (1 - rate) * runs / (runs - 1).clamp_min(1), 0.0)
    expected = (per_episode * runs).sum() / runs.sum()
    return float(brier_skill_score(expected, _base_rate_brier(outcome, mask)))


def members_brier_skill(
    member_forecasts: Tensor,
    outcome: Tensor,
    mask: Tensor | None = None,
    members: float = math.inf,
) -> float:
    """The Brier skill, against the outcomes' overall rate, of an ensemble's mean forecast with
    ``members`` members, from its ``E >= 2`` members' own forecasts ``[B, E]``: would more
    members forecast better, or is the error one they share?

    Averaged over every subset of ``k`` of the ``E`` members, the Brier score of the subset's
    mean forecast is exactly ``Brier(E) + (1/k - 1/E) v``, with ``v`` the members' sample
    variance (unbiased, over members) at each episode's start, averaged over the episodes: the
    variance of a mean of ``k`` drawn from ``E``. For ``k <= E`` this is that average; beyond,
    taking the members as independent draws of their training (as their initialisations and
    data orders make them), it is the unbiased estimate of the Brier score of ``k`` such
    members, and ``members=math.inf`` gives that of their expected forecast: the skill that no
    number of members exceeds. A member's forecast from finitely many samples carries their
    noise into ``v``, so the limit is that of infinitely many samples too.

    Example:
        >>> outcome = torch.tensor([[True], [False], [True], [False]])
        >>> right = torch.tensor([[0.9, 0.7], [0.1, 0.3], [0.7, 0.9], [0.3, 0.1]])
        >>> round(members_brier_skill(right, outcome, members=1), 3)  # a member alone
        0.8
        >>> round(members_brier_skill(right, outcome, members=2), 3)  # both: the mean forecast
        0.84
        >>> round(members_brier_skill(right, outcome), 3)  # their disagreement averaged away
        0.88
    """
    _checks.check_rank("member_forecasts", member_forecasts, 2, "[B, E]")
    _checks.check_floating("member_forecasts", member_forecasts)
    _checks.check_probability("member_forecasts", member_forecasts)
    if member_forecasts.shape[1] < 2:
        raise ValueError(
            "member_forecasts: expected the forecasts of at least 2 members [B, E >= 2], got "
            f"shape {tuple(member_forecasts.shape)}"
        )
    if not (isinstance(members, int | float) and members >= 1):
        raise ValueError(
            f"members: expected a number of members >= 1 (or math.inf), got {members!r}"
        )
    mask = _runs_mask(mask, outcome, "the outcomes'")
    brier = episode_brier(member_forecasts.mean(1), outcome, mask)
    runs = mask.sum(1).to(torch.float64)
    spread = member_forecasts.to(torch.float64).var(1)  # per start, unbiased over members
    spread = (spread * runs).sum() / runs.sum()  # per episode
    brier = brier + (1.0 / members - 1.0 / member_forecasts.shape[1]) * spread
    return float(brier_skill_score(brier, _base_rate_brier(outcome, mask)))


def _base_rate_brier(outcome: Tensor, mask: Tensor) -> Tensor:
    """The Brier score of the constant forecast of the episodes' own rate (the reference of
    the skills above)."""
    rate = outcome[mask].to(torch.float64).mean()
    return episode_brier(rate.expand(outcome.shape[0]), outcome, mask)


def _average_ranks(x: Tensor) -> Tensor:
    """Ranks 1..n of ``x`` ``[n]``, ties given their average rank."""
    order = torch.argsort(x, stable=True)
    ranks = torch.empty_like(x, dtype=torch.float64)
    ranks[order] = torch.arange(1, x.numel() + 1, dtype=torch.float64)
    values, inverse = torch.unique(x, return_inverse=True)
    sums = torch.zeros(values.numel(), dtype=torch.float64).index_add_(0, inverse, ranks)
    counts = torch.zeros(values.numel(), dtype=torch.float64).index_add_(
        0, inverse, torch.ones_like(ranks)
    )
    return (sums / counts)[inverse]


def rank_correlation(x: Tensor, y: Tensor) -> Tensor:
    """Spearman's ρ between ``x`` and ``y`` ``[n]`` (average ranks for ties); NaN when either
    is constant (no ranking to compare).

    Example:
        >>> float(rank_correlation(torch.tensor([0.1, 0.5, 0.9]), torch.tensor([0.0, 0.2, 1.0])))
        1.0
    """
    _checks.check_same_shape("x", x, "y", y)
    _checks.check_rank("x", x, 1, "[n]")
    _checks.check_finite("x", x)  # an integer tensor is finite: checked as it is, no copy
    _checks.check_finite("y", y)
    rx, ry = _average_ranks(x.to(torch.float64)), _average_ranks(y.to(torch.float64))
    rx, ry = rx - rx.mean(), ry - ry.mean()
    denominator = (rx.square().sum() * ry.square().sum()).sqrt()
    if float(denominator) == 0.0:
        return torch.tensor(math.nan, dtype=torch.float64)
    return (rx * ry).sum() / denominator


def auroc(score: Tensor, label: Tensor) -> Tensor:
    """Area under the ROC curve of ``score`` for bool ``label`` (both ``[n]``): the probability
    that a random positive scores above a random negative, ties counting half (Mann-Whitney).
    NaN when all labels are equal.

    Example:
        >>> labels = torch.tensor([True, True, False, False])
        >>> float(auroc(torch.tensor([0.9, 0.8, 0.3, 0.8]), labels))
        0.875
    """
    _checks.check_same_shape("score", score, "label", label)
    if label.dtype != torch.bool:
        raise TypeError(f"label: expected a bool tensor, got {label.dtype}")
    _checks.check_finite("score", score)
    positives, negatives = int(label.sum()), int((~label).sum())
    if positives == 0 or negatives == 0:
        return torch.tensor(math.nan, dtype=torch.float64)
    ranks = _average_ranks(score.reshape(-1).to(torch.float64))
    u = ranks[label.reshape(-1)].sum() - positives * (positives + 1) / 2
    return u / (positives * negatives)


class StartReliability(NamedTuple):
    """Reliability over start states: per bin of forecasts, the episodes' observed frequency."""

    bin_edges: Tensor  #: ``[n_bins + 1]``
    #: ``[n_bins]`` mean forecast over the bin's episodes (a start's forecast once per episode,
    #: as the frequency counts them; NaN for an empty bin)
    mean_forecast: Tensor
    frequency: Tensor  #: ``[n_bins]`` success frequency over the bin's episodes
    low: Tensor  #: ``[n_bins]`` lower end of its binomial interval
    high: Tensor  #: ``[n_bins]`` upper end
    starts: Tensor  #: ``[n_bins]`` start states in the bin
    episodes: Tensor  #: ``[n_bins]`` episodes in the bin


def start_reliability(
    forecast: Tensor,
    outcome: Tensor,
    mask: Tensor | None = None,
    n_bins: int = 5,
    confidence: float = 0.95,
) -> StartReliability:
    """Reliability diagram over start states, with a ``confidence`` binomial (Jeffreys)
    interval on each bin's frequency (all the bin's episodes pooled)."""
    _checks.check_positive_int("n_bins", n_bins)
    f, mask = _outcomes(forecast, outcome, mask)
    index = (f * n_bins).long().clamp(0, n_bins - 1)
    hits = (outcome & mask).sum(1).to(torch.float64)
    runs = mask.sum(1).to(torch.float64)

    def per_bin(values: Tensor) -> Tensor:
        return torch.zeros(n_bins, dtype=torch.float64).index_add_(0, index, values)

    starts, episodes, successes = per_bin(torch.ones_like(f)), per_bin(runs), per_bin(hits)
    low, high = binomial_interval(successes, episodes.clamp_min(1), confidence)
    empty = episodes == 0
    nan = torch.full_like(f[:1].expand(n_bins), math.nan)
    return StartReliability(
        torch.linspace(0.0, 1.0, n_bins + 1, dtype=torch.float64),
        torch.where(empty, nan, per_bin(f * runs) / episodes.clamp_min(1)),
        torch.where(empty, nan, successes / episodes.clamp_min(1)),
        torch.where(empty, nan, low),
        torch.where(empty, nan, high),
        starts.long(),
        episodes.long(),
    )


def crps_samples(samples: Tensor, observed: Tensor) -> Tensor:
    """CRPS of the empirical distribution of ``samples`` ``[K]`` for each ``observed`` ``[M]``:
    ``E|X - y| - ½ E|X - X'|`` (Gneiting & Raftery 2007), ``[M]``; lower is better.

    Example:
        >>> crps_samples(torch.tensor([1.0, 1.0]), torch.tensor([1.0, 3.0])).tolist()
        [0.0, 2.0]
    """
    x, y = samples.reshape(-1).to(torch.float64), observed.reshape(-1).to(torch.float64)
    if x.numel() == 0:
        raise ValueError("samples: expected at least one sample, got none")
    _checks.check_finite("samples", x)
    _checks.check_finite("observed", y)
    spread = (x[:, None] - x[None, :]).abs().mean()
    return (x[:, None] - y[None, :]).abs().mean(0) - 0.5 * spread


#: an AUROC below this, over at least ``_BACKWARDS_STARTS`` start states, is forecasts ranking
#: the real outcomes backwards (success counted on one side as failure on the other), not a
#: weak forecast: one that tells nothing scores about 0.5
_BACKWARDS = 0.2
_BACKWARDS_STARTS = 10


def validate_forecasts(
    forecast: Tensor,
    outcome: Tensor,
    mask: Tensor | None = None,
    *,
    base_rate: float | None = None,
    n_bins: int = 5,
) -> dict[str, float]:
    """The per-start and per-episode scores of forecasts ``[B]`` against outcomes ``[B, R]``.

    Returns a dict: ``forecast`` (mean of ``f_b`` over episodes), ``real`` (success rate over
    all episodes), ``gap`` (``|forecast - real|``), ``per_start_mae``, ``spearman`` (NaN when
    either side is constant), ``real_rate_span`` (max - min of the real per-start rates),
    ``auroc`` (over single episodes; NaN when all outcomes agree), ``brier`` (over episodes),
    ``brier_base`` (the Brier of the constant forecast ``base_rate``, default the episodes' own
    rate), ``brier_skill`` (against it), ``ece`` (episode-weighted over ``n_bins`` bins),
    ``starts`` and ``episodes``; ``bias`` (the mean over start states of forecast minus real
    rate, signed) with ``bias_low`` and ``bias_high``, its 95 % Student's t interval over the
    start states (:func:`~rcvae_torchrl.competency.intervals.mean_interval`): on a few start
    states a small ``gap`` is no evidence of an unbiased forecast while the interval is wide.
    Scores are not a verdict: :class:`~rcvae_torchrl.training.OutcomeCheck` tests the bias and
    the per-start misses and says whether the forecast can be trusted.
    """
    f, mask = _outcomes(forecast, outcome, mask)
    rates, runs = per_start_rates(outcome, mask)
    labels = outcome[mask]
    scores = f[:, None].expand_as(outcome)[mask]
    real = float(labels.to(torch.float64).mean())
    if base_rate is not None:
        _checks.check_unit_interval("base_rate", base_rate)
    base = real if base_rate is None else float(base_rate)
    brier = float(episode_brier(f, outcome, mask))
    brier_base = float(((base - labels.to(torch.float64)) ** 2).mean())
    reliability = start_reliability(f, outcome, mask, n_bins)
    weights = reliability.episodes.to(torch.float64) / float(runs.sum())
    gaps = (reliability.mean_forecast - reliability.frequency).abs().nan_to_num(0.0)
    mean_forecast = float(scores.mean())  # episode-weighted, as the real rate is
    errors = (f.to(torch.float64) - rates).cpu()  # per start; its mean weighs starts alike
    bias_low, bias_high = mean_interval(errors, 0.95)
    ranked = float(auroc(scores, labels))
    if ranked < _BACKWARDS and f.numel() >= _BACKWARDS_STARTS:
        warnings.warn(
            f"outcome: the forecasts rank the real outcomes backwards (AUROC {ranked:.3f} over "
            f"{labels.numel()} episodes: the episodes that failed had the higher forecasts); "
            "are the real outcomes those of the forecast's task? (for a survival boundary, "
            "count real_outcomes' successes with boundary.success_over_time, not its failure "
            "predicate; a predicate negated on one side only does this)",
            UserWarning,
            stacklevel=2,
        )
    return {
        "forecast": mean_forecast,
        "real": real,
        "gap": abs(mean_forecast - real),
        "per_start_mae": float((f - rates).abs().mean()),
        "spearman": float(rank_correlation(f, rates)),
        "real_rate_span": float(rates.max() - rates.min()),
        "auroc": ranked,
        "brier": brier,
        "brier_base": brier_base,
        "brier_skill": float(brier_skill_score(brier, brier_base)),
        "ece": float((weights * gaps).sum()),
        "starts": int(f.numel()),
        "episodes": int(runs.sum()),
        "bias": float(errors.mean()),
        "bias_low": bias_low,
        "bias_high": bias_high,
    }


def time_to_success_scores(
    forecast_steps: Tensor,
    real_steps: Tensor,
    mask: Tensor | None = None,
    *,
    horizon: int | None = None,
) -> dict[str, float]:
    """The forecast distribution of the time to success against the real times, by CRPS.

    Times are first-success steps, the horizon ``T`` standing for "not within the horizon"
    (the time is censored there, and so are the scores). For each start state ``b`` the
    forecast is the empirical distribution of its imagined times; the reference
    (climatological) forecast is the distribution of all real times of all start states,
    the same for every start. Lower is better; ``skill = 1 - crps / crps_climatology``.

    Args:
        forecast_steps: ``[B, K]`` imagined first-success steps (e.g. all ``E·N`` samples).
        real_steps: ``[B, R]`` real first-success steps.
        mask: bool ``[B, R]``, the real runs that exist.
        horizon: ``T``; where given, a time beyond it is refused: real episodes run longer
            than the forecast looked ahead must be censored at ``T`` first
            (:meth:`~rcvae_torchrl.agent.RealOutcomes.within`), else their later successes
            score as misses of times the forecast never judged (a cart-pole's 2-s forecast
            scored against times of up to 8 s: skill -2.34 where the censored times gave
            +0.03).

    Returns:
        ``{"crps", "crps_climatology", "skill"}``, mean over real episodes (in steps).
    """
    _checks.check_rank("forecast_steps", forecast_steps, 2, "[B, K]")
    _checks.check_rank("real_steps", real_steps, 2, "[B, R]")
    if forecast_steps.shape[0] != real_steps.shape[0]:
        raise ValueError(
            f"real_steps: expected {forecast_steps.shape[0]} rows (one per start state), got "
            f"{tuple(real_steps.shape)}"
        )
    for name, steps in (("forecast_steps", forecast_steps), ("real_steps", real_steps)):
        _checks.check_finite(name, steps)
        if 0 in steps.shape:
            raise ValueError(
                f"{name}: expected at least one time per start, got {tuple(steps.shape)}"
            )
    mask = _runs_mask(mask, real_steps, "real_steps'")
    if horizon is not None:
        _checks.check_positive_int("horizon", horizon)
        for name, steps in (("forecast_steps", forecast_steps), ("real_steps", real_steps[mask])):
            if bool((steps > horizon).any()):
                raise ValueError(
                    f"{name}: expected first-success steps of at most the horizon {horizon} "
                    f"(T: not within it), got {int((steps > horizon).sum())} beyond it, up to "
                    f"{float(steps.max()):g}; censor them at T (RealOutcomes.within(T) for real "
                    "episodes run longer than the forecast looked ahead)"
                )
    climatology = real_steps[mask]
    ours, reference = [], []
    for b in range(real_steps.shape[0]):
        observed = real_steps[b][mask[b]]
        ours.append(crps_samples(forecast_steps[b], observed))
        reference.append(crps_samples(climatology, observed))
    crps, crps_ref = float(torch.cat(ours).mean()), float(torch.cat(reference).mean())
    return {
        "crps": crps,
        "crps_climatology": crps_ref,
        "skill": float(brier_skill_score(crps, crps_ref)),
    }


#: Below this many expected successes (or failures) per group the chi-square law is not
#: trusted (Cochran's rule) and :func:`same_chance_p_value` draws its p-value instead.
_SPARSE = 5.0
#: Draws of the successes over the groups for a sparse table's p-value (seeded).
_SAME_CHANCE_DRAWS = 4000


def same_chance_p_value(rates: Tensor, runs: int) -> float:
    """The p-value of "every group has the same chance" from each group's success rate
    ``rates`` ``[G]`` over ``runs`` draws each: Pearson's chi-square test of one chance for
    all (``G - 1`` degrees of freedom). The groups are an ensemble's members (their imagined
    samples) or a check's start states (their real episodes). 1.0 with one group, or where
    every draw of every group agrees (all succeed or all fail).

    Where the table is sparse (fewer than 5 successes, or failures, expected per group) the
    chi-square law does not hold (with 100 groups of 30 runs at a chance of 0.002 it gave
    p < 0.01 in 3 % of draws): there the p-value is the share of 4,000 seeded draws of the
    same successes over the groups (multivariate hypergeometric, the permutation test of the
    statistic given the total) whose statistic reaches the observed one, counting it too."""
    r = torch.as_tensor(rates).detach().double().flatten()
    _checks.check_positive_int("runs", runs)
    if not bool(((r >= 0) & (r <= 1)).all()):  # NaN fails too
        raise ValueError(f"rates: expected success rates in [0, 1], got {r.tolist()[:5]}")
    mean = float(r.mean()) if r.numel() else math.nan
    if r.numel() < 2 or runs < 1 or not 0 < mean < 1:
        return 1.0
    groups, trials = r.numel(), r.numel() * runs
    successes = round(float(r.sum()) * runs)
    if min(successes, trials - successes) / groups < _SPARSE:
        return _drawn_same_chance_p_value(r, runs, successes)
    from scipy.stats import chi2

    statistic = runs * float(((r - mean) ** 2).sum()) / (mean * (1 - mean))
    return float(chi2.sf(statistic, groups - 1))


def _drawn_same_chance_p_value(rates: Tensor, runs: int, successes: int) -> float:
    """:func:`same_chance_p_value` of a sparse table: the chi-square statistic (up to its
    constant factor, the same given the total) against the groups' counts drawn with the same
    total of ``successes`` over ``runs`` draws per group, seeded."""
    import numpy as np

    counts = np.rint(rates.cpu().numpy() * runs)  # the rates may live on a GPU
    draws = np.random.default_rng(1).multivariate_hypergeometric(
        np.full(counts.size, runs), successes, size=_SAME_CHANCE_DRAWS
    )
    spread = ((counts - successes / counts.size) ** 2).sum()
    drawn = ((draws - successes / counts.size) ** 2).sum(axis=1)
    reached = int((drawn >= spread - 1e-9).sum())
    return (reached + 1) / (_SAME_CHANCE_DRAWS + 1)

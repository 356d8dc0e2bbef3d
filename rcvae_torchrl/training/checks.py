"""Has the model learned what it must? Per-dimension self-checks on held-out episodes.

A falling validation loss does not say that every state dimension was learned: a dimension the
model predicts no better than copying the previous state (or than guessing its mean) makes a
forecast that looks confident and is wrong. :func:`check_model` measures, per state
dimension, on held-out episodes:

- the one-step error (teacher forced: the true history, the model's point prediction of the
  next state) against two baselines: copying the previous state, and the dimension's spread in
  the data (the error of predicting its mean);
- the open-loop error after ``k`` steps (the mean of imagined rollouts driven by the episode's
  own actions) against the same baselines (copying the start state);
- the coverage of its spread: from the first state of every held-out episode, imagined rollouts
  driven by the episode's own actions for ``coverage_steps`` steps (all members' samples
  pooled, as a forecast pools them); how often the real state then lies inside the samples'
  central ``interval`` (a prediction interval between two order statistics of the samples,
  whose coverage for a draw of the same distribution is known exactly).

A predicted dimension whose one-step error is not at least ``min_gain`` below the better of the
two baselines is flagged: the model has not learned it. So is one whose mean open-loop forecast
after ``k`` steps is further from the real state than the better of its two baselines, by more
than chance allows (:attr:`ModelChecks.drifting`): the mean of a right model's samples is the
best guess of the state given the start and the actions, which no baseline beats but by the
noise of its finitely many samples, so a model further off drifts, however well it predicts one
step (an acrobot model whose mean forecast 10 steps ahead was 1.2-1.46 times the data's spread
off passed every other check). A dimension whose coverage is below the interval's, by more than
chance allows (a one-sided binomial test at level ``alpha``, Bonferroni over the dimensions
checked), is flagged too: the model is overconfident there (its spread too narrow, or off
centre), which a model whose randomness per episode was not learned shows. A dimension whose
real state lies strictly inside the samples' central half more often than half the time, by
more than chance allows (the same test, the other tail), is named underconfident
(:attr:`ModelChecks.underconfident`): its spread is wider than its errors, so the aleatoric bits
there overstate the env's noise (an acrobot model trained on noise-free episodes forecast 19-22
bits of "aleatoric" doubt). It does not fail the checks: the outcome forecasts of such a model
can still be right, but its split of the doubt is not.
:func:`train_ensemble <rcvae_torchrl.training.train_ensemble>` runs the checks after training,
warns naming the flagged dimensions, and stores them with the model; the competency assessor
flags a forecast made with a model that failed them.

Passing them does not make a forecast right: they look ``coverage_steps`` ahead at most, a
forecast much further, and an undertrained model can pass them and forecast far from reality.
:class:`OutcomeCheck` checks the forecast itself, against real episodes from start states it is
not scored on.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import torch
from tensordict import TensorDictBase

from rcvae_torchrl import _checks, fingerprint
from rcvae_torchrl._checks import (
    ROUNDING,
    check_bool,
    check_entries,
    check_non_negative,
    check_open_unit_interval,
    check_positive_int,
    check_seed,
    check_unit_interval,
    is_integer,
)
from rcvae_torchrl._text import signed
from rcvae_torchrl.competency import check_same_predicates, same_chance_p_value
from rcvae_torchrl.competency._checks import check_probability
from rcvae_torchrl.competency.intervals import (
    binomial_interval,
    mean_interval,
    mean_p_value,
    without_spread,
)
from rcvae_torchrl.competency.report import register_report_part
from rcvae_torchrl.data import (
    TRAJ_KEY,
    check_same_agent,
    episode_spans,
    make_window_buffer,
    sample_windows,
)
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout import imagine

__all__ = ["ModelCheckWarning", "ModelChecks", "OutcomeCheck", "check_model"]


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
    #: per dimension, the held-out episodes whose real state after ``coverage_steps`` lay in
    #: the imagined interval (``[S]``; ``None``: not measured, too few episodes)
    covered: torch.Tensor | None = None
    #: the held-out episodes long enough for the coverage check (measured when at least
    #: ``min_episodes``)
    episodes: int = 0
    coverage_steps: int = 0
    interval: float = 0.0  #: the exact coverage of the interval for a draw of the samples' law
    alpha: float = 0.01
    min_episodes: int = 10
    #: per dimension, the held-out episodes whose real state lay strictly inside the samples'
    #: central half (``[S]``; ``None``: not measured)
    covered_half: torch.Tensor | None = None
    half_interval: float = 0.0  #: that interval's exact coverage for a draw of the samples' law
    #: per dimension, the one-sided p-value of "the mean open-loop forecast after ``k`` steps is
    #: further off than the better baseline" (``[S]``; ``None``: not measured, too few
    #: held-out episodes)
    k_step_p: torch.Tensor | None = None
    #: the imagined samples each open-loop mean averages (E times the samples per member)
    k_samples: int = 0

    @property
    def unlearned(self) -> tuple[int, ...]:
        """Checked dimensions whose one-step error is not ``min_gain`` below both baselines."""
        best = torch.minimum(self.copy_one_step, self.spread)
        bad = self.one_step >= (1.0 - self.min_gain) * best
        return tuple(d for d in self.checked if bool(bad[d]))

    @property
    def coverage(self) -> torch.Tensor | None:
        """The fraction of held-out episodes inside the interval, per dimension ``[S]``."""
        return None if self.covered is None else self.covered / self.episodes

    @property
    def overconfident(self) -> tuple[int, ...]:
        """Checked dimensions covered less often than ``interval`` by more than chance allows
        (one-sided binomial test at level ``alpha`` / the number of dimensions checked)."""
        return self._beyond_chance(self.covered, self.interval, fewer=True)

    @property
    def underconfident(self) -> tuple[int, ...]:
        """Checked dimensions whose real state lay strictly inside the samples' central half
        more often than :attr:`half_interval` by more than chance allows (one-sided binomial
        test at level ``alpha`` / the number of dimensions checked): the spread there is wider
        than the model's errors, and its aleatoric bits overstate the noise. A dimension the
        model gets exactly (an interval of width 0) is never inside it."""
        return self._beyond_chance(self.covered_half, self.half_interval, fewer=False)

    def _beyond_chance(
        self, counts: torch.Tensor | None, probability: float, *, fewer: bool
    ) -> tuple[int, ...]:
        """Checked dimensions whose count of episodes inside an interval of exact coverage
        ``probability`` is ``fewer`` (else more) than chance allows: a one-sided binomial
        test at level ``alpha`` / the number of dimensions checked."""
        if counts is None or not self.checked or not probability:
            return ()
        from scipy.stats import binom

        level = self.alpha / len(self.checked)
        k = counts.to(torch.float64).numpy()
        p = (
            binom.cdf(k, self.episodes, probability)
            if fewer
            else binom.sf(k - 1, self.episodes, probability)
        )
        return tuple(d for d in self.checked if p[d] < level)

    def wide_sentence(self) -> str:
        """Where the spread is too wide (:attr:`underconfident`), one sentence saying so
        ('' otherwise)."""
        if not self.underconfident:
            return ""
        parts = [
            f"{self.names[d]} ({int(self.covered_half[d])} of {self.episodes})"
            for d in self.underconfident
        ]
        return (
            f"the world model's spread is too wide for {', '.join(parts)}: "
            f"{self.coverage_steps} steps into held-out episodes the real state lay inside its "
            f"central {self.half_interval:.0%} too often, so its aleatoric bits there overstate "
            "the env's noise"
        )

    @property
    def drifting(self) -> tuple[int, ...]:
        """Checked dimensions whose mean open-loop forecast after ``k`` steps is further from
        the real state than the better of copying the start state and guessing the mean, by
        more than chance allows: a one-sided t-test over the held-out episodes (each episode's
        windows one unit) of the squared errors' excess over ``1 + 1/k_samples`` times the
        baseline's (what a right model's mean of that many samples may lose to noise), at
        level ``alpha`` / the number of dimensions checked."""
        if self.k_step_p is None or not self.checked:
            return ()
        level = self.alpha / len(self.checked)
        return tuple(d for d in self.checked if float(self.k_step_p[d]) < level)

    @property
    def flagged(self) -> tuple[int, ...]:
        """Checked dimensions the model has not learned, drifts on, or is overconfident
        about."""
        bad = set(self.unlearned) | set(self.drifting) | set(self.overconfident)
        return tuple(d for d in self.checked if d in bad)

    @property
    def coverage_measured(self) -> bool:
        """Whether the coverage check ran (enough held-out episodes were long enough)."""
        return self.covered is not None

    @property
    def passed(self) -> bool:
        """Every check ran and none flagged a dimension. A model whose coverage could not be
        measured has not passed: an overconfident spread would have gone unseen."""
        return not self.flagged and self.coverage_measured

    def message(self) -> str:
        """One sentence naming the flagged dimensions and their errors ('' when none)."""
        sentences = []
        if self.unlearned:
            parts = [
                f"{self.names[d]} (one-step error {float(self.one_step[d]):.3g} vs "
                f"{float(torch.minimum(self.copy_one_step[d], self.spread[d])):.3g} for a "
                "trivial baseline)"
                for d in self.unlearned
            ]
            sentences.append(
                "the world model has not learned "
                + _listed(parts)
                + f": it predicts these dimensions not at least {self.min_gain:.0%} better than "
                "copying the previous state or guessing their mean, so forecasts that depend on "
                "them are not trustworthy"
            )
        if self.drifting:
            parts = [
                f"{self.names[d]} (error {float(self.k_step[d]):.3g} vs "
                f"{float(torch.minimum(self.copy_k_step[d], self.spread[d])):.3g})"
                for d in self.drifting
            ]
            sentences.append(
                f"the world model drifts: {self.k} steps into held-out episodes, driven by their "
                "own actions, its mean forecast is further from the real state than copying the "
                "start state or guessing the mean, for " + _listed(parts) + ": forecasts "
                "further ahead than a step that depend on them are not trustworthy"
            )
        if self.overconfident:
            parts = [
                f"{self.names[d]} ({int(self.covered[d])} of {self.episodes})"
                for d in self.overconfident
            ]
            sentences.append(
                f"the world model is overconfident: {self.coverage_steps} steps into held-out "
                f"episodes, the real state lay inside its {self.interval:.0%} interval too "
                "rarely for " + _listed(parts) + ": its spread there is too narrow or off "
                "centre, so forecasts that depend on them are not trustworthy"
            )
        if not self.coverage_measured:
            sentences.append(
                f"the world model's spread is unchecked: {self.episodes} held-out "
                f"{'episode lasts' if self.episodes == 1 else 'episodes last'} over "
                f"{self.coverage_steps} steps, the coverage check needs "
                f"{self.min_episodes}, so an overconfident model would go unseen; hold out "
                "more (or longer) episodes"
            )
        return "; ".join(sentences)

    def describe(self) -> str:
        """One sentence either way: :meth:`message` when the model did not pass, else what it
        passed (and what the checks cannot see)."""
        if not self.passed:
            return self.message()
        covered = self.covered[list(self.checked)] if self.checked else self.covered[:0]
        inside = (
            f"; {self.coverage_steps} steps into {self.episodes} held-out episodes the real "
            f"state lay inside its {self.interval:.0%} interval in {int(covered.min())} to "
            f"{int(covered.max())} of them, dimension by dimension, not too rarely for any"
            if covered.numel()
            else ""
        )
        drift = (
            f", and {self.k} steps ahead, open loop, no further off than those baselines"
            if self.k_step_p is not None
            else ""
        )
        wide = self.wide_sentence()
        if wide:
            wide = f". But {wide}"
        elif self.covered_half is not None:
            wide = (
                f", nor too often inside its central {self.half_interval:.0%} (a spread too wide)"
            )
        else:
            wide = (
                ". The checks do not name a spread that is too wide: a model too unsure of its "
                "states passes them, and only a check of its forecasts against real episodes "
                "finds it"
            )
        return (
            f"the world model passed its self-checks: each of the {len(self.checked)} "
            f"dimensions checked it predicts one step ahead at least {self.min_gain:.0%} better "
            f"than copying the previous state or guessing its mean{drift}{inside}{wide}"
        )

    def as_dict(self) -> dict[str, Any]:
        """Plain values (for checkpoints and JSON)."""
        out: dict[str, Any] = {
            "names": list(self.names),
            "k": self.k,
            "checked": list(self.checked),
            "min_gain": self.min_gain,
            "flagged": [self.names[d] for d in self.flagged],
            "overconfident": [self.names[d] for d in self.overconfident],
            "episodes": self.episodes,
            "coverage_steps": self.coverage_steps,
            "interval": self.interval,
            "alpha": self.alpha,
            "min_episodes": self.min_episodes,
            "covered": None if self.covered is None else self.covered.tolist(),
            "covered_half": None if self.covered_half is None else self.covered_half.tolist(),
            "half_interval": self.half_interval,
            "underconfident": [self.names[d] for d in self.underconfident],
            "drifting": [self.names[d] for d in self.drifting],
            "k_step_p": None if self.k_step_p is None else self.k_step_p.tolist(),
            "k_samples": self.k_samples,
        }
        for key in ("one_step", "copy_one_step", "spread", "k_step", "copy_k_step"):
            out[key] = getattr(self, key).tolist()
        return out

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ModelChecks:
        """The inverse of :meth:`as_dict` (e.g. read back from JSON); a record missing an
        entry it needs raises ValueError naming it."""
        tensors_at = ("one_step", "copy_one_step", "spread", "k_step", "copy_k_step")
        check_entries(
            "values",
            values,
            (*tensors_at, "names", "k", "checked", "min_gain"),
            "a ModelChecks.as_dict()",
        )
        tensors = {k: torch.tensor(values[k], dtype=torch.float64) for k in tensors_at}
        covered = values.get("covered")  # absent from checks saved before coverage existed
        return cls(
            tuple(values["names"]),
            k=int(values["k"]),
            checked=tuple(values["checked"]),
            min_gain=float(values["min_gain"]),
            covered=None if covered is None else torch.tensor(covered, dtype=torch.float64),
            episodes=int(values.get("episodes", 0)),
            coverage_steps=int(values.get("coverage_steps", 0)),
            interval=float(values.get("interval", 0.0)),
            alpha=float(values.get("alpha", 0.01)),
            min_episodes=int(values.get("min_episodes", 10)),
            covered_half=None
            if values.get("covered_half") is None
            else torch.tensor(values["covered_half"], dtype=torch.float64),
            half_interval=float(values.get("half_interval", 0.0)),
            k_step_p=None
            if values.get("k_step_p") is None
            else torch.tensor(values["k_step_p"], dtype=torch.float64),
            k_samples=int(values.get("k_samples", 0)),
            **tensors,
        )


#: dimensions a message names one by one; the rest are counted (all are in the checks' fields)
_NAMED = 8


def _listed(parts: list[str]) -> str:
    """``parts`` joined, the first :data:`_NAMED` of them and a count of the others: a
    78-dimensional model's warning named 30 dimensions in 2,500 characters, opening every
    summary of its forecasts."""
    shown = ", ".join(parts[:_NAMED])
    more = len(parts) - _NAMED
    return shown if more <= 0 else f"{shown} and {more} more"


def _rmse(error: torch.Tensor) -> torch.Tensor:
    """Root mean square over every axis but the last: ``[..., S] -> [S]`` (float64)."""
    return error.to(torch.float64).square().reshape(-1, error.shape[-1]).mean(0).sqrt()


def _longest_episode(data: TensorDictBase) -> int:
    return int(episode_spans(data)[1].max())


#: draws of the real outcomes from the forecasts, for the outcome check's exact p-values
_DRAWS = 4000
#: the share of a new start drawn like a forecast check's own that its cover keeps
_COVER_QUANTILE = 0.99


def _coverage(
    ensemble: RCVAEEnsemble,
    data: TensorDictBase,
    steps: int,
    samples_per_member: int,
    interval: float,
    generator: torch.Generator,
) -> tuple[torch.Tensor, int, float, torch.Tensor, float]:
    """From the start of every held-out episode longer than ``steps``: per dimension, how many
    real states after ``steps`` steps lie between the order statistics i and n + 1 − i of the
    n imagined ones (``[S]``), the episode count, and the interval's exact coverage
    (n + 1 − 2i) / (n + 1) for a draw of the samples' own law; then the same count and coverage
    for the samples' central half, strictly inside (an interval of width 0 holds nothing)."""
    first, lengths = episode_spans(data)
    first = first[lengths > steps]
    if first.numel() == 0:
        none = torch.zeros(ensemble.config.obs_dim, dtype=torch.float64)
        return none, 0, 0.0, none.clone(), 0.0
    device = ensemble.device
    frames = first[:, None] + torch.arange(steps)
    starts = data.get("observation")[first].to(device)
    actions = data.get("action")[frames].to(device)
    truth = data.get(("next", "observation"))[first + steps - 1].to(device)
    rollouts = imagine(
        ensemble, starts, actions, samples_per_member=samples_per_member, generator=generator
    )
    samples = rollouts.get("observation")[..., steps - 1, :].flatten(0, 1)  # [n, B, S]
    n = samples.shape[0]
    rank = max(1, int((1.0 - interval) / 2 * (n + 1)))  # 1-based order statistic
    ordered = samples.sort(dim=0).values
    low, high = ordered[rank - 1], ordered[n - rank]
    # within float rounding of the interval is inside: a dimension the model gets exactly (a
    # clock advanced by a state constraint) has an interval of width 0 that the real value
    # misses by 1e-7
    rounding = ROUNDING * (1 + truth.abs())
    inside = (truth >= low - rounding) & (truth <= high + rounding)
    exact = (n + 1 - 2 * rank) / (n + 1)
    half = max(1, int(0.25 * (n + 1)))
    low_half, high_half = ordered[half - 1], ordered[n - half]
    # strictly inside, beyond rounding: a real state on a width-0 interval is not in it
    inside_half = (truth > low_half + rounding) & (truth < high_half - rounding)
    return (
        inside.sum(0).to(torch.float64).cpu(),
        int(first.numel()),
        exact,
        inside_half.sum(0).to(torch.float64).cpu(),
        (n + 1 - 2 * half) / (n + 1),
    )


def _dims(dims: object, cfg: Any) -> tuple[int, ...]:
    """``check_model``'s ``dims``: sorted distinct indices of predicted dimensions, from
    indices or names; a ``ValueError`` names any other."""
    if isinstance(dims, (str, bytes)) or not isinstance(dims, Sequence) or not dims:
        raise TypeError(f"dims: expected a non-empty sequence of dimensions, got {dims!r}")
    names, out = cfg.names, set()
    for dim in dims:
        if isinstance(dim, str):
            if dim not in names:
                raise ValueError(f"dims: {dim!r} is not a dimension's name ({', '.join(names)})")
            dim = names.index(dim)
        if isinstance(dim, bool) or not isinstance(dim, int) or not 0 <= dim < len(names):
            raise ValueError(
                f"dims: expected dimensions in [0, {len(names)}) or their names, got {dim!r}"
            )
        if dim not in cfg.predicted_dims:
            raise ValueError(f"dims: {names[dim]} is not predicted by the model: nothing to check")
        out.add(dim)
    return tuple(sorted(out))


#: the fewest held-out episodes whose windows the open-loop drift test takes as its units
_DRIFT_EPISODES = 3


def _drift_p_values(
    forecast: torch.Tensor,
    truth: torch.Tensor,
    baseline: torch.Tensor,
    samples: int,
    episodes: torch.Tensor,
) -> torch.Tensor | None:
    """Per dimension (``[S]``, CPU), the one-sided p-value of "the mean forecast's squared error
    exceeds ``1 + 1/samples`` times the baseline's" over windows ``[W, S]``: a right model's
    mean of ``samples`` draws errs by its law's variance plus a ``1/samples`` share of it, and
    that variance is no more than any baseline's squared error. Windows of one episode are not
    independent, so each episode's mean excess is one unit of a t-test (``None``: fewer than
    :data:`_DRIFT_EPISODES` episodes; 1 where every episode's excess is the same and not
    above 0, 0 where it is above). An error within float rounding of the truth
    (:data:`ROUNDING`, relative above 1) is none: a dimension the model gets exactly (a clock
    advanced by a state constraint, whose period may equal ``k`` so that the copy is exact too)
    does not drift by 1e-7."""
    from scipy.stats import t as student_t

    truth = truth.to(torch.float64)
    error = forecast.to(torch.float64) - truth
    error = torch.where(error.abs() <= ROUNDING * (1 + truth.abs()), 0.0, error)
    excess = error.square() - (1 + 1 / samples) * (truth - baseline).square()
    excess = excess.cpu()
    ids, unit = torch.unique(episodes.cpu(), return_inverse=True)
    n = len(ids)
    if n < _DRIFT_EPISODES:
        return None
    counts = torch.bincount(unit, minlength=n).to(torch.float64)
    per_episode = torch.zeros(n, excess.shape[-1], dtype=torch.float64).index_add_(0, unit, excess)
    per_episode /= counts[:, None]
    mean, sd = per_episode.mean(0), per_episode.std(0, correction=1)
    stat = (mean / (sd / n**0.5)).numpy()
    p = torch.from_numpy(student_t.sf(stat, n - 1)).to(torch.float64)
    flat = sd <= 1e-12 * (1 + per_episode.abs().max(0).values)
    return torch.where(flat, (mean <= 0).to(torch.float64), p)


def _windows(data: TensorDictBase, length: int, count: int, seed: int) -> TensorDictBase:
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        return sample_windows(make_window_buffer(data, length), count, length)


def _check_level(name: str, value: object) -> None:
    """Require a test's level in (0, 1): at level 1 a test always rejects."""
    check_open_unit_interval(name, value, "a level", " (a test at level 1 always rejects)")


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
    coverage_steps: int = 20,
    interval: float = 0.9,
    alpha: float = 0.01,
    min_episodes: int = 10,
    dims: Sequence[int | str] | None = None,
    seed: int = 0,
    warn: bool = True,
) -> ModelChecks:
    """The self-checks of the module docstring on held-out episodes ``data`` ``[frames]``.

    Args:
        ensemble: the trained model (its config's ``names`` name the dimensions).
        data: held-out whole episodes (``split_episodes``' validation part).
        k: open-loop steps (windows of ``k + 1`` frames) of the drift check. Like the
            coverage check far ahead, it wants episodes whose actions did not answer the noise
            met on the way: a closed-loop controller's corrections in a noisy env can keep the
            real state nearer its start than a right model driven by the same actions.
        window: length of the one-step windows.
        windows: windows drawn for each check.
        samples_per_member: imagined samples per member for the open-loop mean.
        min_gain: how far below the better baseline a dimension's one-step error must be.
        coverage_steps: steps from each held-out episode's start to the coverage check (at most
            the episode's length minus one; episodes shorter than that are left out). Far ahead,
            episodes of a closed-loop policy in a stochastic env are not a fair truth: the
            policy's later actions answer the noise the episode met, which a model driven by
            the same actions cannot know, and the check then names dimensions the model has
            right. Check far horizons on episodes of open-loop actions (e.g. the recorded
            actions replayed in the real env) instead.
        interval: the central probability of the interval (its exact coverage, between two
            order statistics of the E·N samples, is the nearest the sample count allows).
        alpha: the level of the coverage test.
        min_episodes: fewer held-out episodes than this leave coverage unmeasured, and the
            checks then do not pass (:attr:`ModelChecks.passed`): the message says so.
        dims: the dimensions to check (indices, or the names of the config's
            ``observation_names``), each a predicted one; default: every predicted dimension
            that changes in ``data`` (those that do not are never checked). The tests' level
            is shared over the dimensions checked: of a 78-dimensional quadruped, the one its
            survival hung on lay inside its interval in 49 of 60 held-out episodes (p =
            0.0007), not beyond chance over 78 dimensions, and its forecasts were 0.28 off;
            checked alone (``dims=["torso_upright"]``) it is named. Check such dimensions in
            a call of their own beside the check of every dimension: ``checks={"dims": [...]}``
            in :func:`~rcvae_torchrl.training.train_ensemble` replaces training's check of
            every dimension by theirs alone.
        seed: the windows and the samples are drawn from it.
        warn: emit a :class:`ModelCheckWarning` naming the flagged dimensions.
    """
    if not isinstance(ensemble, RCVAEEnsemble):
        raise TypeError(f"ensemble: expected an RCVAEEnsemble, got {type(ensemble).__name__}")
    if not isinstance(data, TensorDictBase):
        raise TypeError(
            f"data: expected a flat TensorDict of held-out episodes [frames], got "
            f"{type(data).__name__}"
        )
    if not is_integer(k) or k < 1:
        raise ValueError(f"k: expected a positive integer (open-loop steps), got {k!r}")
    for name, value in (
        ("windows", windows),
        ("samples_per_member", samples_per_member),
        ("coverage_steps", coverage_steps),
        ("min_episodes", min_episodes),
    ):
        check_positive_int(name, value)
    check_unit_interval("interval", interval, include_zero=False)
    _check_level("alpha", alpha)
    check_non_negative("min_gain", min_gain)
    check_bool("warn", warn)
    seed = check_seed("seed", seed)
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
    observed = data.get("observation").to(device, torch.float64)
    spread = observed.std(0, correction=0)
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
    baseline = torch.where(copy_k_step <= spread, starts.to(torch.float64), observed.mean(0))
    k_step_p = _drift_p_values(
        forecast, truth_k, baseline, e * samples_per_member, many.get(TRAJ_KEY)[:, 0]
    )
    changing = (copy_one_step > 0) | (spread > 0)
    wanted = cfg.predicted_dims if dims is None else _dims(dims, cfg)
    checked = tuple(d for d in wanted if bool(changing[d]))
    steps = min(coverage_steps, longest - 1)
    coverage = _coverage(ensemble, data, steps, samples_per_member, interval, generator)
    covered, episodes, exact, covered_half, half_exact = coverage
    if episodes < min_episodes:
        covered, exact, covered_half, half_exact = None, 0.0, None, 0.0
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
        covered=covered,
        episodes=episodes,
        coverage_steps=steps,
        interval=exact,
        alpha=float(alpha),
        min_episodes=min_episodes,
        covered_half=covered_half,
        half_interval=half_exact,
        k_step_p=k_step_p,
        k_samples=e * samples_per_member,
    )
    if warn and not checks.passed:
        warnings.warn(checks.message(), ModelCheckWarning, stacklevel=2)
    return checks


#: A constant forecast's Brier score at most this leaves nothing to tell apart (every run of
#: every start alike, up to rounding). The t-test's own guard is
#: :func:`~rcvae_torchrl.competency.intervals.mean_p_value`'s.
_NO_SPREAD = 1e-9
#: The tests read a forecast within [this, 1 - this]: one made from finitely many imagined
#: episodes does not tell a chance below about 1/1000 from 0 (nor one above 0.999 from 1).
_RESOLUTION = 1e-3


def _shifted(logit: torch.Tensor, mean: torch.Tensor | float) -> torch.Tensor:
    """``σ(logit + c)`` with one offset ``c`` per row, found by bisection so that the row's
    mean is ``mean``: ``logit`` ``[n]`` and ``mean`` a number, or ``mean`` ``[..., 1]`` (one
    row each, the result ``[..., n]``)."""
    mean = torch.as_tensor(mean, dtype=logit.dtype)
    mean = mean.reshape(1) if mean.dim() == 0 else mean
    low = torch.full_like(mean, -30.0)
    high = torch.full_like(mean, 30.0)
    for _ in range(60):  # the mean is increasing in c: halve the bracket
        mid = (low + high) / 2
        above = torch.sigmoid(logit + mid).mean(-1, keepdim=True) > mean
        high, low = torch.where(above, mid, high), torch.where(above, low, mid)
    return torch.sigmoid(logit + (low + high) / 2)


def _excess(g: torch.Tensor, real: torch.Tensor, runs: int) -> torch.Tensor:
    """:attr:`OutcomeCheck.excess_error` of shifted forecasts ``g`` and real rates ``real``
    ``[..., n]`` (over the last dimension): ``sqrt(max(0, mean((g - r)²) - mean(g·(1 - g)) /
    R))``."""
    noise = (g * (1 - g)).mean(-1) / runs
    return ((g - real).square().mean(-1) - noise).clamp_min(0.0).sqrt()


@dataclass(frozen=True)
class OutcomeCheck:
    """Forecasts of success against the real success rates of the same start states.

    A self-check of the forecast itself, on start states other than the ones it is scored on
    (e.g. the first states of held-out episodes): the agent's forecast per start, and the rate
    at which R real episodes of the same agent from that start succeeded. A model that has
    learned what decides the outcome forecasts each start's real rate; a systematic difference
    is a bias that the forecasts of other starts from the same distribution share. The test
    is two-sided, on the per-start differences (a one-sample t-test: the R real episodes of
    one start need not be independent, as in a deterministic env, where they agree).

    Right on average is not right per task: where the R episodes of a start are independent
    draws of its chance (a stochastic env), a second test asks whether the forecasts miss
    their own starts' rates, beyond a shift they all share, by more than the chance of R
    episodes allows (:attr:`per_start_p_value`, :attr:`scattered`), and :attr:`excess_error`
    says by how much; :meth:`describe` gives both.

    Check the forecast as it is made: a closed-loop forecast against closed-loop real
    episodes. Judged open loop instead (the recorded actions of held-out episodes, imagined
    and replayed), a model whose closed-loop forecasts were within 0.04 of reality was 0.6 too
    pessimistic: over seconds its open-loop errors carry an object past a small target, errors
    that an agent reacting to the imagined states corrects.

    A check that finds no bias has passed only where it rules out one that matters: its
    interval of the gap must lie within ``± tolerance`` of 0 (:attr:`precise`). From a
    dozen starts with one episode each, forecasts of 0.5 against a real rate of 0.17 are no
    bias the tests can name (interval -0.02 to +0.68), and no sign of forecasts to trust
    either: such a check is unchecked, as one with too few starts is.

    Build it with :meth:`from_outcomes`. Its fields are not changed after it is made, so each
    Monte-Carlo p-value is drawn once and kept.
    """

    forecast: torch.Tensor  #: ``[n]`` the forecast P(success) per start
    real: torch.Tensor  #: ``[n]`` the success rate of its real episodes
    runs: int  #: R, real episodes per start
    alpha: float = 0.01
    min_starts: int = 10
    #: what was forecast, for the message (e.g. "the agent from held-out episodes' starts")
    what: str = "the forecasts"
    #: the largest bias a check that passes leaves possible: its interval of the gap (at the
    #: test's level) must lie within ``± tolerance``
    tolerance: float = 0.2
    #: what the forecasts answered (a report's :attr:`~rcvae_torchrl.competency.CompetencyReport
    #: .task`: its boundary, deadline and world model); ``None`` where not known (bare
    #: forecasts), and then the check vouches for no report
    task: str | None = None
    #: the start states the forecasts were made from, ``[n, D]`` (a report's observations);
    #: ``None`` where not known, and then the check cannot tell which starts it vouches for
    start_states: torch.Tensor | None = None
    #: ``[D]``, the unit of each dimension in :meth:`covers`: the spread of the world model's
    #: training states (a report's novelty check,
    #: :attr:`~rcvae_torchrl.training.StateNovelty.scale`); ``None``: the start states' own
    #: spread
    state_scale: torch.Tensor | None = None
    #: how the agent's policy acted in the real episodes (their
    #: :attr:`~rcvae_torchrl.agent.RealOutcomes.acting`, else the report's); ``None`` where not
    #: known. A report whose imagined policy acted otherwise is not vouched for
    acting: str | None = None
    #: the agent: the digest of its policy's weights or a weightless module's settings (the
    #: real episodes' :attr:`~rcvae_torchrl.agent.RealOutcomes.agent`, else the report's);
    #: ``None`` where not known. A report of another agent is not vouched for
    agent: str | None = None
    #: ``[n]`` bool, the starts whose outcome was settled before the agent acted (already in
    #: the success or the failure region: a report's ``("start_state", "in_success")`` and
    #: ``"in_failure"``); ``None`` where not known. Their forecasts of 0 or 1 show nothing
    #: of the model, and :attr:`sure_only` does not count them
    began_settled: torch.Tensor | None = None

    def __post_init__(self) -> None:
        for name in ("forecast", "real"):
            _checks.check_tensor(name, getattr(self, name))
            _checks.check_rank(name, getattr(self, name), 1, "[n]")
        if self.real.shape != self.forecast.shape:
            raise ValueError(
                f"real: expected one success rate per forecast ({self.forecast.shape[0]}), got "
                f"{self.real.shape[0]}"
            )
        for name in ("forecast", "real"):  # probabilities and rates, finite and in [0, 1]
            value = getattr(self, name)
            if not bool(((value >= 0) & (value <= 1)).all()):  # NaN fails too
                raise ValueError(
                    f"{name}: expected values in [0, 1] (a probability, a success rate), got "
                    f"{value[~((value >= 0) & (value <= 1))][:3].tolist()}"
                )
        check_positive_int("runs", self.runs)
        check_positive_int("min_starts", self.min_starts)
        if isinstance(self.alpha, bool) or not isinstance(self.alpha, (int, float)):
            raise TypeError(f"alpha: expected a level in (0, 1), got {self.alpha!r}")
        if not 0.0 < self.alpha < 1.0:
            raise ValueError(f"alpha: expected a level in (0, 1), got {self.alpha!r}")
        check_unit_interval("tolerance", self.tolerance, include_zero=False)
        for name in ("task", "acting", "agent", "what"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, str):
                raise TypeError(f"{name}: expected a str or None, got {value!r}")
        if self.start_states is not None:
            _checks.check_tensor("start_states", self.start_states)
            _checks.check_rank("start_states", self.start_states, 2, "[n, D]")
            # a NaN start is near no state: covers() would vouch for none
            _checks.check_finite("start_states", self.start_states)
            if self.start_states.shape[0] != self.forecast.shape[0]:
                raise ValueError(
                    "start_states: expected one start state per forecast "
                    f"({self.forecast.shape[0]}), got {self.start_states.shape[0]}"
                )
        if self.began_settled is not None and (
            self.began_settled.dtype != torch.bool or self.began_settled.shape != self.real.shape
        ):
            raise ValueError(
                f"began_settled: expected a bool tensor [n={self.forecast.shape[0]}], got dtype "
                f"{self.began_settled.dtype} and shape {tuple(self.began_settled.shape)}"
            )
        if self.state_scale is not None:
            _checks.check_tensor("state_scale", self.state_scale)
            dim = None if self.start_states is None else self.start_states.shape[-1]
            if self.state_scale.dim() != 1 or (dim is not None and self.state_scale.numel() != dim):
                raise ValueError(
                    f"state_scale: expected one positive unit per dimension [D={dim}], got shape "
                    f"{tuple(self.state_scale.shape)}"
                )
            _checks.check_finite("state_scale", self.state_scale)
            if not bool((self.state_scale > 0).all()):
                raise ValueError("state_scale: expected positive units, got one <= 0")

    @staticmethod
    def episodes_to_find(bias: float, *, alpha: float = 0.01, power: float = 0.9) -> int:
        """How many real outcomes a check needs to name forecasts biased by ``bias`` (their
        mean minus the real rate) at level ``alpha``, two-sided, with probability ``power``,
        whatever the success rate: the binomial sample size
        ``((z(1 - alpha / 2) + z(power)) * 0.5 / bias) ** 2``, rounded up, where 0.5 is the
        largest spread of one outcome. Count independent outcomes: in a deterministic env a
        start repeats its outcome, so count starts; in a stochastic one a start's runs share
        its chance, so its R runs count for less than R starts would. Forecasts that also
        miss their own starts' chances, beyond the bias they share, spread the per-start
        differences further and need more. 100 outcomes give a gap a standard error of at
        most 0.05, but name a bias of 0.08 with probability 0.17 to 0.28 only by this
        approximation (success rates of 0.5 to 0.8), 0.14 to 0.19 simulated.

        The size is the t-test's, by the normal approximation; :attr:`biased` also asks the
        outcomes' exact chance, which is more conservative. Simulated with one outcome per start
        (600 draws for each sign), 375 outcomes named a bias of ±0.10 with probability 0.875 at a
        chance of 0.5 and 0.96 with chances spread over 0.05-0.95: ``power`` is a target that
        chances near 0.5 fall a little short of.

        Example:
            >>> OutcomeCheck.episodes_to_find(0.10)
            372
            >>> OutcomeCheck.episodes_to_find(0.05)
            1488
        """
        check_unit_interval("bias", bias, include_zero=False)
        for name, value in (("alpha", alpha), ("power", power)):
            check_unit_interval(name, value, include_zero=False)
            if value >= 1.0:
                raise ValueError(f"{name}: expected a float in (0, 1), got {value!r}")
        from scipy.stats import norm

        z = float(norm.ppf(1.0 - alpha / 2.0) + norm.ppf(power))
        return math.ceil((z * 0.5 / bias) ** 2 - 1e-9)  # an exact square is not rounded up

    @classmethod
    def from_outcomes(
        cls,
        forecast: torch.Tensor | Any,
        real_success: torch.Tensor | Any,
        *,
        alpha: float = 0.01,
        min_starts: int = 10,
        what: str = "the forecasts",
        tolerance: float = 0.2,
        task: str | None = None,
        start_states: torch.Tensor | None = None,
        state_scale: torch.Tensor | None = None,
        began_settled: torch.Tensor | None = None,
    ) -> OutcomeCheck:
        """From forecasts ``[n]`` (probabilities) and real outcomes, bool ``[n, R]``.

        ``forecast`` may be the :class:`~rcvae_torchrl.competency.CompetencyReport` itself and
        ``real_success`` the :class:`~rcvae_torchrl.agent.RealOutcomes` of
        :func:`~rcvae_torchrl.agent.real_outcomes`: a real success then counts only within the
        report's deadline (its ``time_limit`` steps), as in
        :func:`~rcvae_torchrl.agent.score_forecast`; real episodes run for more steps than the
        forecast looked ahead would otherwise judge another task. The check then keeps the
        report's ``task`` and vouches only for reports of the same task
        (:meth:`~rcvae_torchrl.competency.CompetencyReport.with_forecast_check`); from bare
        forecasts, pass ``task=report.task`` of the report they come from. It keeps the
        report's start states too (or ``start_states`` ``[n, D]`` given with bare forecasts), and
        vouches for forecasts of start states like them alone (:meth:`covers`), each dimension
        in units of its spread in the world model's training states where the report has a
        novelty check (or ``state_scale`` ``[D]`` given). Real episodes of another agent
        than the report's (other policy weights, ``agent``; a policy acting in another
        exploration mode, ``acting``), or judged by another boundary (``predicates``), are
        refused. ``began_settled`` ``[n]`` bool: the starts whose outcome was settled before
        the agent acted (read from a report; give it with bare forecasts), for
        :attr:`sure_only`."""
        deadline = getattr(forecast, "time_limit", None)
        check_same_agent(forecast, real_success, name="real_success")
        check_same_predicates(forecast, real_success, name="real_success")
        acted = getattr(forecast, "acting", None), getattr(real_success, "acting", None)
        agents = getattr(forecast, "agent", None), getattr(real_success, "agent", None)
        if hasattr(forecast, "competency") and deadline is not None:  # a CompetencyReport
            if callable(getattr(forecast, "flattened", None)):  # [2, 3] or one start: as
                forecast = forecast.flattened()  # the real outcomes count them
            known = getattr(forecast, "task", "") or None
            if task is not None and known is not None and task != known:
                raise ValueError(
                    "task: expected the task of the forecasts' report, got "
                    f"{fingerprint.task_difference(task, known)}; leave task out with a report "
                    "(it is the report's)"
                )
            task = known if task is None else task
            if start_states is None:
                start_states = getattr(forecast, "start_states", None)
            novelty = getattr(forecast, "novelty", None)
            scale = getattr(novelty, "scale", None)
            dims = None if start_states is None else start_states.shape[-1]
            if state_scale is None and scale is not None and scale.numel() == dims:
                state_scale = scale
            data = getattr(forecast, "data", None)
            began = [None if data is None else data.get(("start_state", k), None) for k in _BEGAN]
            if began_settled is None and all(b is not None for b in began):
                began_settled = (began[0] | began[1]).reshape(-1).cpu()
            forecast = forecast.competency["p_success"]
        # real episodes from other start states (or in another order) judge other tasks
        _checks.check_same_starts(
            "real_success", start_states, getattr(real_success, "starts", None), "real episodes"
        )
        if task is not None and not isinstance(task, str):
            raise TypeError(f"task: expected a report's task (a str), got {type(task).__name__}")
        if callable(getattr(real_success, "within", None)):  # a RealOutcomes
            if deadline is not None:
                real_success = real_success.within(deadline)
            real_success = real_success.success
        _checks.check_tensor("forecast", forecast)
        _checks.check_rank("forecast", forecast, 1, "[n]")
        _checks.check_floating("forecast", forecast)
        check_probability("forecast", forecast)
        _checks.check_tensor("real_success", real_success)
        n, shape = forecast.shape[0], tuple(real_success.shape)
        if real_success.dtype != torch.bool or len(shape) != 2 or shape[0] != n:
            raise ValueError(
                f"real_success: expected a bool tensor [n={n}, R >= 1], got dtype "
                f"{real_success.dtype} and shape {shape}"
            )
        if shape[1] < 1:
            raise ValueError("real_success: expected at least one real episode per start, got 0")
        check_unit_interval("alpha", alpha, include_zero=False)
        check_positive_int("min_starts", min_starts)
        return cls(
            forecast.detach().to(torch.float64).cpu(),
            real_success.to(torch.float64).mean(1).cpu(),
            runs=int(real_success.shape[1]),
            alpha=float(alpha),
            min_starts=int(min_starts),
            what=str(what),
            tolerance=float(tolerance),
            task=task,
            start_states=None
            if start_states is None
            else torch.as_tensor(start_states).detach().cpu().double(),
            state_scale=None
            if state_scale is None
            else torch.as_tensor(state_scale).detach().cpu().double(),
            acting=acted[1] if acted[1] is not None else acted[0],
            agent=agents[1] if agents[1] is not None else agents[0],
            began_settled=None
            if began_settled is None
            else torch.as_tensor(began_settled).detach().cpu(),
        )

    @property
    def starts(self) -> int:
        return int(self.forecast.numel())

    @property
    def measured(self) -> bool:
        """Whether there were enough start states whose outcome was in doubt (``min_starts``
        that are not :attr:`settled`)."""
        return self.starts - self.settled >= self.min_starts

    @property
    def settled(self) -> int:
        """Start states whose forecast and real runs all agree on the outcome from the start:
        a forecast within 0.001 of 0 where every real run failed, or of 1 where every one
        succeeded (a walker already lying, a ball already past the line). Right there, any
        model is: they show nothing of the forecasts in doubt, and a check of them alone
        would pass with an interval of zero width."""
        return int(self._settled.sum())

    @cached_property
    def _settled(self) -> torch.Tensor:
        """Which starts are :attr:`settled`, bool ``[n]``."""
        f, r = self.forecast, self.real
        return ((f <= _RESOLUTION) & (r == 0)) | ((f >= 1 - _RESOLUTION) & (r == 1))

    @cached_property
    def _sure(self) -> torch.Tensor:
        """The starts forecast 0 or 1 (within 0.001) whose outcome was not settled before the
        agent acted (where that is known, :attr:`began_settled`), bool ``[n]``."""
        sure = ~self.in_doubt(self.forecast)
        return sure if self.began_settled is None else sure & ~self.began_settled

    def in_doubt(self, forecast: torch.Tensor) -> torch.Tensor:
        """Which of ``forecast`` (probabilities, any shape) are in doubt: neither 0 nor 1
        within the 0.001 that tells a sure forecast (where :attr:`sure_only` vouches for none
        of them)."""
        return (forecast > _RESOLUTION) & (forecast < 1 - _RESOLUTION)

    @property
    def sure(self) -> int:
        """Start states forecast 0 or 1 (within 0.001) whose outcome was not settled before
        the agent acted: the forecasts a near-exact model of a deterministic env gives."""
        return int(self._sure.sum())

    @property
    def sure_misses(self) -> int:
        """Of the :attr:`sure` start states, those where some real run went the other way."""
        return int((self._sure & ~self._settled).sum())

    @cached_property
    def sure_bound(self) -> float:
        """The share of sure forecasts that are wrong, at most (its exact one-sided
        Clopper-Pearson bound at ``1 - alpha`` from :attr:`sure_misses` of :attr:`sure`: 0 of
        21 bounds it by 0.197 at alpha 0.01); NaN with no sure start."""
        n, k = self.sure, self.sure_misses
        if n == 0:
            return float("nan")
        if k >= n:
            return 1.0
        from scipy.stats import beta

        return float(beta.ppf(1 - self.alpha, k + 1, n - k))

    @property
    def sure_only(self) -> bool:
        """Too few start states in doubt to check forecasts in doubt (not :attr:`measured`),
        no bias found, and the sure forecasts right as far as ``tolerance``: at most that
        share of them wrong (:attr:`sure_bound`; each wrong one is off by about 1, so their
        bias is within ``tolerance`` too). The check has then :attr:`passed` for forecasts of
        0 or 1 alone: a near-exact model of a deterministic env forecasts almost every start
        so, and its forecasts could otherwise never be checked (a calm point-robot trial: 298
        of 300 starts forecast 0 or 1, all right, and the check unmeasured). A report whose
        own forecasts are in doubt is not vouched for
        (:attr:`~rcvae_torchrl.competency.CompetencyReport.warning`). Only where it is known
        which starts were settled before the agent acted (:attr:`began_settled`: from a
        report, or given): a walker already lying is forecast 0 by any model."""
        return (
            self.began_settled is not None  # else a start settled before it acted would count
            and not self.measured
            and not self.biased
            and self.sure > 0
            and self.sure_bound <= self.tolerance
        )

    @property
    def gap(self) -> float:
        """Mean forecast minus mean real rate: > 0 too optimistic, < 0 too pessimistic."""
        if self.starts == 0:
            return float("nan")
        return float(self._gaps.mean())

    @cached_property
    def _gaps(self) -> torch.Tensor:
        """Each start's forecast minus its real rate, in float64 ``[n]``: what :attr:`gap`,
        :attr:`p_value`, :attr:`standard_error` and :meth:`interval` are made of."""
        return (self.forecast - self.real).to(torch.float64)

    @property
    def p_value(self) -> float:
        """Two-sided p-value of "no bias" (NaN with fewer than 2 starts)."""
        return mean_p_value(self._gaps)

    @cached_property
    def exact_p_value(self) -> float:
        """Two-sided p-value of "the forecasts are the starts' chances", judged by the mean
        gap alone: the gap against 4,000 draws of the real outcomes from the forecasts
        themselves (seeded: the same number on every call), R independent episodes per start
        where some start's episodes disagree, else one outcome per start repeated (as in a
        deterministic env; forecasts read within [0.001, 0.999]); twice the smaller tail, at
        most 1. Exact where the t-test of :attr:`p_value` is not: with few successes (or
        failures) its estimate of the spread rests on a handful of episodes. NaN with no
        start."""
        if self.starts == 0:
            return float("nan")
        runs = self.runs if self._independent_runs else 1
        draws = _DRAWS
        generator = torch.Generator().manual_seed(1)
        f = self.forecast.clamp(_RESOLUTION, 1 - _RESOLUTION)
        counts = torch.binomial(
            torch.full((draws, f.numel()), float(runs), dtype=f.dtype),
            f.expand(draws, -1),
            generator,
        )
        simulated = (f - counts / runs).mean(-1)
        gap, tie = float((f - self.real).mean()), 1e-12  # equal up to rounding: reached
        upper = (int((simulated >= gap - tie).sum()) + 1) / (draws + 1)
        lower = (int((simulated <= gap + tie).sum()) + 1) / (draws + 1)
        return min(1.0, 2 * min(upper, lower))

    @property
    def standard_error(self) -> float:
        """The standard error of :attr:`gap`: the sample standard deviation of the per-start
        differences over √n (NaN with fewer than 2 starts). With one real episode per start
        it is at most about 0.5 / √n, whatever the success rate."""
        diff = self._gaps
        if diff.numel() < 2:
            return float("nan")
        return float(diff.std(correction=1)) / diff.numel() ** 0.5

    def interval(self, confidence: float | None = None) -> tuple[float, float]:
        """A ``confidence`` interval of :attr:`gap` (Student's t over the starts, within
        [-1, 1]); by default
        at the test's own level, ``1 - alpha``, so that it holds 0 exactly when the t-test
        passes (and then the check passes; it also passes where the outcomes' exact chance
        does not find the gap beyond chance, :attr:`biased`)."""
        confidence = 1.0 - self.alpha if confidence is None else confidence
        check_unit_interval("confidence", confidence, include_zero=False)
        if self.starts < 2:
            return float("nan"), float("nan")
        # within [-1, 1], as every such interval of the library (a gap of probabilities)
        return mean_interval(self._gaps, confidence)

    @property
    def per_start_measured(self) -> bool:
        """Whether the per-start test applies: measured, with R >= 2 real episodes per start
        and some start whose episodes did not all agree. Where every start's episodes agree
        (as in a deterministic env, whose R runs of one start are one outcome repeated), R
        runs are no R independent draws of the start's chance, and no per-start rate can be
        told from the forecast's."""
        return self.measured and self.runs >= 2 and self._independent_runs

    @cached_property
    def _independent_runs(self) -> bool:
        """Whether some start's real episodes disagree: then its R runs are taken for R
        independent draws of its chance, else for one outcome repeated."""
        return bool(((self.real > 0) & (self.real < 1)).any())

    @cached_property
    def per_start_p_value(self) -> float:
        """p-value of "each start's real episodes succeed at its own forecast's rate, but for
        a shift all starts share": beyond the mean (:attr:`p_value`, which judges the shift),
        whether the per-start differences scatter more than the binomial chance of R
        independent episodes allows. The shift is one logit offset ``c`` for all starts
        (:meth:`shifted`, fitted so that the shifted forecasts' mean is the real rate; a
        forecast of 0 stays 0), the statistic the binomial deviance over the starts,
        ``2 Σ [k log(k / (R·g)) + (R - k) log((R - k) / (R·(1 - g)))]`` with ``k`` a start's
        successes and ``g`` the shifted forecasts (kept within [0.001, 0.999]: a forecast from
        finitely many imagined episodes does not tell a chance below about 1/1000 from 0). It
        is compared with 4,000 draws of the counts from ``g``, each with its own offset fitted
        again, seeded: every call gives the same number. NaN when not
        :attr:`per_start_measured`.

        The deviance, not Pearson's ``Σ (k - R·g)² / (R·g·(1 - g))``: a settled start
        (forecast near 0 or 1) puts a rare, huge Pearson term into the draws (one failure in
        30 runs at ``g = 0.999`` adds 33, against 5 to the deviance), which buries the misses
        of the other starts. In 200 simulated checks of 20 starts that miss (logit error of
        sd 0.6, 30 runs each) beside 20 settled ones, Pearson's found the misses in 3.5 % at
        level 0.01 and the deviance in 84 % (without the settled starts: 85 % and 88 %); where
        nothing missed, both rejected 0.5 to 2.5 %.
        """
        if not self.per_start_measured:
            return float("nan")
        runs = float(self.runs)

        def deviance(counts: torch.Tensor) -> torch.Tensor:
            g = _shifted(self._logit, counts.mean(-1, keepdim=True) / runs).clamp(
                _RESOLUTION, 1 - _RESOLUTION
            )
            hits = counts * (counts / (runs * g)).log()
            misses = (runs - counts) * ((runs - counts) / (runs * (1 - g))).log()
            zero = torch.zeros((), dtype=counts.dtype)  # 0 log 0 = 0
            return 2 * (
                torch.where(counts > 0, hits, zero) + torch.where(counts < runs, misses, zero)
            ).sum(-1)

        observed_counts = (self.real * runs).round()
        g = _shifted(self._logit, observed_counts.mean() / runs).clamp(_RESOLUTION, 1 - _RESOLUTION)
        draws = _DRAWS
        generator = torch.Generator().manual_seed(0)
        simulated = torch.binomial(
            torch.full((draws, g.numel()), runs, dtype=g.dtype), g.expand(draws, -1), generator
        )
        observed = deviance(observed_counts)
        return float((int((deviance(simulated) >= observed).sum()) + 1) / (draws + 1))

    def shifted(self) -> torch.Tensor:
        """The forecasts with the shift all starts share taken out: ``σ(logit f + c)`` ``[n]``,
        one offset ``c`` with the real rate as their mean (a forecast of 0 or 1 stays)."""
        return _shifted(self._logit, self.real.mean())

    @cached_property
    def _logit(self) -> torch.Tensor:
        """The forecasts' logits, as the tests read them (within [0.001, 0.999])."""
        return self.forecast.clamp(_RESOLUTION, 1 - _RESOLUTION).logit()

    @property
    def excess_error(self) -> float:
        """How far a start's forecast lies from its true chance beyond the shift all starts
        share and the chance of R episodes: the root-mean-square of ``g - r`` for the shifted
        forecasts ``g`` (:meth:`shifted`) with the binomial noise taken out,
        ``sqrt(max(0, mean((g - r)²) - mean(g·(1 - g)) / R))`` (NaN when not
        :attr:`per_start_measured`)."""
        if not self.per_start_measured:
            return float("nan")
        return float(_excess(self.shifted(), self.real, self.runs))

    def excess_error_interval(self, confidence: float = 0.9) -> tuple[float, float]:
        """A ``confidence`` interval of :attr:`excess_error`: the percentile bootstrap over the
        start states (2,000 resamples of them with replacement, the shift fitted again in each;
        seeded: every call gives the same interval). From a few dozen starts the estimate is
        noisy: with forecasts that were the truth, 40 starts of 10 runs gave estimates above
        0.05 in a quarter of the draws (up to 0.12). ``(nan, nan)`` when not
        :attr:`per_start_measured`."""
        check_unit_interval("confidence", confidence, include_zero=False)
        if not self.per_start_measured:
            return float("nan"), float("nan")
        n = self.starts
        picks = torch.randint(n, (_BOOTSTRAP, n), generator=torch.Generator().manual_seed(0))
        real = self.real[picks]
        values = _excess(_shifted(self._logit[picks], real.mean(-1, keepdim=True)), real, self.runs)
        tails = torch.tensor([(1 - confidence) / 2, (1 + confidence) / 2], dtype=values.dtype)
        low, high = torch.quantile(values, tails).tolist()
        return low, high

    @property
    def task_spread(self) -> float:
        """How far the starts' true chances differ, beyond the chance of R episodes: the
        standard deviation of the real rates ``r`` over the starts with the binomial noise
        taken out, ``sqrt(max(0, var(r) - mean(r·(1 - r)) / (R - 1)))`` (``var`` with Bessel's
        correction; each ``r·(1 - r) / (R - 1)`` is the unbiased noise of one rate). Whether
        the rates differ beyond that noise at all is a test of its own
        (:func:`~rcvae_torchrl.competency.same_chance_p_value`, which :meth:`describe` reads).
        NaN when not :attr:`per_start_measured`."""
        if not self.per_start_measured or self.starts < 2:
            return float("nan")
        r = self.real.double()
        noise = float((r * (1 - r)).mean()) / (self.runs - 1)
        return max(0.0, float(r.var(correction=1)) - noise) ** 0.5

    @property
    def scattered(self) -> bool:
        """Per-start measured, and the forecasts miss their starts' real rates by more than
        the chance of R episodes allows (level ``alpha``), whether or not they are biased on
        average."""
        return self.per_start_measured and self.per_start_p_value < self.alpha

    @cached_property
    def _cover(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float, float] | None:
        """The check's start states scaled (each dimension by :attr:`state_scale`, else by
        its spread among them; one that does not vary, by a millionth of its size), their
        centre and scale, the level of :meth:`covers` and the share of new starts like them it
        keeps; ``None`` without start states, or with fewer than 2."""
        if self.start_states is None or self.start_states.shape[0] < 2:
            return None
        from rcvae_torchrl._conformal import conformal_level

        states = self.start_states
        center = states.mean(0)
        scale = self.state_scale
        if scale is None:
            spread = states.std(0, correction=0)
            scale = torch.where(spread > 0, spread, 1e-6 * center.abs().clamp_min(1.0))
        scaled = (states - center) / scale
        apart = torch.cdist(scaled, scaled).fill_diagonal_(torch.inf).amin(1)
        level, kept = conformal_level(apart, _COVER_QUANTILE)
        return scaled, center, scale, level, kept

    def covers(self, states: torch.Tensor) -> torch.Tensor | None:
        """``[m]`` bool: whether each of ``states`` ``[m, D]`` lies among the check's own
        start states: no farther from the nearest of them (each dimension in units of
        :attr:`state_scale`, the training states' spread, else of their own spread) than 99 %
        of them lie from their own nearest other (a conformal level: a new
        start drawn like them stays within it with probability 0.99, or n / (n + 1) with
        fewer than 99 of them). A check vouches for forecasts of start states like its own:
        one made on a cart-pole's hanging starts said nothing of starts with the cart moving
        4 m/s, where the forecasts were 0.3 off. In their own spread, a dimension that varies
        among them by float noise alone (a quadruped's force sensors at rest) counts as much
        as one that matters, and hides a start far off in it; in the training states' it
        counts as the noise it is. ``None`` where the check keeps fewer than 2 start states."""
        cover = self._cover
        if cover is None:
            return None
        scaled, center, scale, level, _ = cover
        states = torch.as_tensor(states)
        _checks.check_tensor("states", states)
        if states.dim() != 2 or states.shape[-1] != scaled.shape[-1]:
            raise ValueError(
                f"states: expected start states [m, D={scaled.shape[-1]}] like the check's, "
                f"got shape {tuple(states.shape)}"
            )
        query = (states.detach().cpu().double() - center) / scale
        return torch.cdist(query, scaled).amin(1) <= level * (1 + 1e-9)

    def coverage_p_value(self, states: torch.Tensor) -> float:
        """p-value of "``states`` ``[m, D]`` are drawn like the check's start states": the
        chance of at least as many of them outside :meth:`covers`' level, each outside with
        probability at most one minus the share it keeps (binomial; conservative). NaN where
        the check keeps no start states."""
        covered = self.covers(states)
        if covered is None:
            return float("nan")
        from scipy.stats import binom

        outside, keep = int((~covered).sum()), self._cover[-1]
        return float(binom.sf(outside - 1, covered.numel(), 1.0 - keep)) if outside else 1.0

    @property
    def brier_skill(self) -> float:
        """The forecasts' Brier skill over every real episode against one forecast for all
        starts, the check's own success rate: ``1 - B / B_0``, each start's R runs scored at
        its forecast (B) and at the mean real rate (B_0). Above 0 where the forecasts tell
        the starts apart better than one number does; NaN where the real rates leave nothing
        to tell (every run of every start alike)."""
        f, r = self.forecast, self.real
        noise = r * (1 - r)  # each start's runs about their own rate, the same for both
        constant = float(((r.mean() - r).square() + noise).mean())
        if constant <= _NO_SPREAD:
            return float("nan")
        return 1.0 - float(((f - r).square() + noise).mean()) / constant

    @property
    def no_better_than_constant(self) -> bool:
        """The forecasts miss their starts' real rates by more than R episodes' chance allows
        (:attr:`scattered`) and score no better than one forecast for every start
        (:attr:`brier_skill` <= 0): right on average perhaps, but they do not tell one task
        from another (a cart-pole model after 150 training steps forecast 0.04-0.16 for
        starts whose real rates ran from 0 to 0.88)."""
        return self.scattered and not self.brier_skill > 0

    @property
    def biased(self) -> bool:
        """The forecasts differ from the real rates by more than chance allows (level
        ``alpha``): by the t-test over the starts (:attr:`p_value`: a bias that the forecasts
        of other starts from the same distribution share) and by the outcomes' exact chance
        were the forecasts the starts' chances (:attr:`exact_p_value`), which keeps a few rare
        successes from reading as a bias. Together they hold their level with any number of
        starts (simulated under no bias, 100 or 375 starts of one or 30 runs: 0.002 to 0.014 at
        level 0.01); the t-test alone does not where success is rare (every start at a chance
        of 0.02: 0.14 with 100 starts, 0.67 with 20), which is why both are asked. So a bias is
        named with fewer than ``min_starts`` in doubt too (six starts
        forecast 0.95-1.0 whose 60 real runs all failed): the count decides only whether a
        check that names none has :attr:`passed`."""
        p_value, exact = self.p_value, self.exact_p_value
        return p_value < self.alpha and exact < self.alpha  # False where NaN (< 2 starts)

    @property
    def precise(self) -> bool:
        """Measured, and the gap's interval (:meth:`interval`) within ``± tolerance`` of 0: a
        bias that large is ruled out (two one-sided tests). An interval merely no wider than
        that would pass a gap of +0.13 whose interval reached +0.27 (an acrobot model that
        was 0.26 too optimistic on the starts scored). The gap's bound from the count of real
        successes (a Wilson interval of the real rate at the same level, over the independent
        outcomes: every run where some start's runs disagree, else one per start) must be
        within the tolerance too: where every outcome agrees the t interval has no width, and
        ten starts forecast 0.02 whose ten runs all failed passed, though a chance of 0.22
        fails ten runs in 8 % of draws."""
        low, high = self.interval()
        if not (self.measured and max(-low, high) <= self.tolerance):
            return False
        low, high = self._count_interval
        return max(-low, high) <= self.tolerance

    @cached_property
    def _count_interval(self) -> tuple[float, float]:
        """The gap's interval from the count of real successes: the mean forecast minus a
        Wilson interval of the real rate at level ``1 - alpha`` over the independent outcomes
        (every run where some start's runs disagree, else one per start)."""
        outcomes = self.starts * (self.runs if self._independent_runs else 1)
        successes = (self.real.to(torch.float64).mean() * outcomes).round()
        lowest, highest = binomial_interval(successes, outcomes, 1.0 - self.alpha, "wilson")
        mean = float(self.forecast.mean())
        return mean - float(highest), mean - float(lowest)

    @property
    def passed(self) -> bool:
        """Measured and precise, no bias found, and, where R runs per start tell each start's
        rate, forecasts that tell the starts apart (not :attr:`no_better_than_constant`); or,
        with too few starts in doubt for that, the forecasts of 0 and 1 right
        (:attr:`sure_only`), which vouches for such forecasts alone."""
        return (
            self.precise and not self.biased and not self.no_better_than_constant
        ) or self.sure_only

    @property
    def verdict(self) -> str:
        """``"passed"``, ``"too optimistic"``, ``"too pessimistic"``, ``"no better than a
        constant"`` (:attr:`no_better_than_constant`, whatever the interval's width: more
        starts would not mend forecasts that do not tell the starts apart), ``"too
        imprecise"`` (no bias found, with an interval reaching beyond ``± tolerance``) or
        ``"not measured"``."""
        if self.biased:
            return "too optimistic" if self.gap > 0 else "too pessimistic"
        if self.sure_only:
            return "passed"
        if not self.measured:
            return "not measured"
        if self.no_better_than_constant:  # before imprecision: more starts would not mend it
            return "no better than a constant"
        return "passed" if self.precise else "too imprecise"

    def message(self) -> str:
        """One sentence when the check did not pass ('' when it did; :meth:`describe` says
        it either way)."""
        return "" if self.passed else self.describe()

    def describe(self) -> str:
        """One sentence: the verdict, the mean forecast and real rate, the gap with its
        interval at the test's level, the two p-values (:attr:`biased`) and, where it applies,
        the per-start test's verdict; where that test cannot run, a Brier skill at or below 0
        (:attr:`brier_skill`) is said, though no verdict rests on it."""
        if self.sure_only:
            agreed = "in every one" if self.sure_misses == 0 else f"in all but {self.sure_misses}"
            doubt = self.starts - self.settled
            return (
                f"{self.what} are right where they are sure, as far as the check can tell: "
                f"{self.sure} of the {self.starts} start states were forecast 0 or 1 (within "
                f"0.001) from a start whose outcome was not yet settled, and their real runs "
                f"agreed {agreed} (at most {self.sure_bound:.1%} of such forecasts wrong, "
                f"{1 - self.alpha:.0%} bound); the {doubt} start states in doubt are too few to "
                f"check forecasts in doubt (the outcome check needs {self.min_starts}), so it "
                "vouches for forecasts of 0 or 1 alone"
            )
        if not self.measured and self.settled and not self.biased:
            return (
                f"{self.what} are not measured by the outcome check: {self.settled} of the "
                f"{self.starts} start states were forecast 0 or 1 and every real run agreed "
                "(forecast 0 where every one failed, or 1 where every one succeeded), which "
                f"shows nothing of the forecasts in doubt, and it needs {self.min_starts} others"
                f"{self._too_few_sure()}; check start states whose outcome is in doubt"
                f"{self._lean()}"
            )
        if not self.measured and not self.biased:
            return (
                f"{self.what} are not measured by the outcome check: {self.starts} start "
                f"states, where it needs {self.min_starts}"
            )
        low, high = self.interval()
        verdict = "unbiased as far as the tests can tell" if self.passed else self.verdict
        if not self.biased and self.p_value < self.alpha:  # the interval below excludes 0
            verdict = (
                "not named biased: a bias is named only where both tests find the gap beyond "
                "chance, and only the t-test does; the outcomes' exact chance allows it"
            )
        elif not self.biased and self.exact_p_value < self.alpha:
            verdict = (
                "not named biased: a bias is named only where both tests find the gap beyond "
                "chance, and only the outcomes' exact chance does; the t-test over the starts "
                "allows it (its interval holds 0)"
            )
        elif not self.biased and not self.precise and not self.no_better_than_constant:
            verdict = "checked too imprecisely to pass"
        wide = ""
        if not self.biased and not self.precise and not self.no_better_than_constant:
            runs = " (or more real episodes per start)" if self._independent_runs else ""
            reach = "the interval reaches"
            if self.measured and max(-low, high) <= self.tolerance:  # the count's bound reaches
                first, last = self._count_interval
                reach = (
                    f"the count of real successes leaves the gap anywhere in {signed(first)} to "
                    f"{signed(last)}, which reaches"
                )
            wide = (
                f": no bias is named, but {reach} beyond ±{self.tolerance:g}, so a "
                "bias that large is not ruled out and the check has not passed; check more start "
                f"states{runs}"
            )
        return (
            f"{self.what} are {verdict}: from {self.starts} start states they forecast "
            f"success {float(self.forecast.mean()):.2f} on average where {self.runs} real "
            f"episode{'' if self.runs == 1 else 's'} from each succeeded "
            f"{float(self.real.mean()):.2f} (gap {signed(self.gap)}, "
            f"{100 * (1 - self.alpha):g} % interval {signed(low)} to {signed(high)}; "
            f"{self._t_test_words()}, {_drawn_p(self.exact_p_value)} by the outcomes' exact "
            "chance, "
            f"{_DRAWS:,} draws){wide}" + self._per_start_sentence()
        )

    def _t_test_words(self) -> str:
        """The t-test's p-value in words; where every start's difference is the same there is
        no spread to test against, and the p-value (0, or 1 for no difference) says so."""
        if without_spread(self._gaps):
            return f"p = {self.p_value:g}: every start's gap the same, no spread for a t-test"
        return f"p = {self.p_value:.2g} by a t-test over the starts"

    def _too_few_sure(self) -> str:
        """Where the check knows which starts were settled before the agent acted and some
        forecasts of 0 or 1 were not, why those alone do not pass it (:attr:`sure_only`): how
        far their count bounds the share wrong, and how many it takes ('' otherwise)."""
        if self.began_settled is None or self.sure == 0 or self.sure_bound <= self.tolerance:
            return ""
        needed = math.ceil(math.log(self.alpha) / math.log(1 - self.tolerance))
        wrong = "none" if self.sure_misses == 0 else str(self.sure_misses)
        return (
            f"; nor can it vouch for the forecasts of 0 or 1 alone: {wrong} wrong of the "
            f"{self.sure} made from starts not settled before the agent acted bound the share "
            f"wrong at {self.sure_bound:.0%} ({1 - self.alpha:.0%} bound), above the tolerance "
            f"{self.tolerance:g} (with none wrong it takes {needed} such starts)"
        )

    def _lean(self) -> str:
        """Where a check too small to measure already finds its starts that are not settled
        (:attr:`settled`) off by more than their outcomes' exact chance allows, though not by
        the t-test too (so not :attr:`biased`), what they show ('' otherwise)."""
        if self.measured or self.biased or not self.exact_p_value < self.alpha:
            return ""
        doubt = ~self._settled
        forecast, real = float(self.forecast[doubt].mean()), float(self.real[doubt].mean())
        lean = "optimistic" if forecast > real else "pessimistic"
        return (
            f"; the {int(doubt.sum())} other starts already lean {lean}: they forecast "
            f"{forecast:.2f} on average where their real episodes succeeded {real:.2f} "
            f"({_drawn_p(self.exact_p_value)} by the outcomes' exact chance; the t-test over "
            f"all {self.starts} starts, p = {self.p_value:.3g}, does not name it)"
        )

    def _per_start_sentence(self) -> str:
        """How far the forecasts miss each start's own rate (where R independent runs tell)."""
        if self.measured and self.runs >= 2 and not self._independent_runs:
            return (
                f"; per start not tested: each start's {self.runs} episodes agree, so they "
                "are taken for one outcome repeated (a deterministic env's; in a stochastic "
                "one, no start's outcome varied in these runs) and tell no start's chance"
                + self._no_skill_seen()
            )
        if not self.per_start_measured:
            return self._no_skill_seen()
        shift = " beyond the shift they share" if self.biased else ""
        if self.no_better_than_constant:
            return (
                f"; per start they miss their start's real rate{shift} by more than the chance "
                f"of {self.runs} episodes allows, by about {self._excess_said()}, and score no "
                "better than one "
                f"forecast of {float(self.real.mean()):.2f} for every start (Brier skill "
                f"{signed(self.brier_skill)} over the real episodes): they do not tell one start "
                "state's task from another, so the check has not passed"
            )
        if self.scattered:
            return (
                f"; per start they miss their start's real rate{shift} by more than the chance "
                f"of {self.runs} episodes allows, by about {self._excess_said()}"
                + ("" if self.biased else ": trust them on average more than for one task")
            )
        alike = ""
        if not same_chance_p_value(self.real, self.runs) < self.alpha:
            alike = (
                f"; nor do the real rates differ between starts more than the chance of "
                f"{self.runs} episodes makes them (no task shown easier or harder than another), "
                "so nothing here shows whether the forecasts tell one task from another"
            )
        return (
            f"; per start they miss their start's real rate{shift} by no more than the chance "
            f"of {self.runs} episodes can hide (p = {self.per_start_p_value:.2g}: not shown to "
            "miss, which few episodes per start cannot tell from agreeing)"
            + (alike or self._no_skill_seen())
        )

    def _excess_said(self) -> str:
        """:attr:`excess_error` with its 90 % interval and the per-start test's p-value."""
        low, high = self.excess_error_interval(0.9)
        return (
            f"{self.excess_error:.2f} (root mean square, 90 % interval {low:.2f} to {high:.2f} "
            f"over resampled starts; p = {self.per_start_p_value:.2g})"
        )

    def _no_skill_seen(self) -> str:
        """Where the per-start test cannot run (one outcome per start, or runs that repeat one
        outcome), what the real episodes still show: forecasts that scored no better than one
        forecast for every start ('' where they scored better, or nothing varied). The verdict
        does not rest on it: with one outcome per start, so few starts rarely tell such a
        score from chance (a ball-in-cup model forecast 0.45 for 20 starts of which 4
        succeeded, Brier skill -0.67, and its check could only call the gap imprecise)."""
        skill = self.brier_skill
        if not skill <= 0:  # better than one forecast, or NaN: nothing varied
            return ""
        return (
            f"; they also scored no better than one forecast of {float(self.real.mean()):.2f} "
            f"for every start (Brier skill {signed(skill)} over the real episodes): nothing here "
            "shows that they tell one start state's task from another"
        )

    def as_dict(self) -> dict[str, Any]:
        """Plain values (for JSON), with the derived figures."""
        return {
            "forecast": self.forecast.tolist(),
            "real": self.real.tolist(),
            "runs": self.runs,
            "alpha": self.alpha,
            "min_starts": self.min_starts,
            "what": self.what,
            "tolerance": self.tolerance,
            "task": self.task,
            "acting": self.acting,
            "agent": self.agent,
            "start_states": None if self.start_states is None else self.start_states.tolist(),
            "state_scale": None if self.state_scale is None else self.state_scale.tolist(),
            "starts": self.starts,
            "gap": self.gap,
            "p_value": self.p_value,
            "exact_p_value": self.exact_p_value,
            "passed": self.passed,
            "per_start_p_value": self.per_start_p_value,
            "excess_error": self.excess_error,
            "excess_error_interval": list(self.excess_error_interval())
            if self.per_start_measured
            else None,
            "task_spread": self.task_spread,
            "scattered": self.scattered,
            "brier_skill": self.brier_skill,
            "no_better_than_constant": self.no_better_than_constant,
            "began_settled": None if self.began_settled is None else self.began_settled.tolist(),
            "sure": self.sure,
            "sure_misses": self.sure_misses,
            "sure_bound": self.sure_bound if self.sure else None,  # None: no sure start
            "sure_only": self.sure_only,
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> OutcomeCheck:
        """The inverse of :meth:`as_dict` (e.g. read back from JSON); a record missing an
        entry it needs, or whose stored gap its forecasts and real rates do not give (a rate
        edited by hand), raises ValueError naming it. The verdict is judged again from the
        numbers; a stored ``passed`` that differs is warned of, not taken."""
        check_entries(
            "values",
            values,
            ("forecast", "real", "runs", "alpha", "min_starts"),
            "an OutcomeCheck.as_dict()",
        )
        for key in ("runs", "min_starts"):  # 2.7 runs is no count (int() would make it 2)
            if isinstance(values[key], bool) or not isinstance(values[key], int):
                raise TypeError(f"values[{key!r}]: expected an integer, got {values[key]!r}")
        check = cls(
            torch.tensor(values["forecast"], dtype=torch.float64),
            torch.tensor(values["real"], dtype=torch.float64),
            runs=values["runs"],
            alpha=float(values["alpha"]),
            min_starts=values["min_starts"],
            what=str(values.get("what", "the forecasts")),
            tolerance=float(values.get("tolerance", 0.2)),
            task=values.get("task"),
            acting=values.get("acting"),
            agent=values.get("agent"),
            start_states=None
            if values.get("start_states") is None
            else torch.tensor(values["start_states"], dtype=torch.float64),
            state_scale=None
            if values.get("state_scale") is None
            else torch.tensor(values["state_scale"], dtype=torch.float64),
            began_settled=None  # absent from checks saved before it existed
            if values.get("began_settled") is None
            else torch.tensor(values["began_settled"], dtype=torch.bool),
        )
        # the gap is arithmetic of the record's own forecasts and outcomes (to float32's
        # rounding, for a check made of float32 rates)
        stored, said = values.get("gap"), values.get("passed")
        if stored is not None and (
            isinstance(stored, bool) or not isinstance(stored, (int, float))
        ):
            raise TypeError(f"values['gap']: expected a number (the check's gap), got {stored!r}")
        if said is not None and not isinstance(said, bool):
            raise TypeError(f"values['passed']: expected True or False, got {said!r}")
        if stored is not None and abs(stored - check.gap) > 1e-6:
            raise ValueError(
                f"values: the stored gap {stored:+.6f} is not the one the record's forecasts and "
                f"real rates give ({check.gap:+.6f}): the record was edited or damaged; make the "
                "check again (write it with write_json(..., checksum=True) to have such edits "
                "refused when read)"
            )
        # a verdict is judged from the numbers by this version's rules: a stored one that
        # differs was edited, or written under other rules, and is said, not taken
        if said is not None and said != check.passed:
            warnings.warn(
                f"values['passed']: the record says {said}, but its forecasts and real rates "
                f"give {check.passed} ({check.verdict}) by this version's rules, which judge "
                "it: the entry was edited, or written under other rules",
                UserWarning,
                stacklevel=2,
            )
        return check


#: resamples of the start states for :meth:`OutcomeCheck.excess_error_interval`
_BOOTSTRAP = 2000

#: a report's start-state flags of an outcome settled before the agent acted
_BEGAN = ("in_success", "in_failure")


def _drawn_p(p_value: float) -> str:
    """A p-value from :data:`_DRAWS` draws, said as below the smallest they can give where it
    is that (2 / (draws + 1), not a measured value)."""
    floor = 2 / (_DRAWS + 1)
    return f"< {floor:.2g}" if p_value <= floor * (1 + 1e-9) else f"{p_value:.2g}"


register_report_part("forecast_check", OutcomeCheck.from_dict)

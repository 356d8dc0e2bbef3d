"""Does the env still move as the world model learned? A check of real transitions.

:class:`~rcvae_torchrl.training.StateNovelty` asks whether a state is like the training states.
An env whose physics changed (a longer pole, a heavier ball, other friction) goes through the
same states and only moves between them otherwise: no state is novel, the members can agree,
and the forecasts are wrong all the same. :class:`DynamicsNovelty` asks the transitions: how far
the model's one-step predictions miss the real next states of an episode, against how far they
miss on held-out episodes of the distribution the model was trained on. It needs real episodes
of the env in question (a few, of the agent at work, say) but no outcome of any task.

An episode's score, per predicted dimension: the root mean square of the model's one-step error
over the episode's first :attr:`~DynamicsNovelty.steps` transitions (the members' mean of
:meth:`~rcvae_torchrl.models.RCVAEEnsemble.predict_next`, teacher forced from the episode's
first state), in units of that dimension's one-step error on training episodes. The episode's
score is its largest over the dimensions: a change in one dimension's dynamics is not diluted
by all the others. Its level is the conformal level of the held-out episodes' scores at
``quantile``: an episode from the held-out episodes' distribution scores above it with
probability at most ``1 - quantile``, whatever the env. :func:`check_dynamics` counts the given
episodes above the level; the binomial tail of that count at that rate is its p-value.

Episodes of another policy than the one that collected the training episodes visit other
states, where the model may predict worse although the physics did not change: a check that
fails says that the model predicts these episodes' transitions worse than those it was trained
for, whether the env or the states visited differ (:class:`~rcvae_torchrl.training.StateNovelty`
tells the second). :func:`~rcvae_torchrl.training.train_ensemble` fits one on its training and
validation episodes (``ensemble.dynamics``, saved in checkpoints); a report takes a check with
:meth:`~rcvae_torchrl.competency.CompetencyReport.with_dynamics_check`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

from rcvae_torchrl import _checks, fingerprint
from rcvae_torchrl._checks import check_positive_int, check_unit_interval
from rcvae_torchrl._conformal import conformal_level
from rcvae_torchrl.competency.report import register_report_part
from rcvae_torchrl.data import TRAJ_KEY, check_episode_ids, check_frames_type, episode_spans
from rcvae_torchrl.models import RCVAEEnsemble

__all__ = ["DynamicsCheck", "DynamicsNovelty", "check_dynamics"]

#: transitions of each episode scored, from its first state
STEPS = 20
#: the fewest held-out episodes (of at least ``steps + 1`` frames) a level is measured on
MIN_HELD_OUT = 10
#: a dimension whose one-step error on training episodes is below this (relative to its
#: values) is predicted exactly (a clock a state constraint advances): not judged
_EXACT = 1e-6
#: episodes per block of predictions
_BLOCK = 256
#: dimensions a failed check names: those whose median score over its episodes is at least
#: this many times the held-out episodes', at most three
_NAMED_RATIO = 1.5
_NAMED = 3


def _model_digest(ensemble: RCVAEEnsemble) -> str:
    return fingerprint.model_digest(ensemble.behaviour())


def _episodes(name: str, data: object, ensemble: RCVAEEnsemble, steps: int) -> tuple[Tensor, ...]:
    """The first ``steps + 1`` frames of every episode of flat ``data`` that has them:
    observations ``[B, steps + 1, S]`` and actions ``[B, steps + 1, A]`` (the model's dtype and
    device), and the number of episodes too short."""
    check_frames_type(data, name)
    assert isinstance(data, TensorDictBase)
    keys = set(data.keys(True))
    missing = [
        str(k)
        for k in ("observation", "action", ("next", "observation"), TRAJ_KEY)
        if k not in keys
    ]
    if data.ndim != 1 or missing:
        raise ValueError(
            f"{name}: expected flat episodes [frames] with 'observation', 'action', "
            f"('next', 'observation') and {TRAJ_KEY!r}, got batch {tuple(data.shape)}"
            + (f" without {', '.join(missing)}" if missing else "")
        )
    if data.shape[0] == 0:
        raise ValueError(f"{name}: expected at least one frame, got none")
    cfg = ensemble.config
    for key, last in (("observation", cfg.obs_dim), ("action", cfg.action_dim)):
        for entry in (key, ("next", key)) if key == "observation" else (key,):
            x = data.get(entry)
            label = f"{name}[{entry!r}]"
            _checks.check_floating(label, x)
            if x.shape[-1] != last or x.dim() != 2:
                raise ValueError(
                    f"{label}: expected [frames, {last}] (the model's), got {tuple(x.shape)}"
                )
            _checks.check_finite(label, x)
    check_episode_ids(data, name)
    first, lengths = episode_spans(data)
    long = first[lengths > steps]  # steps transitions: steps + 1 states
    frames = long[:, None] + torch.arange(steps + 1)
    obs = data.get("observation")[frames[:, :steps]]
    last = data.get(("next", "observation"))[frames[:, steps - 1]]
    obs = torch.cat([obs, last[:, None]], 1)
    actions = data.get("action")[frames]
    actions[:, steps] = actions[:, steps - 1]  # the last state's action is never read
    like = next(ensemble.parameters())
    return obs.to(like), actions.to(like), int(len(first) - len(long))


@torch.no_grad()
def _errors(ensemble: RCVAEEnsemble, obs: Tensor, actions: Tensor) -> Tensor:
    """``[B, steps, S]``: the members' mean one-step prediction minus the truth (float64)."""
    e, out = ensemble.ensemble_size, []
    for i in range(0, obs.shape[0], _BLOCK):
        o, a = obs[i : i + _BLOCK], actions[i : i + _BLOCK]
        predicted = ensemble.predict_next(o.expand(e, *o.shape), a.expand(e, *a.shape)).mean(0)
        out.append((predicted - o[:, 1:]).to(torch.float64).cpu())
    return torch.cat(out) if out else obs.new_zeros(0, obs.shape[1] - 1, obs.shape[2])


@dataclass(frozen=True, eq=False)
class DynamicsNovelty:
    """How unlike the held-out episodes' transitions an episode's are (see the module's
    docstring). Build it with :meth:`fit`; check episodes with :func:`check_dynamics`."""

    #: ``[S]`` per dimension, the root mean square one-step error on training episodes: the
    #: unit of a score (0 where not judged)
    scale: Tensor
    #: the dimensions judged: predicted ones the model does not get exactly
    dims: tuple[int, ...]
    #: the score that ``quantile`` of the held-out episodes stay at or below
    level: float
    #: the probability the level keeps (conformal: at most ``held_out / (held_out + 1)``)
    quantile: float
    #: transitions of each episode scored, from its first state
    steps: int
    #: the held-out episodes the level was measured on
    held_out: int
    #: ``[S]`` per dimension, the held-out episodes' median score (the named dimensions of a
    #: failed check are those whose median lies far above it)
    reference: Tensor
    #: the world model it was measured with (:func:`~rcvae_torchrl.fingerprint.model_digest`
    #: of its behaviour): scores of other weights or functions are not on its scale
    model: str
    #: a name per dimension
    names: tuple[str, ...]

    def __post_init__(self) -> None:
        s = self.scale.shape[0] if isinstance(self.scale, Tensor) else -1
        if not isinstance(self.scale, Tensor) or self.scale.dim() != 1:
            raise TypeError(f"scale: expected a [S] tensor, got {self.scale!r}")
        if not isinstance(self.reference, Tensor) or self.reference.shape != (s,):
            raise ValueError(f"reference: expected a [{s}] tensor, got {self.reference!r}")
        if len(self.names) != s:
            raise ValueError(f"names: expected {s} names, got {len(self.names)}")
        dims = tuple(self.dims)
        if not dims or any(
            isinstance(d, bool) or not isinstance(d, int) or not 0 <= d < s for d in dims
        ):
            raise ValueError(f"dims: expected dimensions in [0, {s}), at least one, got {dims!r}")
        object.__setattr__(self, "dims", dims)
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))
        if not (isinstance(self.level, (int, float)) and math.isfinite(self.level)):
            raise ValueError(f"level: expected a finite score, got {self.level!r}")
        check_unit_interval("quantile", self.quantile, include_zero=False)
        check_positive_int("steps", self.steps)
        check_positive_int("held_out", self.held_out)
        if not isinstance(self.model, str):
            raise TypeError(f"model: expected a digest (str), got {self.model!r}")

    @classmethod
    def fit(
        cls,
        ensemble: RCVAEEnsemble,
        train_data: TensorDictBase,
        held_out: TensorDictBase,
        *,
        steps: int = STEPS,
        quantile: float = 0.95,
        max_episodes: int = 500,
        seed: int = 0,
    ) -> DynamicsNovelty:
        """Measure ``ensemble``'s one-step errors: their unit per dimension on (at most
        ``max_episodes`` of) the training episodes ``train_data``, and the level of the
        episodes' scores on the held-out episodes ``held_out`` (flat episodes, as training
        takes them; those of fewer than ``steps + 1`` frames are left out). Raises
        ``ValueError`` for fewer than :data:`MIN_HELD_OUT` held-out episodes long enough."""
        check_positive_int("steps", steps)
        check_positive_int("max_episodes", max_episodes)
        check_unit_interval("quantile", quantile, include_zero=False)
        obs, actions, _ = _episodes("train_data", train_data, ensemble, steps)
        if obs.shape[0] == 0:
            raise ValueError(
                f"train_data: no episode of at least {steps + 1} frames ({steps} transitions "
                "are scored per episode); pass a smaller steps"
            )
        if obs.shape[0] > max_episodes:
            generator = torch.Generator().manual_seed(seed)
            keep = torch.randperm(obs.shape[0], generator=generator)[:max_episodes]
            obs, actions = obs[keep.to(obs.device)], actions[keep.to(obs.device)]
        scale = _errors(ensemble, obs, actions).square().mean((0, 1)).sqrt()
        size = obs.to(torch.float64).abs().mean((0, 1)).cpu()
        predicted = set(ensemble.config.predicted_dims)
        dims = tuple(
            d
            for d in range(scale.shape[0])
            if d in predicted and float(scale[d]) > _EXACT * (1 + float(size[d]))
        )
        if not dims:
            raise ValueError(
                "ensemble: it predicts every dimension exactly on train_data (no one-step "
                "error): no transition could be judged unlike them"
            )
        scale = torch.where(
            torch.isin(torch.arange(scale.shape[0]), torch.tensor(dims)), scale, 0.0
        )
        held_obs, held_actions, _ = _episodes("held_out", held_out, ensemble, steps)
        if held_obs.shape[0] < MIN_HELD_OUT:
            raise ValueError(
                f"held_out: expected at least {MIN_HELD_OUT} episodes of at least {steps + 1} "
                f"frames to measure a level on, got {held_obs.shape[0]}"
            )
        per_dim = _scores(_errors(ensemble, held_obs, held_actions), scale, dims)
        level, kept = conformal_level(per_dim.max(1).values, quantile)
        return cls(
            scale=scale,
            dims=dims,
            level=max(level, 1e-12),
            quantile=kept,
            steps=steps,
            held_out=held_obs.shape[0],
            reference=per_dim.median(0).values,
            model=_model_digest(ensemble),
            names=tuple(ensemble.config.names),
        )

    def scores(self, ensemble: RCVAEEnsemble, episodes: TensorDictBase) -> tuple[Tensor, int]:
        """``[B, S]`` the per-dimension scores of the ``B`` episodes of ``episodes`` long
        enough (NaN in dimensions not judged), and the number too short to score. Refused for
        another model than the one measured (other weights, config or functions)."""
        if _model_digest(ensemble) != self.model:
            raise ValueError(
                "ensemble: not the world model this check was measured with (its weights, "
                "config or functions differ: retrained, loaded otherwise, or a selection of "
                "members); measure it again, DynamicsNovelty.fit(ensemble, train_data, held_out)"
            )
        obs, actions, short = _episodes("episodes", episodes, ensemble, self.steps)
        return _scores(_errors(ensemble, obs, actions), self.scale, self.dims), short

    def as_dict(self) -> dict[str, Any]:
        return {
            "scale": self.scale.clone(),
            "dims": list(self.dims),
            "level": float(self.level),
            "quantile": float(self.quantile),
            "steps": int(self.steps),
            "held_out": int(self.held_out),
            "reference": self.reference.clone(),
            "model": self.model,
            "names": list(self.names),
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> DynamicsNovelty:
        fields = ("scale", "dims", "level", "quantile", "steps", "held_out", "reference", "model")
        _checks.check_entries("values", values, (*fields, "names"), "a DynamicsNovelty.as_dict()")
        return cls(
            **{k: values[k] for k in fields},
            names=tuple(values["names"]),
        )


def _scores(errors: Tensor, scale: Tensor, dims: tuple[int, ...]) -> Tensor:
    """``[B, S]``: per episode and dimension, the RMS error over its steps in ``scale`` units;
    NaN outside ``dims``."""
    out = torch.full(errors.shape[::2], math.nan, dtype=torch.float64)
    index = list(dims)
    out[:, index] = errors[..., index].square().mean(1).sqrt() / scale[index]
    return out


@dataclass(frozen=True, eq=False)
class DynamicsCheck:
    """The verdict of :func:`check_dynamics` on some real episodes."""

    #: episodes scored
    episodes: int
    #: episodes left out, of fewer than ``steps + 1`` frames
    short: int
    #: episodes scoring above the level
    beyond: int
    #: the most a share of episodes of the held-out distribution scores above it
    rate: float
    #: the level of the test
    alpha: float
    #: ``[S]`` per dimension, these episodes' median score over the held-out episodes' (NaN
    #: where not judged)
    ratios: Tensor
    names: tuple[str, ...]
    #: the world model's digest (:attr:`DynamicsNovelty.model`)
    model: str

    def __post_init__(self) -> None:
        for name in ("episodes", "short", "beyond"):
            _checks.check_non_negative_int(name, getattr(self, name))
        if self.beyond > self.episodes:
            raise ValueError(
                f"beyond: expected at most the {self.episodes} episodes, got {self.beyond}"
            )
        check_unit_interval("rate", self.rate)
        check_unit_interval("alpha", self.alpha, include_zero=False)
        if not isinstance(self.ratios, Tensor) or self.ratios.shape != (len(self.names),):
            raise ValueError(f"ratios: expected a [{len(self.names)}] tensor, got {self.ratios!r}")
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))

    @property
    def measured(self) -> bool:
        """Whether any episode was scored."""
        return self.episodes > 0

    @property
    def p_value(self) -> float:
        """P(at least ``beyond`` of ``episodes`` above the level) for episodes of the held-out
        distribution (a binomial tail at ``rate``; 1 when none was scored)."""
        if self.beyond == 0:
            return 1.0
        from scipy.stats import binom

        return float(binom.sf(self.beyond - 1, self.episodes, self.rate))

    @property
    def passed(self) -> bool:
        """No more episodes above the level than chance allows (``p_value >= alpha``), with at
        least one episode scored."""
        return self.measured and self.p_value >= self.alpha

    def named(self) -> list[str]:
        """The dimensions whose median score lies furthest above the held-out episodes'."""
        ratios = torch.nan_to_num(self.ratios, nan=0.0)
        order = ratios.argsort(descending=True)[:_NAMED]
        return [
            f"{self.names[i]} ({float(ratios[i]):.1f} times its held-out error)"
            for i in order.tolist()
            if float(ratios[i]) >= _NAMED_RATIO
        ]

    def describe(self) -> str:
        if not self.measured:
            return (
                f"no episode long enough to check ({self.short} shorter than the transitions "
                "scored)"
            )
        share = (
            f"{self.beyond} of {self.episodes} real episodes predicted worse than the held-out "
            f"episodes' level (at most {self.rate:.0%} of those expected, p = {self.p_value:.2g})"
        )
        if self.passed:
            return f"{share}: they move as the world model learned"
        named = self.named()
        where = f", most in {', '.join(named)}" if named else ""
        return (
            f"{share}{where}: the env moves otherwise than the world model learned, or these "
            "episodes go where its training episodes did not"
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "episodes": int(self.episodes),
            "short": int(self.short),
            "beyond": int(self.beyond),
            "rate": float(self.rate),
            "alpha": float(self.alpha),
            "ratios": self.ratios.clone(),
            "names": list(self.names),
            "model": self.model,
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> DynamicsCheck:
        fields = ("episodes", "short", "beyond", "rate", "alpha", "ratios", "names", "model")
        _checks.check_entries("values", values, fields, "a DynamicsCheck.as_dict()")
        return cls(**{k: values[k] for k in fields if k != "names"}, names=tuple(values["names"]))


def check_dynamics(
    ensemble: RCVAEEnsemble,
    episodes: TensorDictBase,
    *,
    alpha: float = 0.01,
    novelty: DynamicsNovelty | None = None,
) -> DynamicsCheck:
    """Whether the real ``episodes`` (flat, as training takes them: ``"observation"``,
    ``"action"``, ``("next", "observation")`` and episode ids) move as the world model learned:
    how many of them its one-step predictions miss by more than ``novelty``'s level (default
    ``ensemble.dynamics``, fitted by :func:`~rcvae_torchrl.training.train_ensemble`), against
    the share of held-out episodes that do. Episodes of fewer than ``novelty.steps + 1`` frames
    are left out (counted in ``short``)."""
    check_unit_interval("alpha", alpha, include_zero=False)
    novelty = getattr(ensemble, "dynamics", None) if novelty is None else novelty
    if not isinstance(novelty, DynamicsNovelty):
        raise ValueError(
            "novelty: the world model has no dynamics check (ensemble.dynamics is None: trained "
            "with dynamics=False, with too few validation episodes, or loaded from an older "
            "checkpoint); measure one: DynamicsNovelty.fit(ensemble, train_data, held_out)"
        )
    scores, short = novelty.scores(ensemble, episodes)
    beyond = int((scores[:, list(novelty.dims)].max(1).values > novelty.level).sum())
    median = (
        scores.median(0).values if scores.shape[0] else torch.full_like(novelty.scale, math.nan)
    )
    return DynamicsCheck(
        episodes=scores.shape[0],
        short=short,
        beyond=beyond,
        rate=1.0 - novelty.quantile,
        alpha=float(alpha),
        ratios=median / novelty.reference.clamp_min(1e-12),
        names=novelty.names,
        model=novelty.model,
    )


register_report_part("dynamics_check", DynamicsCheck.from_dict)

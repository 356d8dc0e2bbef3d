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
first state), in units of that dimension's one-step error on training episodes.
:func:`check_dynamics` compares the given episodes' scores with the held-out episodes', dimension
by dimension, with a one-sided Mann-Whitney rank test (are theirs larger?), and takes the
smallest p-value times the number of dimensions (Bonferroni): a change in one dimension's
dynamics is not diluted by all the others. Under the same dynamics, held-out and new episodes
are draws of one distribution for the trained model, so a rank test holds its level for any
number of episodes on either side, on average over held-out samples (for one fixed sample, more
or less: one of 10 references of 20 linear-system episodes failed 5 % of unchanged batches at
level 0.01), and each copy of an episode counts as another draw (a warning says where episodes
repeat): a level set by the held-out scores alone (their largest,
say) would let through more than its nominal share for some held-out samples and fewer for
others (with 20 held-out episodes, more than 10 % for one sample in eight), and a test of a
count beyond it at the nominal share would then fail in-distribution episodes more often the
more were checked. One thing sets the held-out episodes apart: their validation loss chose the
weights training kept, so they are predicted a little better than fresh ones; the test allows
new episodes :data:`TOLERANCE` times their errors (``tolerance=``).
Beside the test, the check counts the episodes whose largest score lies beyond that level
(:attr:`DynamicsNovelty.level`): the ones far off, told apart. A change within the noise the
model learned (a parameter it saw vary from episode to episode, moved to the edge of its range)
keeps each step's error as large as before and passes that test, but every episode's errors then
lean one way: with ``shift=True`` :func:`check_dynamics` also ranks each episode's mean signed
error against the held-out episodes' (two-sided), against held-out episodes of the same policy.

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
import warnings
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from tensordict import TensorDictBase
from torch import Tensor

from rcvae_torchrl import _checks, fingerprint
from rcvae_torchrl._checks import check_positive_int, check_unit_interval
from rcvae_torchrl._conformal import conformal_level
from rcvae_torchrl._text import signed
from rcvae_torchrl.competency.report import register_report_part
from rcvae_torchrl.data import TRAJ_KEY, check_episode_ids, check_frames_type, episode_spans
from rcvae_torchrl.models import RCVAEEnsemble

__all__ = ["DynamicsCheck", "DynamicsNovelty", "check_dynamics", "rank_p_values"]

#: transitions of each episode scored, from its first state
STEPS = 20
#: the fewest held-out episodes (of at least ``steps`` frames) a check is measured on
MIN_HELD_OUT = 10
#: a dimension whose one-step error on training episodes is below this (relative to its
#: values) is predicted exactly (a clock a state constraint advances): not judged
_EXACT = 1e-6
#: episodes per block of predictions
_BLOCK = 256
#: how many times the held-out episodes' one-step errors those of new episodes may reach before
#: they count as larger (:func:`check_dynamics`)
TOLERANCE = 1.1
#: dimensions a failed check names, at most: those whose own test fails, by p-value
_NAMED = 3


def _model_digest(ensemble: RCVAEEnsemble) -> str:
    return fingerprint.model_digest(ensemble.behaviour())


def _episodes(name: str, data: object, ensemble: RCVAEEnsemble, steps: int) -> tuple[Tensor, ...]:
    """The first ``steps`` transitions (frames) of every episode of flat ``data`` that has
    them: its ``steps + 1`` states ``[B, steps + 1, S]`` and actions ``[B, steps + 1, A]`` (the
    last one a copy, never read; the model's dtype and device), and the number of episodes too
    short."""
    check_frames_type(data, name)
    assert isinstance(data, TensorDictBase)
    keys = set(data.keys(True))
    missing = [
        str(k)
        for k in ("observation", "action", ("next", "observation"), TRAJ_KEY)
        if k not in keys
    ]
    if data.ndim != 1 or missing:
        several = (
            f" (several envs' frames [N, T]: pass {name}.reshape(-1), each env's in order)"
            if data.ndim == 2
            else ""
        )
        raise ValueError(
            f"{name}: expected flat episodes [frames] with 'observation', 'action', "
            f"('next', 'observation') and {TRAJ_KEY!r}, got batch {tuple(data.shape)}"
            + (f" without {', '.join(missing)}" if missing else "")
            + several
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
    long = first[lengths >= steps]  # a frame is a transition: steps frames, steps + 1 states
    frames = long[:, None] + torch.arange(steps)
    last = data.get(("next", "observation"))[frames[:, -1]]
    obs = torch.cat([data.get("observation")[frames], last[:, None]], 1)
    actions = data.get("action")[frames]
    actions = torch.cat([actions, actions[:, -1:]], 1)  # the last state's action: never read
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
    #: ``[H, S]`` the held-out episodes' scores (NaN in dimensions not judged): what the
    #: scores of new episodes are ranked against
    held_out_scores: Tensor
    #: the largest score over the dimensions that ``quantile`` of the held-out episodes stay at
    #: or below (conformal): beyond it an episode is far off
    level: float
    #: the probability the level keeps (at most ``H / (H + 1)``; on average over held-out
    #: samples: for one sample, more or less)
    quantile: float
    #: transitions of each episode scored, from its first state
    steps: int
    #: the world model it was measured with (:func:`~rcvae_torchrl.fingerprint.model_digest`
    #: of its behaviour): scores of other weights or functions are not on its scale
    model: str
    #: a name per dimension
    names: tuple[str, ...]
    #: ``[H, S]`` the held-out episodes' mean signed errors in units (NaN in dimensions not
    #: judged): what a shift test ranks new episodes' against (``check_dynamics(shift=True)``);
    #: ``None`` in a record made before they were kept
    held_out_shifts: Tensor | None = None

    def __post_init__(self) -> None:
        s = self.scale.shape[0] if isinstance(self.scale, Tensor) else -1
        if not isinstance(self.scale, Tensor) or self.scale.dim() != 1:
            raise TypeError(f"scale: expected a [S] tensor, got {self.scale!r}")
        held = self.held_out_scores
        if not isinstance(held, Tensor) or held.dim() != 2 or held.shape[1] != s:
            raise ValueError(f"held_out_scores: expected a [H, {s}] tensor, got {held!r}")
        if held.shape[0] < MIN_HELD_OUT:
            raise ValueError(
                f"held_out_scores: expected at least {MIN_HELD_OUT} held-out episodes, got "
                f"{held.shape[0]}"
            )
        object.__setattr__(self, "names", _names(self.names, s))
        if not self.scale.is_floating_point() or not bool(
            (torch.isfinite(self.scale) & (self.scale >= 0)).all()
        ):
            raise ValueError(f"scale: expected finite units >= 0, got {self.scale}")
        dims = tuple(self.dims)
        if not dims or any(
            isinstance(d, bool) or not isinstance(d, int) or not 0 <= d < s for d in dims
        ):
            raise ValueError(f"dims: expected dimensions in [0, {s}), at least one, got {dims!r}")
        object.__setattr__(self, "dims", dims)
        if not bool((self.scale[list(dims)] > 0).all()):
            raise ValueError(f"scale: expected a unit > 0 in every dimension judged {dims}")
        level = self.level
        if isinstance(level, bool) or not isinstance(level, (int, float)):
            raise TypeError(f"level: expected a number, got {level!r}")
        if not (math.isfinite(level) and level > 0):
            raise ValueError(f"level: expected a finite score > 0, got {level!r}")
        check_unit_interval("quantile", self.quantile, include_zero=False)
        check_positive_int("steps", self.steps)
        judged = held[:, list(dims)]
        if not bool(torch.isfinite(judged).all()):
            raise ValueError("held_out_scores: expected finite scores in the dimensions judged")
        if not isinstance(self.model, str):
            raise TypeError(f"model: expected a digest (str), got {self.model!r}")
        shifts = self.held_out_shifts
        if shifts is not None:
            if not isinstance(shifts, Tensor) or shifts.shape != held.shape:
                raise ValueError(
                    f"held_out_shifts: expected None or a {list(held.shape)} tensor (as "
                    f"held_out_scores), got {shifts!r}"
                )
            if not bool(torch.isfinite(shifts[:, list(dims)]).all()):
                raise ValueError("held_out_shifts: expected finite values in the dimensions judged")

    @property
    def held_out(self) -> int:
        """The held-out episodes measured."""
        return int(self.held_out_scores.shape[0])

    @property
    def reference(self) -> Tensor:
        """``[S]`` per dimension, the held-out episodes' median score."""
        return self.held_out_scores.quantile(0.5, dim=0)

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
        takes them; those of fewer than ``steps`` frames are left out). Raises
        ``ValueError`` for fewer than :data:`MIN_HELD_OUT` held-out episodes long enough.

        ``held_out`` is what checked episodes are ranked against: episodes of the env the
        model learned that it was not trained on. ``train_ensemble`` takes its validation
        episodes; where the episodes to check are an agent's, its own episodes in that env
        compare like with like (a smoother agent than the data's policy scores below the
        validation episodes whatever the env, and only a change that lifts its errors above
        theirs shows). ``steps``: where the env's dynamics act late in an episode (an object
        pushed seconds in), score the transitions that reach it (a forecast's horizon)."""
        _check_ensemble(ensemble)
        check_positive_int("steps", steps)
        check_positive_int("max_episodes", max_episodes)
        _checks.check_non_negative_int("seed", seed)
        # as StateNovelty.fit: a level over every episode is no level
        _checks.check_open_unit_interval("quantile", quantile, "a share")
        obs, actions, _ = _episodes("train_data", train_data, ensemble, steps)
        if obs.shape[0] == 0:
            raise ValueError(
                f"train_data: no episode of at least {steps} frames (the transitions scored "
                "per episode); fit with a smaller steps=, DynamicsNovelty.fit(..., steps=...)"
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
                f"held_out: expected at least {MIN_HELD_OUT} episodes of at least {steps} "
                f"frames to measure a level on, got {held_obs.shape[0]}"
            )
        held_errors = _errors(ensemble, held_obs, held_actions)
        per_dim = _scores(held_errors, scale, dims)
        level, kept = conformal_level(per_dim[:, list(dims)].max(1).values, quantile)
        return cls(
            scale=scale,
            dims=dims,
            held_out_scores=per_dim,
            level=max(level, 1e-12),
            quantile=kept,
            steps=steps,
            model=_model_digest(ensemble),
            names=tuple(ensemble.config.names),
            held_out_shifts=_shifts(held_errors, scale, dims),
        )

    def scores(self, ensemble: RCVAEEnsemble, episodes: TensorDictBase) -> tuple[Tensor, int]:
        """``[B, S]`` the per-dimension scores of the ``B`` episodes of ``episodes`` long
        enough (NaN in dimensions not judged), and the number too short to score. Refused for
        another model than the one measured (other weights, config or functions)."""
        scores, _, short, _ = self.measure(ensemble, episodes)
        return scores, short

    def measure(
        self, ensemble: RCVAEEnsemble, episodes: TensorDictBase
    ) -> tuple[Tensor, Tensor, int, int]:
        """:meth:`scores`, with the episodes' mean signed errors ``[B, S]`` in units beside
        them (which way the model misses each episode, on average; NaN where not judged), and
        how many of the scored episodes repeat an earlier one transition for transition."""
        _check_ensemble(ensemble)
        if _model_digest(ensemble) != self.model:
            raise ValueError(
                "ensemble: not the world model this check was measured with (its weights, "
                "their dtype, its config or its functions differ: retrained, loaded otherwise, "
                "cast with .double(), or a selection of members); measure it again, "
                "DynamicsNovelty.fit(ensemble, train_data, held_out)"
            )
        obs, actions, short = _episodes("episodes", episodes, ensemble, self.steps)
        errors = _errors(ensemble, obs, actions)
        rows = torch.cat([obs.flatten(1), actions.flatten(1)], 1)
        copies = rows.shape[0] - (torch.unique(rows, dim=0).shape[0] if rows.shape[0] else 0)
        shifts = _shifts(errors, self.scale, self.dims)
        return _scores(errors, self.scale, self.dims), shifts, short, copies

    def as_dict(self) -> dict[str, Any]:
        return {
            "scale": self.scale.clone(),
            "dims": list(self.dims),
            "held_out_scores": self.held_out_scores.clone(),
            "level": float(self.level),
            "quantile": float(self.quantile),
            "steps": int(self.steps),
            "model": self.model,
            "names": list(self.names),
            **(
                {}
                if self.held_out_shifts is None
                else {"held_out_shifts": self.held_out_shifts.clone()}
            ),
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> DynamicsNovelty:
        fields = ("scale", "dims", "held_out_scores", "level", "quantile", "steps", "model")
        _checks.check_entries(
            "values",
            values,
            (*fields, "names"),
            "a DynamicsNovelty.as_dict()",
            ("held_out_shifts",),
        )
        parts = {k: values[k] for k in fields}
        for name in ("scale", "held_out_scores"):  # lists where read back from JSON
            parts[name] = _float_tensor(f"values[{name!r}]", parts[name])
        shifts = values.get("held_out_shifts")
        if shifts is not None:
            shifts = _float_tensor("values['held_out_shifts']", shifts)
        return cls(**parts, names=values["names"], held_out_shifts=shifts)


def _check_ensemble(ensemble: object) -> None:
    if not isinstance(ensemble, RCVAEEnsemble):
        raise TypeError(f"ensemble: expected an RCVAEEnsemble, got {type(ensemble).__name__}")


def _check_tolerance(tolerance: object) -> None:
    if (
        isinstance(tolerance, bool)
        or not isinstance(tolerance, (int, float))
        or not math.isfinite(tolerance)
        or tolerance < 1
    ):
        raise ValueError(f"tolerance: expected a finite factor >= 1, got {tolerance!r}")


def _names(names: object, count: int) -> tuple[str, ...]:
    """``count`` dimension names, as a tuple of strings."""
    if isinstance(names, (str, bytes)) or not isinstance(names, (list, tuple)):
        raise TypeError(f"names: expected a list of {count} names, got {names!r}")
    if len(names) != count or not all(isinstance(n, str) for n in names):
        raise ValueError(f"names: expected {count} names (str), got {list(names)!r}")
    return tuple(names)


def _float_tensor(name: str, value: object) -> Tensor:
    """A float64 tensor of ``value`` (a tensor, or nested lists of numbers as JSON holds them;
    ``None`` for NaN); a ``TypeError`` naming ``name`` otherwise."""
    if isinstance(value, Tensor):
        return value.to(torch.float64)
    try:
        return torch.tensor(_nan_for_none(value), dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"{name}: expected a tensor or lists of numbers, got {value!r}") from err


def _nan_for_none(value: Any) -> Any:
    if isinstance(value, list):
        return [_nan_for_none(v) for v in value]
    return math.nan if value is None else value


def _shifts(errors: Tensor, scale: Tensor, dims: tuple[int, ...]) -> Tensor:
    """``[B, S]``: per episode and dimension, the mean signed error over its steps in ``scale``
    units (which way the model misses, on average); NaN outside ``dims``."""
    out = torch.full(errors.shape[::2], math.nan, dtype=torch.float64)
    index = list(dims)
    out[:, index] = errors[..., index].mean(1) / scale[index]
    return out


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

    #: how a report takes it
    #: (:meth:`~rcvae_torchrl.competency.CompetencyReport.with_dynamics_check`)
    attaches_with: ClassVar[str] = "with_dynamics_check"

    #: episodes scored
    episodes: int
    #: episodes left out, of fewer than ``steps`` frames
    short: int
    #: episodes whose largest score lies beyond the level (:attr:`DynamicsNovelty.level`)
    beyond: int
    #: the share of held-out episodes' draws expected beyond it (on average over samples)
    rate: float
    #: the level of the test
    alpha: float
    #: how many times the held-out episodes' errors these may reach (:func:`check_dynamics`)
    tolerance: float
    #: ``[S]`` per dimension, the one-sided rank test's p-value: are these episodes' scores
    #: larger than ``tolerance`` times the held-out episodes'? (NaN where not judged)
    p_values: Tensor
    #: ``[S]`` per dimension, these episodes' median score over the held-out episodes' (NaN
    #: where not judged)
    ratios: Tensor
    names: tuple[str, ...]
    #: the world model's digest (:attr:`DynamicsNovelty.model`)
    model: str
    #: ``[S]`` per dimension, the two-sided rank test's p-value of a shift: do these
    #: episodes' mean signed errors lie elsewhere than the held-out episodes'? (NaN where not
    #: judged); ``None`` where not tested (``check_dynamics(shift=False)``)
    shift_p_values: Tensor | None = None
    #: ``[S]`` per dimension, these episodes' median mean signed error minus the held-out
    #: episodes', in units of the one-step error on training episodes; ``None`` where not tested
    shifts: Tensor | None = None

    def __post_init__(self) -> None:
        for name in ("episodes", "short", "beyond"):
            _checks.check_non_negative_int(name, getattr(self, name))
        if self.beyond > self.episodes:
            raise ValueError(
                f"beyond: expected at most the {self.episodes} episodes, got {self.beyond}"
            )
        check_unit_interval("rate", self.rate)
        check_unit_interval("alpha", self.alpha, include_zero=False)
        _check_tolerance(self.tolerance)
        if not isinstance(self.model, str):
            raise TypeError(f"model: expected a digest (str), got {self.model!r}")
        names = self.names
        s = len(names) if isinstance(names, (list, tuple)) else -1
        object.__setattr__(self, "names", _names(names, max(s, 0)))
        for name in ("p_values", "ratios"):
            value = getattr(self, name)
            if not isinstance(value, Tensor) or value.shape != (s,):
                raise ValueError(f"{name}: expected a [{s}] tensor, got {value!r}")
            if not value.is_floating_point():
                raise TypeError(f"{name}: expected floating values (NaN where not judged)")
        tested = ~self.p_values.isnan()
        p, ratios = self.p_values[tested], self.ratios[tested]
        if bool(((p < 0) | (p > 1)).any()):
            raise ValueError(f"p_values: expected values in [0, 1] or NaN, got {self.p_values}")
        if self.measured and not bool(tested.any()):
            raise ValueError(
                f"p_values: expected a p-value in every dimension tested, got none for "
                f"{self.episodes} episodes scored"
            )
        if bool((ratios.isnan() | (ratios < 0)).any()) or not bool(
            self.ratios[~tested].isnan().all()
        ):
            raise ValueError(
                f"ratios: expected a ratio >= 0 where a p-value is, NaN elsewhere, got "
                f"{self.ratios}"
            )
        if (self.shift_p_values is None) != (self.shifts is None):
            raise ValueError("shift_p_values, shifts: expected both or neither")
        if self.shift_p_values is not None:
            for name in ("shift_p_values", "shifts"):
                value = getattr(self, name)
                if not isinstance(value, Tensor) or value.shape != (s,):
                    raise ValueError(f"{name}: expected None or a [{s}] tensor, got {value!r}")
                if not torch.equal(value.isnan(), self.p_values.isnan()):
                    raise ValueError(
                        f"{name}: expected values where p_values has them (the dimensions "
                        f"tested), NaN elsewhere, got {value}"
                    )
            q = self.shift_p_values[tested]
            if bool(((q < 0) | (q > 1)).any()):
                raise ValueError(
                    f"shift_p_values: expected values in [0, 1] or NaN, got {self.shift_p_values}"
                )

    @property
    def measured(self) -> bool:
        """Whether any episode was scored."""
        return self.episodes > 0

    def _tests(self) -> list[tuple[float, int, str]]:
        """Every test made: (p-value, dimension, kind: ``"errors"`` or ``"shift"``)."""
        out = []
        for kind, values in (("errors", self.p_values), ("shift", self.shift_p_values)):
            if values is not None:
                out += [(float(values[d]), d, kind) for d in range(len(values))]
        return [t for t in out if not math.isnan(t[0])]

    @property
    def p_value(self) -> float:
        """The smallest p-value times the number of tests made (Bonferroni: one per dimension
        tested, two where shifts were tested too), at most 1; 1 when no episode was scored."""
        tests = self._tests()
        if not self.measured or not tests:
            return 1.0
        return min(1.0, min(p for p, _, _ in tests) * len(tests))

    @property
    def passed(self) -> bool:
        """These episodes' one-step errors are no larger than the held-out episodes' beyond
        chance (``p_value >= alpha``), with at least one episode scored."""
        return self.measured and self.p_value >= self.alpha

    def _failing(self) -> dict[int, list[str]]:
        """The dimensions with a failing test (p-value times the tests made below ``alpha``),
        smallest p-value first, each with the kinds of its failing tests."""
        tests = self._tests()
        out: dict[int, list[str]] = {}
        for p, d, kind in sorted(tests):
            if p * len(tests) < self.alpha:
                out.setdefault(d, []).append(kind)
        return out

    def named(self) -> list[str]:
        """The dimensions whose own test fails (p-value times the tests made below
        ``alpha``), smallest p-value first, at most three, each once with what failed: its
        errors' size, which way they lean, or both; none for a check that passed."""
        named = []
        for d, kinds in list(self._failing().items())[:_NAMED]:
            said = []
            if "errors" in kinds:
                said.append(f"{float(self.ratios[d]):.1f} times its held-out error")
            if "shift" in kinds:
                assert self.shifts is not None
                said.append(f"its errors shifted by {signed(self.shifts[d], 2)} of their unit")
            named.append(f"{self.names[d]} ({', '.join(said)})")
        return named

    def describe(self) -> str:
        if not self.measured:
            return (
                f"no episode long enough to check ({self.short} shorter than the transitions "
                "scored)"
            )
        shifted = " and their shift" if self.shift_p_values is not None else ""
        test = (
            f"their one-step errors against {self.tolerance:g} times the held-out episodes'"
            f"{shifted}, p = {self.p_value:.2g}; "
            f"{self.beyond} of {self.episodes} real episodes beyond the held-out episodes' level"
        )
        if self.passed:
            return f"{test}: they move as the world model learned"
        kinds = {kind for found in self._failing().values() for kind in found}
        how = {
            frozenset({"errors"}): "larger",
            frozenset({"shift"}): "shifted",
        }.get(frozenset(kinds), "larger or shifted")
        named = self.named()
        where = f", {how} in {', '.join(named)}" if named else ""
        return (
            f"{test}{where}: the env moves otherwise than the world model learned, or these "
            "episodes go where its training episodes did not"
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "episodes": int(self.episodes),
            "short": int(self.short),
            "beyond": int(self.beyond),
            "rate": float(self.rate),
            "alpha": float(self.alpha),
            "tolerance": float(self.tolerance),
            # lists: a check is small, and written to JSON as often as to torch files
            "p_values": self.p_values.tolist(),
            "ratios": self.ratios.tolist(),
            "names": list(self.names),
            "model": self.model,
            **(
                {}
                if self.shift_p_values is None or self.shifts is None
                else {
                    "shift_p_values": self.shift_p_values.tolist(),
                    "shifts": self.shifts.tolist(),
                }
            ),
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> DynamicsCheck:
        fields = (
            "episodes",
            "short",
            "beyond",
            "rate",
            "alpha",
            "tolerance",
            "p_values",
            "ratios",
            "names",
            "model",
        )
        optional = ("shift_p_values", "shifts")
        _checks.check_entries("values", values, fields, "a DynamicsCheck.as_dict()", optional)
        parts = {k: values[k] for k in fields if k != "names"}
        parts.update({k: values[k] for k in optional if values.get(k) is not None})
        for name in ("p_values", "ratios", *optional):  # lists where read back from JSON
            if name in parts:
                parts[name] = _float_tensor(f"values[{name!r}]", parts[name])
        return cls(**parts, names=values["names"])


def rank_p_values(
    scores: Tensor,
    held_out: Tensor,
    dims: tuple[int, ...],
    tolerance: float = 1.0,
    alternative: str = "greater",
) -> Tensor:
    """``[S]`` per dimension in ``dims``, the one-sided Mann-Whitney p-value of "``scores``
    ``[M, S]`` are larger than ``tolerance`` times ``held_out`` ``[H, S]``" (exact for small
    samples without ties; ``alternative="two-sided"``: are they elsewhere?); NaN elsewhere,
    and everywhere for ``M = 0``."""
    _checks.check_choice("alternative", alternative, ("greater", "two-sided"))
    _check_tolerance(tolerance)
    for name, x in (("scores", scores), ("held_out", held_out)):
        _checks.check_tensor(name, x)
    if scores.ndim != 2 or held_out.ndim != 2 or scores.shape[1] != held_out.shape[1]:
        raise ValueError(
            f"scores, held_out: expected [M, S] and [H, S] (the same S), got "
            f"{tuple(scores.shape)} and {tuple(held_out.shape)}"
        )
    size = held_out.shape[1]
    if any(isinstance(d, bool) or not isinstance(d, int) or not 0 <= d < size for d in dims):
        raise ValueError(f"dims: expected dimensions in 0..{size - 1}, got {tuple(dims)}")
    for name, x in (("scores", scores), ("held_out", held_out)):
        _checks.check_finite(f"{name} (in dims)", x[:, list(dims)])
    from scipy.stats import mannwhitneyu

    out = torch.full((held_out.shape[1],), math.nan, dtype=torch.float64)
    if scores.shape[0] == 0:
        return out
    for d in dims:
        test = mannwhitneyu(
            scores[:, d].double().numpy(),
            tolerance * held_out[:, d].double().numpy(),
            alternative=alternative,
        )
        out[d] = float(test.pvalue)
    return out


def check_dynamics(
    ensemble: RCVAEEnsemble,
    episodes: TensorDictBase,
    *,
    alpha: float = 0.01,
    tolerance: float = TOLERANCE,
    novelty: DynamicsNovelty | None = None,
    shift: bool = False,
) -> DynamicsCheck:
    """Whether the real ``episodes`` (flat, as training takes them: ``"observation"``,
    ``"action"``, ``("next", "observation")`` and episode ids) move as the world model learned:
    per dimension, a one-sided Mann-Whitney test of their scores against the held-out
    episodes' (``novelty``, default ``ensemble.dynamics``, measured by
    :func:`~rcvae_torchrl.training.train_ensemble`), failed where the smallest p-value times
    the dimensions tested is below ``alpha``. Episodes of fewer than ``novelty.steps``
    frames are left out (counted in ``short``). How few episodes can fail it: ``m`` episodes
    beyond every one of ``H`` held-out ones in a dimension give that dimension at best
    p = 1 / C(H + m, m) (scipy's exact Mann-Whitney distribution, used for small samples without
    ties; larger or tied samples get its normal approximation, which overstates the smallest
    p-values), times the ``D`` dimensions tested. With 20 held-out episodes one episode cannot
    fail it at ``alpha=0.01`` (p = D / 21), three can where D <= 17 (D / 1771); with the
    fewest held-out episodes measured (10) three cannot even for 3 dimensions (3 / 286).

    ``tolerance``: how many times the held-out episodes' errors the given ones' may reach
    before they count as larger (the test ranks them against the held-out scores times it).
    The held-out episodes are those whose validation loss chose the weights training kept (its
    early stopping), so they are predicted a little better than fresh episodes of the same env:
    on a point mass and a cart-pole (20 held-out episodes each), 400 fresh episodes of the same
    env had 1.02-1.3 times their median errors, dimension by dimension. With ``tolerance=1``, 3
    of 48 batches of 20 such episodes failed at ``alpha=0.01``; with 1.1, none did, while every
    batch of a point mass 5 % heavier, of one with 10 % more damping or 5 % less gear, and of a
    cart-pole whose pole was 25 % heavier or 1 % longer failed, and 2 of 3 of one whose pole was
    10 % heavier (3 of 3 with 1; 5 % heavier: 0 of 3, against 3 of 3).

    ``shift``: also test, per dimension, whether the episodes' mean signed errors lie
    elsewhere than the held-out episodes' (a two-sided rank test; the Bonferroni count then
    covers both tests). A change within the noise the model learned leaves the errors' size
    as it was but can push every episode the same way (an arm weaker than every one the model
    saw, where each episode's strength is drawn): the size test misses it, the shift test
    need not. Take it only against held-out episodes of the same policy as the checked ones
    (an agent's own episodes in the env the model learned, fitted with
    :meth:`DynamicsNovelty.fit`): another policy visits states where the model errs another
    way, and the test cannot tell that from a change."""
    _check_ensemble(ensemble)
    _checks.check_open_unit_interval(
        "alpha", alpha, "a level", " (a test at level 1 always rejects)"
    )
    _check_tolerance(tolerance)
    _checks.check_bool("shift", shift)
    if novelty is None:
        novelty = getattr(ensemble, "dynamics", None)
        if novelty is None:
            raise ValueError(
                "ensemble: the world model has no dynamics check (ensemble.dynamics is None: "
                f"trained with dynamics=False or with fewer than {MIN_HELD_OUT} validation "
                f"episodes of at least {STEPS} frames, loaded from "
                "an older checkpoint, or made by select_members, which keeps none: it was "
                "measured with the whole ensemble's mean); measure one: "
                "DynamicsNovelty.fit(ensemble, train_data, held_out)"
            )
    if not isinstance(novelty, DynamicsNovelty):
        raise TypeError(
            f"novelty: expected a DynamicsNovelty (or None: ensemble.dynamics), got "
            f"{type(novelty).__name__}"
        )
    if shift and novelty.held_out_shifts is None:
        raise ValueError(
            "shift: the held-out errors hold no signed means (a record made before they were "
            "kept); measure them again, DynamicsNovelty.fit(ensemble, train_data, held_out)"
        )
    scores, shifted, short, copies = novelty.measure(ensemble, episodes)
    if copies:
        warnings.warn(
            f"episodes: {copies} of the {scores.shape[0]} episodes scored repeat another one "
            "transition for transition (a deterministic env started from one state twice); "
            "the rank tests take every copy for an independent episode, and fail more often "
            "than alpha: check distinct episodes",
            UserWarning,
            stacklevel=2,
        )
    dims = list(novelty.dims)
    p_values = rank_p_values(scores, novelty.held_out_scores, novelty.dims, float(tolerance))
    shift_p_values = shifts = None
    if shift:
        assert novelty.held_out_shifts is not None
        held = novelty.held_out_shifts
        shift_p_values = rank_p_values(shifted, held, novelty.dims, alternative="two-sided")
        shifts = torch.full_like(novelty.scale, math.nan, dtype=torch.float64)
        if shifted.shape[0]:  # none scored: NaN, as the p-values
            shifts[dims] = shifted[:, dims].quantile(0.5, 0) - held[:, dims].quantile(0.5, 0)
    ratios = torch.full_like(novelty.scale, math.nan)
    beyond = 0
    if scores.shape[0]:
        reference = novelty.reference[dims].clamp_min(1e-12)  # the held-out medians
        ratios[dims] = scores[:, dims].quantile(0.5, dim=0) / reference
        beyond = int((scores[:, dims].max(1).values > novelty.level).sum())
    return DynamicsCheck(
        episodes=scores.shape[0],
        short=short,
        beyond=beyond,
        rate=1.0 - novelty.quantile,
        alpha=float(alpha),
        tolerance=float(tolerance),
        p_values=p_values,
        ratios=ratios,
        names=novelty.names,
        model=novelty.model,
        shift_p_values=shift_p_values,
        shifts=shifts,
    )


register_report_part("dynamics_check", DynamicsCheck.from_dict)

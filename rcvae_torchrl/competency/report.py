"""The competency report: a TensorDict per start state, and its plain-language summary.

:class:`CompetencyReport` is what :class:`~rcvae_torchrl.competency.CompetencyAssessor` returns
(Acharya, Russell & Ahmed, 2022: Table 1 per start state, Figure 1 per dimension and time).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields, replace
from functools import cached_property
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

from rcvae_torchrl import _checks, fingerprint
from rcvae_torchrl._conformal import conformal_level
from rcvae_torchrl.competency.metrics import bits_per_live_step, rescale_aleatoric
from rcvae_torchrl.competency.validation import same_chance_p_value
from rcvae_torchrl.data.exploration import check_same_agent
from rcvae_torchrl.io import _as_json

__all__ = ["AleatoricShare", "CompetencyReport", "Reference"]

#: Below this many bits of total doubt (summed over dimensions) a report names no dominant
#: part and no cause: at the declared resolution the imagined states mostly share their bins,
#: and which of two small parts is the larger tells nothing (a calm env's in-distribution
#: starts, forecast exactly, read "most of the doubt is epistemic (0.20 of 0.37 bits): the
#: model has not seen states like this").
LITTLE_DOUBT_BITS = 1.0

# Aleatoric bits are the spread the members agree on: the env's randomness, or an error of
# the model that every member makes (a model that has not learned a deterministic env spreads
# its states too), which the ensemble cannot tell apart; the self-checks and a check of the
# forecast against real episodes can.
_REASONS = {
    "epistemic": "the model has not seen states like this",
    "aleatoric": "the members agree that the states vary this much: by chance, or by an error "
    "they all make, which the ensemble cannot tell apart",
}
# With the split calibrated against real episodes (:class:`AleatoricShare`) the aleatoric
# part is the spread they showed and the epistemic part holds the model's shared error too.
_CALIBRATED_REASONS = {
    "epistemic": "the model has not learned these states well enough: its members disagree, "
    "or spread beyond what the agent's real episodes do",
    "aleatoric": "the agent's real episodes spread this much: chance that more data would "
    "not reduce",
}
_CALIBRATED_ROSE = {
    "epistemic": "the model has not learned these states well enough: more data here would "
    "reduce it",
    "aleatoric": "the agent's real episodes spread more here than in the reference: chance",
}
_ROSE = {
    "epistemic": "the model has not seen states like this: more data here would reduce it",
    "aleatoric": "the members agree that the states vary more than in the reference: by "
    "chance, or by an error they all make",
}


#: A reference report of fewer start states is named with its count in every summary.
_FEW_REFERENCE_STARTS = 10
_PARTS = ("aleatoric", "epistemic")


def _is_number(value: object) -> bool:
    """A real number (numpy's too), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


@dataclass(frozen=True)
class Reference:
    """What a report's uncertainty is compared with: mean bits of in-distribution starts, as
    time means or (``per_live_step``) per step of the imagined episodes' life.

    ``aleatoric_high`` / ``epistemic_high``: the bits that an in-distribution start state
    stays at or below with probability ``quantile`` (None: not known; from a report, the
    conformal level of the reference's start states, see
    :meth:`CompetencyReport.with_reference`). One start state's part rose
    only when it is both ``rise`` times the mean and above this level: in-distribution start
    states spread around their mean, and a start as uncertain as many of the reference's own
    is no sign of states the model has not seen. Means over many start states (``overall``,
    ``cause``) are compared with the mean alone.
    """

    aleatoric: float
    epistemic: float
    rise: float = 1.3  #: a part counts as risen when it is at least this many times the reference
    name: str = "in-distribution reference"
    per_live_step: bool = False  #: the bits are ``("uncertainty", "per_live_step", ·)``
    aleatoric_high: float | None = None
    epistemic_high: float | None = None
    quantile: float = 0.95
    #: how its bits were measured (a report's :attr:`CompetencyReport.measure`: estimator, bin
    #: widths, samples per member, ...); None: not known, not compared
    measure: Mapping[str, Any] | None = None
    #: the imagined steps its bits were measured over; None: not known, not compared
    steps: int | None = None
    #: whether its split was calibrated against real episodes (:class:`AleatoricShare`);
    #: None: not known, not compared
    calibrated: bool | None = None

    def __post_init__(self) -> None:
        for field_name in ("aleatoric", "epistemic", "aleatoric_high", "epistemic_high"):
            value = getattr(self, field_name)
            if field_name.endswith("_high") and value is None:
                continue
            if not _is_number(value) or not np.isfinite(value) or value < 0:
                raise ValueError(f"reference.{field_name}: expected bits >= 0, got {value!r}")
        if not self.rise > 1:
            raise ValueError(f"rise: expected a factor > 1, got {self.rise!r}")
        if not (_is_number(self.quantile) and 0.0 < self.quantile < 1.0):
            raise ValueError(
                f"quantile: expected a share of start states in (0, 1), got {self.quantile!r}"
            )


#: the parts of a measure the real spread shares with a report's bits (not the samples per
#: member or the bias correction: the real episodes are one group of samples)
SPREAD_MEASURE = ("estimator", "bin_width", "episode_end")


@dataclass(frozen=True)
class RealSpread:
    """The spread of an agent's real episodes from some start states, in the bits an assessor
    measures imagined episodes in (:meth:`CompetencyAssessor.real_spread`); a report of the
    same agent, task and start states takes it (:meth:`CompetencyReport.with_real_spread`)."""

    #: the ``"uncertainty"`` entries of the real episodes, batch ``[B]`` (``"total"`` =
    #: ``"aleatoric"``, ``"epistemic"`` 0, ``"time_mean"``, ``"summary"``, and with an episode
    #: end ``"live"`` and ``"per_live_step"``)
    bits: TensorDictBase
    #: how they were measured (the assessor's estimator, bin widths and episode end)
    measure: Mapping[str, Any]
    #: the boundary that ended the episodes (:attr:`SuccessBoundary.predicates`)
    predicates: str
    #: the steps measured (the assessor's horizon)
    steps: int
    #: the agent and how it acted (the real outcomes'); ``None`` where not known
    agent: str | None = None
    acting: str | None = None
    #: ``[B, S]`` the start states (the real outcomes'); ``None`` where not known
    starts: Tensor | None = None
    #: the real episodes per start state (R); ``None`` where not known
    runs: int | None = None

    def __repr__(self) -> str:
        count = self.bits.batch_size.numel()
        unit = "per_live_step" if "per_live_step" in self.bits.keys() else "summary"
        bits = float(self.bits.get((unit, "total")).mean())
        agent = None if self.agent is None else self.agent[:12]
        return (
            f"RealSpread(start_states={count}, steps={self.steps}, "
            f"{unit.replace('summary', 'time_mean')}_bits={bits:.2f}, agent={agent!r}, "
            f"acting={self.acting!r})"
        )


@dataclass(frozen=True)
class AleatoricShare:
    """Which share of a world model's aleatoric bits the env's real episodes show, per state
    dimension: fitted where the agent's real episodes were run many times from some start
    states (:meth:`fit`), then applied to its forecasts from others
    (:meth:`CompetencyReport.with_aleatoric_share`), whose split it calibrates.

    A world model's aleatoric part is the spread its members agree on: the env's randomness,
    or an error they all make, which the ensemble cannot tell apart (a model of a
    deterministic env spreads its imagined states too, where the real episodes repeat). The
    real episodes' spread tells them apart: ``share[d] = min(1, real[d] / imagined[d])``, the
    bits of dimension ``d`` summed over the fitted start states, per step of the episodes'
    life where they end at the boundary (how long the imagined and the real episodes last is
    not the spread; else time means). Applied, each dimension keeps that share of its
    aleatoric bits at every step and the rest counts as epistemic, the model's own error
    (its total is kept: :func:`~rcvae_torchrl.competency.rescale_aleatoric`). A share of 0
    says the env repeats what the agent does there; 1, that the model's spread is no more
    than the real one (where it is less, the share stays 1: the model has not learned all of
    the env's randomness, :meth:`CompetencyReport.with_real_spread` says so).

    The plug-in entropy of ``n`` samples reads lower the fewer they are, so the real episodes
    per start must be as many as the imagined samples per member (``R = N``), and the share
    is applied only to forecasts with ``N`` samples per member, of the same world model and
    boundary (:attr:`CompetencyReport.task`), bins and horizon, and agent acting the same way.
    One share per dimension over the whole horizon: fit it on start states like those it is
    applied to, and on other start states than those it is scored on."""

    #: ``[D]`` the share of each dimension's aleatoric bits kept, in [0, 1]
    share: Tensor
    #: ``[D]`` the imagined aleatoric and the real bits it was fitted on (means over the starts)
    imagined: Tensor
    real: Tensor
    #: the start states it was fitted on
    start_states: int
    #: whether the bits are per live step (else time means)
    per_live_step: bool
    #: what the forecasts answer and how their bits were measured, as in the fitted report
    #: (:attr:`CompetencyReport.task`, the :data:`SPREAD_MEASURE` part of its measure, its steps);
    #: '' / None where not known (not compared)
    task: str
    measure: Mapping[str, Any]
    steps: int | None
    dim_names: tuple[str, ...]
    #: the imagined samples per member and real episodes per start it was fitted with (N = R)
    samples_per_member: int | None = None
    #: the agent and how it acted in the real episodes (the spread's); None where not known
    agent: str | None = None
    acting: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "dim_names", _checks.check_names("dim_names", self.dim_names))
        _checks.check_positive_int("start_states", self.start_states)
        _checks.check_bool("per_live_step", self.per_live_step)
        for name in ("steps", "samples_per_member"):
            if getattr(self, name) is not None:
                _checks.check_positive_int(name, getattr(self, name))
        if not isinstance(self.measure, Mapping):
            raise TypeError(f"measure: expected a mapping, got {type(self.measure).__name__}")
        for name in ("share", "imagined", "real"):
            value = getattr(self, name)
            if not isinstance(value, Tensor):
                value = torch.as_tensor(value, dtype=torch.float32)
                object.__setattr__(self, name, value)
            if value.ndim != 1 or len(value) != len(self.dim_names):
                raise ValueError(
                    f"{name}: expected one value per state dimension ({len(self.dim_names)} "
                    f"named), got shape {tuple(value.shape)}"
                )
            if not bool((torch.isfinite(value) & (value >= 0)).all()):
                raise ValueError(f"{name}: expected finite values >= 0, got {value.tolist()}")
        if bool((self.share > 1).any()):
            raise ValueError(f"share: expected shares in [0, 1], got {self.share.tolist()}")

    @classmethod
    def fit(cls, report: CompetencyReport, spread: RealSpread) -> AleatoricShare:
        """The share from ``report`` (a forecast from some start states, as the assessor
        returned it) and ``spread`` (the agent's real episodes from the same start states,
        as many per start as the report's samples per member: :meth:`CompetencyAssessor
        .real_spread`), refused where :meth:`CompetencyReport.with_real_spread` refuses them
        (other start states, agent, bins, steps or boundary)."""
        if not isinstance(report, CompetencyReport):
            raise TypeError(f"report: expected a CompetencyReport, got {type(report).__name__}")
        if report.aleatoric_share is not None:
            raise ValueError(
                "report: its split is calibrated already (with_aleatoric_share); fit on the "
                "report the assessor returned"
            )
        report.with_real_spread(spread)  # the checks that tie the two together
        n = (report.measure or {}).get("samples_per_member")
        if n is not None and spread.runs is not None and spread.runs != n:
            raise ValueError(
                f"spread: expected {n} real episodes per start state, as many as the report's "
                f"imagined samples per member (the plug-in entropy of fewer samples reads "
                f"lower, of more higher), got {spread.runs}"
            )
        imagined = report.uncertainty.get(("time_mean", "aleatoric"))
        if imagined.ndim != report.data.batch_dims + 1:
            raise ValueError(
                "report: expected bits per state dimension (the histogram estimator's), got "
                f"time means of shape {tuple(imagined.shape)}"
            )
        real = spread.bits.get(("time_mean", "total")).reshape(imagined.shape).to(imagined)
        live = report.has_live_steps and "live" in spread.bits.keys()
        if live:  # bits per step of each one's life: the imagined and real episodes end apart
            imagined = _per_live_step(imagined, report.uncertainty.get("live"))
            real = _per_live_step(real, spread.bits.get("live").reshape(*imagined.shape[:-1], -1))
        imagined, real = imagined.reshape(-1, imagined.shape[-1]), real.reshape(-1, real.shape[-1])
        total = imagined.sum(0)
        share = torch.where(
            total > 0,
            (real.sum(0) / total.clamp_min(torch.finfo(total.dtype).tiny)).clamp(0.0, 1.0),
            torch.ones_like(total),
        )
        return cls(
            share=share.detach().cpu().float(),
            imagined=imagined.mean(0).detach().cpu().float(),
            real=real.mean(0).detach().cpu().float(),
            start_states=imagined.shape[0],
            per_live_step=live,
            task=report.task,
            measure=_as_json({k: (report.measure or {}).get(k) for k in SPREAD_MEASURE}),
            steps=report._imagined_steps(),
            dim_names=tuple(report.dim_names),
            samples_per_member=n if n is not None else spread.runs,
            agent=spread.agent,
            acting=spread.acting,
        )

    def as_dict(self) -> dict[str, Any]:
        """Plain values that JSON and ``torch.load(weights_only=True)`` both read back: lists,
        numbers and strings (:meth:`from_dict`)."""
        return {
            "share": self.share.tolist(),
            "imagined": self.imagined.tolist(),
            "real": self.real.tolist(),
            "start_states": self.start_states,
            "per_live_step": self.per_live_step,
            "task": self.task,
            "measure": _as_json(dict(self.measure)),
            "steps": self.steps,
            "dim_names": list(self.dim_names),
            "samples_per_member": self.samples_per_member,
            "agent": self.agent,
            "acting": self.acting,
        }

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> AleatoricShare:
        """What :meth:`as_dict` gave (lists or tensors), checked as the constructor checks."""
        required = ("share", "imagined", "real", "start_states", "per_live_step", "task")
        _checks.check_entries(
            "values", values, (*required, "measure", "steps", "dim_names"), _AS_DICT
        )
        for name in ("share", "imagined", "real"):
            value = values[name]
            if not isinstance(value, (Tensor, list, tuple)):
                raise TypeError(
                    f"values[{name!r}]: expected a list of numbers ({_AS_DICT}), got "
                    f"{type(value).__name__}"
                )
        for name in ("task", "agent", "acting"):
            value = values.get(name)
            if value is not None and not isinstance(value, str):
                raise TypeError(f"values[{name!r}]: expected a str ({_AS_DICT}), got {value!r}")
        if values["measure"] is not None and not isinstance(values["measure"], Mapping):
            raise TypeError(
                f"values['measure']: expected a mapping ({_AS_DICT}), got {values['measure']!r}"
            )
        if isinstance(values["dim_names"], (str, bytes)) or not isinstance(
            values["dim_names"], (list, tuple)
        ):
            raise TypeError(
                f"values['dim_names']: expected a list of names ({_AS_DICT}), got "
                f"{values['dim_names']!r}"
            )
        steps, n = values["steps"], values.get("samples_per_member")
        return cls(
            share=torch.as_tensor(values["share"], dtype=torch.float32),
            imagined=torch.as_tensor(values["imagined"], dtype=torch.float32),
            real=torch.as_tensor(values["real"], dtype=torch.float32),
            start_states=values["start_states"],
            per_live_step=values["per_live_step"],
            task=values["task"],
            measure=dict(values["measure"] or {}),
            steps=steps,
            dim_names=tuple(values["dim_names"]),
            samples_per_member=n,
            agent=values.get("agent"),
            acting=values.get("acting"),
        )

    def describe(self) -> str:
        """One sentence: what the share was fitted on, and how much of the model's aleatoric
        bits it keeps (means over the start states it was fitted on)."""
        unit = "bits per live step" if self.per_live_step else "bits"
        imagined, real = float(self.imagined.sum()), float(self.real.sum())
        kept = float((self.imagined * self.share).sum())
        least = int(self.share.argmin())
        n = self.start_states
        starts = "1 other start state" if n == 1 else f"{n} other start states"
        text = (
            f"The split is calibrated against the agent's real episodes from {starts}, where "
            f"they spread {real:.2f} {unit} and the world model imagined {imagined:.2f} "
            "aleatoric"
        )
        if imagined <= 0:  # nothing imagined there: nothing to keep or to move
            return text + "."
        if not bool(self.share.any()):
            return text + (
                ", so none of its aleatoric bits count as aleatoric: all are the model's own "
                "error (epistemic)."
            )
        return text + (
            f", so it keeps {kept / imagined:.0%} of its aleatoric bits as aleatoric and counts "
            f"the rest as its own error (epistemic); the least kept, {self.dim_names[least]}: "
            f"{float(self.share[least]):.0%}."
        )


_AS_DICT = "an AleatoricShare.as_dict()"


#: How a report record's parts of kinds other packages define are read back (their
#: ``from_dict``), by entry; those packages register them (:func:`register_report_part`)
_PART_READERS: dict[str, Callable[[dict[str, Any]], Any]] = {}
#: the entries of those parts
_PART_ENTRIES = ("forecast_check", "novelty", "dynamics_check")


def _check_dynamics_model(task: str, check: Any, name: str = "check") -> None:
    """Refuse a dynamics check made with another world model than ``task``'s (where the task
    names one)."""
    mine = (fingerprint.task_parts(task) or {}).get("model")
    if mine and check.model != mine:
        raise ValueError(
            f"{name}: made with another world model than this report's (its weights, config "
            "or functions differ); check the real episodes with this report's model"
        )


def register_report_part(entry: str, read: Callable[[dict[str, Any]], Any]) -> None:
    """Read a :meth:`CompetencyReport.as_dict` record's ``entry`` (``"forecast_check"``,
    ``"novelty"`` or ``"dynamics_check"``) with ``read``, its kind's ``from_dict``: the training
    package registers its :class:`~rcvae_torchrl.training.OutcomeCheck`,
    :class:`~rcvae_torchrl.training.StateNovelty` and
    :class:`~rcvae_torchrl.training.DynamicsCheck` when it is imported (as ``import
    rcvae_torchrl`` does), which this package does not import."""
    if entry not in _PART_ENTRIES:
        raise ValueError(f"entry: expected one of {list(_PART_ENTRIES)}, got {entry!r}")
    _PART_READERS[entry] = read


#: What a :meth:`CompetencyReport.as_dict` record says it is, and the entries it holds
_REPORT_KIND = "CompetencyReport"
_REPORT_AS_DICT = "a CompetencyReport.as_dict()"
_REPORT_ENTRIES = (
    "kind",
    "data",
    "batch_size",
    "dim_names",
    "time_limit",
    "dt",
    "confidence",
    "top_k",
    "keys",
    "model_warning",
    "model_caution",
    "survival",
    "measure",
    "task",
    "acting",
    "agent",
    "predicates",
    "time_unit",
    "spread_tolerance",
    "reference",
    "forecast_check",
    "novelty",
    "aleatoric_share",
)
#: entries a record may lack (written before they were): read as None
_REPORT_OPTIONAL = ("dynamics_check",)


def _key_as_list(key: NestedKey) -> str | list[str]:
    return key if isinstance(key, str) else list(key)


def _key_from_list(key: str | Sequence[str]) -> NestedKey:
    return key if isinstance(key, str) else tuple(key)


def _reference_dict(reference: Reference) -> dict[str, Any]:
    values = {f.name: getattr(reference, f.name) for f in fields(reference)}
    if values["measure"] is not None:
        values["measure"] = dict(values["measure"])
    return values


def _tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


def _report_labels(values: Mapping[str, Any]) -> dict[str, Any]:
    """A report record's labels (:meth:`CompetencyReport.as_dict`), checked: its entries,
    their types and ranges, and its deadline, dt and predicates against its task."""
    if isinstance(values, Mapping) and "kind" not in values and "competency" in values:
        raise ValueError(
            "values: a report's data alone (report.data.to_dict(), as saved before whole "
            "reports were), not a CompetencyReport.as_dict() record: it does not say which "
            "task, agent or deadline it answered. Assess again and save report.as_dict(), or "
            "label the data with the assessor that made it: assessor.report(TensorDict(...))"
        )
    _checks.check_entries("values", values, _REPORT_ENTRIES, _REPORT_AS_DICT, _REPORT_OPTIONAL)
    if values["kind"] != _REPORT_KIND:
        raise ValueError(
            f"values['kind']: expected {_REPORT_KIND!r} ({_REPORT_AS_DICT}), got {values['kind']!r}"
        )

    def typed(name: str, kinds: tuple[type, ...], what: str) -> Any:
        value = values[name]
        if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
            raise TypeError(f"values[{name!r}]: expected {what} ({_REPORT_AS_DICT}), got {value!r}")
        return value

    for name in ("task", "model_warning", "model_caution", "time_unit"):
        typed(name, (str,), "a str")
    for name in ("acting", "agent", "predicates"):
        typed(name, (str, type(None)), "a str or None")
    _checks.check_positive_int("values['time_limit']", values["time_limit"])
    _checks.check_non_negative_int("values['top_k']", values["top_k"])
    _checks.check_bool("values['survival']", values["survival"])
    _checks.check_unit_interval("values['confidence']", values["confidence"], include_zero=False)
    if values["confidence"] >= 1:
        raise ValueError(
            f"values['confidence']: expected a coverage below 1, got {values['confidence']!r}"
        )
    dt = typed("dt", (int, float, type(None)), "seconds per step (a number > 0) or None")
    if dt is not None:
        _checks.check_positive("values['dt']", dt)
    names = typed("dim_names", (list, tuple), "a list of dimension names")
    if not all(isinstance(n, str) for n in names):
        raise TypeError(f"values['dim_names']: expected names (str), got {names!r}")
    tolerance = typed("spread_tolerance", (list, tuple), "[factor, bits]")
    if len(tolerance) != 2 or not all(_is_number(v) and v > 0 for v in tolerance):
        raise ValueError(
            f"values['spread_tolerance']: expected [factor, bits], two numbers > 0, got "
            f"{tolerance!r}"
        )
    measure = typed("measure", (Mapping, type(None)), "a dict or None")
    keys = typed("keys", (Mapping,), "a dict of the report's keys")
    if sorted(map(str, keys)) != ["competency", "observation", "uncertainty"]:
        raise ValueError(
            f"values['keys']: expected the keys 'uncertainty', 'competency' and 'observation', "
            f"got {sorted(map(str, keys))}"
        )
    for name, key in keys.items():
        if not (
            isinstance(key, str)
            or (isinstance(key, (list, tuple)) and key and all(isinstance(k, str) for k in key))
        ):
            raise TypeError(
                f"values['keys'][{name!r}]: expected a key (a str or strs), got {key!r}"
            )
    time_limit = int(values["time_limit"])
    said = fingerprint.task_parts(values["task"])
    if said is not None:  # what the task answers is what the labels say
        found = fingerprint.task_labels(values["predicates"] or "", time_limit, dt)
        if values["predicates"] is None:  # a report that knows no boundary: nothing to compare
            del found["boundary"]
        for part, value in found.items():
            if said[part] != value:
                entry = {"deadline": "time_limit", "boundary": "predicates"}.get(part, part)
                raise ValueError(
                    f"values[{entry!r}]: not the {part} the record's task says ({said[part]} "
                    f"there, {value} here): the record was edited or damaged"
                )
    return {
        "keys": {name: _key_from_list(key) for name, key in keys.items()},
        "dim_names": tuple(names),
        "time_limit": time_limit,
        "dt": None if dt is None else float(dt),
        "confidence": float(values["confidence"]),
        "top_k": int(values["top_k"]),
        "model_warning": values["model_warning"],
        "model_caution": values["model_caution"],
        "survival": bool(values["survival"]),
        "measure": None if measure is None else dict(measure),
        "task": values["task"],
        "acting": values["acting"],
        "agent": values["agent"],
        "predicates": values["predicates"],
        "time_unit": values["time_unit"],
        "spread_tolerance": (float(tolerance[0]), float(tolerance[1])),
    }


def _check_tensor_leaves(name: str, values: Mapping[str, Any]) -> None:
    """Every leaf of a record's nested data is a tensor (a list would be taken as one)."""
    for key, value in values.items():
        if isinstance(value, Mapping):
            _check_tensor_leaves(f"{name}[{key!r}]", value)
        elif not isinstance(value, Tensor):
            raise TypeError(
                f"{name}[{key!r}]: expected a tensor (report.data.to_dict()), got "
                f"{type(value).__name__}"
            )


def _report_data(values: Mapping[str, Any], keys: Mapping[str, NestedKey]) -> TensorDict:
    """A report record's data (a copy), checked: tensors of its batch size, holding the
    report's uncertainty and competency, with probabilities in [0, 1]."""
    batch = values["batch_size"]
    if not isinstance(batch, (list, tuple)) or not all(
        isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in batch
    ):
        raise TypeError(
            f"values['batch_size']: expected a list of sizes (ints >= 0), got {batch!r}"
        )
    if not isinstance(values["data"], Mapping):
        raise TypeError(
            f"values['data']: expected a dict of tensors (report.data.to_dict()), got "
            f"{type(values['data']).__name__}"
        )
    _check_tensor_leaves("values['data']", values["data"])
    try:
        data = TensorDict(dict(values["data"]), batch_size=list(batch)).clone()
    except (RuntimeError, TypeError, ValueError) as err:
        raise ValueError(
            f"values['data']: its tensors do not share the report's batch size {list(batch)} "
            f"({err})"
        ) from err
    for part in ("uncertainty", "competency"):
        if not isinstance(data.get(keys[part], None), TensorDictBase):
            raise ValueError(
                f"values['data']: expected the report's {part} entries under {keys[part]!r}, "
                f"got none"
            )
    competency = data.get(keys["competency"])
    for name in ("p_success", "p_success_low", "p_success_high"):
        p = competency.get(name, None)
        if p is None and name != "p_success":  # a report built by hand may lack its interval
            continue
        if p is None or p.shape != data.batch_size:
            raise ValueError(
                f"values['data']: expected {name} of the batch {list(batch)} among the "
                f"competency entries, got {None if p is None else list(p.shape)}"
            )
        if not bool(((p >= 0) & (p <= 1)).all()):
            raise ValueError(
                f"values['data']: {name} holds values outside [0, 1] (from {float(p.min()):g} "
                f"to {float(p.max()):g}): the record was edited or damaged"
            )
    start = data.get(keys["observation"], None)
    if isinstance(start, Tensor) and start.is_floating_point() and not bool(start.isfinite().all()):
        raise ValueError(
            f"values['data']: the start states {keys['observation']!r} hold NaN or inf: the "
            "record was edited or damaged"
        )
    low, high = competency.get("p_success_low", None), competency.get("p_success_high", None)
    if low is not None and high is not None and not bool((low <= high).all()):
        raise ValueError(
            "values['data']: p_success_low exceeds p_success_high for some start (an interval "
            "from high to low): the record was edited or damaged"
        )
    return data


def _per_live_step(time_mean: Tensor, live: Tensor) -> Tensor:
    """``time_mean`` ``[*B, D]`` as bits per live step (``live`` ``[*B, T]``)."""
    return bits_per_live_step(time_mean.movedim(-1, 0), live.to(time_mean)).movedim(0, -1)


@dataclass(frozen=True)
class CompetencyReport:
    """The assessment of a batch of start states, and its plain-language summary.

    ``data`` has batch ``[*B]`` (one entry per start state; ``report[i]`` is start state i)
    and holds, with ``E`` members, ``N`` samples per member, ``T`` steps, ``D`` dimensions:

    - ``"observation"`` ``[*B, D]``: the start states;
    - ``"uncertainty"``: :class:`~rcvae_torchrl.competency.UncertaintyMetric`'s entries
      (``"total"`` / ``"aleatoric"`` / ``"epistemic"`` bits ``[*B, T, D]``, ``"time_mean"``
      ``[*B, D]``, ``"summary"`` ``[*B]`` summed over dimensions, ``"by_dim"`` with names),
      plus ``"peak_step"`` int64 ``[*B, D]``, the time index of each dimension's largest total
      bits, and with ``dt`` ``"peak_time_s"`` = (peak_step + 1)·dt (index t holds s_{t+1});
      joint estimators give ``[*B, T]``, ``[*B]``, ``[*B]`` and no peaks;
    - ``"competency"``: :class:`~rcvae_torchrl.competency.SuccessMetric`'s entries with the
      start state first: ``"p_success"``, ``"p_success_low"``, ``"p_success_high"`` ``[*B]``,
      ``"p_success_member"`` ``[*B, E]``, ``"success"`` / ``"failure"`` ``[*B, E, N]``,
      ``"outcome_uncertainty"`` ``[*B]``, ``"time_to_success"`` (``"first_step"``
      ``[*B, E, N]``, per-step entries ``[*B, T]``, statistics ``[*B]``);
    - ``"start_state"``: ``"in_success"`` and ``"in_failure"`` bool ``[*B]``, whether the start
      state already lies in the boundary's success or failure region (its outcome mostly
      settled before the agent acts; a paragraph says so);
    - ``"novelty"`` (when the world model has a novelty check, ``ensemble.novelty``, which
      training fits: :class:`~rcvae_torchrl.training.StateNovelty`): ``"start"`` ``[*B]``, the
      start state's distance to the training states over the check's level (above 1: unlike
      them); ``"imagined"`` ``[*B]``, the share of its imagined states beyond the states'
      level (every member's first two samples at 20 steps spread over the horizon; a state
      after its imagined episode ended at the boundary's success, failure or time limit is
      never counted beyond it); and ``"leaves"`` int64 ``[*B]``, the time index of the first of
      those steps at which most of these samples are beyond it (-1: none), when the forecast
      starts to extrapolate; where the check knows the training actions' support
      (:meth:`~rcvae_torchrl.training.StateNovelty.with_actions`), ``"actions"`` ``[*B]``,
      the share of the imagined steps whose action lies outside it;
    - ``"rollout"`` (only when asked for): the imagined rollouts ``[*B, E, N, T]``.

    **Summary rules** (:meth:`summary`), one paragraph per start state:

    1. When the world model failed its self-checks (``model_warning``), the paragraph opens
       with a warning naming the dimensions it has not learned; when it has none (trained
       with ``checks=False``, or not trained), a warning saying so: such a forecast is never
       presented as trustworthy. So does a forecast check that did not pass
       (:meth:`with_forecast_check`): ``Warning: forecast check on other start states: the
       forecasts are too optimistic: ...``.
    2. ``P(success within L) = p (c% interval low–high).`` (``P(no failure for L)`` for a
       survival boundary) L = min(time limit, T) steps, in
       seconds when ``dt`` is known; the interval is the Monte-Carlo one of ``SuccessMetric``.
       Where the members' own P differ beyond their imagined samples' chance
       (:func:`~rcvae_torchrl.competency.same_chance_p_value` below :data:`MEMBERS_ALPHA`), a
       sentence gives their range:
       ``The members disagree on it: their own P(success within 3 s) run from 0.20 to 0.75,
       more than their imagined samples' chance allows (p = 0.0069): ...``, the model's own
       doubt about the outcome, which the interval does not cover (the state's bits can read
       mostly aleatoric while the members disagree on the outcome).
    3. With a novelty check: a start state unlike the training states, or whose imagined
       states are unlike them in a larger share than the check's in-distribution episodes'
       states are (its ``episode_level``; :attr:`novel`), gets a caution naming how far it
       lies and the dimensions outside the training states' range: ``Caution: the start
       state is unlike the states the model was trained on (2.4x as far from the training
       states as 99% of held-out episodes' first states are: velocity_0 = 7.6 (training
       -4.2 to 4.3)): the forecast extrapolates, however much the members agree.`` For
       imagined states, the caution also says at which step more than half of that step's
       samples are first unlike the training states (``The first step at which more than half
       of the samples are is t = 2.4 s``), where the forecast starts to extrapolate. An
       imagined episode whose policy takes actions outside the training actions' support in
       more of its steps than the check's ``action_level`` gets a caution too (the model has
       not seen their effect). The members' disagreement is no sure sign of such states:
       members trained on the same data can agree far from it, and where such a start's doubt
       is as in the reference (rule 4) the sentence says so despite the caution.
       :meth:`overall` counts them.
    4. With a :class:`Reference` (in-distribution start states, see :meth:`with_reference`),
       what changed: each part's bits against the reference's, and which part rose
       (at least ``rise`` times the reference; the larger rise when both did): ``Against the
       in-distribution reference, epistemic uncertainty rose 2.1x (0.29 -> 0.61 bits) and
       aleatoric 1.0x (10.2 -> 10.4 bits): the model has not seen states like this.`` (a
       part below the reference "fell to" its ratio; when neither rose, the sentence names a
       part at ``1 / rise`` of the reference or less as fallen below it). One start state's
       part rose only when it is also above the level that ``quantile`` of the reference's
       start states stay at or below (where the reference knows it, see :class:`Reference`):
       ``... neither part rose beyond the reference's own start states, 95% of which reach
       0.46 epistemic bits.``
       The bits are time means, or, when both reports were made with ``episode_end`` (their
       ``"per_live_step"`` entries), bits per step of the imagined episodes' life: with ended
       episodes counted as certain, a time mean also measures how long the episodes last, and
       episodes that fail sooner than the reference's would look less uncertain for it.
       Without a reference, the dominant type: the
       larger of the aleatoric and epistemic time-mean bits summed over dimensions
       (``("uncertainty", "summary", ·)``; a tie counts as aleatoric), given with its share
       of the total: ``Most of the doubt is epistemic (0.70
       of 1.10 bits): the model has not seen states like this.`` When all three are 0 the
       sentence says so; below :data:`LITTLE_DOUBT_BITS` (1 bit) in all it names no part and
       no cause (``Little doubt about the imagined states (0.37 bits, ...): 0.17 aleatoric and
       0.20 epistemic.``). With a warning (rule 1) neither: the bits are given without a cause
       (a model that failed its checks may take missing knowledge for chance, or hide it).
    5. The ``top_k`` dimensions with the largest time-mean total bits (only those above 0),
       each with its mean bits and the time of its peak. Left out for joint estimators.

    The words are only as good as the estimate: with the histogram estimator, a member's
    entropy from ``N`` samples is at most log2 N bits, so when the samples spread over many
    more bins than ``N`` the epistemic part is inflated (up to log2 E bits per dimension).
    Coarser bins or more samples per member help.

    Args:
        data: the report TensorDict described above.
        dim_names: names of the ``D`` dimensions.
        time_limit: L in steps.
        dt: seconds per step, or ``None`` (times in steps).
        confidence: coverage of the P(success) interval.
        top_k: number of dimensions named in the summary.
        uncertainty_key, competency_key, observation_key: where ``data`` holds each part.
        model_warning: why the world model is not trustworthy ('' when it passed its
            self-checks or has none).
        model_caution: what its self-checks found that does not fail them (a spread too
            wide: its aleatoric bits overstate the noise), said beside the split of the doubt.
        survival: whether success is lasting the time limit without a failure
            (:meth:`~rcvae_torchrl.competency.SuccessBoundary.survival`).
        reference: the uncertainty the summary compares with (:meth:`with_reference`).
        forecast_check: the forecast checked against real episodes (:meth:`with_forecast_check`).
        novelty: the world model's novelty check (a
            :class:`~rcvae_torchrl.training.StateNovelty`), for rule 3.
        dynamics_check: whether real episodes of the env move as the world model learned (a
            :class:`~rcvae_torchrl.training.DynamicsCheck`, :meth:`with_dynamics_check`).
    """

    data: TensorDictBase
    dim_names: tuple[str, ...]
    time_limit: int
    dt: float | None
    confidence: float
    top_k: int = 2
    uncertainty_key: NestedKey = "uncertainty"
    competency_key: NestedKey = "competency"
    observation_key: NestedKey = "observation"
    model_warning: str = ""
    reference: Reference | None = None
    #: what the world model's self-checks found that does not fail them (a spread too wide,
    #: :attr:`CompetencyAssessor.model_caution`): said beside the split of the doubt
    model_caution: str = ""
    survival: bool = False
    forecast_check: Any = None
    novelty: Any = None
    #: how the bits were measured (the assessor's estimator, its settings and the samples per
    #: member, :attr:`CompetencyAssessor.measure`); ``None`` where not known
    measure: Mapping[str, Any] | None = None
    #: what the forecasts answer, part by part: a digest of the boundary (its predicates' code
    #: and values), the deadline the report judges, dt, and a digest of the world model (its
    #: weights, config and functions; :meth:`CompetencyAssessor.task`); '' where not known (a
    #: report built by hand). A forecast check must be of the same task
    #: (:meth:`with_forecast_check`)
    task: str = ""
    #: how the agent chose its actions in the imagined episodes: its exploration type's name
    #: (e.g. ``"random"``, a stochastic policy's samples; :func:`~rcvae_torchrl.data
    #: .exploration_mode`); ``None`` where not known or open loop. Real episodes of the policy
    #: acting otherwise do not check it (:meth:`with_forecast_check`)
    acting: str | None = None
    #: the agent whose forecasts these are, as the digest of its policy's weights, or of a
    #: weightless module's settings (:func:`~rcvae_torchrl.fingerprint.agent_digest`); ``None``
    #: where not known (a policy written as a function, open loop, a report built by hand).
    #: Real episodes of another agent do not check it (:meth:`with_forecast_check`,
    #: ``score_forecast``)
    agent: str | None = None
    #: the boundary's :attr:`~rcvae_torchrl.competency.SuccessBoundary.predicates` (they are
    #: in :attr:`task` too): real outcomes judged by other predicates do not score it
    predicates: str | None = None
    #: the unit of ``dt`` and of the times the summaries write (the boundary's ``time_unit``)
    time_unit: str = "s"
    #: how far the aleatoric bits may lie from the real episodes' spread before a summary
    #: says so: ``(factor, bits)``, both exceeded (:meth:`with_real_spread`)
    spread_tolerance: tuple[float, float] = (1.5, 1.0)
    #: the share of the aleatoric bits that real episodes showed, applied to this report's
    #: split (:meth:`with_aleatoric_share`); ``None``: the world model's own split
    aleatoric_share: AleatoricShare | None = None
    #: whether real episodes of the env move as the world model learned
    #: (:meth:`with_dynamics_check`); ``None``: not checked
    dynamics_check: Any = None

    def as_dict(self) -> dict[str, Any]:
        """The whole report as tensors, numbers, strings, lists and dicts, for
        :func:`~rcvae_torchrl.io.save_torch` (:meth:`from_dict` reads it back): its ``data``
        (on the CPU) and batch size, and every label that says what it answers and how far it
        is to be trusted: task, agent, acting, predicates, deadline, dt, the world model's
        warning and caution, how its bits were measured, and its novelty check, reference,
        forecast check and aleatoric share. Saving ``report.data`` alone keeps none of them:
        :meth:`CompetencyAssessor.report` labels bare data with the reading assessor's task and
        knows no agent."""
        return {
            "kind": _REPORT_KIND,
            "data": self.data.detach().to("cpu").clone().to_dict(),  # a copy, not shared
            "batch_size": list(self.data.batch_size),
            "dim_names": list(self.dim_names),
            "time_limit": int(self.time_limit),
            "dt": None if self.dt is None else float(self.dt),
            "confidence": float(self.confidence),
            "top_k": int(self.top_k),
            "keys": {
                name: _key_as_list(getattr(self, f"{name}_key"))
                for name in ("uncertainty", "competency", "observation")
            },
            "model_warning": self.model_warning,
            "model_caution": self.model_caution,
            "survival": bool(self.survival),
            "measure": None if self.measure is None else dict(self.measure),
            "task": self.task,
            "acting": self.acting,
            "agent": self.agent,
            "predicates": self.predicates,
            "time_unit": self.time_unit,
            "spread_tolerance": [float(v) for v in self.spread_tolerance],
            "reference": None if self.reference is None else _reference_dict(self.reference),
            "forecast_check": None
            if self.forecast_check is None
            else self.forecast_check.as_dict(),
            "novelty": None if self.novelty is None else self.novelty.as_dict(),
            "aleatoric_share": None
            if self.aleatoric_share is None
            else self.aleatoric_share.as_dict(),
            "dynamics_check": None
            if self.dynamics_check is None
            else self.dynamics_check.as_dict(),
        }

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> CompetencyReport:
        """The report :meth:`as_dict` gave (e.g. read back with
        :func:`~rcvae_torchrl.io.load_torch`), with its own task, agent and deadline: a check
        of another task or agent is refused as it was before the report was saved. Its parts
        are read back as each one's own ``from_dict`` checks them (its data copied, not
        shared); a record missing an entry, holding one this report does not know, of the
        wrong type or out of range, or whose deadline, dt or predicates are not those its
        ``task`` says, is refused by name."""
        labels = _report_labels(values)
        keys = labels.pop("keys")
        data = _report_data(values, keys)
        total = data.get((*_tuple(keys["uncertainty"]), "total"), None)  # [*B, T, D] or [*B, T]
        if isinstance(total, Tensor) and total.dim() == data.batch_dims + 2:
            dims = total.shape[-1]
            if dims != len(labels["dim_names"]):
                raise ValueError(
                    f"values['dim_names']: expected one name per dimension of the bits ({dims}), "
                    f"got {len(labels['dim_names'])}"
                )
        parts = {}
        readers = {
            **_PART_READERS,
            "aleatoric_share": AleatoricShare.from_dict,
            "reference": lambda part: Reference(**part),
        }
        for name in (*_PART_ENTRIES, "aleatoric_share", "reference"):
            part = values.get(name)  # an optional entry a record may lack
            read = readers.get(name)
            if part is not None and read is None:  # its package not imported
                raise ValueError(
                    f"values[{name!r}]: no reader of this part is registered; import "
                    "rcvae_torchrl.training (which defines it) before reading the report"
                )
            if part is not None and not isinstance(part, Mapping):
                raise TypeError(
                    f"values[{name!r}]: expected None or a dict (its own as_dict()), got "
                    f"{type(part).__name__}"
                )
            try:
                parts[name] = None if part is None else read(dict(part))
            except TypeError as err:  # a part's unknown or missing entries (Reference's own)
                raise ValueError(f"values[{name!r}]: not a record of its kind ({err})") from err
            except ValueError as err:  # named by the entry it came from
                raise ValueError(f"values[{name!r}]: {err}") from err
        if parts.get("dynamics_check") is not None:  # made with this report's model, as when
            _check_dynamics_model(  # it was attached
                labels["task"], parts["dynamics_check"], "values['dynamics_check']"
            )
        return cls(
            data,
            uncertainty_key=keys["uncertainty"],
            competency_key=keys["competency"],
            observation_key=keys["observation"],
            **labels,
            **parts,
        )

    def flattened(self) -> CompetencyReport:
        """This report with its start states in one batch dimension ``[B']`` (the batch
        flattened in order, as :attr:`start_states` gives them and real outcomes count them;
        an unbatched report becomes one of a single start state)."""
        return self if self.data.batch_dims == 1 else replace(self, data=self.data.reshape(-1))

    @property
    def novel(self) -> Tensor | None:
        """``[*B]`` bool: start states unlike the states the model was trained on, or whose
        imagined states are unlike them in a larger share than in-distribution episodes'
        states are (the check's ``episode_level``; ``None``: no novelty check, see
        :class:`~rcvae_torchrl.training.StateNovelty`)."""
        if self.novelty is None or "novelty" not in self.data.keys():
            return None
        start, imagined = _novel_parts(self.data.get("novelty"), self.novelty)
        return start | imagined

    @cached_property  # the report is frozen: each paragraph's warning reads it again
    def uncovered(self) -> Tensor | None:
        """``[*B]`` bool: start states unlike those the forecast check was made on
        (:meth:`~rcvae_torchrl.training.OutcomeCheck.covers`), for whose forecasts the check
        does not vouch; ``None`` without a check, or with one that keeps no start states."""
        check = self.forecast_check
        covers = getattr(check, "covers", None)
        if covers is None or getattr(check, "start_states", None) is None:
            return None
        covered = covers(self.start_states)
        return None if covered is None else ~covered.reshape(self.batch_size)

    @cached_property
    def _uncovered_sentence(self) -> str:
        """Where more of these start states lie outside the check's own than chance allows
        (at the check's level), why the check does not vouch for them ('' otherwise)."""
        uncovered, check = self.uncovered, self.forecast_check
        if uncovered is None or not bool(uncovered.any()):
            return ""
        p_value = check.coverage_p_value(self.start_states)
        if not p_value < check.alpha:
            return ""
        return (
            f"the forecast check vouches for start states like its own, and {int(uncovered.sum())} "
            f"of these {uncovered.numel()} lie farther from all of them than its own lie from "
            f"one another, more than chance allows (p = {p_value:.2g}): it does not vouch for "
            "these forecasts; check them on start states like these"
        )

    @property
    def trustworthy(self) -> bool:
        """True only when the world model passed its self-checks and the forecast passed a
        check against real episodes from other start states (:meth:`with_forecast_check`).
        Without such a check nothing has shown the forecasts right: the self-checks look a few
        steps ahead, and models that passed them have forecast far from reality (a walker's
        survival 0.18-0.35 too low). The check must be of this report's task (a check built
        from bare forecasts ties to none; see :meth:`with_forecast_check`), and made on start
        states like these (more of them outside the check's own than chance allows, see
        :attr:`uncovered`, and it does not vouch for them); and no check of real episodes of
        the env says that it moves otherwise than the model learned
        (:meth:`with_dynamics_check`). Start by start, see :attr:`novel` too."""
        checked = self.forecast_check is not None and self.forecast_check.passed
        return checked and not self.warning

    @property
    def warning(self) -> str:
        """Why this forecast is not trustworthy ('' when nothing says so): ``model_warning``,
        and the sentence of a forecast check that did not pass, of one that passed on start
        states these lie outside (:attr:`uncovered`), of one tied to no task, or of one that
        vouches for forecasts of 0 or 1 alone where some of these lie between, or of one whose
        real episodes' controller had other settings than this report's agent; and the
        sentence of a dynamics check that did not pass (:meth:`with_dynamics_check`)."""
        parts = [self.model_warning] if self.model_warning else []
        moves = self.dynamics_check
        if moves is not None and not moves.passed:
            parts.append(f"dynamics check: {moves.describe()}")
        check = self.forecast_check
        if check is not None and not check.passed:
            parts.append(f"forecast check {self._check_place}: {check.describe()}")
        elif check is not None and (uncovered := self._uncovered_sentence):
            parts.append(uncovered)
        elif check is not None and self.task and not getattr(check, "task", None):
            parts.append(
                "the forecast check attached was built from bare forecasts, which ties it to no "
                "task: it may be another boundary's, deadline's or model's, and vouches for none "
                "of these forecasts; build it from the report of its start states "
                "(OutcomeCheck.from_outcomes(report, outcomes)), or pass task=report.task"
            )
        theirs = getattr(check, "agent", None)
        if check is not None and self.agent and theirs and theirs != self.agent:
            # known by settings (a refusal is for weights): warned of when attached, and here
            parts.append(
                "the forecast check attached may be of another agent: its real episodes' "
                "controller has other settings (class name, gains or code) than the one these "
                "forecasts imagined, so it vouches for none of them; check this agent"
            )
        if check is not None and check.passed and getattr(check, "sure_only", False):
            p = self.competency.get("p_success")
            doubt = int(check.in_doubt(p).sum())
            if doubt:
                parts.append(
                    f"the forecast check vouches for forecasts of 0 or 1 alone (it had too few "
                    f"start states in doubt to check others), and {doubt} of these "
                    f"{p.numel()} forecasts lie between (0.001 to 0.999)"
                )
        return "; ".join(parts)

    @property
    def _binned(self) -> bool:
        """Whether the bits are of binned states (the histogram estimator's: entropies of
        counts, never below 0), where a total under :data:`LITTLE_DOUBT_BITS` is little
        doubt; a joint estimator's differential entropies have no such floor."""
        return (self.measure or {}).get("estimator") == "histogram"

    @property
    def _split_doubted(self) -> bool:
        """Whether the bits' split is no evidence of a cause: the world model failed its
        self-checks (or has none), or its forecasts failed their check. A check that passed on
        other start states than these (:attr:`uncovered`), or one tied to no task, vouches for
        none of these forecasts, but says nothing against the model's split: the rise of the
        epistemic part against a reference is then what tells that these starts lie outside
        what the model learned."""
        check = self.forecast_check
        # a dynamics check that failed does not doubt it: its real episodes go where the
        # model predicts worse, whether the env changed or they left the training states, and
        # the split of the doubt there is the model's own account of it, to read beside it
        return bool(self.model_warning) or (check is not None and not check.passed)

    def with_forecast_check(self, check: Any) -> CompetencyReport:
        """This report, with the check of the same agent's forecasts against its real episodes
        from other start states of the distribution these come from (an
        :class:`~rcvae_torchrl.training.OutcomeCheck`, e.g. from held-out episodes' first
        states). A check that did not pass (a bias, or too few start states to tell) opens
        every summary as a warning, the bits then given without a cause, and the report is not
        :attr:`trustworthy`; one that passed closes :meth:`overall`.

        The check must be of this report's :attr:`task`: a check of another boundary, deadline
        or world model is refused, and one built from bare forecasts (which know no task) makes
        a report that knows its task untrustworthy, with a warning saying why. The agent is
        not part of the task but is checked on its own: a check of real episodes of another
        agent (other policy weights, :attr:`agent`) or of a stochastic policy acting in
        another exploration mode than in the report's imagined episodes is refused."""
        if not (hasattr(check, "passed") and callable(getattr(check, "describe", None))):
            raise TypeError(
                "check: expected an OutcomeCheck (rcvae_torchrl.training.OutcomeCheck."
                f"from_outcomes), got {type(check).__name__}"
            )
        other = getattr(check, "attaches_with", "with_forecast_check")
        if other != "with_forecast_check":
            raise TypeError(
                f"check: a {type(check).__name__}, not a check of the forecasts against real "
                f"outcomes (an OutcomeCheck); attach it with report.{other}(check)"
            )
        task = getattr(check, "task", None)
        if self.task and task and task != self.task:
            raise ValueError(
                "check: made for another task than this report's: "
                f"{fingerprint.task_difference(task, self.task)}; check this report's own "
                "task, from the report of its start states: "
                "OutcomeCheck.from_outcomes(report, outcomes)"
            )
        check_same_agent(self, check, name="check")
        return replace(self, forecast_check=check)

    def with_dynamics_check(self, check: Any) -> CompetencyReport:
        """This report, with the check of whether real episodes of the env it is meant for
        move as its world model learned (a :class:`~rcvae_torchrl.training.DynamicsCheck`,
        :func:`~rcvae_torchrl.training.check_dynamics` of a few of them: no outcome is needed).
        An env whose physics changed goes through states like the training states, so neither
        the novelty check nor the members' disagreement tells it; a check that did not pass
        opens every summary as a warning, and the report is not :attr:`trustworthy`, whatever
        its forecast check says (that check ran in the env its real episodes came from). A
        check made with another world model than this report's is refused."""
        if getattr(check, "attaches_with", None) != "with_dynamics_check":
            raise TypeError(
                "check: expected a DynamicsCheck (rcvae_torchrl.training.check_dynamics), got "
                f"{type(check).__name__}"
            )
        _check_dynamics_model(self.task, check)
        return replace(self, dynamics_check=check)

    def with_real_spread(
        self, spread: RealSpread, factor: float = 1.5, min_bits: float = 1.0
    ) -> CompetencyReport:
        """This report with the spread of the agent's real episodes from the same start states,
        measured as its bits were (:meth:`CompetencyAssessor.real_spread` of
        ``real_outcomes(..., keep_observations=True)`` from them, in the same order). Each
        summary then gives it beside the imagined aleatoric part (per live step where both
        have live steps, else as time means), and where the aleatoric part exceeds it by more
        than ``factor`` times and by ``min_bits`` bits, a caution says that it overstates the
        env's noise: the excess is the world model's own error, which its members share and so
        do not count as epistemic (a deterministic env and agent repeat their episodes: 0 bits
        real). Where it falls short as far, a caution says that the model has not learned the
        randomness of the env and the agent. The spread is kept as the ``"real_spread"``
        entries of :attr:`data`.

        A spread of other start states (or in another order), of another agent, measured
        otherwise (other bins, no episode end), over other steps or ended by another boundary is
        refused: it would not be the spread these bits claim."""
        if not isinstance(spread, RealSpread):
            raise TypeError(
                "spread: expected the RealSpread of CompetencyAssessor.real_spread, got "
                f"{type(spread).__name__}"
            )
        count = spread.bits.batch_size.numel()
        if count != self.batch_size.numel():
            raise ValueError(
                f"spread: expected the real episodes of this report's {self.batch_size.numel()} "
                f"start states, got {count}"
            )
        boundary = {} if self.predicates is None else {"boundary": spread.predicates[:12]}
        said = self._measured_otherwise(spread.measure, spread.steps, **boundary)
        if said:
            raise ValueError(
                f"spread: measured otherwise than this report's bits ({said}); measure it with "
                "the assessor that made the report (assessor.real_spread)"
            )
        check_same_agent(self, spread, name="spread")
        _checks.check_same_starts("spread", self.start_states, spread.starts, "real episodes")
        _checks.check_positive("factor", factor)
        if factor < 1:
            raise ValueError(f"factor: expected >= 1, got {factor!r}")
        _checks.check_non_negative("min_bits", min_bits)
        data = self.data.clone(recurse=False)
        data.set("real_spread", spread.bits.reshape(self.batch_size))
        return replace(self, data=data, spread_tolerance=(float(factor), float(min_bits)))

    def _measured_otherwise(
        self, measure: Mapping[str, Any], steps: int | None, **also: Any
    ) -> str:
        """How bits measured by ``measure`` over ``steps`` (and ``also``: ``boundary``, the
        predicates' digest; ``dimensions``, their names) differ from this report's, in the
        parts of a measure the real spread shares (:data:`SPREAD_MEASURE`); '' where they do
        not. What this report does not know (built by hand) is not compared."""
        known = SPREAD_MEASURE if self.measure is not None else ()
        mine = _as_json({k: self.measure.get(k) for k in known})
        theirs = _as_json({k: measure.get(k) for k in known})
        if self._imagined_steps() is not None:
            mine["steps"], theirs["steps"] = self._imagined_steps(), steps
        ours = {
            "boundary": (self.predicates or "")[:12],
            "dimensions": list(self.dim_names),
            "samples_per_member": (self.measure or {}).get("samples_per_member"),
        }
        for key, value in also.items():
            mine[key], theirs[key] = ours[key], list(value) if key == "dimensions" else value
        differ = [k for k in mine if mine[k] != theirs[k]]
        return "; ".join(f"{k}: {theirs[k]!r}, this report's {mine[k]!r}" for k in differ)

    def with_aleatoric_share(self, share: AleatoricShare) -> CompetencyReport:
        """This report with its split calibrated by ``share`` (:meth:`AleatoricShare.fit`,
        from the agent's real episodes from other start states): each dimension keeps that
        share of its aleatoric bits and the rest counts as epistemic, the world model's own
        error; the total bits, P(success) and everything else stay. Every summary says so and
        names the doubt's causes accordingly. A share of another world model or boundary
        (another :attr:`task`), measured otherwise (other bins, no episode end, other steps)
        or of other dimensions is refused, as is a second share."""
        if not isinstance(share, AleatoricShare):
            raise TypeError(
                "share: expected the AleatoricShare of AleatoricShare.fit, got "
                f"{type(share).__name__}"
            )
        if self.aleatoric_share is not None:
            raise ValueError(
                "share: this report's split is calibrated already; apply a share to the "
                "report the assessor returned"
            )
        if self.reference is not None:
            raise ValueError(
                "share: this report compares its split with a reference already; apply the "
                "share first, to this report and to its reference alike, then with_reference"
            )
        if self.task and share.task and share.task != self.task:
            raise ValueError(
                "share: fitted for another task than this report's: "
                f"{fingerprint.task_difference(share.task, self.task)}; fit it with the "
                "assessor that made this report"
            )
        also: dict[str, Any] = {"dimensions": share.dim_names}
        if share.samples_per_member is not None and self.measure is not None:
            also["samples_per_member"] = share.samples_per_member
        said = self._measured_otherwise(share.measure, share.steps, **also)
        if said:
            raise ValueError(
                f"share: fitted on bits measured otherwise than this report's ({said}); fit it "
                "with the assessor that made this report"
            )
        for what, mine, theirs in (
            ("policy weights' digest", self.agent, share.agent),
            ("exploration type", self.acting, share.acting),
        ):
            if mine is not None and theirs is not None and mine != theirs:
                raise ValueError(
                    f"share: fitted on the real episodes of another agent than this report's "
                    f"(its {what} {theirs[:12]!r}, this report's {mine[:12]!r}): real episodes "
                    "spread as the agent acts and where it goes (a stochastic policy acting "
                    "'random' is another agent than acting 'deterministic'); fit a share with "
                    "this agent's real episodes"
                )
        data = self.data.clone(recurse=False)
        data.set(self.uncertainty_key, rescale_aleatoric(self.uncertainty, share.share))
        return replace(self, data=data, aleatoric_share=share)

    def _spread_sentence(self, uncertainty: TensorDictBase, spread: TensorDictBase | None) -> str:
        """The real episodes' spread beside the aleatoric bits (means over the start states
        given), per live step where both have live steps (and as time means, the unit of the
        split above), with a caution where they lie farther apart than
        :attr:`spread_tolerance`; '' without a real spread."""
        if spread is None:
            return ""
        live = "per_live_step" in spread.keys() and "per_live_step" in uncertainty.keys()
        aleatoric = float(_bits(uncertainty, live).get("aleatoric").mean())
        real = float(_bits(spread, live).get("total").mean())
        n = spread.batch_size.numel()
        starts = "this start state" if n == 1 else f"these {n} start states"
        part = "aleatoric part" if self.aleatoric_share is None else "calibrated aleatoric part"
        if live:
            means = (
                float(_bits(spread, False).get("total").mean()),
                float(_bits(uncertainty, False).get("aleatoric").mean()),
            )
            text = (
                f"The agent's real episodes from {starts} spread {real:.2f} bits per live step "
                f"({means[0]:.2f} as a time mean), the imagined {part} {aleatoric:.2f} "
                f"({means[1]:.2f})."
            )
        else:
            text = (
                f"The agent's real episodes from {starts} spread {real:.2f} bits, the imagined "
                f"{part} {aleatoric:.2f}."
            )
        factor, least = self.spread_tolerance
        if aleatoric > factor * real and aleatoric - real >= least:
            text += (
                " Caution: the aleatoric bits overstate the real episodes' spread: the excess "
                "is the world model's own error, which its members share (so it is not "
                "counted as epistemic), not the env's noise."
            )
        elif real > factor * aleatoric and real - aleatoric >= least:
            text += (
                " Caution: the aleatoric bits understate the real episodes' spread: the world "
                "model has not learned all of the randomness of the env and the agent."
            )
        return text

    def mean_bits(self, per_live_step: bool = False) -> tuple[float, float]:
        """Aleatoric and epistemic time-mean bits (summed over dimensions), averaged over the
        report's start states; with ``per_live_step``, bits per step of the imagined episodes'
        life (``("uncertainty", "per_live_step", ·)``, from an assessment with
        ``episode_end``)."""
        part = _bits(self.uncertainty, per_live_step)
        return float(part.get("aleatoric").mean()), float(part.get("epistemic").mean())

    @property
    def start_states(self) -> Tensor | None:
        """The start states ``[B', S]`` (the batch flattened, in order), or ``None`` where
        :attr:`data` holds none (a report built by hand)."""
        if self.observation_key not in self.data.keys(True):
            return None
        observed = self.data.get(self.observation_key)
        return observed.reshape(-1, observed.shape[-1])

    @property
    def has_live_steps(self) -> bool:
        """Whether the report holds bits per step of the episodes' life (``episode_end``)."""
        return "per_live_step" in self.uncertainty.keys()

    def with_reference(
        self,
        reference: CompetencyReport | Reference,
        *,
        rise: float = 1.3,
        name: str | None = None,
        quantile: float = 0.95,
    ) -> CompetencyReport:
        """This report, with summaries that compare against ``reference``: a report of
        in-distribution start states (e.g. the training starts), or its :class:`Reference`.
        From a report, the reference keeps its mean bits and, with at least 10 start states,
        the level that a new in-distribution start stays at or below with probability
        ``quantile`` (one start state's part rose only above it): the conformal level of its
        start states (:func:`~rcvae_torchrl._conformal.conformal_level`), which with too few
        of them for ``quantile`` is their largest, and the probability it covers is kept."""
        if isinstance(reference, CompetencyReport):
            self._check_measured_alike(reference.measure, reference._imagined_steps())
            live = reference.has_live_steps and self.has_live_steps
            aleatoric, epistemic = reference.mean_bits(live)
            starts = reference.data.numel()
            name = name or "in-distribution reference"
            highs: dict[str, float | None] = {"aleatoric_high": None, "epistemic_high": None}
            if starts < _FEW_REFERENCE_STARTS:  # its bits are noisy: say on how few
                name = f"{name} (of only {starts} start state{'s' if starts > 1 else ''})"
            elif _is_number(quantile) and 0.0 < quantile < 1.0:  # else refused below
                part = _bits(reference.uncertainty, live)
                levels = {k: conformal_level(part.get(k), quantile) for k in _PARTS}
                highs = {f"{k}_high": level for k, (level, _) in levels.items()}
                quantile = levels["epistemic"][1]  # what the levels cover with these starts
            reference = Reference(
                aleatoric,
                epistemic,
                rise,
                name,
                live,
                **highs,
                quantile=quantile,
                measure=reference.measure,
                steps=reference._imagined_steps(),
                calibrated=reference.aleatoric_share is not None,
            )
        elif not isinstance(reference, Reference):
            raise TypeError(
                "reference: expected a CompetencyReport or a Reference, got "
                f"{type(reference).__name__}"
            )
        else:
            self._check_measured_alike(reference.measure, reference.steps)
        if reference.per_live_step and not self.has_live_steps:
            raise ValueError(
                "reference: its bits are per live step, but this report has none (assess with "
                "episode_end=True, or give time-mean bits)"
            )
        mine = self.aleatoric_share is not None
        if reference.calibrated is not None and reference.calibrated != mine:
            kinds = {True: "calibrated against real episodes", False: "the world model's own"}
            raise ValueError(
                f"reference: its split is {kinds[reference.calibrated]}, this report's "
                f"{kinds[mine]}: every rise or fall between them would be the calibration's; "
                "apply the same AleatoricShare to both reports, or to neither"
            )
        return replace(self, reference=reference)

    def _check_measured_alike(self, measure: Mapping[str, Any] | None, steps: int | None) -> None:
        """Refuse a reference (a report, or a :class:`Reference` that keeps how it was
        measured) whose bits were measured otherwise (other bins, bias correction, samples per
        member, or imagined steps): its bits are on another scale, and every ratio against them
        would read as a rise or a fall. What either side does not know is not compared; tuples
        and lists compare alike (a reference read back from JSON)."""
        pairs = {"imagined steps": (steps, self._imagined_steps())}
        if None in pairs["imagined steps"]:  # a report without bits per step
            del pairs["imagined steps"]
        if measure is not None and self.measure is not None:
            theirs, ours = _as_json(measure), _as_json(self.measure)  # as JSON reads them back
            keys = sorted(set(theirs) | set(ours))
            pairs.update({k: (theirs.get(k), ours.get(k)) for k in keys})
        differ = {k: pair for k, pair in pairs.items() if pair[0] != pair[1]}
        if differ:
            said = "; ".join(
                f"{k}: the reference's {theirs!r}, this report's {ours!r}"
                for k, (theirs, ours) in differ.items()
            )
            raise ValueError(
                f"reference: its bits were measured otherwise than this report's ({said}), so "
                "every ratio against them would read as a rise or a fall; assess both with one "
                "assessor (or give a Reference of bits measured as these are)"
            )

    def _imagined_steps(self) -> int | None:
        """T, the steps the bits were measured over (None where the report has no bits per
        step)."""
        total = self.uncertainty.get("total", None)
        return None if total is None else int(total.shape[self.data.batch_dims])

    def cause(self) -> str | None:
        """Over all start states, against the reference: the part that rose (``"epistemic"``
        or ``"aleatoric"``, the larger rise when both did), or ``None`` when neither did."""
        if self.reference is None:
            raise ValueError("reference: expected a report with a reference (with_reference)")
        return _cause(*self.mean_bits(self.reference.per_live_step), self.reference)

    def overall(self) -> str:
        """One paragraph over all start states: the mean forecast, and what changed against the
        reference (without one, the dominant part of the doubt), with how many start states
        rose one by one (a mean can rise by a few outliers); a passed forecast check last, or,
        with none attached, that none is."""
        p = float(self.competency.get("p_success").mean())
        live = self.reference is not None and self.reference.per_live_step
        aleatoric, epistemic = self.mean_bits(live)
        total = float(_bits(self.uncertainty, live).get("total").mean())
        n = self.batch_size.numel()
        text = f"Over {n} start states: mean P({self._outcome()}) = {p:.2f}. "
        warning = self.warning
        if self._split_doubted:  # as in each start's paragraph: the split is no evidence
            text += _unreliable_split_sentence(aleatoric, epistemic, total, _unit(live))
        elif self.reference is None:
            calibrated = self.aleatoric_share is not None
            text += _doubt_sentence(aleatoric, epistemic, total, calibrated, self._binned)
        else:
            novel = self.novel
            cautioned = 0 if novel is None else int(novel.sum())
            clause = (
                f"{cautioned} of the {n} start states, or their imagined states, are unlike the "
                "training states (below)"
                if cautioned
                else ""
            )
            causes = self._one_by_one_causes()
            text += _change_sentence(
                aleatoric, epistemic, self.reference, novel=clause, one_by_one=causes
            )
            text += (
                f" Start state by start state, the rise is epistemic in "
                f"{causes.count('epistemic')} of {len(causes)} and aleatoric in "
                f"{causes.count('aleatoric')}."
            )
        if self.model_caution and not self._split_doubted:
            text += f" Caution: {self.model_caution}."
        if self.aleatoric_share is not None:
            text += f" {self.aleatoric_share.describe()}"
        spread = self._spread_sentence(self.uncertainty, self.data.get("real_spread", None))
        text += f" {spread}" if spread else ""
        text += self._novel_count_sentence()
        disagree = self.members_disagree
        if disagree is not None and bool(disagree.any()):
            text += (
                f" In {int(disagree.sum())} of the {n} start states the members' own "
                f"P({self._outcome()}) differ beyond their imagined samples' chance (each "
                "paragraph gives their range): the intervals beside P leave that doubt out."
            )
        uncovered = self.uncovered
        if uncovered is not None and bool(uncovered.any()) and self.forecast_check.passed:
            text += (
                f" {int(uncovered.sum())} of the {n} start states are unlike those the forecast "
                "check was made on, which does not vouch for their forecasts."
            )
        if self.forecast_check is not None and self.forecast_check.passed:
            text += f" Forecast check {self._check_place}: {self.forecast_check.describe()}."
        elif self.forecast_check is None:
            text += (
                " No check of these forecasts against real episodes is attached to this "
                "report (with_forecast_check)."
            )
        moves = self.dynamics_check
        if moves is not None and moves.passed:
            text += f" Dynamics check: {moves.describe()}."
        return (f"Warning: {warning}. " if warning else "") + text

    @cached_property
    def members_disagree(self) -> Tensor | None:
        """``[*B]`` bool: start states whose members' own P(success) differ beyond the chance
        of their imagined samples (:func:`~rcvae_torchrl.competency.same_chance_p_value` below
        :data:`MEMBERS_ALPHA`; each such start's paragraph gives their range); ``None`` without
        the members' entries."""
        rows = self.data.reshape(-1)[self.competency_key]  # one start's competency per row
        p_values = [_members_p_value(rows[i]) for i in range(rows.shape[0])]
        if not p_values or p_values[0] is None:
            return None
        return (torch.tensor(p_values) < MEMBERS_ALPHA).reshape(self.batch_size)

    def _novel_count_sentence(self) -> str:
        """How many start states are unlike the training states, and in how many others the
        imagined states are (:attr:`novel`)."""
        novel = self.novel
        if novel is None:
            return f" {_NOT_JUDGED}" if self.novelty is None else ""
        starts = int(_novel_parts(self.data.get("novelty"), self.novelty)[0].sum())
        imagined = int(novel.sum()) - starts
        return (
            f" Novelty: {starts} of {novel.numel()} start states are unlike the states the "
            f"model was trained on, and {imagined} more imagine more of their states unlike "
            f"them than in-distribution episodes do (over {self.novelty.episode_level:.0%})"
            + (
                " or act outside the training actions."
                if getattr(self.novelty, "judges_actions", False)
                else "."
            )
        )

    def _one_by_one_causes(self) -> list[str | None]:
        """Each start state's rise, by the rule of its own paragraph (``None``: none): a mean
        over the starts can rise with a few outliers, or hide them."""
        part = _bits(self.uncertainty, self.reference.per_live_step)
        pairs = zip(
            part.get("aleatoric").reshape(-1).tolist(),
            part.get("epistemic").reshape(-1).tolist(),
            strict=True,
        )
        return [_cause(a, e, self.reference, one_start=True) for a, e in pairs]

    @property
    def batch_size(self) -> torch.Size:
        """``[*B]``, the start states' batch."""
        return self.data.batch_size

    @property
    def uncertainty(self) -> TensorDictBase:
        """The ``"uncertainty"`` entries."""
        return self.data.get(self.uncertainty_key)

    @property
    def competency(self) -> TensorDictBase:
        """The ``"competency"`` entries."""
        return self.data.get(self.competency_key)

    def __getitem__(self, index: Any) -> CompetencyReport:
        """The report of some start states (``data[index]``)."""
        return replace(self, data=self.data[index])

    def summary(self, index: int | tuple[int, ...] | None = None) -> str:
        """Plain-language summary (see the class docstring for the rules).

        Args:
            index: one start state (an int, or a tuple for a multi-dimensional batch, e.g.
                ``(0, 0)`` of a ``[4, 1]`` batch). ``None``: the one paragraph of an unbatched
                report, else one paragraph per start state, each headed ``Start state i:``.
        """
        if index is not None and not self.data.batch_dims:
            raise IndexError(
                f"index: this report is of one start state (batch ()), so it has no start "
                f"states to pick; got {index!r}: call summary() without an index"
            )
        if index is not None:
            try:
                one = self.data[index]
            except IndexError as err:
                raise IndexError(
                    f"index: expected one start state of the batch {tuple(self.batch_size)}, "
                    f"got {index!r}"
                ) from err
            if one.batch_dims:
                raise ValueError(
                    f"index: expected one start state of the batch {tuple(self.batch_size)}, "
                    f"got {index!r} (selects {tuple(one.batch_size)})"
                )
            return self._paragraph(one)
        if not self.data.batch_dims:
            return self._paragraph(self.data)
        return "\n\n".join(
            f"Start state {i[0] if len(i) == 1 else i}: {self._paragraph(self.data[i])}"
            for i in np.ndindex(*self.batch_size)
        )

    def __str__(self) -> str:
        return self.summary()

    def _outcome(self) -> str:
        """What P() is of: ``success within 30 s``, or ``no failure for 30 s`` (survival)."""
        duration = _duration(self.time_limit, self.dt, self.time_unit)
        return f"no failure for {duration}" if self.survival else f"success within {duration}"

    def _paragraph(self, one: TensorDictBase) -> str:
        competency, uncertainty = one.get(self.competency_key), one.get(self.uncertainty_key)
        warning = self.warning
        flags = self._novel_flags(one)
        sentences = [
            _success_sentence(
                float(competency.get("p_success")),
                float(competency.get("p_success_low")),
                float(competency.get("p_success_high")),
                self.confidence,
                self._outcome(),
            ),
            _members_sentence(competency, self._outcome()),
            self._settled_sentence(one),
            self._unchecked_sentence(),
            self._per_start_caution(),
            self._uncovered_caution(one),
            self._novelty_sentence(one, flags),
            self._uncertainty_sentence(
                uncertainty, self._split_doubted, flags, self._actions_only(one, flags)
            ),
            "" if self.aleatoric_share is None else self.aleatoric_share.describe(),
            self._spread_sentence(uncertainty, one.get("real_spread", None)),
        ]
        if "peak_step" in uncertainty.keys():
            sentences.append(
                _dims_sentence(
                    uncertainty.get(("time_mean", "total")),
                    uncertainty.get("peak_step"),
                    self.dim_names,
                    (self.dt, self.time_unit),
                    self.top_k,
                    _imagined_samples(competency),
                )
            )
        if warning:
            sentences.insert(0, f"Warning: {warning}.")
        return " ".join(s for s in sentences if s)

    def _settled_sentence(self, one: TensorDictBase) -> str:
        """A start state already in the success or the failure region (``("start_state",
        ·)``, absent from older reports): its outcome is mostly settled before the agent acts."""
        entries = one.get("start_state", None)
        if entries is None:
            return ""
        for region in ("success", "failure"):
            if bool(entries.get(f"in_{region}")):
                return (
                    f"The start state already lies in the {region} region: its outcome is "
                    "mostly settled before the agent acts, and says little of the agent."
                )
        return ""

    def _unchecked_sentence(self) -> str:
        """A forecast with no check against real episodes attached: not ``trustworthy``, said
        beside each start's P (a reader of one start's paragraph does not see
        :meth:`overall`)."""
        if self.forecast_check is not None:
            return ""
        return (
            "Unchecked: no check of these forecasts against real episodes is attached "
            "(with_forecast_check), so nothing shows this one right."
        )

    @cached_property
    def _check_place(self) -> str:
        """Where the attached forecast check was made, against this report's start states: "on
        other start states" (none of these among its own, or its own not known), "on these
        start states" (all of them), or on some of them."""
        own, starts = getattr(self.forecast_check, "start_states", None), self.start_states
        if own is None or starts is None:
            return "on other start states"
        mine = starts.detach().cpu().double()
        if mine.shape[-1] != own.shape[-1]:
            return "on other start states"
        among = torch.cdist(mine, own.double(), p=math.inf).le(1e-6).any(-1)
        if bool(among.all()):
            return "on these start states"
        if not bool(among.any()):
            return "on other start states"
        return f"on {int(among.sum())} of these {among.numel()} start states and others"

    def _per_start_caution(self) -> str:
        """A passed forecast check whose forecasts miss their own starts' rates beyond chance
        (right on average, not per task): said beside each start's P, whose interval covers
        only the imagined samples' chance."""
        check = self.forecast_check
        if check is None or not check.passed or not getattr(check, "scattered", False):
            return ""
        return (
            f"Caution: on other start states the forecasts, right on average, missed their own "
            f"start's real rate by about {check.excess_error:.2f} beyond chance; the interval "
            "above covers only the imagined samples' chance."
        )

    def _uncovered_caution(self, one: TensorDictBase) -> str:
        """One start state outside the start states a passed forecast check was made on."""
        check = self.forecast_check
        if check is None or not check.passed or getattr(check, "start_states", None) is None:
            return ""
        covered = check.covers(one.get(self.observation_key).reshape(1, -1))
        if covered is None or bool(covered.all()):
            return ""
        return (
            "Caution: this start state is unlike those the forecast check was made on, which "
            "does not vouch for its forecast."
        )

    def _actions_only(self, one: TensorDictBase, flags: tuple[bool, bool]) -> bool:
        """Whether the imagined episode's caution (``flags[1]``) is for its actions alone, its
        states no more unlike the training states than in-distribution episodes' are."""
        if not flags[1]:
            return False
        return not bool(one.get(("novelty", "imagined")) > self.novelty.episode_level)

    def _novel_flags(self, one: TensorDictBase) -> tuple[bool, bool]:
        """One start state's two novelty cautions (start, imagined episode; :attr:`novel`),
        neither without a novelty check."""
        if self.novelty is None or "novelty" not in one.keys():
            return False, False
        start, imagined = _novel_parts(one.get("novelty"), self.novelty)
        return bool(start), bool(imagined)

    def _novelty_sentence(self, one: TensorDictBase, flags: tuple[bool, bool]) -> str:
        """A start state unlike the training states, and in which dimensions; or imagined
        states unlike them in a larger share than in-distribution episodes' states are
        (``flags``: :meth:`_novel_flags`)."""
        start, imagined = flags
        if self.novelty is None:
            return _NOT_JUDGED
        if not (start or imagined):
            return ""
        acting = ""
        if bool(_unseen_acting(one.get("novelty"), self.novelty)):
            acting = (
                f" Caution: {float(one.get(('novelty', 'actions'))):.0%} of the imagined steps "
                "take actions outside those the model was trained on (past the range its "
                "training actions took, or between the values they took), where in-distribution "
                f"episodes have at most {self.novelty.action_level:.0%}: the model has not seen "
                "their effect, and the forecast extrapolates, however much the members agree."
            )
        share = float(one.get(("novelty", "imagined")))
        states = share > self.novelty.episode_level
        if start:
            state = one.get(self.observation_key)
            detail = self.novelty.describe(state, self.dim_names, start=True)
            also = f", and so are {share:.0%} of its imagined states" if states else ""
            return (
                f"Caution: the start state is unlike the states the model was trained on "
                f"({detail}){also}: the forecast extrapolates, however much the members agree."
                + acting
            )
        if not states:
            return acting.lstrip()
        level = self.novelty.episode_level  # the imagined states alone are cautioned
        usual = (
            f"where {self.novelty.episode_quantile:.0%} of in-distribution episodes have "
            f"at most {level:.0%}"
            if self.novelty.episodes_measured
            else f"more than ten times the share of held-out states ({level:.0%})"
        )
        leaves = int(one.get(("novelty", "leaves"), -1))  # absent in older reports
        where = (
            ": the forecast extrapolates there"
            if leaves < 0
            else f". The first step at which more than half of the samples are unlike them "
            f"is {_when(leaves, self.dt, self.time_unit)}: the forecast extrapolates from there"
        )
        return (
            f"Caution: {share:.0%} of the imagined states are unlike the states the model was "
            f"trained on, {usual}{where}, however much the members agree." + acting
        )

    def _uncertainty_sentence(
        self,
        uncertainty: TensorDictBase,
        warned: bool,
        flags: tuple[bool, bool] = (False, False),
        actions_only: bool = False,
    ) -> str:
        # the bits the reference compares (per live step where it does), in every sentence
        live = self.reference is not None and self.reference.per_live_step
        part = _bits(uncertainty, live)
        aleatoric, epistemic, total = (
            float(part.get(k)) for k in ("aleatoric", "epistemic", "total")
        )
        if warned:  # a model that failed its checks: its split is not evidence
            return _unreliable_split_sentence(aleatoric, epistemic, total, _unit(live))
        caution = f" Caution: {self.model_caution}." if self.model_caution else ""
        if self.reference is None:
            calibrated = self.aleatoric_share is not None
            return _doubt_sentence(aleatoric, epistemic, total, calibrated, self._binned) + caution
        start, imagined = flags  # the novelty cautions (:meth:`_novel_flags`)
        novel_clause = (
            "the start is unlike the training states (above)"
            if start
            else "its imagined actions are unlike the training actions (above)"
            if imagined and actions_only
            else "its imagined states are unlike the training states (above)"
            if imagined
            else ""
        )
        return (
            _change_sentence(
                aleatoric, epistemic, self.reference, one_start=True, novel=novel_clause
            )
            + caution
        )


#: what a report says where its world model has no novelty check
_NOT_JUDGED = (
    "Novelty not judged: the world model has no novelty check (ensemble.novelty, which "
    "train_ensemble fits; or StateNovelty.from_episodes), so nothing here says whether the "
    "start states and imagined states are like those it was trained on."
)


def _novel_parts(entries: TensorDictBase, novelty: Any) -> tuple[Tensor, Tensor]:
    """The two cautions of the novelty check (``"novelty"`` ``entries``): the start state
    beyond the start level, and the imagined episode beyond the episode level, or its
    actions outside the training actions' support beyond the action level."""
    start, imagined = entries.get("start") > 1, entries.get("imagined") > novelty.episode_level
    return start, imagined | _unseen_acting(entries, novelty)


def _unseen_acting(entries: TensorDictBase, novelty: Any) -> Tensor:
    """``[*B]`` bool: imagined episodes whose share of steps with actions outside the training
    actions' support (``"actions"``) is above the check's ``action_level``; all ``False``
    where either is not known (a check of states alone, an older report)."""
    shares = entries.get("actions", None)
    level = getattr(novelty, "action_level", math.nan)
    if shares is None or not math.isfinite(level):
        return torch.zeros_like(entries.get("start"), dtype=torch.bool)
    return shares > level


def _success_sentence(p: float, low: float, high: float, confidence: float, outcome: str) -> str:
    """``P(success within 30 s) = 0.84 (95% interval 0.78–0.89).``"""
    return f"P({outcome}) = {p:.2f} ({confidence:.0%} interval {low:.2f}–{high:.2f})."


#: The level at which the members' own P(success) are said to differ beyond the chance of their
#: imagined samples (:func:`~rcvae_torchrl.competency.same_chance_p_value`).
MEMBERS_ALPHA = 0.01


def _members_p_value(competency: TensorDictBase) -> float | None:
    """Whether one start's members' own P(success) differ beyond the chance of their imagined
    samples: :func:`~rcvae_torchrl.competency.same_chance_p_value` of them; ``None`` without
    the members' entries (for several starts, the test of all their members together)."""
    members, success = competency.get("p_success_member", None), competency.get("success", None)
    if members is None or success is None:
        return None
    return same_chance_p_value(members, int(success.shape[-1]))


def _members_sentence(competency: TensorDictBase, outcome: str) -> str:
    """Where the members' own P differ beyond their imagined samples' chance
    (:data:`MEMBERS_ALPHA`), what the interval beside P leaves out: the members' own doubt
    about the outcome (a cart-pole swing-up's members gave one start 0.20 to 0.75 while its
    state's bits read "most of the doubt is aleatoric", 98 % of them). '' otherwise, or
    without the members' entries."""
    p_value = _members_p_value(competency)
    if p_value is None or not p_value < MEMBERS_ALPHA:
        return ""
    members = competency.get("p_success_member")
    low, high = float(members.min()), float(members.max())
    return (
        f"The members disagree on it: their own P({outcome}) run from {low:.2f} to {high:.2f}, "
        f"more than their imagined samples' chance allows (p = {p_value:.2g}): part of the "
        "doubt about this outcome is what the model has not learned (epistemic), which the "
        "interval does not cover."
    )


def _doubt_sentence(
    aleatoric: float,
    epistemic: float,
    total: float,
    calibrated: bool = False,
    binned: bool = False,
) -> str:
    """The dominant uncertainty type (larger of the two; a tie is aleatoric) and its share;
    its cause as the world model's own split tells it, or as a split ``calibrated`` against
    real episodes does. Bits of ``binned`` states (the histogram estimator's) below
    :data:`LITTLE_DOUBT_BITS` in all: little doubt, no part and no cause named."""
    if aleatoric == epistemic == total == 0.0:
        return "No doubt about the imagined states (0.00 bits): all samples agree."
    if binned and total < LITTLE_DOUBT_BITS:  # which of two small parts is larger is chance
        return (
            f"Little doubt about the imagined states ({total:.2f} bits, under "
            f"{LITTLE_DOUBT_BITS:g}: at the declared resolution they mostly share their bins): "
            f"{aleatoric:.2f} aleatoric and {epistemic:.2f} epistemic."
        )
    kind, bits = ("epistemic", epistemic) if epistemic > aleatoric else ("aleatoric", aleatoric)
    reason = (_CALIBRATED_REASONS if calibrated else _REASONS)[kind]
    return f"Most of the doubt is {kind} ({bits:.2f} of {total:.2f} bits): {reason}."


def _unreliable_split_sentence(
    aleatoric: float, epistemic: float, total: float, unit: str = "bits"
) -> str:
    """The bits without a cause: a model that failed its self-checks (or has none) may call
    missing knowledge chance (an unlearned dimension spread by its noise) or hide it (an
    overconfident one)."""
    return (
        f"Uncertainty: {aleatoric:.2f} {unit} aleatoric and {epistemic:.2f} epistemic of "
        f"{total:.2f}; with the warning above this split does not say "
        "whether more data would help."
    )


def _unit(per_live_step: bool) -> str:
    return "bits per live step" if per_live_step else "bits"


def _ratio(value: float, reference: float) -> float:
    if reference > 0:
        return value / reference
    return float("inf") if value > 0 else 1.0


def _ratios(aleatoric: float, epistemic: float, reference: Reference) -> dict[str, float]:
    """Each part over the reference's (epistemic first)."""
    return {
        "epistemic": _ratio(epistemic, reference.epistemic),
        "aleatoric": _ratio(aleatoric, reference.aleatoric),
    }


def _change_sentence(
    aleatoric: float,
    epistemic: float,
    reference: Reference,
    one_start: bool = False,
    novel: str = "",
    one_by_one: Sequence[str | None] | None = None,
) -> str:
    """What changed against the reference, and which part rose (the larger rise); for
    ``one_start``, a part rose only above the reference's start states' spread. Where the
    novelty check cautioned (``novel``: which starts, as a clause) and the doubt is as in the
    reference, it is said to be so despite the caution, not to show no sign of unseen
    states. A mean over start states whose part rose while none of them rose beyond the
    reference's spread (``one_by_one``: each start's rise) is said to be within that spread:
    a mean of small bits rises 1.3x with the draw of its starts, and no cause is named."""
    ratios = _ratios(aleatoric, epistemic, reference)
    values = {"epistemic": epistemic, "aleatoric": aleatoric}
    refs = {"epistemic": reference.epistemic, "aleatoric": reference.aleatoric}
    unit = _unit(reference.per_live_step)
    shown = {k: _shown(ratios[k], reference.rise) for k in ratios}
    verbs = {k: _verb(float(shown[k])) for k in shown}
    # the second part takes the first's verb unless its own differs ("stayed at" after
    # "rose"); a fall is always said
    if verbs["aleatoric"] == verbs["epistemic"] != "fell to ":
        verbs["aleatoric"] = ""
    parts = [
        f"{k} {'uncertainty ' if i == 0 else ''}{verbs[k]}"
        f"{shown[k]}x ({refs[k]:.2f} -> {values[k]:.2f} {unit})"
        for i, k in enumerate(("epistemic", "aleatoric"))
    ]
    neither = f"neither part rose {reference.rise:g}x or more"
    text = f"Against the {reference.name}, {parts[0]} and {parts[1]}"
    cause = _cause(aleatoric, epistemic, reference, one_start)
    unconfirmed = (
        cause is not None
        and one_by_one is not None
        and _high(reference, cause) is not None
        and cause not in one_by_one
    )
    if cause is not None and not unconfirmed:
        rose = _CALIBRATED_ROSE if reference.calibrated else _ROSE
        return text + f": the rise is {cause}, {rose[cause]}."
    within = [
        k
        for k in ("epistemic", "aleatoric")
        if ratios[k] >= reference.rise and _high(reference, k) is not None
    ]
    if within:  # risen against the mean, not above the spread of the reference's starts
        levels = " and ".join(f"{_high(reference, k):.2f} {k} {unit}" for k in within)
        return (
            text + f": neither part rose beyond the reference's own start states: "
            f"{reference.quantile:.0%} of such starts stay at or below {levels}."
        )
    fell = [k for k in ("epistemic", "aleatoric") if ratios[k] * reference.rise <= 1]
    if fell:
        return text + f": {neither}, the {' and '.join(fell)} doubt fell below the reference's."
    if novel:
        return text + (
            f": {neither}, the doubt is as in the reference although {novel}: the "
            "members agree where none has data."
        )
    return text + (
        f": {neither}, the doubt is as in the reference (no sign of states the model has not "
        "seen, which does not rule them out: a check against real episodes can)."
    )


def _shown(ratio: float, rise: float) -> str:
    """``ratio`` with one decimal, or two where one would put it on the other side of a
    threshold the sentence judges it by (``rise``, and ``1 / rise`` for a fall): 1.26 is
    not shown as 1.3x beside "neither part rose"."""
    one = round(ratio, 1)
    misleads = (one >= rise) != (ratio >= rise) or (one * rise <= 1) != (ratio * rise <= 1)
    return f"{ratio:.2f}" if misleads else f"{one:.1f}"


def _verb(ratio: float) -> str:
    """``rose`` / ``fell to`` / ``stayed at`` by the ratio as printed: a ratio shown as 1.0x
    neither rose nor fell."""
    if ratio < 1:
        return "fell to "
    return "rose " if ratio > 1 else "stayed at "


def _high(reference: Reference, part: str) -> float | None:
    """The level ``reference.quantile`` of its start states stay at or below, for ``part``."""
    return reference.aleatoric_high if part == "aleatoric" else reference.epistemic_high


def _cause(
    aleatoric: float, epistemic: float, reference: Reference, one_start: bool = False
) -> str | None:
    """The part at least ``rise`` times the reference (the larger rise when both are); for
    ``one_start``, also above the level of its start states' ``quantile`` where known."""
    ratios = _ratios(aleatoric, epistemic, reference)
    values = {"epistemic": epistemic, "aleatoric": aleatoric}

    def risen(k: str) -> bool:
        high = _high(reference, k) if one_start else None
        return ratios[k] >= reference.rise and (high is None or values[k] > high)

    parts = [k for k in ratios if risen(k)]
    return max(parts, key=lambda k: ratios[k]) if parts else None


def _bits(uncertainty: TensorDictBase, per_live_step: bool) -> TensorDictBase:
    """The ``"summary"`` bits, or with ``per_live_step`` the ``"per_live_step"`` ones."""
    if not per_live_step:
        return uncertainty.get("summary")
    if "per_live_step" not in uncertainty.keys():
        raise ValueError(
            "per_live_step: the report has no bits per live step (assess with episode_end=True)"
        )
    return uncertainty.get("per_live_step")


def _imagined_samples(competency: TensorDictBase) -> int | None:
    """``E·N``, the imagined samples of one start (its ``"success"`` ``[E, N]``)."""
    success = competency.get("success", None)
    return None if success is None else int(success.shape[-2:].numel())


#: a dimension's time-mean bits at this share of log2 of the samples or more is named as at
#: the samples' ceiling
_CEILING_SHARE = 0.95


def _dims_sentence(
    time_mean: Tensor,
    peak_step: Tensor,
    names: Sequence[str],
    step: tuple[float | None, str],
    top_k: int,
    samples: int | None = None,
) -> str:
    """The ``top_k`` dimensions by time-mean bits ``[D]`` (above 0) with their peak ``[D]``
    (a time, with ``step = (dt, unit)``); one whose bits reach the ceiling of the ``samples``
    imagined (log2 of their number, where every sample has a bin of its own) is said to be
    there: its bits count the samples, not their spread."""
    order = torch.argsort(time_mean, descending=True, stable=True)[:top_k].tolist()
    ceiling = math.log2(samples) if samples and samples > 1 else math.inf
    parts = []
    for d in order:
        bits = float(time_mean[d])
        if bits <= 0:
            continue
        at = (
            f"; at the ceiling of its {samples} samples, log2 {samples} = {ceiling:.2f} bits: "
            "each sample in a bin of its own, the bins too narrow to measure its spread"
            if bits >= _CEILING_SHARE * ceiling
            else ""
        )
        parts.append(
            f"{names[d]} (time mean {bits:.2f} bits, peak at {_when(int(peak_step[d]), *step)}{at})"
        )
    return f"Most uncertain: {', '.join(parts)}." if parts else ""


def _duration(steps: int, dt: float | None, unit: str = "s") -> str:
    return f"{steps} steps" if dt is None else f"{round(steps * dt, 6):g} {unit}"


def _when(index: int, dt: float | None, unit: str = "s") -> str:
    """Index t of the time axis holds s_{t+1}: step t + 1, time (t + 1)·dt."""
    return f"step {index + 1}" if dt is None else f"t = {round((index + 1) * dt, 6):g} {unit}"

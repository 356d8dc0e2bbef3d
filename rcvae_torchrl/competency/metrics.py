"""Competency metrics over imagined rollouts, as TensorDict modules with configurable keys.

Both modules read a TensorDict with batch dims ``[E, N, *B, T]`` (ensemble member, sample per
member, start state(s), time) holding observations ``[E, N, *B, T, D]`` and return a new
TensorDict with no batch dims: :class:`UncertaintyMetric` under ``"uncertainty"``,
:class:`SuccessMetric` under ``"competency"`` (keys renamed with ``set_keys``, as TorchRL's
losses do). They are thin wrappers over
:func:`~rcvae_torchrl.competency.decompose_uncertainty` and the outcome functions.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

from rcvae_torchrl._spread import spread_steps
from rcvae_torchrl.competency import _checks
from rcvae_torchrl.competency._keys import KeyedModule
from rcvae_torchrl.competency.boundary import SuccessBoundary
from rcvae_torchrl.competency.decomposition import (
    ESTIMATORS,
    check_estimator_args,
    decompose_uncertainty,
)
from rcvae_torchrl.competency.entropy import BinWidth
from rcvae_torchrl.competency.intervals import binomial_interval
from rcvae_torchrl.competency.outcome import (
    outcome_uncertainty,
    success_probability,
    time_to_success,
)

__all__ = ["SuccessMetric", "UncertaintyMetric", "bits_per_live_step", "rescale_aleatoric"]

_LAYOUT = "[E, N, *B, T, D]"
#: start states (and steps spread over the horizon) in which bins of their own are looked for
_SATURATION_ROWS = 16


def bits_per_live_step(time_mean: Tensor, live: Tensor) -> Tensor:
    """Bits per step of the imagined episodes' life: ``time_mean`` ``[*B]`` (bits averaged
    over the ``T`` steps of the horizon, ended episodes counted as certain) times ``T`` over
    the steps an episode runs on average, ``live`` ``[*B, T]`` being the share of episodes
    still running at each step. A time mean also measures how long the episodes last; this
    takes that out.

    Example:
        >>> live = torch.tensor([1.0, 1.0, 0.0, 0.0])  # every episode ends after 2 of 4 steps
        >>> float(bits_per_live_step(torch.tensor(0.5), live))  # 2 bits over 2 live steps
        1.0
    """
    steps = live.sum(dim=-1).clamp_min(torch.finfo(live.dtype).tiny)
    return time_mean * live.shape[-1] / steps


def rescale_aleatoric(uncertainty: TensorDictBase, share: Tensor) -> TensorDictBase:
    """:class:`UncertaintyMetric`'s entries with each dimension's aleatoric bits times its
    ``share`` ``[D]`` (in [0, 1]) and the rest of them counted as epistemic: the total is
    kept, ``epistemic = total - share * aleatoric`` at every step, in the time means, the
    summaries (per live step too) and ``"by_dim"``, where they are. Per-dimension entries
    only (``"total"`` ``[*B, T, D]``), as the histogram estimator gives them.

    Example:
        >>> bits = UncertaintyMetric(bin_width=0.5)(
        ...     TensorDict(observation=torch.randn(2, 8, 3, 4, 2))
        ... )["uncertainty"]
        >>> half = rescale_aleatoric(bits, torch.tensor([0.5, 1.0]))
        >>> bool(torch.allclose(half["total"], bits["total"]))
        True
    """
    total, aleatoric = uncertainty.get("total"), uncertainty.get("aleatoric")
    if share.ndim != 1 or total.ndim < 2 or share.shape[0] != total.shape[-1]:
        raise ValueError(
            f"share: expected one share per state dimension [{total.shape[-1]}] of bits "
            f"[*B, T, D], got share {tuple(share.shape)} for bits {tuple(total.shape)}"
        )
    if not bool(((share >= 0) & (share <= 1)).all()):  # NaN fails too
        raise ValueError(f"share: expected shares in [0, 1], got {share.tolist()}")
    share = share.to(total)
    out = uncertainty.clone(recurse=False)

    def split(entries: TensorDictBase, scale: Tensor | float) -> TensorDictBase:
        entries = entries.clone(recurse=False)
        entries.set("aleatoric", entries.get("aleatoric") * scale)
        entries.set("epistemic", entries.get("total") - entries.get("aleatoric"))
        return entries

    out.set("aleatoric", aleatoric * share)
    out.set("epistemic", total - aleatoric * share)
    old = aleatoric.mean(-2)
    if "time_mean" in uncertainty.keys():
        old = uncertainty.get(("time_mean", "aleatoric"))
        out.set("time_mean", split(uncertainty.get("time_mean"), share))
    # the summaries reduce the time means over the dimensions (a sum or a mean): scaled alike
    kept = (old * share).sum(-1) / old.sum(-1).clamp_min(torch.finfo(old.dtype).tiny)
    for key in ("summary", "per_live_step"):
        if key in uncertainty.keys():
            out.set(key, split(uncertainty.get(key), kept))
    if "by_dim" in uncertainty.keys():
        by_dim = uncertainty.get("by_dim").clone(recurse=False)
        for i, name in enumerate(by_dim.keys()):
            by_dim.set(name, split(by_dim.get(name), share[i]))
        out.set("by_dim", by_dim)
    return out


def _observation(tensordict: TensorDictBase, key: NestedKey) -> Tensor:
    """``tensordict[key]`` ``[E, N, *B, T, D]``: present, a floating tensor, finite, with at
    least two members and one sample, time step and dimension (an empty batch ``*B`` is
    allowed)."""
    if not isinstance(tensordict, TensorDictBase):
        raise TypeError(f"tensordict: expected a TensorDict, got {type(tensordict).__name__}")
    name = f"tensordict[{key!r}]"
    obs = tensordict.get(key, None)
    if obs is None:
        raise KeyError(
            f"tensordict: expected an {key!r} entry {_LAYOUT}, got keys "
            f"{sorted(map(str, tensordict.keys(include_nested=True, leaves_only=True)))}"
        )
    _checks.check_tensor(name, obs)
    _checks.check_min_rank(name, obs, 4, _LAYOUT)
    _checks.check_floating(name, obs)
    for axis, label, least in ((0, "E", 2), (1, "N", 1), (-2, "T", 1), (-1, "D", 1)):
        if obs.shape[axis] < least:
            raise ValueError(
                f"{name}: expected shape {_LAYOUT} with {label} >= {least}, got {tuple(obs.shape)}"
            )
    _checks.check_finite(name, obs)
    return obs


class UncertaintyMetric(KeyedModule):
    """Total / aleatoric / epistemic uncertainty of imagined observations, in bits.

    The paper's equations 2 and 3 per time step (its Figure 1) and averaged over time (its
    Table 1), for each observation dimension. Output entries under ``"uncertainty"``, each a
    sub-TensorDict with ``"total"``, ``"aleatoric"`` and ``"epistemic"``:

    - the three entries themselves: per time step, ``[*B, T, D]`` (``[*B, T]`` for joint
      estimators: ``"knn"``, ``"mixture"``, ``"gaussian"`` with ``joint=True``);
    - ``"time_mean"``: averaged over time, ``[*B, D]`` (``[*B]`` joint);
    - ``"summary"``: averaged over time and reduced over dimensions with ``dim_reduction``
      (``"sum"``: bits of the product of the per-dimension marginals, an upper bound on the
      joint entropy; ``"mean"``: bits per dimension), ``[*B]``. The paper's Table 1 reports one
      number of bits per condition without saying how it combines dimensions; the per-dimension
      ``time_mean`` lets you pick the dimensions yourself. Joint estimators give the time mean;
    - ``"by_dim"`` (only with ``dim_names``): ``{name: {"total", "aleatoric", "epistemic"}}``
      time series ``[*B, T]`` for each named dimension.

    With ``episode_end=True`` the metric also reads ``tensordict["ended"]`` (bool
    ``[E, N, *B, T]``, e.g. from :meth:`SuccessBoundary.ended_over_time`): samples of episodes
    that have ended count in one shared terminal bin (histogram estimator only; see
    :func:`~rcvae_torchrl.competency.decompose_uncertainty`). A step where every episode has
    ended has no uncertainty, so the time means then also measure how long the episodes last;
    two more entries measure the doubt while they run. The terminal bin is in every dimension:
    at a step where a share ``live`` of the samples runs, a dimension's bits are ``h(live) +
    live·H(running samples)``, ``h`` the binary entropy of whether an episode has ended, so a
    ``"sum"`` over dimensions counts that part once per dimension (a dimension constant within
    an episode, such as a goal, has exactly that part and no other):

    - ``"live"`` ``[*B, T]``: the share of the ``E·N`` imagined episodes still running;
    - ``"per_live_step"``: the ``"summary"`` bits summed over time and divided by the steps the
      episodes run on average (the sum of ``"live"``), ``[*B]``: bits per step of an episode's
      life, which episodes that end sooner or later than others' do not change.

    Args:
        bin_width: histogram bin width, scalar or ``[D]`` (required by ``"histogram"``; optional
            discretisation for ``"gaussian"`` / ``"knn"``).
        estimator: ``"histogram"`` (default), ``"gaussian"``, ``"knn"`` or ``"mixture"``.
        dim_names: optional names of the ``D`` observation dimensions.
        dim_reduction: ``"sum"`` or ``"mean"`` for ``"summary"``.
        episode_end: read the ``ended`` entry and give ended episodes a terminal bin.
        **estimator_args: other estimator arguments (e.g. ``k``, ``joint``, ``bound``).

    Example:
        >>> metric = UncertaintyMetric(bin_width=0.1, dim_names=["x", "y"])
        >>> obs = torch.randn(5, 20, 3, 8, 2)  # E, N, B, T, D
        >>> rollout = TensorDict({"observation": obs}, batch_size=obs.shape[:-1])
        >>> out = metric(rollout)
        >>> out["uncertainty", "total"].shape, out["uncertainty", "time_mean", "epistemic"].shape
        (torch.Size([3, 8, 2]), torch.Size([3, 2]))
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable keys: ``observation`` and ``ended`` (inputs), ``uncertainty`` (output
        root)."""

        observation: NestedKey = "observation"
        ended: NestedKey = "ended"
        uncertainty: NestedKey = "uncertainty"

    _inputs = ("observation",)
    _outputs = ("uncertainty",)
    tensor_keys: _AcceptedKeys
    bin_width: Tensor | None

    def __init__(
        self,
        bin_width: BinWidth | None = None,
        estimator: str = "histogram",
        dim_names: Sequence[str] | None = None,
        dim_reduction: Literal["sum", "mean"] = "sum",
        episode_end: bool = False,
        **estimator_args: Any,
    ) -> None:
        super().__init__()
        _checks.check_choice("estimator", estimator, tuple(ESTIMATORS))
        _checks.check_choice("dim_reduction", dim_reduction, ("sum", "mean"))
        if episode_end and estimator != "histogram":
            raise ValueError(
                f"episode_end: only the histogram estimator has a bin for ended episodes, got "
                f"estimator={estimator!r}"
            )
        if estimator == "histogram" and bin_width is None:
            raise ValueError(
                "bin_width: expected a positive width for the histogram estimator, got None"
            )
        if estimator == "mixture" and bin_width is not None:
            raise ValueError(
                f"bin_width: expected None for the mixture estimator (it has no bins), "
                f"got {bin_width!r}"
            )
        check_estimator_args(estimator, estimator_args)
        _checks.check_bool("episode_end", episode_end)
        if isinstance(bin_width, str):
            raise TypeError(f"bin_width: expected a number or a tensor [D], got {bin_width!r}")
        width = None if bin_width is None else torch.as_tensor(bin_width, dtype=torch.float32)
        self.register_buffer("bin_width", width)
        self.estimator = estimator
        self.estimator_args = estimator_args
        self.dim_names = None if dim_names is None else _checks.check_names("dim_names", dim_names)
        self.dim_reduction = dim_reduction
        self.episode_end = bool(episode_end)
        self._warned_saturated = False  # bins too narrow for the samples: said once
        self._sync_keys()

    def _sync_keys(self) -> None:
        super()._sync_keys()
        if getattr(self, "episode_end", False):
            self.in_keys = [*self.in_keys, self.tensor_keys.ended]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Decompose ``tensordict[observation]`` ``[E, N, *B, T, D]``; see the class docstring."""
        obs = _observation(tensordict, self.tensor_keys.observation)
        if self.dim_names is not None and len(self.dim_names) != obs.shape[-1]:
            raise ValueError(
                f"dim_names: expected {obs.shape[-1]} names (one per observation dimension), "
                f"got {len(self.dim_names)}"
            )
        args = dict(self.estimator_args)
        if self.bin_width is not None:
            args["bin_width"] = self.bin_width
        if self.episode_end:
            key = self.tensor_keys.ended
            if key not in tensordict.keys(include_nested=True):
                raise KeyError(
                    f"tensordict: expected an {key!r} entry (bool [E, N, *B, T]) with "
                    f"episode_end=True, got keys {sorted(map(str, tensordict.keys()))}"
                )
            args["ended"] = tensordict.get(key)
        parts = decompose_uncertainty(obs, self.estimator, **args).as_dict()
        per_dim = parts["total"].ndim == obs.ndim - 2
        if self.estimator == "histogram" and not self._warned_saturated:
            self._warn_saturated(obs, args.get("ended"))
        out = TensorDict(parts)
        time_axis = -2 if per_dim else -1
        out["time_mean"] = TensorDict({k: v.mean(dim=time_axis) for k, v in parts.items()})
        out["summary"] = TensorDict({k: self._summary(v, per_dim) for k, v in parts.items()})
        if self.episode_end:
            live = (~args["ended"]).to(obs.dtype).mean(dim=(0, 1))  # [*B, T]
            out["live"] = live
            out["per_live_step"] = TensorDict(
                {k: bits_per_live_step(v, live) for k, v in out["summary"].items()}
            )
        if per_dim and self.dim_names is not None:
            out["by_dim"] = TensorDict(
                {
                    name: TensorDict({k: v[..., i] for k, v in parts.items()})
                    for i, name in enumerate(self.dim_names)
                }
            )
        result = TensorDict()
        result.set(self.tensor_keys.uncertainty, out)
        return result

    def _warn_saturated(self, obs: Tensor, ended: Tensor | None) -> None:
        """Warn (once per metric) when a dimension's bins are so narrow that each member's
        samples fall in bins of their own at most steps (where no sample has ended; looked at
        in up to :data:`_SATURATION_ROWS` start states and as many steps spread over the
        horizon): its
        bits are then ``log2 N``, a count of the samples, not a measure of their spread (a
        width far below the samples' spread, or too few samples per member for it)."""
        samples, dims = obs.shape[1], obs.shape[-1]
        if samples < 2:
            return
        flat = obs.reshape(*obs.shape[:2], -1, *obs.shape[-2:])  # [E, N, B', T, D]
        if flat.shape[2] == 0 or flat.shape[3] == 0:  # no start state or no step to look at
            return
        rows = spread_steps(flat.shape[2], _SATURATION_ROWS)
        steps = spread_steps(flat.shape[3], _SATURATION_ROWS)
        picked = flat[:, :, rows][:, :, :, steps]
        bins = torch.floor(picked / self.bin_width.to(picked).expand(dims))
        own = (bins.sort(dim=1).values.diff(dim=1) != 0).all(dim=1).all(dim=0)  # [B', T', D]
        running = torch.ones(own.shape[:-1], dtype=torch.bool, device=own.device)
        if ended is not None:
            running = ~ended.reshape(*ended.shape[:2], -1, ended.shape[-1])[:, :, rows][
                :, :, :, steps
            ].any(dim=1).any(dim=0)
        if not bool(running.any()):
            return
        share = (own & running[..., None]).flatten(0, 1).float().sum(0) / running.sum()
        saturated = (share > 0.5).nonzero().flatten().tolist()
        if not saturated:
            return
        names = self.dim_names or tuple(f"obs[{d}]" for d in range(dims))
        width = self.bin_width.expand(dims)
        which = ", ".join(
            f"{names[d]} (width {float(width[d]):.3g}, at {float(share[d]):.0%} of the steps)"
            for d in saturated
        )
        self._warned_saturated = True  # once per metric: every call of an assessor would repeat it
        warnings.warn(
            f"bin_width: in {which}, each member's {samples} samples fall in bins of their own: "
            f"the bits there are log2 {samples} = {math.log2(samples):.2f}, the number of "
            "samples, not their spread; give a width nearer the resolution that matters for "
            "the dimension, or more samples per member",
            stacklevel=2,
        )

    def _summary(self, value: Tensor, per_dim: bool) -> Tensor:
        if not per_dim:
            return value.mean(dim=-1)
        reduced = value.sum(dim=-1) if self.dim_reduction == "sum" else value.mean(dim=-1)
        return reduced.mean(dim=-1)


class SuccessMetric(KeyedModule):
    """Forecast P(success) of imagined rollouts against a :class:`SuccessBoundary`.

    Output entries under ``"competency"``:

    - ``"success"``, ``"failure"``: bool ``[E, N, *B]`` per trajectory;
    - ``"p_success"`` ``[*B]`` (mean over all ``E·N`` trajectories), ``"p_success_member"``
      ``[E, *B]``;
    - ``"p_success_low"``, ``"p_success_high"`` ``[*B]``: a ``confidence`` interval for
      P(success) from the ``E·N`` trajectories treated as independent draws
      (:func:`~rcvae_torchrl.competency.binomial_interval`, Jeffreys by default) — Monte-Carlo
      noise only; model disagreement is in ``"outcome_uncertainty"``;
    - ``"outcome_uncertainty"``: ``"total"`` / ``"aleatoric"`` / ``"epistemic"`` binary entropies
      in bits ``[*B]`` (:func:`~rcvae_torchrl.competency.outcome_uncertainty`);
    - ``"time_to_success"``: ``"first_step"`` ``[E, N, *B]`` (``T`` when never),
      ``"step_probability"`` and ``"success_by_step"`` ``[*B, T]``, ``"mean_steps"`` and
      ``"median_steps"`` ``[*B]`` among successes (inf when none), and with the boundary's
      ``dt`` also ``"mean_s"`` / ``"median_s"`` in seconds.

    Args:
        boundary: the task's success / failure boundary.
        confidence: coverage of the P(success) interval.
        interval: ``"jeffreys"`` or ``"wilson"``.

    Example:
        >>> boundary = SuccessBoundary(lambda obs: obs[..., 0] > 1.0, time_limit=5)
        >>> obs = torch.randn(4, 25, 3, 10, 2)  # E, N, B, T, D
        >>> rollout = TensorDict({"observation": obs}, batch_size=obs.shape[:-1])
        >>> out = SuccessMetric(boundary)(rollout)
        >>> out["competency", "p_success"].shape, out["competency", "success"].shape
        (torch.Size([3]), torch.Size([4, 25, 3]))
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable keys: ``observation`` (input), ``competency`` (output root)."""

        observation: NestedKey = "observation"
        competency: NestedKey = "competency"

    _inputs = ("observation",)
    _outputs = ("competency",)
    tensor_keys: _AcceptedKeys

    def __init__(
        self,
        boundary: SuccessBoundary,
        confidence: float = 0.95,
        interval: Literal["jeffreys", "wilson"] = "jeffreys",
    ) -> None:
        super().__init__()
        if not isinstance(boundary, SuccessBoundary):
            raise TypeError(f"boundary: expected a SuccessBoundary, got {type(boundary).__name__}")
        _checks.check_choice("interval", interval, ("jeffreys", "wilson"))
        _checks.check_confidence(confidence)
        self.boundary = boundary
        self.confidence = confidence
        self.interval = interval
        #: warn when rollouts end before a reach boundary's time limit (off where the caller
        #: has said so already: the competency assessor warns at its construction)
        self.warn_short = True

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Evaluate ``tensordict[observation]`` ``[E, N, *B, T, D]``; see the class docstring."""
        obs = _observation(tensordict, self.tensor_keys.observation)
        self._check_length(obs.shape[-2])
        success_over_time, success, failure = self.boundary.outcome(obs)
        p, p_member = success_probability(success)
        trials = success.shape[0] * success.shape[1]
        low, high = binomial_interval(
            success.sum(dim=(0, 1)), trials, self.confidence, self.interval
        )
        out = TensorDict(
            {
                "success": success,
                "failure": failure,
                "p_success": p,
                "p_success_member": p_member,
                "p_success_low": low,
                "p_success_high": high,
                "outcome_uncertainty": outcome_uncertainty(success).as_dict(),
                "time_to_success": self._time_to_success(success_over_time),
            }
        )
        result = TensorDict()
        result.set(self.tensor_keys.competency, out)
        return result

    def _check_length(self, steps: int) -> None:
        """Rollouts of ``steps`` steps against the boundary's time limit: a survival boundary
        is decided at its limit (shorter rollouts would read as never surviving), and a reach
        boundary's forecast then answers the shorter deadline."""
        limit = self.boundary.time_limit
        if steps >= limit:
            return
        if self.boundary.is_survival:
            raise ValueError(
                f"observation: a survival boundary is decided at its time limit ({limit} "
                f"steps), so the rollouts must last that long; expected T >= {limit}, got "
                f"T = {steps}"
            )
        if self.warn_short and limit < math.inf:
            warnings.warn(
                f"observation: rollouts of {steps} steps, shorter than the boundary's time limit "
                f"of {limit} steps: P(success) answers success within {steps} steps; roll out "
                f"at least {limit} steps for the boundary's deadline",
                stacklevel=3,
            )

    def _time_to_success(self, success_over_time: Tensor) -> dict[str, Tensor]:
        stats = time_to_success(success_over_time)._asdict()
        if self.boundary.dt is not None:
            # Index t of an imagined rollout holds s_{t+1}: the state t + 1 steps after s_0.
            stats["mean_s"] = (stats["mean_steps"] + 1) * self.boundary.dt
            stats["median_s"] = (stats["median_steps"] + 1) * self.boundary.dt
        return stats

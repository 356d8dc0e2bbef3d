"""Is a state like those the model was trained on? A check of novelty, apart from the ensemble.

The members' disagreement (the epistemic bits) is one sign of states the model has not seen,
but not a sure one: members trained on the same data can agree far from it, all extrapolating
alike. :class:`StateNovelty` asks the data itself. A state's novelty is its distance to its
``k``-th nearest training state, each dimension in units of its spread in the training states
(a root mean square over the dimensions, so 1.0 is one spread in every dimension). The level it
is compared with is the one a share ``quantile`` of held-out states reach: states of held-out
episodes, from the distribution the training episodes came from, so an in-distribution state is
called novel in about ``1 - quantile`` of cases, whatever the env. A state beyond the level is
*unlike the training states*: its forecast extrapolates, however much the members agree.

:func:`train_ensemble <rcvae_torchrl.training.train_ensemble>` fits one on its training and
validation episodes and keeps it with the model (``ensemble.novelty``, saved in checkpoints);
the competency assessor then says, start state by start state, which are unlike the training
states and in which dimensions.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

from rcvae_torchrl import _checks
from rcvae_torchrl._checks import check_positive_int, check_unit_interval

__all__ = ["StateNovelty"]

#: rows of queries per distance block (a block is ``rows x reference states`` floats)
_BLOCK_ROWS = 256
#: the training states' central share that :meth:`StateNovelty.describe` quotes per dimension
_RANGE_SHARE = 0.99


@dataclass(frozen=True)
class StateNovelty:
    """How unlike the training states a state is (see the module's docstring).

    Build it with :meth:`fit` (states) or :meth:`from_episodes` (flat episodes, as training
    takes them).
    """

    states: Tensor  #: ``[M, D]`` the reference training states (float32)
    center: Tensor  #: ``[D]`` their mean
    scale: Tensor  #: ``[D]`` their spread (std; a tiny positive value where constant)
    low: Tensor  #: ``[D]`` the low end of their central 99 %, per dimension
    high: Tensor  #: ``[D]`` the high end
    level: float  #: the distance that ``quantile`` of the held-out states stay at or below
    k: int
    quantile: float
    held_out: int  #: the held-out states the level was measured on

    @classmethod
    def fit(
        cls,
        states: Tensor,
        held_out: Tensor,
        *,
        k: int = 5,
        quantile: float = 0.99,
        max_states: int = 20_000,
        keep: Tensor | None = None,
        seed: int = 0,
    ) -> StateNovelty:
        """Fit on training ``states`` ``[N, D]``, its level measured on ``held_out`` ``[H, D]``.

        Args:
            states: the training states.
            held_out: states of held-out episodes from the same distribution (not the training
                episodes' own: neighbours in time would make every state look familiar).
            k: the neighbour whose distance counts (1: the nearest; more is less noisy).
            quantile: the share of held-out states that the level covers: about
                ``1 - quantile`` of in-distribution states are called unlike the training
                states. With fewer than ``q / (1 - q)`` held-out states the level is their
                largest distance, and the quantile kept is ``H / (H + 1)``.
            max_states: at most this many training states are kept (a seeded uniform draw; the
                ``keep`` ones always), and the level is measured on at most this many held-out
                states.
            keep: ``[N]`` bool, training states always kept (e.g. every episode's first state:
                the start states assessments begin from).
            seed: the seed of the draws.
        """
        states = _states("states", states)
        held_out = _states("held_out", held_out, states.shape[-1])
        check_positive_int("k", k)
        check_unit_interval("quantile", quantile, include_zero=False)
        if not quantile < 1:
            raise ValueError(f"quantile: expected a share in (0, 1), got {quantile!r}")
        check_positive_int("max_states", max_states)
        if states.shape[0] <= k:
            raise ValueError(
                f"states: expected more than k = {k} training states, got {states.shape[0]}"
            )
        generator = torch.Generator().manual_seed(seed)
        states = states[_draw(states.shape[0], max_states, keep, generator)].float()
        held_out = held_out[_draw(held_out.shape[0], max_states, None, generator)].float()
        center = states.mean(0)
        spread = states.std(0, correction=0)
        # a dimension constant in training: any other value is unseen, by a tiny unit
        scale = torch.where(spread > 0, spread, 1e-6 * center.abs().clamp_min(1.0))
        edges = torch.tensor([(1 - _RANGE_SHARE) / 2, (1 + _RANGE_SHARE) / 2])
        low, high = states.double().quantile(edges.double(), dim=0).float()
        fitted = cls(states, center, scale, low, high, math.inf, k, float(quantile), 0)
        distances = fitted.distance(held_out).double().sort().values
        # the conformal level: the ceil((H + 1) q)-th smallest of H held-out distances covers a
        # new in-distribution state with probability >= q; with too few held-out states for
        # that, the largest, which covers H / (H + 1), and that is the quantile kept
        count = held_out.shape[0]
        quantile = min(float(quantile), count / (count + 1))
        rank = min(math.ceil((count + 1) * quantile - 1e-9), count)
        level = max(float(distances[rank - 1]), 1e-12)
        return cls(states, center, scale, low, high, level, k, quantile, count)

    @classmethod
    def from_episodes(
        cls,
        train_data: TensorDictBase,
        val_data: TensorDictBase,
        *,
        key: str = "observation",
        **kwargs: Any,
    ) -> StateNovelty:
        """Fit on flat episodes ``[frames]`` (as :func:`~rcvae_torchrl.training.train_ensemble`
        takes them): every state of ``train_data`` (``key`` and ``("next", key)``, every
        episode's first state kept), the level from ``val_data``'s. ``kwargs`` go to
        :meth:`fit`."""
        from rcvae_torchrl.data import episode_spans

        parts = {}
        for name, data in (("train_data", train_data), ("val_data", val_data)):
            if not isinstance(data, TensorDictBase):
                raise TypeError(f"{name}: expected a TensorDict, got {type(data).__name__}")
            if key not in data.keys() or ("next", key) not in data.keys(True):
                raise KeyError(f"{name}: expected {key!r} and ('next', {key!r}) entries")
            parts[name] = torch.cat([data.get(key), data.get(("next", key))])
        keep = torch.zeros(parts["train_data"].shape[0], dtype=torch.bool)
        keep[episode_spans(train_data)[0]] = True
        return cls.fit(parts["train_data"], parts["val_data"], keep=keep, **kwargs)

    @property
    def dim(self) -> int:
        return self.states.shape[-1]

    def distance(self, states: Tensor) -> Tensor:
        """``[*B, D] -> [*B]``: the distance to the ``k``-th nearest reference state, in
        spreads (root mean square over the dimensions of the scaled differences)."""
        states = _states("states", states, self.dim, flat=False)
        flat = states.reshape(-1, self.dim).to(self.center.device, torch.float32)
        flat = ((flat - self.center) / self.scale).contiguous()
        reference = ((self.states - self.center) / self.scale).contiguous()
        k = min(self.k, reference.shape[0])
        out = [
            torch.cdist(block, reference).topk(k, largest=False).values[:, -1]
            for block in flat.split(_BLOCK_ROWS)
        ]
        distance = torch.cat(out) if out else flat.new_zeros(0)
        return (distance / math.sqrt(self.dim)).reshape(states.shape[:-1])

    def ratio(self, states: Tensor) -> Tensor:
        """``[*B]``: the distance over the level (above 1: unlike the training states)."""
        return self.distance(states) / self.level

    def unlike(self, states: Tensor) -> Tensor:
        """``[*B]`` bool: beyond the level."""
        return self.ratio(states) > 1

    def outside(self, state: Tensor) -> Tensor:
        """``[D]`` bool: the dimensions of one ``state`` outside the training states'
        central 99 %."""
        state = _states("state", state, self.dim, flat=False).float()
        return (state < self.low) | (state > self.high)

    def describe(self, state: Tensor, names: Sequence[str] | None = None, top: int = 3) -> str:
        """Why one ``state`` ``[D]`` is unlike the training states, in words: its distance
        against the level, and the dimensions outside the training states' central 99 % (up
        to ``top``, the farthest first) or, when none is, that the combination is new."""
        state = _states("state", state, self.dim, flat=False)
        if state.dim() != 1:
            raise ValueError(f"state: expected one state [D], got shape {tuple(state.shape)}")
        names = tuple(names) if names is not None else tuple(f"dim {d}" for d in range(self.dim))
        if len(names) != self.dim:
            raise ValueError(f"names: expected {self.dim} names, got {len(names)}")
        ratio = float(self.ratio(state))
        text = (
            f"{ratio:.1f}x as far from the training states as {self.quantile:.0%} of held-out "
            "states are"
        )
        outside = self.outside(state)
        if not bool(outside.any()):
            return text + " (every dimension within its training range: the combination is new)"
        state = state.float()
        beyond = torch.maximum(self.low - state, state - self.high).clamp_min(0) / self.scale
        order = [d for d in beyond.argsort(descending=True, stable=True).tolist() if outside[d]]
        parts = [
            f"{names[d]} = {float(state[d]):.3g} (training {float(self.low[d]):.3g} to "
            f"{float(self.high[d]):.3g})"
            for d in order[:top]
        ]
        more = len(order) - top
        return text + ": " + ", ".join(parts) + (f" and {more} more" if more > 0 else "")

    def as_dict(self) -> dict[str, Any]:
        """Tensors and plain values (for checkpoints)."""
        return {
            "states": self.states.clone(),
            "center": self.center.clone(),
            "scale": self.scale.clone(),
            "low": self.low.clone(),
            "high": self.high.clone(),
            "level": self.level,
            "k": self.k,
            "quantile": self.quantile,
            "held_out": self.held_out,
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> StateNovelty:
        """The inverse of :meth:`as_dict`; a wrong shape, type or value raises ValueError."""
        states = _states("novelty.states", values["states"])
        dim = states.shape[-1]
        vectors = {}
        for name in ("center", "scale", "low", "high"):
            vector = _checks.check_tensor(f"novelty.{name}", values[name])
            _checks.check_shape(f"novelty.{name}", vector, (dim,), "[D]")
            _checks.check_finite(f"novelty.{name}", vector)
            vectors[name] = vector.float()
        if not bool((vectors["scale"] > 0).all()):
            raise ValueError("novelty.scale: expected spreads > 0")
        level = values["level"]
        if not (_checks._is_number(level) and math.isfinite(level) and level > 0):
            raise ValueError(f"novelty.level: expected a distance > 0, got {level!r}")
        check_positive_int("novelty.k", values["k"])
        check_positive_int("novelty.held_out", values["held_out"])
        check_unit_interval("novelty.quantile", values["quantile"], include_zero=False)
        return cls(
            states.float(),
            level=float(level),
            k=int(values["k"]),
            quantile=float(values["quantile"]),
            held_out=int(values["held_out"]),
            **vectors,
        )


def _states(name: str, x: object, dim: int | None = None, *, flat: bool = True) -> Tensor:
    """Finite floating states: ``[N, D]`` with ``flat``, else ``[*B, D]``, D = ``dim``."""
    x = _checks.check_tensor(name, x)
    _checks.check_floating(name, x)
    if flat:
        _checks.check_rank(name, x, 2, "[N, D]")
    else:
        _checks.check_min_rank(name, x, 1, "[*B, D]")
    if dim is not None and x.shape[-1] != dim:
        raise ValueError(f"{name}: expected {dim} state dimensions, got {x.shape[-1]}")
    _checks.check_finite(name, x)
    return x


def _draw(n: int, most: int, keep: Tensor | None, generator: torch.Generator) -> Tensor:
    """Indices of at most ``most`` of ``n`` rows (a uniform draw), and every ``keep`` row."""
    if keep is not None:
        keep = _checks.check_tensor("keep", keep)
        if keep.dtype != torch.bool or keep.shape != (n,):
            raise ValueError(
                f"keep: expected a bool tensor of shape ({n},), got {keep.dtype} "
                f"{tuple(keep.shape)}"
            )
    if n <= most:
        return torch.arange(n)
    chosen = torch.zeros(n, dtype=torch.bool)
    chosen[torch.randperm(n, generator=generator)[:most]] = True
    if keep is not None:
        chosen |= keep
    return chosen.nonzero().squeeze(-1)

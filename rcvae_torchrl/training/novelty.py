"""Is a state like those the model was trained on? A check of novelty, apart from the ensemble.

The members' disagreement (the epistemic bits) is one sign of states the model has not seen,
but not a sure one: members trained on the same data can agree far from it, all extrapolating
alike. :class:`StateNovelty` asks the data itself. A state's novelty is its distance to its
``k``-th nearest training state, each dimension in units of its spread in the training states
(a root mean square over the dimensions, so 1.0 is one spread in every dimension). The level it
is compared with is the one a share ``quantile`` of held-out states reach: states of held-out
episodes, from the distribution the training episodes came from, so an in-distribution state is
called novel in about ``1 - quantile`` of cases, whatever the env (a conformal level). A state
beyond the level is *unlike the training states*: its forecast extrapolates, however much the
members agree. Start states and whole episodes have levels of their own, measured the same way
on first states and on episodes that training did not see (:meth:`StateNovelty.fit`). A start
state is also judged in groups of its dimensions alone (:attr:`StateNovelty.groups`: the
entries of several dimensions, such as a target's position), where a combination new in one
entry would be diluted by all the others, and by how far its farthest dimension lies past the
training states' range (:attr:`StateNovelty.range_scale`), where one dimension far out would
be too.

:func:`train_ensemble <rcvae_torchrl.training.train_ensemble>` fits one on its training and
validation episodes and keeps it with the model (``ensemble.novelty``, saved in checkpoints);
the competency assessor then says, start state by start state, which are unlike the training
states and in which dimensions.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

from rcvae_torchrl import _checks, _spread
from rcvae_torchrl._checks import (
    check_bool,
    check_positive_int,
    check_seed,
    check_unit_interval,
    is_integer,
)
from rcvae_torchrl._conformal import conformal_level
from rcvae_torchrl.competency.report import register_report_part
from rcvae_torchrl.data import TRAJ_KEY, ObservationLayout, episode_ids, episode_spans

__all__ = [
    "ACTION_BINS",
    "ACTION_FLOOR",
    "EPISODE_STEPS",
    "StateNovelty",
    "entry_groups",
    "spread_steps",
]

#: rows of queries per distance block (a block is ``rows x reference states`` floats)
_BLOCK_ROWS = 256
#: the training states' central share that :meth:`StateNovelty.describe` quotes per dimension
_RANGE_SHARE = 0.99
#: how far past that range (in spreads) a dimension must lie to be named as outside it
_RANGE_MARGIN = 0.05
#: candidates beyond the k nearest by cdist's fast distances that are measured again exactly
_RECHECKED = 8
#: the steps of an episode (real or imagined) whose states the episode level looks at
EPISODE_STEPS = 20
#: equal bins per action dimension between the training actions' extremes whose emptiness
#: marks values the model never saw an action take (a relaxed discrete action's ±1 leaves
#: every bin between them empty)
ACTION_BINS = 20
#: the least share of an episode's steps with unseen actions that cautions it: a policy that
#: leaves the training actions' support now and then does not make its forecast extrapolate
ACTION_FLOOR = 0.05


def spread_steps(length: int, count: int = EPISODE_STEPS) -> Tensor:
    """``min(length, count)`` step indices spread evenly over an episode of ``length`` steps
    (its first and last among them)."""
    return _spread.spread_steps(length, count)


def entry_groups(names: Sequence[str] | None) -> tuple[tuple[int, ...], ...]:
    """The dimensions of each entry of two or more dimensions, fewer than all, that names
    ``key[0]``, ``key[1]``, ... form (an :class:`~rcvae_torchrl.data.ObservationLayout`'s, as
    :func:`~rcvae_torchrl.data.prepare_env` gives them): the groups that
    :func:`~rcvae_torchrl.training.train_ensemble` has its novelty check judge on their own.
    None without names, or where every name is its own entry."""
    if names is None:
        return ()
    want = "None or a non-empty sequence of dimension names (str, one per dimension)"
    if (
        isinstance(names, (str, bytes))
        or not isinstance(names, Sequence)
        or not all(isinstance(name, str) for name in names)
    ):
        raise TypeError(f"names: expected {want}, got {names!r}")
    if not names:
        raise ValueError(f"names: expected {want}, got {names!r}")
    layout = ObservationLayout.from_names(tuple(names))
    starts = [sum(layout.sizes[:i]) for i in range(len(layout.sizes))]
    return tuple(
        tuple(range(start, start + size))
        for start, size in zip(starts, layout.sizes, strict=True)
        if 1 < size < layout.dim
    )


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
    #: the level of start states: the distance that ``start_quantile`` of the episodes' first
    #: states (held-out ones, and training ones against the other episodes' states) stay at or
    #: below, or the held-out states' where theirs is higher (``level`` when none were
    #: measured)
    start_level: float = math.nan
    start_quantile: float = math.nan
    start_held_out: int = 0  #: the first states it was measured on (0: the states' level)
    #: the share of an episode's states beyond ``level`` (at :data:`EPISODE_STEPS` steps spread
    #: over it) that ``episode_quantile`` of the measured episodes stay at or below; without
    #: episodes, ten times the share of states beyond the level, ``10 (1 - quantile)``
    episode_level: float = math.nan
    episode_quantile: float = math.nan
    episodes_measured: int = 0  #: the episodes it was measured on
    #: groups of dimensions in which start states are also judged on their own (e.g. the
    #: entries of two or more dimensions of an :class:`~rcvae_torchrl.data.ObservationLayout`):
    #: a start whose values in a group are each within their range, and together unlike any
    #: training state's (a target placed where no training target was), lies far from the
    #: training states in the group's dimensions while near them in all dimensions together.
    #: Imagined states are judged in all dimensions together: a model generates them a little
    #: off values the real states repeat exactly (a touch sensor's 0), which one group's
    #: dimensions alone would call new
    groups: tuple[tuple[int, ...], ...] = ()
    #: per group, the joint distance's level over the group's own: a group's distance times
    #: it is on the joint distance's scale (a start's distance is the largest of them)
    group_scales: tuple[float, ...] = ()
    #: the scale of a start's range view: how far its farthest dimension lies past the
    #: training states' central 99 % (in spreads), times it, is on the joint distance's scale;
    #: 0: not judged (checkpoints from before it). One dimension far out of its range is
    #: diluted in the distance over all dimensions together (a walker's torso at 2 m, every
    #: other dimension as in training, lay within the joint level)
    range_scale: float = 0.0
    #: ``[D]``, per dimension, how far past its range (in spreads) ``1 - (1 - quantile) / D``
    #: of the training states, and of their episodes' first states, stay (the larger; at least
    #: a twentieth of a spread): the range view reads each dimension's excess in these units,
    #: so that dimensions whose values run far past their range by nature (a contact force's
    #: spikes) do not set the level for one that never does (a quadruped thrown sideways at
    #: 2 m/s was like the training states while its force sensors set the range's level);
    #: ``None``: one unit for all (checkpoints from before)
    range_levels: Tensor | None = None
    #: ``[A]``, the training actions' lowest and highest value per dimension, and ``[A, K]``
    #: which of ``K`` equal bins between them hold training actions: the support of the
    #: actions the model learned from (:meth:`unseen_actions`). ``None``: fitted on states
    #: alone (or a checkpoint from before)
    action_low: Tensor | None = None
    action_high: Tensor | None = None
    action_bins: Tensor | None = None
    #: the share of an episode's steps whose action is unseen that ``episode_quantile`` of the
    #: held-out episodes stay at or below, and no less than :data:`ACTION_FLOOR`: an imagined
    #: episode whose policy acts unseen more often is unlike the training data in its actions
    action_level: float = math.nan

    def __post_init__(self) -> None:
        groups = _groups(self.groups, self.states.shape[-1])
        object.__setattr__(self, "groups", groups)
        scales = tuple(float(x) for x in self.group_scales) or (1.0,) * len(groups)
        if len(scales) != len(groups) or not all(math.isfinite(x) and x > 0 for x in scales):
            raise ValueError(
                f"group_scales: expected one positive scale per group ({len(groups)}), got "
                f"{self.group_scales!r}"
            )
        object.__setattr__(self, "group_scales", scales)
        if not (math.isfinite(self.range_scale) and self.range_scale >= 0):
            raise ValueError(f"range_scale: expected a scale >= 0, got {self.range_scale!r}")
        # the reference in spreads, as every distance reads it (scaled once, not per call)
        object.__setattr__(self, "_scaled", self._in_spreads(self.states))
        if math.isnan(self.start_level):  # no first states: starts are states like any other
            object.__setattr__(self, "start_level", self.level)
            object.__setattr__(self, "start_quantile", self.quantile)
        if math.isnan(self.episode_level):
            object.__setattr__(self, "episode_level", min(1.0, 10 * (1 - self.quantile)))
            object.__setattr__(self, "episode_quantile", self.quantile)

    @classmethod
    def fit(
        cls,
        states: Tensor,
        held_out: Tensor,
        *,
        k: int = 5,
        quantile: float = 0.99,
        max_states: int = 20_000,
        firsts: Tensor | None = None,
        episodes: Tensor | None = None,
        held_out_starts: Tensor | None = None,
        held_out_episodes: Tensor | None = None,
        groups: Sequence[Sequence[int]] = (),
        seed: int = 0,
    ) -> StateNovelty:
        """Fit on training ``states`` ``[N, D]``, its level measured on ``held_out`` ``[H, D]``.

        Start states get a level of their own (``start_level``): episodes start where few
        other states lie (at rest, spread over a region the episodes soon leave), so a new
        start is farther from the training states than most held-out states are, and the
        states' level would call many in-distribution starts unlike them. It is measured on
        the held-out episodes' first states and on every training episode's first state, each
        against the training states of the other episodes (there are few held-out episodes).
        It is never below the level of held-out states in general (then ``start_held_out`` is
        0): a start may lie anywhere along the training episodes' course (training begins its
        windows all along it), and first states that all repeat one state (a reset with
        little noise) would otherwise call every other state new.

        Args:
            states: the training states.
            held_out: states of held-out episodes from the same distribution (not the training
                episodes' own: neighbours in time would make every state look familiar).
            k: the neighbour whose distance counts (1: the nearest; more is less noisy).
            quantile: the share of held-out states that the level covers: about
                ``1 - quantile`` of in-distribution states are called unlike the training
                states. With fewer than ``q / (1 - q)`` held-out states the level is their
                largest distance, and the quantile kept is ``H / (H + 1)``.
            max_states: at most this many training states are kept (a seeded uniform draw;
                ``firsts`` always), and the level is measured on at most this many held-out
                states.
            firsts: ``[N]`` bool, the training states that are an episode's first state.
            episodes: ``[N]`` int, each training state's episode (its states in time order):
                with ``firsts``, every training episode's first state measures the start level,
                against the other episodes' states; and every episode measures the episode
                level (below).
            held_out_starts: ``[H0, D]``, the held-out episodes' first states, for the start
                level. Without these and ``episodes``, starts are judged by the states' level.
            held_out_episodes: ``[H]`` int, each held-out state's episode (its states in time
                order), for the episode level.
            groups: groups of dimensions (each a sequence of distinct indices) in which start
                states are also judged on their own, as :attr:`groups`. Each group's distance
                is scaled so that its level, measured on the held-out states, is the joint
                distance's; a start's distance is then the largest, and the start level is
                measured on it, so the share of in-distribution starts called unlike the
                training states stays about ``1 - quantile`` however many groups there are.
            seed: the seed of the draws.

        The episode level judges an imagined episode: the share of an episode's states beyond
        the states' level, at :data:`EPISODE_STEPS` steps spread over it, that ``quantile`` of
        the held-out and training episodes (each against the other episodes' states) stay at
        or below. Real episodes pass through sparse regions too (their starts, fast moves), so
        some of their states lie beyond the level; an imagined episode is unlike the training
        data when more of its states do than in in-distribution episodes.
        """
        states = _states("states", states)
        dim = states.shape[-1]
        held_out = _states("held_out", held_out, dim)
        if held_out.shape[0] == 0:
            raise ValueError(
                f"held_out: expected at least one held-out state [H >= 1, {dim}], got none "
                f"(shape {tuple(held_out.shape)})"
            )
        check_positive_int("k", k)
        _checks.check_open_unit_interval("quantile", quantile, "a share")
        seed = check_seed("seed", seed)
        check_positive_int("max_states", max_states)
        if max_states <= k:
            raise ValueError(
                f"max_states: expected more than k = {k} (the reference states must hold a "
                f"k-th nearest neighbour), got {max_states}"
            )
        if states.shape[0] <= k:
            raise ValueError(
                f"states: expected more than k = {k} training states, got {states.shape[0]}"
            )
        firsts = _row_flags("firsts", firsts, states.shape[0], torch.bool)
        episodes = _row_flags("episodes", episodes, states.shape[0], torch.long)
        held_out_episodes = _row_flags(
            "held_out_episodes", held_out_episodes, held_out.shape[0], torch.long
        )
        every = states.float()  # before the draw: the episodes' own states, for their shares
        generator = torch.Generator().manual_seed(seed)
        drawn = _draw(states.shape[0], max_states, firsts, generator)
        held_out_all = held_out.float()
        held_out = held_out_all[_draw(held_out.shape[0], max_states, None, generator)]
        states = states[drawn].float()
        center = states.mean(0)
        spread = states.std(0, correction=0)
        # a dimension constant in training: any other value is unseen, by a tiny unit
        scale = torch.where(spread > 0, spread, 1e-6 * center.abs().clamp_min(1.0))
        edges = torch.tensor([(1 - _RANGE_SHARE) / 2, (1 + _RANGE_SHARE) / 2])
        low, high = states.double().quantile(edges.double(), dim=0).float()
        groups = _groups(groups, dim)
        fitted = cls(
            states, center, scale, low, high, math.inf, k, float(quantile), 0, groups=groups
        )
        if held_out_starts is not None:
            held_out_starts = _states("held_out_starts", held_out_starts, dim).float()
        ids = own = None
        if firsts is not None and episodes is not None:
            ids, own = episodes[drawn], firsts[drawn]
        # each dimension's range level, over the training states and over their first states
        # (which may sit past a dimension's range by nature: a reset at rest, where the
        # episodes' course moves): the larger. Not over the held-out states: the levels of
        # the views are measured there, and levels fitted to them would be too low elsewhere
        measured_by = [states] + ([] if own is None else [states[own]])
        # at the quantile 1 - (1 - quantile) / D: the farthest dimension is the largest of D,
        # so that many dimensions' rare excesses do not make every state's largest one rare
        beyond = [fitted._beyond(x) for x in measured_by if x.shape[0]]  # [., D] in spreads
        each = 1 - (1 - quantile) / dim
        range_levels = torch.tensor(
            [max(_conformal_level(b[:, d], each)[0] for b in beyond) for d in range(dim)]
        ).clamp_min(_RANGE_MARGIN)
        fitted = dataclasses.replace(fitted, range_levels=range_levels)
        # the distances in each view (all dimensions, each group's, the range's): held-out
        # states'
        general = fitted._views(held_out)
        level, kept = _conformal_level(general[:, 0], quantile)
        # and first states
        calibration = []
        if held_out_starts is not None:
            calibration.append(fitted._views(held_out_starts))
        if own is not None:
            calibration.append(fitted._views(states[own], ids[own], ids))
        views = torch.cat(calibration) if calibration else general[:0]
        measured = views.shape[0]
        # each group's distance, and the range's, on the joint one's scale, their levels over
        # the first states made equal; a view's level there no lower than over the states in
        # general (first states at rest, all velocities 0, would make it 0 and any motion at
        # the start a million times the level), nor the range's below 1 (each dimension's own
        # range level)
        if not measured:  # no first states: starts are states like any other
            views = general
        # the joint distance's level over the first states, or over the held-out states in
        # general where that is higher (first states that repeat one state, a reset with
        # little noise, lie nearer the training states than any state of their course): each
        # view is scaled to it from its own level over the same states
        joint = max(
            _conformal_level(views[:, 0], quantile)[0], _conformal_level(general[:, 0], quantile)[0]
        )
        first = [_conformal_level(v, quantile)[0] for v in views[:, 1:].T]
        usual = [_conformal_level(v, quantile)[0] for v in general[:, 1:].T]
        usual[-1] = max(usual[-1], 1.0)  # no lower than each dimension's own level
        scales = tuple(joint / max(f, u) for f, u in zip(first, usual, strict=True))
        fitted = dataclasses.replace(fitted, group_scales=scales[:-1], range_scale=scales[-1])
        start_level, start_kept = _conformal_level(fitted._combined(views), quantile)
        # a start no farther than the held-out states in general is like the training states,
        # whose every state a window of training began at: first states that repeat one state
        # (a reset with little noise) would set a level that calls any state of an episode's
        # course new
        floor, floor_kept = _conformal_level(fitted._combined(general), quantile)
        if floor > start_level:
            start_level, start_kept, measured = floor, floor_kept, 0
        levels: dict[str, Any] = {"start_level": start_level, "start_quantile": start_kept}
        if measured:
            levels["start_held_out"] = measured
        shares = []
        if held_out_episodes is not None:
            shares.append(fitted._episode_shares(held_out_all, held_out_episodes, level))
        if episodes is not None:
            shares.append(fitted._episode_shares(every, episodes, level, episodes[drawn]))
        if shares:
            share_level, share_kept = _conformal_level(torch.cat(shares), quantile)
            levels.update(
                episode_level=min(1.0, share_level),
                episode_quantile=share_kept,
                episodes_measured=sum(x.numel() for x in shares),
            )
        levels.update(
            groups=groups,
            group_scales=fitted.group_scales,
            range_scale=fitted.range_scale,
            range_levels=range_levels,
        )
        return cls(states, center, scale, low, high, level, k, kept, held_out.shape[0], **levels)

    def _episode_shares(
        self, states: Tensor, episodes: Tensor, level: float, reference_ids: Tensor | None = None
    ) -> Tensor:
        """Per episode of ``states`` (rows of ``episodes`` in time order), the share of its
        states beyond ``level`` at :data:`EPISODE_STEPS` steps spread over it; with
        ``reference_ids``, each against the reference states of the other episodes."""
        order = torch.argsort(episodes, stable=True)
        counts = torch.unique_consecutive(episodes[order], return_counts=True)[1]
        starts = torch.cumsum(counts, 0) - counts
        picks = [
            order[start + spread_steps(int(count), EPISODE_STEPS)]
            for start, count in zip(starts.tolist(), counts.tolist(), strict=True)
        ]
        rows = torch.cat(picks)
        owner = episodes[rows] if reference_ids is not None else None
        beyond = (self._distance(states[rows], owner, reference_ids) > level).double()
        sizes = [p.numel() for p in picks]
        return torch.stack([part.mean() for part in beyond.split(sizes)])

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
        takes them): every state of ``train_data`` (``key`` and ``("next", key)``), the level
        from ``val_data``'s states, and the start states' level from both data's episodes'
        first states (see :meth:`fit`). ``kwargs`` go to :meth:`fit`."""
        parts = {}
        for name, data in (("train_data", train_data), ("val_data", val_data)):
            if not isinstance(data, TensorDictBase):
                raise TypeError(f"{name}: expected a TensorDict, got {type(data).__name__}")
            if key not in data.keys() or ("next", key) not in data.keys(True):
                raise KeyError(f"{name}: expected {key!r} and ('next', {key!r}) entries")
            episode_ids(data, name)
            parts[name] = torch.cat([data.get(key), data.get(("next", key))])
        check_novelty_episodes(train_data)
        frames = train_data.shape[0]
        firsts = torch.zeros(2 * frames, dtype=torch.bool)
        firsts[episode_spans(train_data)[0]] = True
        episodes = train_data.get(TRAJ_KEY).reshape(-1).long()
        held_out_episodes = val_data.get(TRAJ_KEY).reshape(-1).long()
        # an episode's rows: its states in time order, then its next states in time order; the
        # steps spread over them cover it twice over, as evenly
        fitted = cls.fit(
            parts["train_data"],
            parts["val_data"],
            firsts=firsts,
            episodes=episodes.repeat(2),
            held_out_starts=val_data.get(key)[episode_spans(val_data)[0]],
            held_out_episodes=held_out_episodes.repeat(2),
            **kwargs,
        )
        if "action" not in train_data.keys() or "action" not in val_data.keys():
            return fitted
        return fitted.with_actions(
            train_data.get("action"), val_data.get("action"), held_out_episodes
        )

    def with_actions(
        self, actions: Tensor, held_out: Tensor, held_out_episodes: Tensor
    ) -> StateNovelty:
        """This check, also judging actions: the support of the training ``actions``
        ``[N, A]`` (their extremes per dimension and which of :data:`ACTION_BINS` bins between
        them they fill), and the level of the share of an episode's steps with actions outside
        it, measured on the held-out ``held_out`` actions ``[H, A]`` of episodes
        ``held_out_episodes`` ``[H]`` (conformal at :attr:`quantile`, at least
        :data:`ACTION_FLOOR`). A world model has not seen the effect of an action outside the
        support (beyond the range the data's actions took, or between the values they took:
        a relaxed discrete action's ±1), however like the training states its imagined states
        look."""
        actions = _states("actions", actions).float()
        held_out = _states("held_out", held_out, actions.shape[-1]).float()
        ids = _row_flags("held_out_episodes", held_out_episodes, held_out.shape[0], torch.long)
        low, high = actions.min(0).values, actions.max(0).values
        index = _action_position(actions, low, high).long().clamp(0, ACTION_BINS - 1)
        bins = torch.zeros(actions.shape[-1], ACTION_BINS, dtype=torch.bool)
        bins.scatter_(1, index.T, True)
        fitted = dataclasses.replace(self, action_low=low, action_high=high, action_bins=bins)
        unseen = fitted.unseen_actions(held_out).double()
        _, episode, counts = torch.unique(ids, return_inverse=True, return_counts=True)
        shares = torch.zeros(counts.numel(), dtype=torch.float64).index_add_(0, episode, unseen)
        level = _conformal_level(shares / counts, self.quantile)[0]
        return dataclasses.replace(fitted, action_level=max(ACTION_FLOOR, min(1.0, level)))

    @property
    def judges_actions(self) -> bool:
        """Whether the check knows the training actions' support (:meth:`with_actions`)."""
        return self.action_bins is not None

    def unseen_actions(self, actions: Tensor) -> Tensor:
        """``[*B, A] -> [*B]`` bool: actions outside the training actions' support in some
        dimension (past their extremes by more than a bin, or in a bin no training action
        fell in); all ``False`` where the check does not judge actions."""
        actions = _checks.check_tensor("actions", actions)
        if self.action_bins is None:
            return torch.zeros(actions.shape[:-1], dtype=torch.bool, device=actions.device)
        bins = self.action_bins.to(actions.device)
        _checks.check_shape("actions", actions, (*actions.shape[:-1], bins.shape[0]), "[*B, A]")
        _checks.check_finite("actions", actions)  # a NaN action would read as seen
        position = _action_position(actions, self.action_low, self.action_high)
        far = (position < -1) | (position > ACTION_BINS + 1)  # a bin's width past the extremes
        index = position.long().clamp(0, ACTION_BINS - 1)
        empty = ~bins[torch.arange(bins.shape[0], device=bins.device), index]
        return (far | empty).any(-1)

    @staticmethod
    def episode_steps(length: int) -> Tensor:
        """The steps of an episode of ``length`` steps (real or imagined) whose states the
        episode level looks at (:func:`spread_steps`)."""
        return spread_steps(length)

    @property
    def dim(self) -> int:
        return self.states.shape[-1]

    def distance(self, states: Tensor, *, starts: bool = False) -> Tensor:
        """``[*B, D] -> [*B]``: the distance to the ``k``-th nearest reference state, in
        spreads (root mean square over the dimensions of the scaled differences); for
        ``starts`` (start states of episodes), the largest of that and each of the
        :attr:`groups`' distances on its scale."""
        states = _states("states", states, self.dim, flat=False)
        flat = states.reshape(-1, self.dim).to(self.center.device, torch.float32)
        return self._distance(flat, starts=starts).reshape(states.shape[:-1])

    def _distance(
        self,
        states: Tensor,
        ids: Tensor | None = None,
        reference_ids: Tensor | None = None,
        *,
        starts: bool = False,
    ) -> Tensor:
        """``[Q, D] -> [Q]`` (see :meth:`distance`); with ``ids`` ``[Q]`` and
        ``reference_ids`` ``[M]``, a state's own episode's reference states left out."""
        return self._combined(self._views(states, ids, reference_ids, starts=starts))

    def _combined(self, views: Tensor) -> Tensor:
        """``[Q, 1 + G + 1] -> [Q]``: the largest of the distance in all dimensions, each
        group's and the range's on its scale (the first column alone where there are no
        others)."""
        if views.shape[-1] == 1:
            return views[:, 0]
        scales = views.new_tensor((1.0, *self.group_scales, self.range_scale))
        return (views * scales).max(dim=-1).values

    def _views(
        self,
        states: Tensor,
        ids: Tensor | None = None,
        reference_ids: Tensor | None = None,
        *,
        starts: bool = True,
    ) -> Tensor:
        """``[Q, D] -> [Q, 1 + G + 1]``: the distance in all dimensions, then (for ``starts``)
        in each group's dimensions alone (root mean square over the group's dimensions) and
        the range's, how far the farthest dimension lies past the training states' central
        99 %, each in units of its :attr:`range_levels` (none scaled); ``[Q, 1]`` without
        ``starts``."""
        flat = self._in_spreads(states)
        out = []
        for i in range(0, flat.shape[0], _BLOCK_ROWS):  # none for no states
            block = flat[i : i + _BLOCK_ROWS]
            own = None if ids is None else ids[i : i + _BLOCK_ROWS, None] == reference_ids[None]
            views = [self._nearest(block, own).values[:, -1] / math.sqrt(self.dim)]
            for group in self.groups if starts else ():
                index = list(group)
                near = self._nearest(block[:, index], own, self._scaled[:, index])
                views.append(near.values[:, -1] / math.sqrt(len(group)))
            if starts:
                beyond = self._beyond(states[i : i + _BLOCK_ROWS])
                if self.range_levels is not None:
                    beyond = beyond / self.range_levels.to(beyond.device)
                views.append(beyond.amax(-1))
            out.append(torch.stack(views, dim=-1))
        columns = 2 + len(self.groups) if starts else 1
        return torch.cat(out) if out else flat.new_zeros(0, columns)

    def _in_spreads(self, states: Tensor) -> Tensor:
        """``states`` ``[Q, D]`` centred and in units of the training spread, as the reference
        states are held."""
        return ((states - self.center) / self.scale).contiguous()

    def _nearest(
        self, scaled: Tensor, own: Tensor | None = None, reference: Tensor | None = None
    ) -> Any:
        """The ``k`` nearest reference states of ``scaled`` states ``[Q, D]`` (``torch.topk``'s
        values and indices, ``[Q, k]``); ``own`` ``[Q, M]`` marks reference states left out;
        ``reference``: the scaled reference states in the dimensions of ``scaled`` (default
        all of them)."""
        reference = self._scaled if reference is None else reference
        # cdist's fast path (a matrix product) loses the small distances to rounding (about
        # 1e-4 where states repeat a value exactly, which a group's scale can blow up): the
        # candidates it finds are measured again exactly
        distances = torch.cdist(scaled, reference)
        if own is not None:
            distances = distances.masked_fill(own, math.inf)
        k = min(self.k, reference.shape[0])
        candidates = distances.topk(min(k + _RECHECKED, reference.shape[0]), largest=False)
        exact = (scaled[:, None, :] - reference[candidates.indices]).norm(dim=-1)
        exact = exact.masked_fill(candidates.values == math.inf, math.inf)
        nearest = exact.topk(k, largest=False)
        return torch.return_types.topk(
            (nearest.values, candidates.indices.gather(1, nearest.indices))
        )

    def ratio(self, states: Tensor, *, starts: bool = False) -> Tensor:
        """``[*B]``: the distance over the level, or for ``starts`` (start states of episodes)
        over ``start_level``; above 1: unlike the training states."""
        if starts:
            return self.distance(states, starts=True) / self.start_level
        return self.distance(states) / self.level

    def unlike(self, states: Tensor, *, starts: bool = False) -> Tensor:
        """``[*B]`` bool: beyond the level (of ``starts``, see :meth:`ratio`)."""
        return self.ratio(states, starts=starts) > 1

    def outside(self, state: Tensor) -> Tensor:
        """``[*B, D]`` bool: the dimensions of ``state`` outside the training states'
        central 99 % by more than a twentieth of their spread (a value at the edge of a
        dimension whose training states pile up there, a cosine of 1, sits a rounding past
        it)."""
        return self._beyond(_states("state", state, self.dim, flat=False)) > _RANGE_MARGIN

    def _beyond(self, state: Tensor) -> Tensor:
        """How far ``state`` lies past the training states' central 99 %, in spreads."""
        state = state.float()
        return torch.maximum(self.low - state, state - self.high).clamp_min(0) / self.scale

    def describe(
        self,
        state: Tensor,
        names: Sequence[str] | None = None,
        top: int = 3,
        *,
        start: bool = False,
    ) -> str:
        """Why one ``state`` ``[D]`` (a ``start`` state) is unlike the training states, in
        words: its distance against the level, the dimensions outside the training states'
        central 99 % (:meth:`outside`; up to ``top``, the farthest first), and, for a state
        beyond the level, the group whose combination alone crosses it (said first where the
        dimensions past their ranges would not call the start unlike on their own) or, where no
        dimension lies outside its range, that the combination is new and the ``top``
        dimensions in which it lies farthest from its ``k`` nearest training states. A state
        within the level is said to be so."""
        state = _states("state", state, self.dim, flat=False)
        if state.dim() != 1:
            raise ValueError(f"state: expected one state [D], got shape {tuple(state.shape)}")
        if not is_integer(top) or top < 1:
            raise ValueError(f"top: expected a positive integer (dimensions to name), got {top!r}")
        check_bool("start", start)
        if names is None:
            names = tuple(f"dim {d}" for d in range(self.dim))
        elif (
            isinstance(names, (str, bytes))
            or not isinstance(names, Sequence)
            or not all(isinstance(name, str) for name in names)
        ):
            raise TypeError(
                f"names: expected None or a sequence of {self.dim} dimension names (str), got "
                f"{names!r}"
            )
        names = tuple(names)
        if len(names) != self.dim:
            raise ValueError(f"names: expected {self.dim} names, got {len(names)}")
        ratio = float(self.ratio(state, starts=start))
        if start and self.start_held_out:
            held = f"{self.start_quantile:.0%} of held-out episodes' first states"
        else:
            held = f"{self.quantile:.0%} of held-out states"
        text = f"{ratio:.1f}x as far from the training states as {held} are"
        beyond = self._beyond(state)
        outside = beyond > _RANGE_MARGIN  # as :meth:`outside`
        # a group whose combination alone crosses the level (groups judge starts)
        group = self._crossing_group(state) if start and ratio > 1 else None
        if not bool(outside.any()):
            if ratio <= 1:
                return text + " (within the level: like the training states)"
            if group is not None:  # new in one group's dimensions, not in all together
                return text + (
                    " (every dimension within its training range: the combination of "
                    f"{', '.join(names[d] for d in group)} is new)"
                )
            farthest = ", ".join(names[d] for d in self._farthest(state)[:top])
            return text + (
                " (every dimension within its training range: the combination is new, farthest "
                f"from the nearest training states in {farthest})"
            )
        order = [d for d in beyond.argsort(descending=True, stable=True).tolist() if outside[d]]
        parts = [
            f"{names[d]} = {float(state[d]):.3g} (training {float(self.low[d]):.3g} to "
            f"{float(self.high[d]):.3g})"
            for d in order[:top]
        ]
        more = len(order) - top
        listed = ", ".join(parts) + (f" and {more} more" if more > 0 else "")
        if ratio <= 1:  # not called unlike: say so before the dimensions past the 99 %
            return text + (
                " (within the level: like the training states as a whole, though past the "
                f"central 99 % of their values in {listed})"
            )
        if group is None or bool(outside[list(group)].all()):
            return text + ": " + listed
        # farthest in a group whose values are not all outside their ranges
        combination = f"the combination of {', '.join(names[d] for d in group)} is new"
        if self._range_ratio(state) > 1:  # the values past their ranges call it unlike too
            return text + f": {listed}; {combination}"
        # they alone would not: the group is the cause, said first
        return (
            text + f": {combination} (past the central 99 % of the training values too: {listed})"
        )

    def _range_ratio(self, state: Tensor) -> float:
        """How far one ``state`` ``[D]``'s farthest dimension past its range goes toward the
        start level on the range's scale (above 1: that alone calls the start unlike)."""
        views = self._views(state.to(self.center)[None])[0]
        return float(views[-1]) * self.range_scale / self.start_level

    def _crossing_group(self, state: Tensor) -> tuple[int, ...] | None:
        """The group farthest beyond the start level on its scale for one start ``state``,
        where one is beyond it."""
        if not self.groups:
            return None
        views = self._views(state.to(self.center)[None])[0, 1:-1]
        scaled = views * views.new_tensor(self.group_scales) / self.start_level
        which = int(scaled.argmax())
        return self.groups[which] if float(scaled[which]) > 1 else None

    def _farthest(self, state: Tensor) -> list[int]:
        """The dimensions of one ``state`` ``[D]``, the farthest from its ``k`` nearest
        reference states first (mean absolute difference, in spreads)."""
        scaled = self._in_spreads(state.to(self.center)[None])
        nearest = self._nearest(scaled).indices[0]
        gap = (self._scaled[nearest] - scaled).abs().mean(0)
        return gap.argsort(descending=True, stable=True).tolist()

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
            "start_level": self.start_level,
            "start_quantile": self.start_quantile,
            "start_held_out": self.start_held_out,
            "episode_level": self.episode_level,
            "episode_quantile": self.episode_quantile,
            "episodes_measured": self.episodes_measured,
            "groups": [list(group) for group in self.groups],
            "group_scales": list(self.group_scales),
            "range_scale": self.range_scale,
            "range_levels": None if self.range_levels is None else self.range_levels.clone(),
            "action_low": None if self.action_low is None else self.action_low.clone(),
            "action_high": None if self.action_high is None else self.action_high.clone(),
            "action_bins": None if self.action_bins is None else self.action_bins.clone(),
            "action_level": self.action_level,
        }

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> StateNovelty:
        """The inverse of :meth:`as_dict`; a missing entry, a wrong shape, type or value raises
        ValueError."""
        _checks.check_entries(
            "novelty",
            values,
            (
                *("states", "center", "scale", "low", "high", "level", "start_level", "k"),
                *("held_out", "start_held_out", "episodes_measured", "quantile"),
                *("start_quantile", "episode_quantile", "episode_level"),
            ),
            "a StateNovelty.as_dict()",
        )
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
        for name in ("level", "start_level"):
            level = values[name]
            if not (_checks._is_number(level) and math.isfinite(level) and level > 0):
                raise ValueError(f"novelty.{name}: expected a distance > 0, got {level!r}")
        check_positive_int("novelty.k", values["k"])
        check_positive_int("novelty.held_out", values["held_out"])
        _checks.check_non_negative_int("novelty.start_held_out", values["start_held_out"])
        _checks.check_non_negative_int("novelty.episodes_measured", values["episodes_measured"])
        for name in ("quantile", "start_quantile", "episode_quantile"):
            check_unit_interval(f"novelty.{name}", values[name], include_zero=False)
        check_unit_interval("novelty.episode_level", values["episode_level"])
        return cls(
            states.float(),
            level=float(values["level"]),
            k=int(values["k"]),
            quantile=float(values["quantile"]),
            held_out=int(values["held_out"]),
            start_level=float(values["start_level"]),
            start_quantile=float(values["start_quantile"]),
            start_held_out=int(values["start_held_out"]),
            episode_level=float(values["episode_level"]),
            episode_quantile=float(values["episode_quantile"]),
            episodes_measured=int(values["episodes_measured"]),
            # checkpoints from before groups were judged have none
            groups=_groups(values.get("groups", ()), dim, "novelty.groups"),
            group_scales=_scales(values.get("group_scales", ())),
            range_scale=float(values.get("range_scale", 0.0)),  # 0: not judged before it
            range_levels=_range_levels(values.get("range_levels"), dim),
            **_action_support(values),
            **vectors,
        )


def _action_position(actions: Tensor, low: Tensor, high: Tensor) -> Tensor:
    """``[*B, A]``: each action's place between the training actions' extremes ``low`` and
    ``high`` ``[A]``, in bins of :data:`ACTION_BINS` (0 at ``low``, ``ACTION_BINS`` at
    ``high``)."""
    low, high = low.to(actions.device), high.to(actions.device)
    return (actions.float() - low) / (high - low).clamp_min(1e-6) * ACTION_BINS


def _action_support(values: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's action support (:meth:`StateNovelty.with_actions`), checked; none where
    it was saved without one (fitted on states alone, or before actions were judged)."""
    bins = values.get("action_bins")
    if bins is None:
        return {}
    bins = _checks.check_tensor("novelty.action_bins", bins)
    if bins.dtype != torch.bool or bins.dim() != 2:
        raise ValueError(
            f"novelty.action_bins: expected a bool tensor [A, K], got {bins.dtype} "
            f"{tuple(bins.shape)}"
        )
    out = {"action_bins": bins}
    for name in ("action_low", "action_high"):
        vector = _checks.check_tensor(f"novelty.{name}", values[name])
        _checks.check_shape(f"novelty.{name}", vector, (bins.shape[0],), "[A]")
        _checks.check_finite(f"novelty.{name}", vector)
        out[name] = vector.float()
    check_unit_interval("novelty.action_level", values["action_level"], include_zero=False)
    out["action_level"] = float(values["action_level"])
    return out


def _range_levels(values: object, dim: int) -> Tensor | None:
    """A checkpoint's per-dimension range levels ``[D]`` (positive), or ``None`` (saved
    before them)."""
    if values is None:
        return None
    levels = _checks.check_tensor("novelty.range_levels", values)
    _checks.check_shape("novelty.range_levels", levels, (dim,), "[D]")
    _checks.check_finite("novelty.range_levels", levels)
    if not bool((levels > 0).all()):
        raise ValueError("novelty.range_levels: expected levels > 0")
    return levels.float()


def _groups(groups: object, dim: int, name: str = "groups") -> tuple[tuple[int, ...], ...]:
    """Groups of state dimensions: each a non-empty sequence of distinct ints in [0, dim)."""
    if isinstance(groups, (str, bytes, Tensor)) or not isinstance(groups, Sequence):
        raise TypeError(f"{name}: expected a sequence of dimension groups, got {groups!r}")
    out = []
    for group in groups:
        if isinstance(group, (str, bytes)) or not isinstance(group, Sequence):
            raise TypeError(f"{name}: expected each group as a sequence of ints, got {group!r}")
        values = tuple(group)
        if (
            not values
            or not all(isinstance(d, int) and not isinstance(d, bool) for d in values)
            or len(set(values)) != len(values)
            or min(values) < 0
            or max(values) >= dim
        ):
            raise ValueError(
                f"{name}: expected each group as distinct dimensions in [0, {dim}), got "
                f"{list(values)}"
            )
        out.append(values)
    return tuple(out)


def _scales(scales: object) -> tuple[float, ...]:
    """``novelty.group_scales`` from a checkpoint: a sequence of numbers."""
    if not isinstance(scales, Sequence) or not all(_checks._is_number(x) for x in scales):
        raise ValueError(f"novelty.group_scales: expected a list of numbers, got {scales!r}")
    return tuple(float(x) for x in scales)


def check_novelty_episodes(train_data: TensorDictBase) -> None:
    """Refuse training data of fewer than 2 episodes for the novelty check: each episode's
    first state is measured against the other episodes' states (one episode left none, and
    the check failed with NaN scales after a whole training run)."""
    count = len(episode_spans(train_data)[0])
    if count < 2:
        raise ValueError(
            f"train_data: the novelty check measures each training episode's first state "
            f"against the other episodes' states: expected at least 2 training episodes, got "
            f"{count}; collect more, or train with novelty=False (no check of novel states)"
        )


def _conformal_level(distances: Tensor, quantile: float) -> tuple[float, float]:
    """The level of ``H`` held-out distances and the quantile it keeps
    (:func:`~rcvae_torchrl._conformal.conformal_level`), above zero."""
    if distances.numel() == 0:
        raise ValueError("held_out: expected at least one held-out state, got none")
    level, kept = conformal_level(distances, quantile)
    return max(level, 1e-12), kept


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


def _row_flags(name: str, x: object, n: int, dtype: torch.dtype) -> Tensor | None:
    """``None``, or a ``[n]`` tensor of ``dtype`` (int: any integer dtype, as int64)."""
    if x is None:
        return None
    x = _checks.check_tensor(name, x)
    integer = not x.is_floating_point() and not x.is_complex() and x.dtype != torch.bool
    right = x.dtype == torch.bool if dtype == torch.bool else integer
    if not right or x.shape != (n,):
        kind = "a bool" if dtype == torch.bool else "an integer"
        raise ValueError(
            f"{name}: expected {kind} tensor of shape ({n},), got {x.dtype} {tuple(x.shape)}"
        )
    return x.to(dtype)


def _draw(n: int, most: int, keep: Tensor | None, generator: torch.Generator) -> Tensor:
    """Indices of at most ``most`` of ``n`` rows (a uniform draw), and every ``keep`` row."""
    if n <= most:
        return torch.arange(n)
    chosen = torch.zeros(n, dtype=torch.bool)
    chosen[torch.randperm(n, generator=generator)[:most]] = True
    if keep is not None:
        chosen |= keep
    return chosen.nonzero().squeeze(-1)


register_report_part("novelty", StateNovelty.from_dict)

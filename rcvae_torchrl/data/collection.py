"""Collecting whole episodes with TorchRL's ``Collector``."""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import unravel_key
from torchrl.collectors import Collector
from torchrl.data import ReplayBuffer
from torchrl.envs import EnvBase, SerialEnv
from torchrl.envs.utils import ExplorationType
from tqdm.auto import tqdm

from rcvae_torchrl._checks import (
    ROUNDING,
    check_non_negative_int,
    check_positive_int,
    check_positive_int_or_none,
)
from rcvae_torchrl.distributed import work_generator
from rcvae_torchrl.threads import threads_kept

from .exploration import acting, action_bounds, exploration_mode
from .prepare import check_env, seed_env

__all__ = [
    "TRAJ_KEY",
    "check_actions",
    "check_episode_ids",
    "check_frames_type",
    "collect_episodes",
    "episode_ids",
    "merge_episodes",
    "warn_narrow_bounds",
]

TRAJ_KEY = ("collector", "traj_ids")


def episode_ids(data: object, name: str = "data") -> torch.Tensor:
    """The episode id of every frame of flat episodes ``data`` ``[frames]`` (its
    :data:`TRAJ_KEY` entry), or an error naming ``name`` and what is missing."""
    if not isinstance(data, TensorDictBase):
        raise TypeError(f"{name}: expected a TensorDict of episodes, got {type(data).__name__}")
    ids = data.get(TRAJ_KEY, None)
    if ids is None:
        raise KeyError(
            f"{name}: expected episode ids under {TRAJ_KEY!r} (collect_episodes writes them; "
            f"give data of your own one id per episode there), got entries "
            f"{', '.join(sorted(map(str, data.keys(True, True)))[:8])}"
        )
    if ids.ndim != 1 or ids.is_floating_point() or ids.dtype == torch.bool:
        raise ValueError(
            f"{name}[{TRAJ_KEY!r}]: expected integer ids of flat frames [frames], got "
            f"{ids.dtype} {tuple(ids.shape)}"
        )
    return ids


@threads_kept()  # a SerialEnv changes torch's thread count when it closes
def collect_episodes(
    make_env: Callable[[], EnvBase],
    policy: Callable[[TensorDictBase], TensorDictBase],
    num_episodes: int,
    *,
    seed: int = 0,
    num_envs: int = 1,
    frames_per_batch: int = 1000,
    max_frames: int | None = None,
    first_id: int = 0,
    progress: bool = True,
    desc: str = "collect",
    exploration_type: ExplorationType | str | None = None,
) -> TensorDict:
    """Run ``policy`` in envs from ``make_env`` until ``num_episodes`` episodes have ended.

    Returns a flat TensorDict ``[frames]`` of ``num_episodes`` whole episodes, each contiguous
    and in time order, with TorchRL's transition layout (``"observation"``, ``"action"``,
    ``("next", ...)``) and unique episode ids under :data:`TRAJ_KEY`
    (``("collector", "traj_ids")``). Unfinished episodes are dropped.

    Args:
        make_env: zero-argument env factory (e.g. a ``functools.partial`` of an env
            constructor).
        policy: a TorchRL policy (TensorDictModule or callable on tensordicts).
        num_episodes: episodes to collect (>= 1).
        seed: seeds the env(s) (start states and noise: :func:`seed_env`, which restarts a
            transform's own random stream such as :class:`ActionNoise`'s; with ``num_envs``
            envs, each from a seed drawn from ``seed`` and its index), not the policy: an
            exploration policy with its own generator (``GaussianExploration``,
            ``UniformRandomPolicy``) is seeded where it is made, so the same data needs a new
            one.
        num_envs: envs stepped together in a ``SerialEnv``: the policy runs once per step for
            all of them, which pays off when a policy call costs more than an env step.
        frames_per_batch: collector batch size (rounded up to a multiple of the frames one step
            gives: ``num_envs`` times the env's own batch size).
        max_frames: safety cap on frames (default: 1,000 × (``num_episodes`` + ``num_envs``
            − 1), room for episodes of up to 1,000 steps in every env). Reaching it before
            ``num_episodes`` episodes have ended is a ``ValueError``.
        first_id: the id of the first episode.
        exploration_type: how a stochastic policy (a TorchRL ``ProbabilisticActor``) acts:
            :func:`~rcvae_torchrl.data.exploration_mode` (by default the caller's
            ``set_exploration_type``, else sampled, as TorchRL's collectors run it). Its samples
            come from torch's global random stream, seeded by ``seed`` for the collection and
            restored afterwards: the same seed gives the same episodes.
    """
    if isinstance(make_env, EnvBase) or not callable(make_env):
        raise TypeError(
            "make_env: expected a function that makes the env (e.g. lambda: env, or a "
            f"functools.partial of its constructor), got {_what(make_env)}"
        )
    if not isinstance(desc, str):
        raise TypeError(f"desc: expected the progress bar's label (a str), got {desc!r}")
    for name, value in (
        ("num_episodes", num_episodes),
        ("num_envs", num_envs),
        ("frames_per_batch", frames_per_batch),
    ):
        check_positive_int(name, value)
    check_positive_int_or_none("max_frames", max_frames)
    check_non_negative_int("first_id", first_id)
    if policy is None or not callable(policy):  # None: the collector would act at random
        raise TypeError(
            f"policy: expected a TorchRL policy (a module or a callable on tensordicts), got "
            f"{_what(policy)}"
        )
    max_frames = max_frames or 1000 * (num_episodes + num_envs - 1)
    if num_envs == 1:
        env = make_env()
        if not isinstance(env, EnvBase):
            raise TypeError(f"make_env: expected it to return a TorchRL env, got {_what(env)}")
    else:  # each env's own random streams (an ActionNoise) from a seed of its own
        env = SerialEnv(
            num_envs,
            [functools.partial(_seeded, make_env, seed, i) for i in range(num_envs)],
        )
    rows = max(1, env.batch_size.numel())  # frames one step gives (a SerialEnv's, a batched env's)
    _check_policy_inputs(env, policy)
    warn_narrow_bounds(env, policy)
    seed_env(env, seed)  # the env(s), and one env's transforms with random streams
    mode = exploration_mode(exploration_type)
    collector = Collector(
        env,
        policy,
        frames_per_batch=-(-frames_per_batch // rows) * rows,
        total_frames=-1,
        split_trajs=False,
        auto_register_policy_transforms=False,
        exploration_type=mode,
    )
    parts, ended, frames = [], 0, 0
    bar = tqdm(total=num_episodes, desc=desc, disable=not progress, leave=False)
    try:
        with torch.no_grad(), acting(mode, seed=seed):
            for batch in collector:
                parts.append(batch.reshape(-1).clone())
                finished = int(batch["next", "done"].sum())
                ended, frames = ended + finished, frames + batch.numel()
                bar.update(min(finished, num_episodes - bar.n))
                if ended >= num_episodes or frames >= max_frames:
                    break
    except Exception as err:
        _refuse_policy_actions(env, policy, err)
        raise
    finally:
        collector.shutdown()
        bar.close()
    data = _whole_episodes(torch.cat(parts), num_episodes, first_id)
    check_actions(env, data)
    _check_finite_observations(env, data)
    return data


def _refuse_policy_actions(env: EnvBase, policy: object, err: Exception) -> None:
    """After a collection failed with ``err``: where the policy's action has another shape
    than the env's batch and action spec give (a simulator handed it fails inside its own step,
    a broadcast error that does not name the policy), a ``ValueError`` saying so, from ``err``.
    Checked only once a step failed, so that a collection draws nothing more from the
    policy's random streams than its steps do."""
    try:
        with torch.no_grad():
            td = env.reset()
            out = policy(td)
        action = (td if out is None else out).get(env.action_key, None)
        wanted = (*env.batch_size, *env.action_spec_unbatched.shape)
    except Exception:  # the diagnosis failed too: the original error says more
        return
    if isinstance(action, torch.Tensor) and tuple(action.shape) != wanted:
        raise ValueError(
            f"policy: expected actions of shape {wanted} (the env's batch "
            f"{list(env.batch_size)} and its action_spec's "
            f"{list(env.action_spec_unbatched.shape)}), got {tuple(action.shape)}; the env "
            f"failed on them: {type(err).__name__}: {err}"
        ) from err


def _seeded(make_env: Callable[[], EnvBase], seed: int, index: int) -> EnvBase:
    """Env ``index`` of a collection's ``SerialEnv``: made, and its random streams (the base
    env's, an :class:`ActionNoise`'s) seeded from ``(seed, index)``: the same seed in every
    env would give each one the same noise."""
    env = make_env()
    seed_env(env, work_generator(seed % 2**63, index, 4).initial_seed())
    return env


def _check_finite_observations(env: EnvBase, data: TensorDictBase) -> None:
    """The env's floating observations must be finite: name the first episode and step where
    one is not (a model cannot learn from them, and training would refuse them later)."""
    for key in (("next", "observation"), "observation"):
        value = data.get(key, None)
        if value is None or not value.is_floating_point():
            continue
        bad = ~torch.isfinite(value).reshape(value.shape[0], -1).all(-1)
        if bool(bad.any()):
            frame = int(bad.nonzero()[0, 0])
            episode = int(data.get(TRAJ_KEY)[frame])
            start = int((data.get(TRAJ_KEY) == episode).nonzero()[0, 0])
            raise ValueError(
                f"env: {type(env).__name__} gave non-finite {key!r} (NaN or inf) in "
                f"{int(bad.sum())} of {bad.numel()} frames, first in episode {episode} at step "
                f"{frame - start}; a world model cannot learn from them"
            )


def check_actions(env: EnvBase, data: TensorDictBase, name: str = "policy") -> None:
    """Every action recorded in ``data`` must be one that ``env``'s action spec allows.

    TorchRL records the action the policy wrote, while an env may clip or cast it before it
    acts: a world model trained on such data would learn from actions that were never applied.
    Raises ``TypeError`` for another dtype than the spec's and ``ValueError`` for actions out of
    its bounds (or NaN), naming ``name`` (the policy that chose them) and how far out they are.
    """
    check_env(env)
    if not isinstance(data, TensorDictBase):
        raise TypeError(f"data: expected a TensorDict of frames, got {_what(data)}")
    spec = env.action_spec_unbatched
    action = data.get(env.action_key, None)
    if action is None:
        raise KeyError(
            f"data: expected the actions under the env's action_key {env.action_key!r}, got "
            f"entries {', '.join(sorted(map(str, data.keys(True, True)))[:8])}"
        )
    trailing = tuple(action.shape[action.dim() - len(spec.shape) :])
    if action.dim() < len(spec.shape) or trailing != tuple(spec.shape):
        raise ValueError(
            f"{name}: expected actions [..., {', '.join(map(str, spec.shape))}] (the env's "
            f"action_spec shape {list(spec.shape)}), got shape {tuple(action.shape)}"
        )
    if action.dtype != spec.dtype:
        raise TypeError(
            f"{name}: expected actions of the env's action_spec dtype {spec.dtype}, got "
            f"{action.dtype}; cast them in the policy"
        )
    if bool(spec.is_in(action)):
        return
    space = getattr(spec, "space", None)
    low, high = getattr(space, "low", None), getattr(space, "high", None)
    detail = ""
    nan = action.isnan().reshape(-1, action.shape[-1]).any(dim=-1)
    if bool(nan.any()):
        detail = f": {int(nan.sum())} of {nan.numel()} actions are NaN"
    elif low is not None and high is not None:
        below, above = (low - action).clamp_min(0), (action - high).clamp_min(0)
        excess = torch.maximum(below, above)
        out = excess > 0
        detail = (
            f": {int(out.any(dim=-1).sum())} of {out[..., 0].numel()} actions fall outside "
            f"[{low.tolist()}, {high.tolist()}], by up to {float(excess.max()):.4g}"
        )
    raise ValueError(
        f"{name}: expected actions inside the env's action_spec{detail}; clip them in the policy "
        "(the env would act on other actions than the ones recorded)"
    )


def _check_policy_inputs(env: EnvBase, policy: object) -> None:
    """A policy that declares ``in_keys`` must find them among the env's entries (observations,
    state, done flags): say which are missing, and how an env gets an ``"observation"``."""
    out_keys = getattr(policy, "out_keys", None)
    wanted = unravel_key(env.action_key)
    if isinstance(out_keys, (list, tuple)) and wanted not in map(unravel_key, out_keys):
        raise KeyError(
            f"policy: writes {list(out_keys)}, not the env's action {env.action_key!r}; "
            f"give it out_keys=[{env.action_key!r}]"
        )
    keys = getattr(policy, "in_keys", None)
    if not isinstance(keys, (list, tuple)):
        return
    specs = (env.full_observation_spec, env.full_state_spec, env.full_done_spec)
    available = {key for spec in specs for key in spec.keys(True, True)}
    # a planner's model env makes its own state from the observation (the model state)
    made = getattr(getattr(policy, "env", None), "made_from_observation", ())
    available |= {unravel_key(key) for key in made}
    missing = [key for key in keys if key not in available and (key,) not in available]
    if missing:
        raise KeyError(
            f"policy: reads {missing}, which {type(env).__name__} does not write (it writes "
            f'{sorted(map(str, available))}); for a world model\'s "observation", concatenate '
            "the env's entries with rcvae_torchrl.data.prepare_env(env, observation_keys=[...])"
        )


def _what(value: object) -> str:
    """``value`` named for an error by its type (an env as one)."""
    return f"{'the env ' if isinstance(value, EnvBase) else ''}{type(value).__name__}"


def warn_narrow_bounds(env: EnvBase, policy: object, stacklevel: int = 3) -> None:
    """Warn when an exploration policy (one that holds its action bounds ``low``, ``high``,
    as :class:`~rcvae_torchrl.data.GaussianExploration` and
    :class:`~rcvae_torchrl.data.UniformRandomPolicy` do) covers less than the env's action
    range: its default [-1, 1] is narrower than many envs' (a torque in [-2, 2]), and a world
    model never shown the rest cannot forecast it. ``stacklevel``: ``warnings.warn``'s, counted
    from this function (3: the line that called the function calling it)."""
    module = getattr(policy, "module", policy)  # a TensorDictModule's wrapped module
    low, high = getattr(module, "low", None), getattr(module, "high", None)
    if not (isinstance(low, torch.Tensor) and isinstance(high, torch.Tensor)):
        return
    try:
        env_low, env_high = action_bounds(env)
    except ValueError:  # an unbounded action spec: nothing to cover
        return
    tol = 1e-6 * (env_high - env_low).abs().clamp_min(1.0)
    narrow = (low > env_low + tol) | (high < env_high - tol)
    if bool(narrow.broadcast_to(env_low.shape).any()):
        warnings.warn(
            f"policy: {type(module).__name__} draws actions in [{_fmt(low)}, {_fmt(high)}], "
            f"less than the env's action range [{_fmt(env_low)}, {_fmt(env_high)}]: the data "
            "will not show the world model the rest; pass low=, high= from "
            "rcvae_torchrl.data.action_bounds(env) if that is not meant",
            stacklevel=stacklevel,
        )


def _fmt(bound: torch.Tensor) -> str:
    values = bound.reshape(-1).tolist()
    return f"{values[0]:g}" if len(set(values)) == 1 else str([round(v, 4) for v in values])


def _whole_episodes(data: TensorDict, num_episodes: int, first_id: int) -> TensorDict:
    """The first ``num_episodes`` finished episodes, each contiguous, ordered by id and
    renumbered ``first_id, first_id + 1, ...``."""
    ids = data[TRAJ_KEY]
    finished = torch.unique(ids[data["next", "done"].reshape(-1)])[:num_episodes]
    if finished.numel() < num_episodes:
        raise ValueError(
            f"max_frames: {data.numel()} frames were collected and only {finished.numel()} of "
            f"the {num_episodes} episodes asked for ended; raise max_frames, or, where the env's "
            "episodes never end by themselves (TorchRL's PendulumEnv), cut them with a time "
            "limit: env.append_transform(torchrl.envs.StepCounter(max_steps))"
        )
    data = data[torch.isin(ids, finished)]
    order = torch.sort(data[TRAJ_KEY], stable=True).indices
    data = data[order]
    data[TRAJ_KEY] = torch.searchsorted(finished, data[TRAJ_KEY]) + first_id
    return data


def check_frames_type(data: object, name: str = "data") -> None:
    """Refuse anything but a TensorDict of frames, naming a replay buffer's way to its frames."""
    if isinstance(data, TensorDictBase):
        return
    hint = (
        "; a TorchRL ReplayBuffer keeps its frames in its storage: pass them as collected, "
        "rb[:] (not rb.sample(), whose frames are not episodes)"
        if isinstance(data, ReplayBuffer)
        else ""
    )
    raise TypeError(
        f"{name}: expected a flat TensorDict of episodes [frames], got {type(data).__name__}{hint}"
    )


def check_episode_ids(data: TensorDictBase, name: str = "data") -> None:
    """Every episode id must tag one contiguous block of frames (one episode), in time order.

    Two collections concatenated without renumbering reuse ids; a window sampler would then
    stitch different episodes together. Raises ``ValueError`` naming the repeated ids. Where
    the data has ``"observation"`` and ``("next", "observation")``, each frame's next
    observation must be the observation of the frame after it under the same id (up to float
    rounding): frames drawn from a replay buffer by ``sample()`` and sorted by id pass the
    first check and are not episodes; the error names the first pair that does not join.
    """
    ids = episode_ids(data, name)
    runs = torch.unique_consecutive(ids)
    if runs.numel() != torch.unique(runs).numel():
        values, counts = torch.unique(runs, return_counts=True)
        repeated = values[counts > 1][:5].tolist()
        if _joins_in_time(data, ids):
            raise ValueError(
                f"{name}: expected one contiguous block of frames per episode id, but the frames "
                f"of ids {repeated} lie in several blocks, which join up step by step once sorted "
                "by id (a TorchRL collector's batches over several envs interleave their "
                f"episodes): sort the frames by episode id, stably: "
                f"data[torch.argsort(data[{TRAJ_KEY!r}], stable=True)] (collect_episodes does)"
            )
        raise ValueError(
            f"{name}: expected one contiguous block of frames per episode id, but ids "
            f"{repeated} tag several blocks of frames that do not join up step by step even "
            "sorted by id: either several episodes under one id (join collections with "
            "merge_episodes, or collect with first_id past the ids you have), or frames out of "
            "time order (shuffled, or drawn with a replay buffer's sample(): pass the frames "
            "as collected, or sort them by id and step, e.g. by a StepCounter's step_count)"
        )
    pairs = _pairs_apart(data, ids)
    if pairs is not None and bool(pairs[1].any()):
        same, apart = pairs
        first = int(same.nonzero()[apart.nonzero()[0, 0], 0])
        raise ValueError(
            f"{name}: expected each episode's frames in time order (a frame's ('next', "
            "'observation') is the 'observation' of the frame after it under the same id), but "
            f"{int(apart.sum())} of {int(same.sum())} such pairs do not join (the first: frames "
            f"{first} and {first + 1}, id {int(ids[first])}): frames drawn from a replay buffer "
            "by sample(), or shuffled, are not episodes; pass the frames as collected (a TorchRL "
            "ReplayBuffer's stored frames: rb[:])"
        )


def _pairs_apart(
    data: TensorDictBase, ids: torch.Tensor, order: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Neighbouring frames (in ``order``, default as stored) under one episode id: ``same``
    (per neighbouring pair, one id) and, per such pair, whether the first frame's next
    observation differs from the second's observation beyond float rounding; None without
    both observations."""
    obs, nxt = data.get("observation", None), data.get(("next", "observation"), None)
    if obs is None or nxt is None:
        return None
    if order is not None:
        ids, obs, nxt = ids[order], obs[order], nxt[order]
    same = ids[1:] == ids[:-1]
    later, earlier = obs[1:][same], nxt[:-1][same]
    # in one dtype: an episode's observations and next observations may be stored in two
    later, earlier = later.to(torch.float64), earlier.to(torch.float64)
    close = torch.isclose(later, earlier, rtol=ROUNDING, atol=ROUNDING, equal_nan=True)
    if close.shape[0] == 0:  # no two frames under one id (episodes of one frame each)
        return same, torch.zeros(0, dtype=torch.bool, device=close.device)
    return same, ~close.reshape(close.shape[0], -1).all(-1)


def _joins_in_time(data: TensorDictBase, ids: torch.Tensor) -> bool:
    """Whether, sorted stably by id, each frame's next observation is the following frame's
    observation within every episode id: one episode's frames cut into blocks, not several
    episodes under one id."""
    pairs = _pairs_apart(data, ids, torch.argsort(ids, stable=True))
    return pairs is not None and not bool(pairs[1].any())


def merge_episodes(*datasets: TensorDictBase) -> TensorDict:
    """Concatenate flat episode datasets ``[frames]``, renumbering ids so they stay unique.

    Each dataset's episodes keep their order; ids become ``0, 1, ...`` across all of them.
    An episode that repeats another frame for frame (every floating entry equal: a dataset
    passed twice, or collected twice with the same seeds) is warned about: merged, it would
    count twice in training, and in a split into training and held-out episodes it can land
    on both sides.

    Example:
        >>> from tensordict import TensorDict
        >>> one = TensorDict({TRAJ_KEY: torch.tensor([0, 0, 1]), "x": torch.rand(3)}, [3])
        >>> two = TensorDict({TRAJ_KEY: torch.tensor([5, 5]), "x": torch.rand(2)}, [2])
        >>> merge_episodes(one, two)[TRAJ_KEY].tolist()
        [0, 0, 1, 2, 2]
    """
    if not datasets:
        raise ValueError("datasets: expected at least one dataset, got none")
    for i, data in enumerate(datasets):
        if not isinstance(data, TensorDictBase):
            raise TypeError(
                f"datasets[{i}]: expected a TensorDict of episodes, got {type(data).__name__}"
            )
    parts, offset = [], 0
    keys = set(datasets[0].keys(True, True))
    for i, data in enumerate(datasets):
        check_episode_ids(data, f"datasets[{i}]")
        mine = set(data.keys(True, True))
        if mine != keys:
            missing, extra = sorted(map(str, keys - mine)), sorted(map(str, mine - keys))
            what = " and ".join(
                [f"lacks {missing}"] * bool(missing) + [f"has {extra} besides"] * bool(extra)
            )
            raise ValueError(
                f"datasets[{i}]: expected the entries of datasets[0], but it {what}; keep the "
                "entries all share with data.select(*keys) (a transform of one collection's env, "
                "an InitTracker's 'is_init', adds its own)"
            )
        ids = data.get(TRAJ_KEY)
        runs = torch.unique_consecutive(ids, return_inverse=True)[1]
        renumbered = data.clone()
        renumbered.set(TRAJ_KEY, runs + offset)
        offset += int(runs.max()) + 1 if runs.numel() else 0
        parts.append(renumbered)
    merged = torch.cat(parts)
    _warn_repeated_episodes(merged)
    return merged


def _warn_repeated_episodes(merged: TensorDictBase) -> None:
    """Warn where an episode of the merged datasets (ids ``0, 1, ...``, each episode's frames
    together) repeats another one frame for frame: the same length, and the same sums of every
    floating entry over its frames, plain and weighted by the frame's step."""
    floats = [v for v in merged.values(True, True) if v.is_floating_point()]
    if not floats or not len(merged):
        return
    frames = sum(v.double().reshape(len(merged), -1).nan_to_num().sum(-1) for v in floats)
    ids = merged.get(TRAJ_KEY).long()
    length = torch.bincount(ids)
    step = torch.arange(len(merged)) - (length.cumsum(0) - length)[ids] + 1
    sums = torch.zeros(len(length), 2, dtype=torch.float64)
    sums[:, 0].index_add_(0, ids, frames)
    sums[:, 1].index_add_(0, ids, frames * step)  # the frames' order counts too
    signature = torch.cat([sums, length[:, None].double()], dim=1)
    counts = torch.unique(signature, dim=0, return_counts=True)[1]
    repeated = int((counts - 1).sum())
    if repeated:
        warnings.warn(
            f"datasets: {repeated} of the {len(length)} merged episodes repeat another one frame "
            "for frame (a dataset passed twice, or collected twice with the same seeds): they "
            "would count twice in training, and a split into training and held-out episodes "
            "can put one copy on each side; merge each episode once",
            UserWarning,
            stacklevel=3,
        )

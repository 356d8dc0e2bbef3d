"""Running a policy for whole episodes in a real env, from its own starts or from given ones."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase, unravel_key
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.batched_envs import BatchedEnvBase
from torchrl.envs.utils import ExplorationType
from tqdm.auto import tqdm

from rcvae_torchrl._checks import check_non_negative_int, check_positive_int, check_seeds
from rcvae_torchrl.data import (
    TRAJ_KEY,
    acting,
    check_actions,
    exploration_mode,
    planner_generators,
    seed_env,
    warn_narrow_bounds,
)
from rcvae_torchrl.rollout import policy_reset

__all__ = ["EpisodeStats", "ResetToState", "run_episodes", "seed_episodes"]

#: ``(env, start) -> tensordict``: reset ``env`` and put it in the given start state (a row of
#: ``starts``: an observation, or a TensorDict from :func:`~rcvae_torchrl.agent.draw_starts`).
ResetToState = Callable[[EnvBase, Any], TensorDictBase]


def reset_to(reset_to_state: ResetToState, env: EnvBase, state: Any) -> TensorDictBase:
    """``reset_to_state(env, state)``, checked: it must give the env's reset tensordict, and
    where ``state`` is a TensorDict with an ``"observation"``, or a tensor of the reset
    observation's shape (a start given as its observation), the reset's must be that one (to
    1e-4, relative above 1): a reset that did not take the state starts elsewhere."""
    td = reset_to_state(env, state)
    if not isinstance(td, TensorDictBase):
        raise TypeError(
            "reset_to_state: expected the env's reset TensorDict (e.g. what "
            f"env.reset(td, set_state=True) returns), got {type(td).__name__}"
        )
    wanted = state.get("observation", None) if isinstance(state, TensorDictBase) else None
    got = td.get("observation", None)
    if isinstance(state, torch.Tensor) and isinstance(got, torch.Tensor):
        # a start given as its observation; a tensor of another shape (a simulator state of
        # the user's own) is not compared
        wanted = state if state.shape == got.shape and state.is_floating_point() else None
    if isinstance(wanted, torch.Tensor) and isinstance(got, torch.Tensor):
        if wanted.shape != got.shape:
            raise ValueError(
                f"reset_to_state: the env's reset observation has shape {tuple(got.shape)}, the "
                f"start's {tuple(wanted.shape)}"
            )
        gap = (got.double() - wanted.double().to(got.device)).abs()
        off = gap > 1e-4 * wanted.double().abs().clamp_min(1.0).to(got.device)
        if bool(off.any()):
            raise ValueError(
                f"reset_to_state: the env's reset observation differs from the start's by up "
                f"to {float(gap.max()):.4g} ({int(off.sum())} of {off.numel()} entries): the "
                "env did not start from the given state (does its reset take a state? e.g. "
                "TorchRL's reset(td, set_state=True), or a batching transform whose reset "
                "drops it), or the start's observation is not its state's (a state edited by "
                "hand: rcvae_torchrl.agent.observe_starts gives it the env's observation)"
            )
    return td


@dataclass
class EpisodeStats:
    """Outcomes of episodes run by :func:`run_episodes`."""

    success: torch.Tensor  #: ``[n]`` bool: the success flag was raised during the episode
    steps: torch.Tensor  #: ``[n]`` int64: steps to success, or the episode's length
    data: TensorDict  #: flat transitions ``[frames]`` with episode ids under ``TRAJ_KEY``

    @property
    def success_rate(self) -> float:
        return self.success.float().mean().item()


def seed_episodes(env: EnvBase, seeds: Sequence[int]) -> None:
    """Seed ``env`` for the episodes ``seeds``: an env with ``batch_size=[]`` takes one seed; a
    batched env ``[N]`` takes ``N``, with ``env.set_seeds(seeds)`` when it has it (one seed per
    sub-env; a TorchRL ``ParallelEnv`` or ``SerialEnv`` would only pass the call on to its
    sub-envs), else with :func:`~rcvae_torchrl.data.seed_env` of the first, and a warning: the
    episodes are then not those of one env run episode by episode."""
    base = env
    while isinstance(base, TransformedEnv):
        base = base.base_env
    # a TorchRL batched env passes an unknown attribute on to its sub-envs (and a transformed
    # one recursed looking for it): ask the type, not the instance
    if env.batch_size and not isinstance(base, BatchedEnvBase) and hasattr(type(base), "set_seeds"):
        base.set_seeds([int(s) for s in seeds])
        return
    if env.batch_size:
        warnings.warn(
            f"env: {type(base).__name__} [{', '.join(map(str, env.batch_size))}] has no "
            "set_seeds(seeds), so it is seeded with its first episode's seed only: its episodes "
            "are not those of one env run episode by episode, and noise inside its sub-envs (a "
            "SerialEnv's or ParallelEnv's transforms) is not restarted; for outcomes equal to "
            "one env's, pass a function that makes one env, with workers=K",
            UserWarning,
            stacklevel=3,
        )
    seed_env(env, int(seeds[0]))


def run_episodes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    *,
    seeds: Sequence[int],
    starts: torch.Tensor | TensorDictBase | None = None,
    reset_to_state: ResetToState | None = None,
    max_steps: int,
    success: str | Callable[[torch.Tensor], torch.Tensor] = "success",
    first_id: int = 0,
    progress: bool = True,
    desc: str = "episodes",
    decided_by: int | None = None,
    exploration_type: ExplorationType | str | None = None,
) -> EpisodeStats:
    """One episode per seed: seed ``env`` (:func:`~rcvae_torchrl.data.seed_env`, which also
    restarts transforms with their own noise) then reset, drawing the start state and the noise,
    or reset to the given start states ``starts`` (``[n, S]`` observations or a TensorDict
    ``[n]``) with ``reset_to_state`` (see :mod:`rcvae_torchrl.agent.starts`).

    Calls ``policy.reset()`` before each episode when the policy's class has one (a planner's
    warm start must not leak across episodes). An episode ends at the env's ``done`` or after
    ``max_steps``; it succeeds when ``success`` holds at any step: ``success`` names a flag the
    env writes under ``"next"`` (default ``"success"``), or is a function of the observations
    ``[T, S] -> [T]`` bool (for envs without a success flag). An episode the env itself
    truncates (its own time limit) before ``max_steps`` without a success is refused with a
    ``ValueError`` (:func:`check_not_cut_short`): whether it would have succeeded is unknown;
    unless it ran ``decided_by`` steps (a boundary's time limit, after which a success no
    longer counts): its outcome is then known.

    A stochastic policy (a TorchRL ``ProbabilisticActor``) acts in ``exploration_type``
    (:func:`~rcvae_torchrl.data.exploration_mode`: by default the caller's
    ``set_exploration_type``, else sampled, as TorchRL's collectors run it), its samples drawn
    from torch's global random stream seeded by each episode's seed (and restored afterwards);
    so are a planner's generators (:func:`~rcvae_torchrl.data.planner_generators`: its
    ``generator`` and that of the model env it plans in, a TorchRL planner's ``env``): the same
    seeds give the same episodes, whatever was drawn before.

    A batched env (``env.batch_size == [N]``, e.g. a vectorised simulator with ``set_seeds``)
    runs the episodes ``N`` at a time, side by side, with one policy call per step for all of
    them (a planner plans all ``N`` states at once); each sub-env is seeded with its episode's
    seed (:func:`seed_episodes`), the last group is padded with repeats of its last episode
    (dropped), and a sub-env's episode ends at its first ``done``. With a policy that acts on
    each state alone (no shared randomness) and whose rounding does not depend on the batch,
    the episodes equal the one-env run's: wrap a stateless policy in
    :class:`~rcvae_torchrl.agent.FixedRowsPolicy` for that (even an elementwise policy can
    round a state otherwise in a batch than alone).
    """
    check_positive_int("max_steps", max_steps)
    check_non_negative_int("first_id", first_id)
    check_success(success)
    seeds = check_seeds("seeds", seeds)
    if len(seeds) == 0:
        raise ValueError("seeds: expected at least one seed (one episode each), got none")
    if starts is not None:
        if not isinstance(starts, (torch.Tensor, TensorDictBase)):
            raise TypeError(
                f"starts: expected start states as a tensor [n, S] or a TensorDict [n], got "
                f"{type(starts).__name__} (torch.as_tensor converts an array)"
            )
        if len(starts) != len(seeds):
            raise ValueError(
                f"starts: expected one start state per seed ({len(seeds)}), got {len(starts)}"
            )
        if reset_to_state is None:
            raise ValueError("reset_to_state: expected a function to start from given states")
    warn_narrow_bounds(env, policy)
    if decided_by is not None:
        check_positive_int("decided_by", decided_by)
    limit = max_steps if decided_by is None else min(max_steps, decided_by)
    mode = exploration_mode(exploration_type)
    if env.batch_size:
        return _batched_episodes(
            env, policy, seeds, starts, reset_to_state, (max_steps, limit), success, first_id,
            progress, desc, mode,
        )  # fmt: skip
    wins, steps, parts = [], [], []
    for i, seed in enumerate(tqdm(seeds, desc=desc, disable=not progress, leave=False)):
        seed_env(env, int(seed))
        td = env.reset() if starts is None else reset_to(reset_to_state, env, starts[i])
        reset = policy_reset(policy)  # a planner's warm start (not an env's reset)
        if reset is not None:
            reset()
        with acting(mode, seed=int(seed), generators=planner_generators(policy)):
            episode = _rollout(env, policy, max_steps, td, break_when_any_done=True)
        check_actions(env, episode)
        won = _success_flags(episode, success)
        check_not_cut_short(episode, won.any(), torch.tensor(episode.shape[0]), limit)
        wins.append(bool(won.any()))
        steps.append(int(won.float().argmax()) + 1 if won.any() else episode.shape[0])
        episode[TRAJ_KEY] = torch.full(episode.shape, first_id + i, dtype=torch.int64)
        parts.append(episode.exclude("is_init"))
    return EpisodeStats(torch.tensor(wins), torch.tensor(steps), torch.cat(parts))


def _rollout(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    max_steps: int,
    td: TensorDictBase,
    **kwargs: Any,
) -> TensorDictBase:
    """``env.rollout`` of ``policy`` from ``td``; a module that does not take the env's
    TensorDict (a tensor policy ``observation -> action``) is named with how to wire it. The
    actions of a TensorDict policy are checked before the env acts on them
    (``_CheckedPolicy``)."""
    if isinstance(policy, TensorDictModuleBase) or not isinstance(policy, torch.nn.Module):
        policy = _CheckedPolicy(policy, env)  # a TensorDict module or a plain function
    try:
        with torch.no_grad():
            return env.rollout(max_steps, policy, auto_reset=False, tensordict=td, **kwargs)
    except TypeError as err:
        # a module that is no TensorDict module; a TypeError of a TensorDict function is not
        # the policy's kind
        if isinstance(policy, TensorDictModuleBase) or not isinstance(policy, torch.nn.Module):
            raise
        raise TypeError(
            f"policy: calling {type(policy).__name__} in the env failed ({err}); a policy in a "
            'real env maps the env\'s TensorDict to one with an "action": wire a tensor policy '
            'observation -> action with TensorDictModule(policy, in_keys=["observation"], '
            'out_keys=["action"]) (rcvae_torchrl.agent.make_policy_module)'
        ) from err


class _CheckedPolicy(TensorDictModuleBase):
    """``policy``, its action checked at every call before ``env`` acts on it: the shape the
    env's batch and action spec give, and finite values. A simulator handed another shape or
    a NaN fails inside its own step (a broadcast error, a physics warning) without naming the
    policy; bounds and dtype are checked on the whole episode afterwards
    (:func:`~rcvae_torchrl.data.check_actions`)."""

    def __init__(self, policy: Callable[[TensorDictBase], Any], env: EnvBase) -> None:
        super().__init__()
        check_policy(policy)
        self.policy = policy
        # a plain function of the TensorDict declares no keys (a rollout selects none)
        self.in_keys = list(getattr(policy, "in_keys", []))
        self.out_keys = list(getattr(policy, "out_keys", [env.action_key]))
        self.action_key = env.action_key
        self.batch = tuple(env.batch_size)
        self.action_shape = tuple(env.action_spec_unbatched.shape)
        self.calls = 0

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = self.policy(tensordict)
        out = tensordict if out is None else out
        action = out.get(self.action_key, None)
        step, self.calls = self.calls, self.calls + 1
        if not isinstance(action, torch.Tensor):
            raise KeyError(
                f"policy: expected it to write the env's action {self.action_key!r} at every "
                f"step, got none at step {step}"
            )
        wanted = (*self.batch, *self.action_shape)
        if tuple(action.shape) != wanted:
            raise ValueError(
                f"policy: expected actions of shape {wanted} (the env's batch {list(self.batch)} "
                f"and its action_spec's {list(self.action_shape)}), got {tuple(action.shape)} at "
                f"step {step}"
            )
        if action.is_floating_point() and not bool(torch.isfinite(action).all()):
            bad = int((~torch.isfinite(action)).sum())
            raise ValueError(
                f"policy: expected finite actions, got {bad} of {action.numel()} NaN or inf at "
                f"step {step}; the env cannot act on them"
            )
        return out


def check_policy(policy: object) -> None:
    """Require a TorchRL policy: a callable on the env's TensorDict."""
    if not callable(policy):
        raise TypeError(f"policy: expected a TorchRL policy (callable), got {policy!r}")


def check_success(success: object) -> None:
    """Require what judges an episode a success: the name of a flag the env writes under
    ``"next"``, or a function of the observations ``[T, S] -> [T]`` bool."""
    key = isinstance(success, str) or (
        isinstance(success, tuple) and success and all(isinstance(k, str) for k in success)
    )
    if not (key or callable(success)):
        raise TypeError(
            f"success: expected the name of the env's success flag (e.g. 'success') or a "
            f"function of the observations [T, S] -> [T] bool, got {success!r}"
        )


def _success_flags(
    episode: TensorDictBase, success: str | Callable[[torch.Tensor], torch.Tensor]
) -> torch.Tensor:
    """The per-step success flags of ``episode`` (shape ``episode.shape``), from the env's
    flag named ``success`` or a function of the observations."""
    if callable(success):
        won = success(episode["next", "observation"])
        if not isinstance(won, torch.Tensor) or won.dtype != torch.bool:
            got = won.dtype if isinstance(won, torch.Tensor) else type(won).__name__
            raise TypeError(f"success: expected a bool tensor [T] of the episode, got {got}")
    else:
        flags = episode.get("next")
        if success not in flags.keys(True, True):
            given = unravel_key(success) if isinstance(success, (str, tuple)) else success
            under = (
                f"; the name is read under 'next': pass success={given[1]!r}"
                if isinstance(given, tuple) and given[0] == "next" and len(given) == 2
                else ""
            )
            raise KeyError(
                f"success: the env writes no {success!r} flag (its entries under 'next': "
                f"{sorted(map(str, flags.keys(True, True)))}){under}; pass success= the name "
                "of its flag, or a function of an episode's observations [T, S] -> [T] bool "
                "(e.g. a SuccessBoundary's success_over_time)"
            )
        won = flags.get(success)
        if won.dtype != torch.bool:  # a reward of 1e-40 would count as a success
            raise TypeError(
                f"success: expected the env's {success!r} entry to be a bool flag, got dtype "
                f"{won.dtype}; pass success= a function of an episode's observations [T, S] -> "
                "[T] bool (e.g. a SuccessBoundary's success_over_time), or the name of a bool "
                "flag the env writes"
            )
    if won.numel() != episode.numel():
        raise ValueError(
            f"success: expected one flag per step of the episode ({episode.numel()}), got "
            f"shape {tuple(won.shape)}"
        )
    return won.reshape(episode.shape)


def check_not_cut_short(
    episode: TensorDictBase, hit: torch.Tensor, length: torch.Tensor, max_steps: int
) -> None:
    """Raise when an episode the env itself cut short (``truncated``: its own time limit, e.g.
    a ``StepCounter``) before ``max_steps`` has no success: whether it would have succeeded
    in the steps it was not given is unknown, and counting it as a failure would be wrong.

    ``episode``: a rollout ``[T]`` or ``[N, T]``; ``hit``: whether each succeeded (``[]`` or
    ``[N]``); ``length``: the steps each ran (to its first ``done``). An env without a
    ``truncated`` entry counts a ``done`` without ``terminated`` as one; an env with neither
    cuts nothing short.
    """
    step = episode.get("next")
    keys = step.keys()
    if "truncated" in keys:
        truncated = step.get("truncated")
    elif "terminated" in keys:
        truncated = step.get("done") & ~step.get("terminated")
    else:
        return
    truncated = truncated.reshape(episode.shape)
    last = (length - 1).clamp_min(0).unsqueeze(-1)
    cut = truncated.gather(-1, last).squeeze(-1) & ~hit & (length < max_steps)
    if bool(cut.any()):
        first = int(length.reshape(-1)[cut.reshape(-1).nonzero()[0, 0]])
        # episodes are checked as they are run: one, or the group that ran together
        which = (
            "an episode was"
            if cut.numel() == 1
            else f"{int(cut.sum())} of the {cut.numel()} episodes run together were"
        )
        raise ValueError(
            f"env: {which} cut short by the env itself (truncated, e.g. by its own time limit) "
            f"before max_steps={max_steps} and without a success, the first after {first} "
            f"steps: whether it would have succeeded is unknown. Let the env run at least "
            f"{max_steps} steps (a StepCounter's max_steps; a dm_control task's time limit in "
            f"seconds, e.g. DMControlEnv(domain, task, time_limit=...)), or ask for success "
            f"within {first} steps"
        )


def episode_groups(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    seeds: Sequence[int],
    start: Callable[[EnvBase, list[int], torch.Tensor], TensorDictBase],
    max_steps: int,
    *,
    until_all_done: bool | None = None,
    progress: bool = True,
    desc: str = "episodes",
    exploration_type: ExplorationType | str | None = None,
) -> Iterator[tuple[int, int, TensorDictBase]]:
    """The episodes ``seeds`` in a batched env, ``N = env.batch_size.numel()`` at a time: each
    group begun by ``start(env, its seeds, its episode indices)`` (the last group padded with
    repeats of its last episode), the policy reset (``policy.reset()`` where its class has
    one), then rolled out for ``max_steps`` (a sub-env that is done stays done; with
    ``until_all_done`` the rollout stops once all are), the policy acting as in
    :func:`run_episodes` (torch's global random stream and a planner's generators seeded by
    the group's first seed).
    Yields ``(first episode index, episodes kept, rollout [N, T])``."""
    n, total = env.batch_size.numel(), len(seeds)
    mode = exploration_mode(exploration_type)
    for low in tqdm(range(0, total, n), desc=desc, disable=not progress, leave=False):
        rows = torch.arange(low, low + n).clamp_max(total - 1)  # pad with the last episode
        td = start(env, [int(seeds[i]) for i in rows], rows)
        reset = policy_reset(policy)
        if reset is not None:
            reset()
        with acting(mode, seed=int(seeds[low]), generators=planner_generators(policy)):
            episode = _rollout(
                env,
                policy,
                max_steps,
                td,
                break_when_any_done=False,
                break_when_all_done=until_all_done,
            )
        yield low, min(n, total - low), episode.reshape(n, episode.shape[-1])


def episode_lengths(done: torch.Tensor) -> torch.Tensor:
    """The length ``[N]`` of each sub-env's episode in a batched rollout's ``done`` ``[N, T]``:
    up to its first done, or the whole rollout."""
    full = torch.full_like(done[:, 0], done.shape[1], dtype=torch.int64)
    return torch.where(done.any(1), done.float().argmax(1) + 1, full)


def _batched_episodes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    seeds: Sequence[int],
    starts: torch.Tensor | TensorDictBase | None,
    reset_to_state: ResetToState | None,
    steps: tuple[int, int],
    success: str | Callable[[torch.Tensor], torch.Tensor],
    first_id: int,
    progress: bool,
    desc: str,
    mode: ExplorationType,
) -> EpisodeStats:
    """:func:`run_episodes` in a batched env ``[N]``: ``N`` episodes side by side at a time;
    ``steps``: ``(max_steps, the step by which the outcome is decided)``."""
    max_steps, limit = steps
    if len(env.batch_size) != 1:
        raise ValueError(f"env: expected batch_size [] or [N], got {list(env.batch_size)}")

    def start(env: EnvBase, group: list[int], rows: torch.Tensor) -> TensorDictBase:
        seed_episodes(env, group)
        return env.reset() if starts is None else reset_to(reset_to_state, env, starts[rows])

    wins, steps, parts = [], [], []
    groups = episode_groups(
        env,
        policy,
        seeds,
        start,
        max_steps,
        until_all_done=True,
        progress=progress,
        desc=desc,
        exploration_type=mode,
    )
    for low, keep, episode in groups:
        check_actions(env, episode)
        won = _success_flags(episode, success)
        length = episode_lengths(episode["next", "done"].reshape(episode.shape))
        before_end = torch.arange(episode.shape[1]) < length.unsqueeze(1)
        hit = (won & before_end).any(1)  # rows past keep pad the last group: not asked for
        check_not_cut_short(episode[:keep], hit[:keep], length[:keep], limit)
        for j in range(keep):
            end = int(length[j])
            flags, kept = won[j, :end], episode[j, :end]
            wins.append(bool(flags.any()))
            steps.append(int(flags.float().argmax()) + 1 if flags.any() else end)
            kept[TRAJ_KEY] = torch.full(kept.shape, first_id + low + j, dtype=torch.int64)
            parts.append(kept.exclude("is_init"))
    return EpisodeStats(torch.tensor(wins), torch.tensor(steps), torch.cat(parts))

"""Imagined rollouts ``[E, N, *B, T]`` from start states, open or closed loop.

Samples x^{m,n}_t of member m, sample n, start state b and time t feed the uncertainty
decomposition of Acharya, Russell & Ahmed (2022), eq. 2-3: sample ``(m, n, b)`` follows member m
throughout (TS-∞), which is what a decomposition per member needs. Entry t describes the
transition s_t -> s_{t+1}, i.e. what ``env.step`` writes under ``"next"`` (``"action"`` is a_t,
as at the root of a TorchRL rollout).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import unravel_key
from torchrl.modules import GRUModule, LSTMModule

from rcvae_torchrl import _checks
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout.loop import (
    ActionBounds,
    Policy,
    StepRecord,
    check_action_bounds,
    rollout,
)
from rcvae_torchrl.rollout.task import Task, alive_mask

__all__ = [
    "ImaginePolicy",
    "as_tensor_policy",
    "chunk_size_for",
    "imagine",
    "plan_actions",
    "policy_reset",
]

ImaginePolicy = TensorDictModuleBase | Policy
"""A TensorDict module (reads ``"observation"``, writes ``"action"``) or a tensor callable."""

#: ``chunk_size="auto"``: trajectories per member rolled out together, by device type. On a CPU
#: a chunk's tensors stay in cache; on a GPU every op of a step is one kernel launch whatever
#: its width, so a small chunk leaves the device idle (on an H100, at 131,072 trajectories per
#: member, chunks of 1024 ran 24x slower than one chunk: benchmarks/gpu_throughput.py).
AUTO_CHUNK_CPU, AUTO_CHUNK_ACCELERATOR = 1024, 65536


def chunk_size_for(chunk_size: int | str | None, device: torch.device | str) -> int | None:
    """The chunk size ``imagine`` uses: ``"auto"`` resolves by ``device`` (:data:`AUTO_CHUNK_CPU`
    on a CPU, else :data:`AUTO_CHUNK_ACCELERATOR`); a count or ``None`` (one chunk) is kept."""
    if chunk_size == "auto":
        try:
            cpu = torch.device(device).type == "cpu"
        except (RuntimeError, TypeError) as err:
            raise ValueError(f"device: expected a torch device, got {device!r} ({err})") from None
        return AUTO_CHUNK_CPU if cpu else AUTO_CHUNK_ACCELERATOR
    _checks.check_positive_int_or_none("chunk_size", chunk_size)
    return chunk_size


_MODEL_KEYS = ("observation", "action", ("rcvae", "loc"), ("rcvae", "scale"), ("rcvae", "latent"))


def as_tensor_policy(
    policy: ImaginePolicy, observation_key: str = "observation", action_key: str = "action"
) -> Policy:
    """A tensor callable ``[..., S] -> [..., A]`` from either kind of policy.

    A TensorDict module is called on a TensorDict holding only ``observation_key``, with the
    observations' leading dims as its batch, and its ``action_key`` entry is returned.
    """
    if not isinstance(policy, TensorDictModuleBase):
        if not callable(policy):
            raise TypeError(f"policy: expected a callable, got {type(policy).__name__}")
        return policy
    writes = [unravel_key(k) for k in policy.out_keys]  # ("action",) is "action"
    if unravel_key(action_key) not in writes:
        raise KeyError(
            f"policy: writes {writes}, not {action_key!r}; give it out_keys=[{action_key!r}]"
        )
    recurrent = [type(m).__name__ for m in policy.modules() if isinstance(m, _RECURRENT)]
    if recurrent:  # before any call: the module fills its missing memory in with zeros
        raise KeyError(
            f"policy: holds a recurrent {recurrent[0]}, whose memory lives in entries beside "
            f"the state (InitTracker's 'is_init', its primer's hidden state) that imagination "
            f"does not carry: it would act as if every step were its first. "
            f"{_KEEP_MEMORY.format(key=observation_key)}"
        )

    def call(observation: torch.Tensor) -> torch.Tensor:
        td = TensorDict({observation_key: observation}, batch_size=observation.shape[:-1])
        try:
            return policy(td).get(action_key)
        except KeyError as err:
            reads = [k for k in getattr(policy, "in_keys", []) if k not in td.keys(True, True)]
            if not reads:
                raise
            raise KeyError(_reads_more(reads, observation_key)) from err

    return call


#: TorchRL's recurrent modules: their memory is kept in entries beside the state
_RECURRENT = (LSTMModule, GRUModule)
#: what a policy with memory does instead
_KEEP_MEMORY = (
    "Keep the memory inside a policy of your own: a callable on {key!r} [E, R, S] -> actions "
    "[E, R, A] with a reset() method, called on each step of a batch of imagined episodes in "
    "turn, and reset() before each batch"
)


def _reads_more(reads: list, observation_key: str) -> str:
    """Why a TensorDict policy that reads ``reads`` besides the state cannot act in
    imagination, and what to do."""
    return (
        f"policy: reads {reads}, but in imagination the world model gives it only "
        f"{observation_key!r} [..., S]: write the policy on {observation_key!r} (the env's "
        "entries concatenated, as rcvae_torchrl.data.prepare_env's layout names them). A "
        "recurrent policy's memory (InitTracker's 'is_init', a primer's hidden state) is not "
        f"carried either. {_KEEP_MEMORY.format(key=observation_key)}"
    )


class _Recorder:
    """Keeps every step's s_{t+1}, a_t, the decoder's Gaussian over s_{t+1} and z_{t+1}."""

    def __init__(self, ensemble: RCVAEEnsemble) -> None:
        self.ensemble = ensemble
        self.steps: list[tuple[torch.Tensor, ...]] = []

    def __call__(self, step: StepRecord) -> None:
        out = step.out
        loc, scale = self.ensemble.state_loc_scale(step.previous, out.delta_mean, out.delta_std)
        self.steps.append((out.observation, step.action, loc, scale, out.latent))

    def stacked(self) -> dict:
        return {k: torch.stack(v, dim=-2) for k, v in zip(_MODEL_KEYS, zip(*self.steps))}


class _FirstMemberActions:
    """Keeps member 0's actions: the plan the policy makes along one imagined rollout."""

    def __init__(self) -> None:
        self.actions: list[torch.Tensor] = []

    def __call__(self, step: StepRecord) -> None:
        self.actions.append(step.action[0])


def _chunks(
    ensemble: RCVAEEnsemble,
    starts: torch.Tensor,
    samples: int,
    chunk_size: int | None,
    plan: torch.Tensor | None,
):
    """For each chunk of trajectory rows (row r = sample r // P of start r % P): the member-major
    start states ``[E, R, S]`` and the open-loop actions ``[T, E, R, A]`` (or None)."""
    rows = torch.arange(samples * starts.shape[0], device=starts.device)
    e = ensemble.ensemble_size
    for chunk in rows.split(chunk_size or rows.numel()):
        start_of = chunk % starts.shape[0]
        state = starts[start_of].expand(e, -1, -1)
        actions = None
        if plan is not None:
            actions = plan[start_of].transpose(0, 1).unsqueeze(1).expand(-1, e, -1, -1)
        yield state, actions


def _rollout_chunks(
    ensemble: RCVAEEnsemble,
    starts: torch.Tensor,
    samples: int,
    horizon: int,
    make_hook,
    *,
    plan: torch.Tensor | None,
    policy: Policy | None,
    bounds: ActionBounds | None,
    generator: torch.Generator | None,
    chunk_size: int | None,
    reset: Callable[[], object] | None = None,
) -> list:
    """Roll every chunk of trajectory rows out (TS-∞, member-major) with a fresh hook each;
    returns the hooks. ``reset`` (a stateful policy's, e.g. a planner's warm start) is called
    before every chunk but the first, whose episodes are new too (the caller resets before
    the first)."""
    hooks = []
    for state, actions in _chunks(ensemble, starts, samples, chunk_size, plan):
        if hooks and reset is not None:
            reset()
        hooks.append(make_hook())
        rollout(
            ensemble,
            "ts_inf",
            state,
            ensemble.initial_hidden(state.shape[1:2], state, generator),
            horizon,
            hooks[-1],
            actions=actions,
            policy=policy,
            bounds=bounds,
            generator=generator,
        )
    return hooks


def policy_reset(policy: object) -> Callable[[], object] | None:
    """A stateful policy's ``reset`` (a method of its class, e.g. a planner's: its warm start
    forgotten), called where imagined episodes begin; ``None`` for a stateless one."""
    return policy.reset if policy is not None and hasattr(type(policy), "reset") else None


def imagine(
    ensemble: RCVAEEnsemble,
    observation: torch.Tensor,
    actions: torch.Tensor | None = None,
    *,
    policy: ImaginePolicy | None = None,
    horizon: int | None = None,
    samples_per_member: int = 1,
    task: Task | None = None,
    bounds: ActionBounds | None = None,
    generator: torch.Generator | None = None,
    chunk_size: int | str | None = "auto",
    requires_grad: bool = False,
) -> TensorDictBase:
    """N TS-∞ samples per member from each start state, open or closed loop.

    Open loop: pass ``actions [*B, T, A]``. Closed loop: pass ``policy`` and ``horizon`` T; the
    policy is called once per step and chunk on the current states ``[E, R, S]`` (R =
    trajectories per member in the chunk) and must return actions ``[E, R, A]``.

    Args:
        ensemble: the world model (E members).
        observation: start states s_0 ``[*B, S]``.
        actions: a_0..a_{T-1} ``[*B, T, A]`` (open loop).
        policy: closed-loop policy (instead of ``actions``), see :data:`ImaginePolicy`.
        horizon: number of steps T in closed loop.
        samples_per_member: N.
        task: adds reward, success and episode ends (see below).
        bounds: clip actions to the real env's bounds, as it does.
        generator: source of all sampling noise (same generator state and chunk size -> same
            samples).
        chunk_size: trajectories per member rolled out together (``None``: all ``N·|B|`` at
            once; ``"auto"``: by the model's device, see :func:`chunk_size_for`: 1024 on a
            CPU, where bounded chunks keep tensors in cache, 65,536 on a GPU). The noise drawn
            depends on it.
        requires_grad: keep the autograd graph (off by default: rollouts are for evaluation).

    Returns:
        TensorDict ``[E, N, *B, T]``: ``"observation"`` s_{t+1} ``[..., S]``, ``"action"`` a_t
        ``[..., A]``, ``("rcvae", "loc")`` / ``("rcvae", "scale")`` ``[..., S]`` the decoder's
        Gaussian over s_{t+1} given the sampled z (passthrough dims: scale 0),
        ``("rcvae", "latent")`` z_{t+1} and ``"member"`` int64. With a ``task``, also what
        ``env.step`` would write: ``"reward"`` ``[..., 1]``, ``"success"``, ``"terminated"``,
        ``"truncated"`` (the horizon's last step, unless terminated) and ``"done"``, bool
        ``[..., 1]``; and ``"mask"`` bool ``[E, N, *B, T]``, True for the steps of the episode
        (up to and including its first ``terminated``).

    Raises:
        ValueError: non-finite or ill-shaped inputs, or non-finite states produced by the model.

    Example:
        >>> from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
        >>> model = RCVAEEnsemble(RCVAEConfig(4, 2, hidden_dim=16, mlp_dim=16), ensemble_size=3)
        >>> imagine(model, torch.zeros(4), torch.zeros(10, 2), samples_per_member=8).batch_size
        torch.Size([3, 8, 10])
    """
    tensor_policy = None if policy is None else as_tensor_policy(policy)
    _check_inputs(ensemble, observation, actions, samples_per_member, tensor_policy, horizon)
    check_action_bounds(bounds, ensemble.config.action_dim)
    _checks.check_bool("requires_grad", requires_grad)
    chunk_size = chunk_size_for(chunk_size, ensemble.device)
    n_steps = actions.shape[-2] if actions is not None else int(horizon)
    grid = (ensemble.ensemble_size, samples_per_member, *observation.shape[:-1])
    starts = observation.reshape(-1, observation.shape[-1])
    plan = None if actions is None else actions.reshape(starts.shape[0], n_steps, -1)
    with torch.set_grad_enabled(requires_grad and torch.is_grad_enabled()):
        hooks = _rollout_chunks(
            ensemble,
            starts,
            samples_per_member,
            n_steps,
            lambda: _Recorder(ensemble),
            plan=plan,
            policy=tensor_policy,
            bounds=bounds,
            generator=generator,
            chunk_size=chunk_size,
            reset=policy_reset(policy),
        )
    parts = [hook.stacked() for hook in hooks]
    out = TensorDict(
        {k: torch.cat([p[k] for p in parts], 1).reshape(*grid, n_steps, -1) for k in _MODEL_KEYS},
        batch_size=[*grid, n_steps],
    )
    _check_output(out.get("observation"))
    member = torch.arange(ensemble.ensemble_size, device=observation.device)
    out.set("member", member.view(-1, *([1] * (out.batch_dims - 1))).expand(out.batch_size).clone())
    if task is not None:
        entries = task.transitions(out.get("observation"), out.get("action"), horizon_ends=True)
        _check_rewards(entries["reward"])
        out.update(entries)
        out.set("mask", alive_mask(entries["terminated"].squeeze(-1)))
    return out


def plan_actions(
    ensemble: RCVAEEnsemble,
    observation: torch.Tensor,
    policy: ImaginePolicy,
    horizon: int,
    *,
    bounds: ActionBounds | None = None,
    generator: torch.Generator | None = None,
    chunk_size: int | str | None = "auto",
) -> torch.Tensor:
    """The policy's actions ``[*B, H, A]`` along one imagined rollout per start (member 0).

    The same actions as ``imagine(ensemble, observation, policy=policy, horizon=horizon)
    ["action"][0, 0]`` from the same generator state (the same steps and noise, every member
    stepped), without what a plan does not need: the decoder's Gaussian, the task, the
    TensorDict of the whole rollout. Used as the policy-guided planner's proposal and as the
    open-loop plan of a closed-loop policy.
    """
    tensor_policy = as_tensor_policy(policy)
    _check_inputs(ensemble, observation, None, 1, tensor_policy, horizon)
    check_action_bounds(bounds, ensemble.config.action_dim)
    chunk_size = chunk_size_for(chunk_size, ensemble.device)
    with torch.no_grad():
        hooks = _rollout_chunks(
            ensemble,
            observation.reshape(-1, observation.shape[-1]),
            1,
            horizon,
            _FirstMemberActions,
            plan=None,
            policy=tensor_policy,
            bounds=bounds,
            generator=generator,
            chunk_size=chunk_size,
        )
    plans = [torch.stack(hook.actions, dim=-2) for hook in hooks]
    return torch.cat(plans).reshape(*observation.shape[:-1], horizon, -1)


def _check_inputs(
    ensemble: RCVAEEnsemble,
    observation: torch.Tensor,
    actions: torch.Tensor | None,
    samples_per_member: int,
    policy: Policy | None,
    horizon: int | None,
) -> None:
    cfg, dtype = ensemble.config, ensemble.dtype
    _checks.check_tensor("observation", observation)
    _checks.check_trailing("observation", observation, (cfg.obs_dim,), f"[*B, S={cfg.obs_dim}]")
    if observation.numel() == 0:
        raise ValueError(
            f"observation: expected at least one start state, got shape {tuple(observation.shape)}"
        )
    _checks.check_floating("observation", observation)
    _checks.check_finite("observation", observation)
    _checks.check_dtype("observation", observation, dtype)
    _checks.check_positive_int("samples_per_member", samples_per_member)
    if (actions is None) == (policy is None):
        raise ValueError("actions, policy: expected exactly one (open loop or closed loop)")
    if policy is not None:
        _checks.check_positive_int("horizon", horizon)
        return
    _checks.check_tensor("actions", actions)
    if horizon is not None and (actions.dim() < 2 or horizon != actions.shape[-2]):
        raise ValueError(
            f"horizon: open loop takes T from the actions, expected None or their T, got "
            f"{horizon!r} for actions of shape {tuple(actions.shape)}"
        )
    what = f"[*B, T, A={cfg.action_dim}] with [*B] = {list(observation.shape[:-1])}"
    if actions.dim() < 2 or actions.shape[-1] != cfg.action_dim or actions.shape[-2] < 1:
        raise ValueError(f"actions: expected shape {what} and T >= 1, got {tuple(actions.shape)}")
    _checks.check_batch_shapes(
        ("observation", "actions"), observation.shape[:-1], actions.shape[:-2]
    )
    _checks.check_floating("actions", actions)
    _checks.check_finite("actions", actions)
    _checks.check_dtype("actions", actions, dtype)


def _check_rewards(reward: torch.Tensor) -> None:
    """Refuse to return non-finite rewards silently (finite states far out of range can
    overflow a reward function)."""
    bad = ~torch.isfinite(reward)
    if bool(bad.any()):
        raise ValueError(
            f"reward_fn: returned {int(bad.sum())} non-finite rewards of {reward.numel()} on "
            "the imagined states; the start states or the model's states are out of the range "
            "the reward function handles"
        )


def _check_output(states: torch.Tensor) -> None:
    """Refuse to return non-finite imagined states silently."""
    bad = ~torch.isfinite(states).flatten(0, -3).all(0).all(-1)
    if bool(bad.any()):
        first = int(bad.nonzero()[0, 0])
        raise ValueError(
            f"imagine: the model produced non-finite states from step {first + 1} on; "
            "check the normaliser statistics and the parameters for NaN/inf"
        )

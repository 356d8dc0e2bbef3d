"""The one-step TensorDict module of the model env, and the model state at reset.

A model env (TorchRL ``ModelBasedEnvBase``) carries the model state through ``step_mdp``:
``("rcvae", "hidden")``, ``("rcvae", "latent")`` and, except for ``"mean"``, ``"member"``. It
builds the state with :func:`init_model_state` at reset and calls :class:`ParticleTransition`
at every step; the step itself is :func:`~rcvae_torchrl.rollout.propagate`.

For ``"ts_inf"`` the particles of a tensordict can follow any members in any order; they are
packed into member-major slots (:class:`~rcvae_torchrl.rollout.layout.MemberLayout`) so that
one batched matmul per layer serves all members, and their noise is drawn in particle order
(so the samples do not depend on the packing).
"""

from __future__ import annotations

from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from rcvae_torchrl import _checks
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout.layout import MemberLayout
from rcvae_torchrl.rollout.sampling import (
    TRAJECTORY_SAMPLINGS,
    Propagated,
    TrajectorySampling,
    draw_noise,
    propagate,
)

__all__ = ["ParticleTransition", "init_model_state", "make_transition_module"]


def _prefixed(prefix: tuple[str, ...], key: NestedKey) -> NestedKey:
    if not prefix:
        return key
    return (*prefix, *key) if isinstance(key, tuple) else (*prefix, key)


class ParticleTransition(TensorDictModuleBase):
    """Sample s_{t+1} for every particle of a tensordict of any batch shape ``[*B]``.

    Reads ``observation [*B, S]``, ``action [*B, A]``, ``hidden`` (``[*B, H]`` for ``"ts_inf"``,
    every member's ``[*B, E, H]`` otherwise) and, for ``"ts_inf"``, ``member [*B]`` (int64);
    writes ``observation``, ``hidden``, ``latent [*B, Z]`` and (not for ``"mean"``) ``member``
    under ``out_prefix``. The latent z_{t+1} is an output only: the recurrence reads the
    sampled state, not the previous latent.

    Args:
        ensemble: the world model.
        trajectory_sampling: ``"ts_inf"``, ``"ts1"`` or ``"mean"``
            (:mod:`~rcvae_torchrl.rollout.sampling`).
        generator: torch generator for all sampling (``None``: the global RNG).
        validate: check shapes, finiteness and member range at each call.
        out_prefix: where outputs go: ``("next",)`` (default, as ``EnvBase.step`` lays out a
            transition) or ``()`` to overwrite the input keys in place, which is what the stock
            ``ModelBasedEnvBase._step`` selects from its world model's output.
        observation_key, action_key, hidden_key, latent_key, member_key: tensordict keys.

    Example:
        >>> from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
        >>> model = RCVAEEnsemble(RCVAEConfig(4, 2, hidden_dim=8, mlp_dim=8), ensemble_size=3)
        >>> step = make_transition_module(model)
        >>> td = init_model_state(model, torch.zeros(6, 4))
        >>> td["action"] = torch.zeros(6, 2)
        >>> step(td)["next", "observation"].shape
        torch.Size([6, 4])
    """

    def __init__(
        self,
        ensemble: RCVAEEnsemble,
        *,
        trajectory_sampling: TrajectorySampling = "ts_inf",
        generator: torch.Generator | None = None,
        validate: bool = True,
        out_prefix: tuple[str, ...] = ("next",),
        observation_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        hidden_key: NestedKey = ("rcvae", "hidden"),
        latent_key: NestedKey = ("rcvae", "latent"),
        member_key: NestedKey = "member",
    ) -> None:
        super().__init__()
        _checks.check_choice("trajectory_sampling", trajectory_sampling, TRAJECTORY_SAMPLINGS)
        self.ensemble = ensemble
        self.trajectory_sampling = trajectory_sampling
        self.generator = generator
        self.validate = validate
        self.keys = (observation_key, action_key, hidden_key, latent_key, member_key)
        self.in_keys = [observation_key, action_key, hidden_key]
        outputs = [observation_key, hidden_key, latent_key]
        if trajectory_sampling != "mean":
            outputs.append(member_key)
        if trajectory_sampling == "ts_inf":
            self.in_keys.append(member_key)
        if not isinstance(out_prefix, tuple) or not all(isinstance(k, str) for k in out_prefix):
            raise TypeError(
                f"out_prefix: expected a tuple of key names (e.g. ('next',) or ()), got "
                f"{out_prefix!r}"
            )
        self.out_keys = [_prefixed(tuple(out_prefix), k) for k in outputs]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs_k, act_k, hid_k, _, mem_k = self.keys
        obs, action = tensordict.get(obs_k), tensordict.get(act_k)
        hidden, member = tensordict.get(hid_k), tensordict.get(mem_k, None)
        if self.validate:
            self._check(obs, action, hidden, member)
        batch, e, h = obs.shape[:-1], self.ensemble.ensemble_size, self.ensemble.carry_dim
        flat_obs, flat_action = obs.reshape(-1, obs.shape[-1]), action.reshape(-1, action.shape[-1])
        if self.trajectory_sampling == "ts_inf":
            out = self._ts_inf(flat_obs, flat_action, hidden.reshape(-1, h), member.reshape(-1))
            new_hidden = out.hidden.reshape(*batch, h)
        else:
            every = hidden.reshape(-1, e, h).transpose(0, 1)
            out = propagate(
                self.ensemble,
                self.trajectory_sampling,
                every,
                flat_obs,
                flat_action,
                generator=self.generator,
            )
            new_hidden = out.hidden.transpose(0, 1).reshape(*batch, e, h)
        latent = out.latent.reshape(*batch, out.latent.shape[-1])  # explicit sizes: B may be 0
        values = [out.observation.reshape(*batch, obs.shape[-1]), new_hidden, latent]
        if self.trajectory_sampling != "mean":
            values.append((member.reshape(-1) if out.member is None else out.member).reshape(batch))
        for key, value in zip(self.out_keys, values):
            tensordict.set(key, value)
        return tensordict

    def _ts_inf(
        self, obs: torch.Tensor, action: torch.Tensor, hidden: torch.Tensor, member: torch.Tensor
    ) -> Propagated:
        layout = MemberLayout(member, self.ensemble.ensemble_size)
        noise = draw_noise(self.ensemble, (obs.shape[0],), obs, self.generator)
        out = propagate(
            self.ensemble,
            "ts_inf",
            layout.pack(hidden),
            layout.pack(obs),
            layout.pack(action),
            noise=tuple(layout.pack(n) for n in noise),
        )
        return Propagated(*(None if v is None else layout.unpack(v) for v in out))

    def _check(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        hidden: torch.Tensor,
        member: torch.Tensor | None,
    ) -> None:
        cfg, e = self.ensemble.config, self.ensemble.ensemble_size
        names = [str(k) for k in self.keys]
        for name, x in zip(names[:3], (obs, action, hidden)):
            if x is None:
                raise KeyError(f"{name}: missing from the input tensordict")
        _checks.check_trailing(names[0], obs, (cfg.obs_dim,), f"[*B, S={cfg.obs_dim}]")
        _checks.check_trailing(names[1], action, (cfg.action_dim,), f"[*B, A={cfg.action_dim}]")
        _checks.check_batch_shapes((names[0], names[1]), obs.shape[:-1], action.shape[:-1])
        ts_inf = self.trajectory_sampling == "ts_inf"
        hid = (self.ensemble.carry_dim,) if ts_inf else (e, self.ensemble.carry_dim)
        _checks.check_trailing(names[2], hidden, hid, f"[*B, {', '.join(map(str, hid))}]")
        _checks.check_batch_shapes((names[0], names[2]), obs.shape[:-1], hidden.shape[: -len(hid)])
        for name, x in zip(names[:3], (obs, action, hidden)):
            _checks.check_finite(name, x)
            _checks.check_dtype(name, x, self.ensemble.dtype)
        if ts_inf:
            if member is None:
                raise KeyError(f"{names[4]}: missing; 'ts_inf' needs the member of each particle")
            _checks.check_batch_shapes((names[0], names[4]), obs.shape[:-1], member.shape)
            _checks.check_member(member, e, names[4])


def make_transition_module(
    ensemble: RCVAEEnsemble,
    *,
    trajectory_sampling: TrajectorySampling = "ts_inf",
    generator: torch.Generator | None = None,
    validate: bool = True,
    out_prefix: tuple[str, ...] = ("next",),
    **keys: NestedKey,
) -> ParticleTransition:
    """Factory for :class:`ParticleTransition` with the library's default keys.

    ``keys`` may override ``observation_key``, ``action_key``, ``hidden_key``, ``latent_key``
    and ``member_key``.
    """
    return ParticleTransition(
        ensemble,
        trajectory_sampling=trajectory_sampling,
        generator=generator,
        validate=validate,
        out_prefix=out_prefix,
        **keys,
    )


def init_model_state(
    ensemble: RCVAEEnsemble,
    observation: torch.Tensor,
    *,
    trajectory_sampling: TrajectorySampling = "ts_inf",
    member: Literal["round_robin", "random"] | torch.Tensor = "round_robin",
    generator: torch.Generator | None = None,
) -> TensorDictBase:
    """The model state at t = 0 for start states ``observation [*B, S]``.

    Returns a TensorDict ``[*B]`` with ``"observation"``, ``("rcvae", "hidden")`` = the carried
    state at t = 0: h_0 = 0 and, with an episode latent, its draw from ``generator`` (its mean
    for ``"mean"``) (``[*B, carry_dim]`` for ``"ts_inf"``, every member's ``[*B, E, carry_dim]``
    otherwise),
    ``("rcvae", "latent")`` = 0 ``[*B, Z]`` (there is no z_0: latents belong to transitions)
    and, except for ``"mean"``, ``"member"`` int64 ``[*B]``: members assigned round-robin over
    the flattened batch (balanced, so no padding in the member-major layout), uniformly at
    random, or given explicitly.
    """
    cfg, e = ensemble.config, ensemble.ensemble_size
    _checks.check_choice("trajectory_sampling", trajectory_sampling, TRAJECTORY_SAMPLINGS)
    _checks.check_trailing("observation", observation, (cfg.obs_dim,), f"[*B, S={cfg.obs_dim}]")
    _checks.check_floating("observation", observation)
    _checks.check_dtype("observation", observation, ensemble.dtype)
    _checks.check_finite("observation", observation)
    batch = observation.shape[:-1]
    # [E, *B, carry]: h_0 = 0 and the episode latent (drawn once, shared by the members)
    carried = ensemble.initial_hidden(
        batch, observation, generator, mean=trajectory_sampling == "mean"
    )
    if trajectory_sampling == "ts_inf":  # every member's row is the same: keep one
        hidden = carried[0].clone()
    else:
        hidden = carried.movedim(0, -2).contiguous()
    state = TensorDict(
        {
            "observation": observation,
            "rcvae": {
                "hidden": hidden,
                "latent": observation.new_zeros(*batch, cfg.latent_dim),
            },
        },
        batch_size=batch,
    )
    if trajectory_sampling != "mean":
        state.set("member", _assign_members(member, batch, e, observation.device, generator))
    return state


def _assign_members(
    member: str | torch.Tensor,
    batch: torch.Size,
    ensemble_size: int,
    device: torch.device,
    generator: torch.Generator | None,
) -> torch.Tensor:
    n = batch.numel()
    if isinstance(member, torch.Tensor):
        _checks.check_batch_shapes(("observation", "member"), batch, member.shape)
        _checks.check_member(member, ensemble_size)
        return member.to(torch.int64)
    if member == "round_robin":
        return (torch.arange(n, device=device) % ensemble_size).reshape(batch)
    if member == "random":
        return torch.randint(ensemble_size, (n,), generator=generator, device=device).reshape(batch)
    raise ValueError(f"member: expected 'round_robin', 'random' or a tensor, got {member!r}")

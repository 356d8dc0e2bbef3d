"""TensorDict entry points: a one-step transition module and the initial model state.

A model env (TorchRL ``ModelBasedEnvBase``) carries the model state through ``step_mdp``:
``("rcvae", "hidden")``, ``("rcvae", "latent")`` and ``"member"``. It builds the state with
:func:`init_model_state` at reset and calls :class:`RCVAETransition` at every step.

Trajectory sampling (Chua et al. 2018, PETS):

- ``"ts_inf"``: each particle follows one member for the whole rollout; ``hidden`` is
  ``[*B, H]``. Particles are packed into member-major slots (:class:`MemberLayout`), so one
  batched matmul per layer serves all members.
- ``"ts1"``: the member is redrawn uniformly at every step. A recurrent member needs its own
  history, so ``hidden`` holds all members' states ``[*B, E, H]``; every member's recurrence is
  updated from the same sampled state, and the step's sample comes from the drawn member
  (E times the compute of ``"ts_inf"``).
"""

from __future__ import annotations

from typing import Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from rcvae_torchrl.models.functional import standard_normal
from rcvae_torchrl.models.layout import MemberLayout
from rcvae_torchrl.models.rcvae import RCVAEEnsemble, StepOutput
from rcvae_torchrl.models.validation import (
    check_batch_shapes,
    check_dtype,
    check_finite,
    check_member,
    check_trailing,
)

__all__ = ["RCVAETransition", "TrajectorySampling", "init_model_state", "make_transition_module"]

TrajectorySampling = Literal["ts_inf", "ts1"]


def _prefixed(prefix: tuple[str, ...], key: NestedKey) -> NestedKey:
    if not prefix:
        return key
    return (*prefix, *key) if isinstance(key, tuple) else (*prefix, key)


class RCVAETransition(TensorDictModuleBase):
    """Sample s_{t+1} for every particle of a tensordict of any batch shape ``[*B]``.

    Reads ``observation [*B, S]``, ``action [*B, A]``, ``hidden [*B, H]`` (``[*B, E, H]`` for
    ``"ts1"``) and ``member [*B]`` (int64; unused by ``"ts1"``); writes
    ``("next", observation)``, ``("next", hidden)``, ``("next", latent) [*B, Z]`` and
    ``("next", member)`` (see ``out_prefix``). The latent z_{t+1} is an output only: the
    recurrence reads the sampled state, not the previous latent.

    Args:
        ensemble: the world model.
        trajectory_sampling: ``"ts_inf"`` or ``"ts1"`` (see module docstring).
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
        if trajectory_sampling not in ("ts_inf", "ts1"):
            raise ValueError(
                f"trajectory_sampling: expected 'ts_inf' or 'ts1', got {trajectory_sampling!r}."
            )
        self.ensemble = ensemble
        self.trajectory_sampling = trajectory_sampling
        self.generator = generator
        self.validate = validate
        self.keys = (observation_key, action_key, hidden_key, latent_key, member_key)
        self.in_keys = [observation_key, action_key, hidden_key, member_key]
        self.out_keys = [
            _prefixed(tuple(out_prefix), k)
            for k in (observation_key, hidden_key, latent_key, member_key)
        ]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs_k, act_k, hid_k, _, mem_k = self.keys
        obs, action = tensordict.get(obs_k), tensordict.get(act_k)
        hidden, member = tensordict.get(hid_k), tensordict.get(mem_k, None)
        if self.validate:
            self._check(obs, action, hidden, member)
        batch, e, h = obs.shape[:-1], self.ensemble.ensemble_size, self.ensemble.config.hidden_dim
        flat = (obs.reshape(-1, obs.shape[-1]), action.reshape(-1, action.shape[-1]))
        if self.trajectory_sampling == "ts_inf":
            out, member = self._step_ts_inf(*flat, hidden.reshape(-1, h), member.reshape(-1))
        else:
            out, member = self._step_ts1(*flat, hidden.reshape(-1, e, h))
        values = (
            out.observation.reshape(*batch, -1),
            out.hidden.reshape(*batch, *out.hidden.shape[1:]),
            out.latent.reshape(*batch, -1),
            member.reshape(batch),
        )
        for key, value in zip(self.out_keys, values):
            tensordict.set(key, value)
        return tensordict

    def _noise(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-particle noise ``[P, Z]``, ``[P, D]``, drawn in particle order (layout-free)."""
        cfg, n = self.ensemble.config, like.shape[0]
        return (
            standard_normal((n, cfg.latent_dim), like, self.generator),
            standard_normal((n, cfg.predicted_dim), like, self.generator),
        )

    def _step_ts_inf(
        self, obs: torch.Tensor, action: torch.Tensor, hidden: torch.Tensor, member: torch.Tensor
    ) -> tuple[StepOutput, torch.Tensor]:
        layout = MemberLayout(member, self.ensemble.ensemble_size)
        noise_z, noise_s = (layout.pack(n) for n in self._noise(obs))
        packed = self.ensemble.step(
            layout.pack(hidden),
            layout.pack(obs),
            layout.pack(action),
            noise_latent=noise_z,
            noise_obs=noise_s,
        )
        return StepOutput(*(layout.unpack(v) for v in packed)), member

    def _step_ts1(
        self, obs: torch.Tensor, action: torch.Tensor, hidden: torch.Tensor
    ) -> tuple[StepOutput, torch.Tensor]:
        e, n = self.ensemble.ensemble_size, obs.shape[0]
        member = torch.randint(e, (n,), generator=self.generator, device=obs.device)
        noise_z, noise_s = (v.expand(e, *v.shape) for v in self._noise(obs))
        out = self.ensemble.step(
            hidden.transpose(0, 1),
            obs.expand(e, *obs.shape),
            action.expand(e, *action.shape),
            noise_latent=noise_z,
            noise_obs=noise_s,
        )
        rows = torch.arange(n, device=obs.device)
        chosen = StepOutput(*(v[member, rows] for v in out))
        return chosen._replace(hidden=out.hidden.transpose(0, 1)), member

    def _check(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        hidden: torch.Tensor,
        member: torch.Tensor | None,
    ) -> None:
        cfg, e = self.ensemble.config, self.ensemble.ensemble_size
        names = [str(k) for k in self.keys]
        check_trailing(names[0], obs, (cfg.obs_dim,), f"[*B, S={cfg.obs_dim}]")
        check_trailing(names[1], action, (cfg.action_dim,), f"[*B, A={cfg.action_dim}]")
        check_batch_shapes((names[0], names[1]), obs.shape[:-1], action.shape[:-1])
        hid = (cfg.hidden_dim,) if self.trajectory_sampling == "ts_inf" else (e, cfg.hidden_dim)
        check_trailing(names[2], hidden, hid, f"[*B, {', '.join(map(str, hid))}]")
        check_batch_shapes((names[0], names[2]), obs.shape[:-1], hidden.shape[: -len(hid)])
        check_finite(names[0], obs)
        check_finite(names[1], action)
        for name, x in zip(names[:3], (obs, action, hidden)):
            check_dtype(name, x, self.ensemble.dtype)
        if self.trajectory_sampling == "ts_inf":
            if member is None:
                raise KeyError(f"{names[4]}: missing; 'ts_inf' needs the member of each particle.")
            check_batch_shapes((names[0], names[4]), obs.shape[:-1], member.shape)
            check_member(member, e, names[4])


def make_transition_module(
    ensemble: RCVAEEnsemble,
    *,
    trajectory_sampling: TrajectorySampling = "ts_inf",
    generator: torch.Generator | None = None,
    out_prefix: tuple[str, ...] = ("next",),
    **keys: NestedKey,
) -> RCVAETransition:
    """Factory for :class:`RCVAETransition` with the library's default keys (DESIGN.md).

    ``keys`` may override ``observation_key``, ``action_key``, ``hidden_key``, ``latent_key``
    and ``member_key``.
    """
    return RCVAETransition(
        ensemble,
        trajectory_sampling=trajectory_sampling,
        generator=generator,
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

    Returns a TensorDict ``[*B]`` with ``"observation"``, ``("rcvae", "hidden")`` = h_0 = 0
    (``[*B, H]``, or ``[*B, E, H]`` for ``"ts1"``), ``("rcvae", "latent")`` = 0 ``[*B, Z]`` (there
    is no z_0: latents belong to transitions) and ``"member"`` int64 ``[*B]``: members assigned
    round-robin over the flattened batch (balanced, so no padding in :class:`MemberLayout`),
    uniformly at random, or given explicitly.
    """
    from tensordict import TensorDict

    cfg, e = ensemble.config, ensemble.ensemble_size
    check_trailing("observation", observation, (cfg.obs_dim,), f"[*B, S={cfg.obs_dim}]")
    check_finite("observation", observation)
    batch = observation.shape[:-1]
    hid = (cfg.hidden_dim,) if trajectory_sampling == "ts_inf" else (e, cfg.hidden_dim)
    return TensorDict(
        {
            "observation": observation,
            "rcvae": {
                "hidden": observation.new_zeros(*batch, *hid),
                "latent": observation.new_zeros(*batch, cfg.latent_dim),
            },
            "member": _assign_members(member, batch, e, observation.device, generator),
        },
        batch_size=batch,
    )


def _assign_members(
    member: str | torch.Tensor,
    batch: torch.Size,
    ensemble_size: int,
    device: torch.device,
    generator: torch.Generator | None,
) -> torch.Tensor:
    n = batch.numel()
    if isinstance(member, torch.Tensor):
        check_batch_shapes(("observation", "member"), batch, member.shape)
        check_member(member, ensemble_size)
        return member.to(torch.int64)
    if member == "round_robin":
        return (torch.arange(n, device=device) % ensemble_size).reshape(batch)
    if member == "random":
        return torch.randint(ensemble_size, (n,), generator=generator, device=device).reshape(batch)
    raise ValueError(f"member: expected 'round_robin', 'random' or a tensor, got {member!r}.")

"""Particle propagation through an RCVAE ensemble: TS-∞, TS-1 and the ensemble mean.

Trajectory sampling (Chua et al. 2018, PETS, §4.2), for particles that all start from states
sampled or given by the caller:

- ``"ts_inf"`` (TS-∞): each particle follows one member for the whole rollout; the member is
  assigned at reset. Member-major tensors ``[E, M, ...]``: one batched matmul per layer.
- ``"ts1"`` (TS-1): the member is redrawn uniformly at every step. A recurrent member needs its
  own history, so a particle carries all members' hidden states ``[E, M, H]``; every member's
  recurrence is updated from the same sampled state and the step's sample comes from the drawn
  member (E times the compute of ``"ts_inf"``).
- ``"mean"``: a deterministic point prediction. A particle carries all members' hidden states;
  each member predicts with its latent at the prior mean and its decoder mean (no noise), and
  the next state is the mean over members of these predictions, s_{t+1} = (1/E) Σ_m ŝ^m_{t+1}.
  This is the mean of the members' point predictions, not the exact expectation of the
  ensemble mixture (the decoder is nonlinear in z). All particles of a start coincide.

The functions here take flat particle batches ``[M, S]`` (``"ts1"``, ``"mean"``) or member-major
ones (``"ts_inf"``); :class:`MeanTransition` is the TensorDict form of ``"mean"``, mirroring
:class:`~rcvae_torchrl.models.RCVAETransition` (which serves ``"ts_inf"`` and ``"ts1"``).
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey

from rcvae_torchrl.models import RCVAEEnsemble, make_transition_module
from rcvae_torchrl.models.functional import standard_normal
from rcvae_torchrl.models.validation import (
    check_batch_shapes,
    check_dtype,
    check_finite,
    check_trailing,
)

__all__ = [
    "PROPAGATIONS",
    "MeanTransition",
    "ParticleStep",
    "Propagation",
    "make_step_module",
    "mean_step",
    "ts1_step",
]

Propagation = Literal["ts_inf", "ts1", "mean"]
PROPAGATIONS: tuple[str, ...] = ("ts_inf", "ts1", "mean")


class ParticleStep(NamedTuple):
    """One step of M particles that carry all members' recurrent states."""

    observation: torch.Tensor  #: s_{t+1} ``[M, S]``
    hidden: torch.Tensor  #: every member's h_{t+1} ``[E, M, H]``
    latent: torch.Tensor  #: z_{t+1} of the drawn member (``"mean"``: member mean) ``[M, Z]``
    member: torch.Tensor | None  #: the member drawn for this step ``[M]`` (``"mean"``: None)


def ts1_step(
    ensemble: RCVAEEnsemble,
    hidden: torch.Tensor,
    observation: torch.Tensor,
    action: torch.Tensor,
    generator: torch.Generator | None = None,
) -> ParticleStep:
    """TS-1: every member steps, the sample of a uniformly drawn member is kept.

    Draws, in this order, the members ``[M]``, the latent noise ``[M, Z]`` and the state noise
    ``[M, D]`` (as :class:`~rcvae_torchrl.models.RCVAETransition` does, so both give the same
    samples from the same generator state).

    Args:
        ensemble: E members.
        hidden: all members' h_t ``[E, M, H]``.
        observation: s_t ``[M, S]``.
        action: a_t ``[M, A]``.
        generator: source of the member draws and the noise.
    """
    e, m = ensemble.ensemble_size, observation.shape[0]
    cfg = ensemble.config
    member = torch.randint(e, (m,), generator=generator, device=observation.device)
    noise_z = standard_normal((m, cfg.latent_dim), observation, generator)
    noise_s = standard_normal((m, cfg.predicted_dim), observation, generator)
    out = ensemble.step(
        hidden,
        observation.expand(e, *observation.shape),
        action.expand(e, *action.shape),
        noise_latent=noise_z.expand(e, *noise_z.shape),
        noise_obs=noise_s.expand(e, *noise_s.shape),
    )
    rows = torch.arange(m, device=observation.device)
    return ParticleStep(out.observation[member, rows], out.hidden, out.latent[member, rows], member)


def mean_step(
    ensemble: RCVAEEnsemble,
    hidden: torch.Tensor,
    observation: torch.Tensor,
    action: torch.Tensor,
) -> ParticleStep:
    """Ensemble mean: s_{t+1} = mean over members of their noise-free predictions.

    Each member uses z_{t+1} = prior mean and Δ̂ = decoder mean. Passthrough dimensions stay
    exact. Shapes as :func:`ts1_step`; the returned latent is the members' mean prior mean.
    """
    e, cfg = ensemble.ensemble_size, ensemble.config
    zeros = observation.new_zeros(())
    out = ensemble.step(
        hidden,
        observation.expand(e, *observation.shape),
        action.expand(e, *action.shape),
        noise_latent=zeros.expand(e, observation.shape[0], cfg.latent_dim),
        noise_obs=zeros.expand(e, observation.shape[0], cfg.predicted_dim),
    )
    # the state change is affine in Δ̂, so averaging Δ̂ averages the predictions, and the
    # passthrough dimensions stay bit-exact
    observation_next = ensemble.apply_delta(observation, out.delta_mean.mean(0))
    return ParticleStep(observation_next, out.hidden, out.latent.mean(0), None)


class MeanTransition(TensorDictModuleBase):
    """The ``"mean"`` propagation as a TensorDict module, for any batch shape ``[*B]``.

    Reads ``observation [*B, S]``, ``action [*B, A]`` and ``hidden [*B, E, H]`` (every member's
    recurrent state); writes ``observation``, ``hidden`` and ``latent [*B, Z]`` under
    ``out_prefix`` (``()``: in place, as a ``ModelBasedEnvBase`` step wants). The same keys and
    layout as :class:`~rcvae_torchrl.models.RCVAETransition` with ``trajectory_sampling="ts1"``,
    without a member.

    Example:
        >>> from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble, init_model_state
        >>> model = RCVAEEnsemble(RCVAEConfig(4, 2, hidden_dim=8, mlp_dim=8), ensemble_size=3)
        >>> td = init_model_state(model, torch.zeros(6, 4), trajectory_sampling="ts1")
        >>> td["action"] = torch.zeros(6, 2)
        >>> MeanTransition(model)(td)["next", "observation"].shape
        torch.Size([6, 4])
    """

    def __init__(
        self,
        ensemble: RCVAEEnsemble,
        *,
        validate: bool = True,
        out_prefix: tuple[str, ...] = ("next",),
        observation_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        hidden_key: NestedKey = ("rcvae", "hidden"),
        latent_key: NestedKey = ("rcvae", "latent"),
    ) -> None:
        super().__init__()
        self.ensemble = ensemble
        self.validate = validate
        self.keys = (observation_key, action_key, hidden_key, latent_key)
        self.in_keys = [observation_key, action_key, hidden_key]
        self.out_keys = [
            _prefixed(tuple(out_prefix), k) for k in (observation_key, hidden_key, latent_key)
        ]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs_k, act_k, hid_k, _ = self.keys
        obs, action, hidden = (tensordict.get(k) for k in (obs_k, act_k, hid_k))
        if self.validate:
            self._check(obs, action, hidden)
        e, cfg = self.ensemble.ensemble_size, self.ensemble.config
        batch = obs.shape[:-1]
        out = mean_step(
            self.ensemble,
            hidden.reshape(-1, e, cfg.hidden_dim).transpose(0, 1),
            obs.reshape(-1, cfg.obs_dim),
            action.reshape(-1, cfg.action_dim),
        )
        values = (
            out.observation.reshape(*batch, cfg.obs_dim),
            out.hidden.transpose(0, 1).reshape(*batch, e, cfg.hidden_dim),
            out.latent.reshape(*batch, cfg.latent_dim),
        )
        for key, value in zip(self.out_keys, values):
            tensordict.set(key, value)
        return tensordict

    def _check(self, obs: torch.Tensor, action: torch.Tensor, hidden: torch.Tensor) -> None:
        cfg, e = self.ensemble.config, self.ensemble.ensemble_size
        names = [str(k) for k in self.keys]
        check_trailing(names[0], obs, (cfg.obs_dim,), f"[*B, S={cfg.obs_dim}]")
        check_trailing(names[1], action, (cfg.action_dim,), f"[*B, A={cfg.action_dim}]")
        check_batch_shapes((names[0], names[1]), obs.shape[:-1], action.shape[:-1])
        check_trailing(names[2], hidden, (e, cfg.hidden_dim), f"[*B, {e}, {cfg.hidden_dim}]")
        check_batch_shapes((names[0], names[2]), obs.shape[:-1], hidden.shape[:-2])
        check_finite(names[0], obs)
        check_finite(names[1], action)
        for name, x in zip(names[:3], (obs, action, hidden)):
            check_dtype(name, x, self.ensemble.dtype)


def _prefixed(prefix: tuple[str, ...], key: NestedKey) -> NestedKey:
    if not prefix:
        return key
    return (*prefix, *key) if isinstance(key, tuple) else (*prefix, key)


def make_step_module(
    ensemble: RCVAEEnsemble,
    trajectory_sampling: Propagation,
    *,
    generator: torch.Generator | None = None,
    validate: bool = True,
    out_prefix: tuple[str, ...] = (),
) -> TensorDictModuleBase:
    """The one-step TensorDict module of a propagation mode, with the library's default keys.

    :class:`~rcvae_torchrl.models.RCVAETransition` for ``"ts_inf"`` and ``"ts1"``,
    :class:`MeanTransition` for ``"mean"``. Outputs go under ``out_prefix`` (default ``()``: in
    place, as a ``ModelBasedEnvBase`` step wants).
    """
    if trajectory_sampling == "mean":
        return MeanTransition(ensemble, validate=validate, out_prefix=out_prefix)
    module = make_transition_module(
        ensemble,
        trajectory_sampling=trajectory_sampling,
        generator=generator,
        out_prefix=out_prefix,
    )
    module.validate = validate
    return module

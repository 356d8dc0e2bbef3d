"""Trajectory sampling: one step of a batch of particles through an RCVAE ensemble.

The three propagation modes of PETS (Chua et al. 2018, §4.2), for particles that start from
states given by the caller:

- ``"ts_inf"`` (TS-∞): each particle follows one member for the whole rollout. Tensors are
  member-major ``[E, M, ·]`` (M particles per member): one batched matmul per layer.
- ``"ts1"`` (TS-1): the member is redrawn uniformly at every step. A recurrent member needs its
  own history, so a particle carries every member's hidden state ``[E, M, H]``; every member's
  recurrence is updated from the same sampled state and the step's sample comes from the drawn
  member (E times the compute of ``"ts_inf"``). States are ``[M, S]``.
- ``"mean"``: a deterministic point prediction. A particle carries every member's hidden state;
  each member predicts with its latent at the prior mean and its decoder mean (no noise), and
  the next state is the mean over members of these predictions (the mean of the members' point
  predictions, not the exact expectation of the mixture: the decoder is nonlinear in z). States
  are ``[M, S]``.

Noise is drawn, in this order, as the latent noise ``[·, Z]`` then the state noise ``[·, D]``
(and for ``"ts1"`` the members first), or given explicitly.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import torch

from rcvae_torchrl import _checks
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.models.functional import standard_normal

__all__ = [
    "TRAJECTORY_SAMPLINGS",
    "Propagated",
    "TrajectorySampling",
    "draw_noise",
    "initial_hidden",
    "propagate",
]

TrajectorySampling = Literal["ts_inf", "ts1", "mean"]
TRAJECTORY_SAMPLINGS: tuple[str, ...] = ("ts_inf", "ts1", "mean")


class Propagated(NamedTuple):
    """One step of M particles.

    ``"ts_inf"``: member-major ``[E, M, ·]``; ``"ts1"`` / ``"mean"``: ``[M, ·]`` states and every
    member's hidden state ``[E, M, H]``.
    """

    observation: torch.Tensor  #: s_{t+1}
    hidden: torch.Tensor  #: h_{t+1}
    latent: torch.Tensor  #: z_{t+1} (the drawn member's; ``"mean"``: the members' mean)
    member: torch.Tensor | None  #: ``"ts1"``: the member drawn for this step ``[M]``
    delta_mean: torch.Tensor | None  #: ``"ts_inf"``: the decoder's mean ``[E, M, D]``
    delta_std: torch.Tensor | None  #: ``"ts_inf"``: the decoder's std ``[E, M, D]``


def initial_hidden(
    ensemble: RCVAEEnsemble,
    particles: int,
    like: torch.Tensor,
    ts_inf: bool,
    generator: torch.Generator | None = None,
    *,
    mean: bool = False,
) -> torch.Tensor:
    """The carried state at t = 0 (:meth:`RCVAEEnsemble.initial_hidden`: h_0 = 0, and an
    episode latent drawn from ``generator``, or at its mean when ``mean``):
    ``[E, particles / E, carry_dim]`` member-major for TS-∞, else every member's
    ``[E, particles, carry_dim]``."""
    batch = particles // ensemble.ensemble_size if ts_inf else particles
    return ensemble.initial_hidden((batch,), like, generator, mean=mean)


def draw_noise(
    ensemble: RCVAEEnsemble, batch: tuple[int, ...], like: torch.Tensor, generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """ε_z ``[*batch, Z]`` then ε_s ``[*batch, D]``, in that order."""
    cfg = ensemble.config
    noise_z = standard_normal((*batch, cfg.latent_dim), like, generator)
    return noise_z, standard_normal((*batch, cfg.predicted_dim), like, generator)


def propagate(
    ensemble: RCVAEEnsemble,
    mode: TrajectorySampling,
    hidden: torch.Tensor,
    observation: torch.Tensor,
    action: torch.Tensor,
    *,
    noise: tuple[torch.Tensor, torch.Tensor] | None = None,
    generator: torch.Generator | None = None,
) -> Propagated:
    """Sample s_{t+1} for every particle (see the module docstring for the layouts).

    Args:
        ensemble: the world model.
        mode: ``"ts_inf"``, ``"ts1"`` or ``"mean"``.
        hidden: h_t (``[E, M, H]`` in every mode).
        observation: s_t, ``[E, M, S]`` (``"ts_inf"``) or ``[M, S]``.
        action: a_t, the shape of ``observation`` with A last.
        noise: ``(ε_z, ε_s)`` shaped like the latent and the predicted state change of the
            step (``[E, M, ·]`` for ``"ts_inf"``, ``[M, ·]`` for ``"ts1"``); drawn from
            ``generator`` when not given. ``"mean"`` draws none.
        generator: source of the noise (and of the ``"ts1"`` members).
    """
    _checks.check_choice("mode", mode, TRAJECTORY_SAMPLINGS)
    if mode == "ts_inf":
        z, s = (None, None) if noise is None else noise
        out = ensemble.step(
            hidden, observation, action, noise_latent=z, noise_obs=s, generator=generator
        )
        return Propagated(
            out.observation, out.hidden, out.latent, None, out.delta_mean, out.delta_std
        )
    if mode == "ts1":
        return _ts1(ensemble, hidden, observation, action, noise, generator)
    return _mean(ensemble, hidden, observation, action)


def _every_member(x: torch.Tensor, e: int) -> torch.Tensor:
    return x.expand(e, *x.shape)


def _ts1(ensemble, hidden, observation, action, noise, generator) -> Propagated:
    e, m = ensemble.ensemble_size, observation.shape[0]
    member = torch.randint(e, (m,), generator=generator, device=observation.device)
    noise_z, noise_s = (
        draw_noise(ensemble, (m,), observation, generator) if noise is None else noise
    )
    out = ensemble.step(
        hidden,
        _every_member(observation, e),
        _every_member(action, e),
        noise_latent=_every_member(noise_z, e),
        noise_obs=_every_member(noise_s, e),
    )
    rows = torch.arange(m, device=observation.device)
    return Propagated(
        out.observation[member, rows], out.hidden, out.latent[member, rows], member, None, None
    )


def _mean(ensemble, hidden, observation, action) -> Propagated:
    e, cfg, m = ensemble.ensemble_size, ensemble.config, observation.shape[0]
    zeros = observation.new_zeros(())
    out = ensemble.step(
        hidden,
        _every_member(observation, e),
        _every_member(action, e),
        noise_latent=zeros.expand(e, m, cfg.latent_dim),
        noise_obs=zeros.expand(e, m, cfg.predicted_dim),
    )
    # the state change is affine in Δ̂, so averaging Δ̂ averages the predictions, and the
    # passthrough dimensions stay bit-exact
    observation_next = ensemble.apply_delta(observation, out.delta_mean.mean(0))
    return Propagated(observation_next, out.hidden, out.latent.mean(0), None, None, None)

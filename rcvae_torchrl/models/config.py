"""Configuration of one recurrent conditional VAE (RCVAE) member."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from rcvae_torchrl._checks import check_names

__all__ = ["RCVAEConfig"]


@dataclass(frozen=True)
class RCVAEConfig:
    """Sizes and bounds of an RCVAE world model p_θ(s_1:T | s_0, a_0:T-1).

    Args:
        obs_dim: state dimension S.
        action_dim: action dimension A.
        hidden_dim: size H of the deterministic recurrent (GRU) state h_t.
        latent_dim: size Z of the stochastic latent z_t.
        mlp_dim: width of the hidden layers of the embedding, prior, posterior and decoder MLPs.
        min_log_std: lower bound of the decoder log-std, in normalised state-change units.
        max_log_std: upper bound of the decoder log-std, in normalised state-change units.
            The decoder log-std is soft-clamped between the two bounds (as in PETS,
            Chua et al. 2018, ``softplus`` bounding), so gradients never vanish at a bound.
        latent_min_std: floor added to the softplus std of the prior and posterior latents
            (as in Dreamer's RSSM), which keeps the KL finite.
        passthrough_dims: indices of state dimensions that are constant within an episode
            (e.g. a target position). They are copied from s_{t-1} to s_t exactly,
            are not predicted by the decoder and are excluded from the likelihood. They are
            still read by the model as inputs.
        state_constraint: name of a known-state constraint applied to every generated state,
            or ``None``; the function is passed to the ensemble in a
            :class:`~rcvae_torchrl.models.ModelFunctions`.
        input_features: name of a feature function of the state whose output the recurrence
            reads besides the state and the action (passed the same way), or ``None``.
        observation_names: a name for each state dimension (e.g. the
            :class:`~rcvae_torchrl.data.ObservationLayout` of the observation), recorded with
            the model and used in its self-checks and reports; default ``obs[i]``.
        episode_latent_dim: size Ze of a latent e drawn once per episode (0: none), for
            randomness that holds for a whole episode and that the start state does not show
            (an unknown mass, friction or actuator strength drawn per episode). Its prior is
            N(0, I); its posterior q(e | window) reads the whole training window; the prior,
            posterior and decoder read it beside h_t, and a rollout carries it unchanged in its
            recurrent state (:attr:`RCVAEEnsemble.carry_dim`). The per-step latent z_t alone
            must redraw such randomness every step, or infer it from a history the start of an
            imagined episode does not have. A rollout draws e from its prior and keeps it: fed
            a real history first (a rollout started mid-episode), only h_t reads it, e is not
            inferred from it.
        control_step: the seconds one step of the training episodes takes (the env's control
            step, frame skips included: :func:`~rcvae_torchrl.data.control_step` reads it), or
            ``None`` (unknown). Recorded with the model: a model env refuses a real env whose
            step differs (an imagined step would stand for a step of another length), and a
            boundary's ``dt`` is checked against it even without a real env.
    """

    obs_dim: int
    action_dim: int
    hidden_dim: int = 128
    latent_dim: int = 8
    mlp_dim: int = 128
    min_log_std: float = -6.0
    max_log_std: float = 0.5
    latent_min_std: float = 0.1
    passthrough_dims: tuple[int, ...] = ()
    state_constraint: str | None = None
    input_features: str | None = None
    observation_names: tuple[str, ...] | None = None
    episode_latent_dim: int = 0
    control_step: float | None = None

    def __post_init__(self) -> None:
        step = self.control_step
        if step is not None:
            if isinstance(step, bool) or not isinstance(step, (int, float)):
                raise TypeError(
                    "RCVAEConfig.control_step must be the seconds per step (a number) or None, "
                    f"got {step!r}."
                )
            if not (math.isfinite(step) and step > 0):
                raise ValueError(
                    "RCVAEConfig.control_step must be a finite number of seconds > 0, got "
                    f"{step!r}."
                )
            object.__setattr__(self, "control_step", float(step))
        ze = self.episode_latent_dim
        if isinstance(ze, bool) or not isinstance(ze, int) or ze < 0:
            raise ValueError(f"RCVAEConfig.episode_latent_dim must be an int >= 0, got {ze!r}.")
        for name in ("obs_dim", "action_dim", "hidden_dim", "latent_dim", "mlp_dim"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"RCVAEConfig.{name} must be a positive int, got {value!r}.")
        for name in ("min_log_std", "max_log_std", "latent_min_std"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError(f"RCVAEConfig.{name} must be a number, got {value!r}.")
            if not math.isfinite(value):
                raise ValueError(f"RCVAEConfig.{name} must be finite, got {value!r}.")
        if not self.min_log_std < self.max_log_std:
            raise ValueError(
                "RCVAEConfig.min_log_std must be below max_log_std, got "
                f"{self.min_log_std} and {self.max_log_std}."
            )
        if self.latent_min_std < 0:
            raise ValueError(f"RCVAEConfig.latent_min_std must be >= 0, got {self.latent_min_std}.")
        for name in ("state_constraint", "input_features"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, str):
                raise TypeError(
                    f"RCVAEConfig.{name} must be the name of a function (a str, looked up in the "
                    f"ensemble's ModelFunctions) or None, got {value!r}."
                )
        dims = self.passthrough_dims
        if isinstance(dims, (str, bytes)) or not isinstance(dims, Sequence):
            raise TypeError(
                f"RCVAEConfig.passthrough_dims must be a sequence of ints, got {dims!r}."
            )
        if any(isinstance(d, bool) or not isinstance(d, int) for d in dims):
            raise TypeError(f"RCVAEConfig.passthrough_dims must hold ints, got {dims!r}.")
        object.__setattr__(self, "passthrough_dims", tuple(dims))
        self._check_passthrough()
        if self.observation_names is not None:
            names = check_names(
                "RCVAEConfig.observation_names", self.observation_names, self.obs_dim
            )
            object.__setattr__(self, "observation_names", names)

    def _check_passthrough(self) -> None:
        dims = self.passthrough_dims
        if len(set(dims)) != len(dims):
            raise ValueError(f"RCVAEConfig.passthrough_dims has duplicates: {dims}.")
        bad = [d for d in dims if not 0 <= d < self.obs_dim]
        if bad:
            raise ValueError(
                f"RCVAEConfig.passthrough_dims must lie in [0, {self.obs_dim}), got {bad}."
            )
        if len(dims) == self.obs_dim:
            raise ValueError("RCVAEConfig.passthrough_dims cannot cover every state dimension.")

    @property
    def names(self) -> tuple[str, ...]:
        """The state dimensions' names (``observation_names``, else ``obs[i]``)."""
        if self.observation_names is not None:
            return self.observation_names
        return tuple(f"obs[{i}]" for i in range(self.obs_dim))

    @property
    def predicted_dims(self) -> tuple[int, ...]:
        """Indices of the state dimensions the decoder predicts (all but the passthrough ones)."""
        skip = set(self.passthrough_dims)
        return tuple(d for d in range(self.obs_dim) if d not in skip)

    @property
    def predicted_dim(self) -> int:
        """Number D of predicted state dimensions."""
        return self.obs_dim - len(self.passthrough_dims)

"""An ensemble of E recurrent conditional VAEs (RCVAEs), one vectorised computation.

Each member models p_θ(s_1:T | s_0, a_0:T−1) (Acharya, Russell & Ahmed 2022, §II-A) with

- a deterministic recurrent state   h_t = GRU(h_{t−1}, x_t),  x_t = φ([ŝ_{t−1}, â_{t−1}]),
  h_0 = 0, where ŝ, â are normalised state and action and s_{t−1} is the true state
  (teacher forcing, training) or the model's own sample (generation);
- a latent z_t with prior p(z_t | h_t) and posterior q(z_t | h_t, Δ̂_t) (training only), where
  Δ̂_t is the normalised state change s_t − s_{t−1} of the predicted dimensions: the posterior
  sees exactly the quantity the decoder has to explain;
- optionally (``episode_latent_dim`` Ze > 0) a latent e drawn once per episode, with a learned
  diagonal Gaussian prior p(e) and a posterior q(e | window) from the whole training window,
  read by the prior, posterior and decoder beside h_t (below, h_t stands for the carried state
  [h_t, e]);
- a Gaussian decoder p(Δ̂_t | h_t, x_t, z_t) with a soft-clamped log-std, and
  s_t = s_{t−1} + denormalise(Δ̂_t) on predicted dimensions, s_t = s_{t−1} on
  ``passthrough_dims`` (copied exactly, excluded from the likelihood).

The decoder also reads x_t (a skip connection around the GRU), so the Markov part of the
dynamics does not have to squeeze through the GRU's saturating gates.

All members' parameters are stacked on a leading dim E (:class:`EnsembleLinear`); every method
takes member-major tensors ``[E, *B, ...]``. The ensemble of independently initialised members
gives the epistemic part of the uncertainty (Lakshminarayanan et al. 2017).
"""

from __future__ import annotations

import dataclasses
import numbers
from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from rcvae_torchrl._checks import (
    check_bool,
    check_dtype,
    check_finite,
    check_floating,
    check_min_rank,
    check_non_negative_int,
    check_tensor,
)
from rcvae_torchrl.models.config import RCVAEConfig
from rcvae_torchrl.models.ensemble_gru import EnsembleGRUCell, gru_scan, gru_step
from rcvae_torchrl.models.ensemble_layers import EnsembleLinear, EnsembleMLP, ensemble_mlp
from rcvae_torchrl.models.functional import (
    Generators,
    gaussian_head,
    reparameterize,
    standard_normal,
)
from rcvae_torchrl.models.functions import ModelFunctions
from rcvae_torchrl.models.normalizer import StateNormalizer

__all__ = ["RCVAEEnsemble", "SequenceOutput", "StepOutput"]


class StepOutput(NamedTuple):
    """One generative step, member-major. Deltas are normalised, of the predicted dims only."""

    hidden: torch.Tensor  #: the carried state [h_t, e] ``[E, *B, carry_dim]``
    latent: torch.Tensor  #: z_t ``[E, *B, Z]``
    observation: torch.Tensor  #: s_t ``[E, *B, S]``
    delta_mean: torch.Tensor  #: decoder mean ``[E, *B, D]``
    delta_std: torch.Tensor  #: decoder std ``[E, *B, D]``


class SequenceOutput(NamedTuple):
    """Distributions over the n transitions of windows ``[E, *B, L]``: ``[E, *B, n, ·]``."""

    prior_mean: torch.Tensor  #: p(z_t | h_t) mean ``[..., Z]``
    prior_std: torch.Tensor  #: ``[..., Z]``
    posterior_mean: torch.Tensor  #: q(z_t | h_t, Δ̂_t) mean ``[..., Z]``
    posterior_std: torch.Tensor  #: ``[..., Z]``
    decoder_mean: torch.Tensor  #: p(Δ̂_t | h_t, x_t, z_t) mean, z_t ~ q ``[..., D]``
    decoder_std: torch.Tensor  #: ``[..., D]``
    target: torch.Tensor  #: the normalised state change Δ̂_t to explain ``[..., D]``
    episode_mean: torch.Tensor | None = None  #: q(e | window) mean ``[E, *B, Ze]`` (Ze > 0)
    episode_std: torch.Tensor | None = None  #: ``[E, *B, Ze]``
    episode_prior_mean: torch.Tensor | None = None  #: p(e) mean, ``[E, 1.., Ze]`` (Ze > 0)
    episode_prior_std: torch.Tensor | None = None  #: ``[E, 1.., Ze]``


class RCVAEEnsemble(nn.Module):
    """E independently initialised RCVAE members with stacked parameters.

    The training pass is ``forward`` (teacher forcing, optionally open loop, for the ELBO);
    generation is :meth:`step`, which :mod:`rcvae_torchrl.rollout` calls for every imagined
    step.

    Args:
        config: sizes and bounds of one member.
        ensemble_size: number of members E (1 gives a single RCVAE).
        functions: the state constraint and input features named in ``config``
            (:class:`~rcvae_torchrl.models.ModelFunctions`); needed only when it names any.
        seed: draws the initial weights from torch's generator seeded by it (its state restored
            afterwards), the same weights in any process; ``None``: from torch's global
            generator as it stands (``torch.manual_seed`` before building). Training's
            ``TrainConfig.seed`` seeds its sampling and noise, not these weights.

    Example:
        >>> cfg = RCVAEConfig(obs_dim=4, action_dim=2, hidden_dim=16, mlp_dim=16)
        >>> model = RCVAEEnsemble(cfg, ensemble_size=3)
        >>> out = model(torch.zeros(3, 8, 10, 4), torch.zeros(3, 8, 10, 2))  # [E, W, L, ·]
        >>> out.decoder_mean.shape
        torch.Size([3, 8, 9, 4])
    """

    def __init__(
        self,
        config: RCVAEConfig,
        ensemble_size: int = 5,
        *,
        functions: ModelFunctions | None = None,
        seed: int | None = None,
    ) -> None:
        super().__init__()
        if not isinstance(config, RCVAEConfig):
            raise TypeError(f"config: expected an RCVAEConfig, got {type(config).__name__}")
        if (
            isinstance(ensemble_size, bool)
            or not isinstance(ensemble_size, int)
            or ensemble_size < 1
        ):
            raise ValueError(f"ensemble_size: expected a positive int, got {ensemble_size!r}.")
        self.config = config
        self.ensemble_size = ensemble_size
        if functions is not None and not isinstance(functions, ModelFunctions):
            raise TypeError(
                "functions: expected a ModelFunctions (its state constraints and input features "
                f"by name) or None, got {type(functions).__name__}"
            )
        self.functions = functions if functions is not None else ModelFunctions()
        self.state_constraint = self.functions.state_constraint(config.state_constraint)
        features = self.functions.features(config.input_features)
        self._features = None if features is None else features.fn
        self.feature_dim = 0 if features is None else features.dim
        self.normalizer = StateNormalizer(config.obs_dim, config.action_dim, self.feature_dim)
        #: the self-checks of the trained model (:func:`rcvae_torchrl.training.check_model`),
        #: set by training and kept in checkpoints; ``None`` until checked
        self.checks = None
        #: how unlike its training states a state is (:class:`rcvae_torchrl.training.StateNovelty`),
        #: set by training and kept in checkpoints; ``None`` until fitted
        self.novelty = None
        #: how far its one-step predictions miss held-out episodes
        #: (:class:`rcvae_torchrl.training.DynamicsNovelty`), set by training and kept in
        #: checkpoints; ``None`` until fitted
        self.dynamics = None
        self.register_buffer("predicted_idx", torch.tensor(config.predicted_dims), persistent=False)
        # D when the predicted dims are 0..D-1 (the passthrough ones a tail): slices suffice
        dims = config.predicted_dims
        self._predicted_head = len(dims) if dims == tuple(range(len(dims))) else None
        if seed is None:
            self._build_networks(config, ensemble_size)
            return
        if (
            isinstance(seed, bool)
            or not isinstance(seed, numbers.Integral)
            or not 0 <= seed < 2**64
        ):
            raise ValueError(f"seed: expected an integer in [0, 2**64) or None, got {seed!r}")
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(int(seed))
            self._build_networks(config, ensemble_size)

    def _build_networks(self, c: RCVAEConfig, e: int) -> None:
        h, m, z, d = c.hidden_dim, c.mlp_dim, c.latent_dim, c.predicted_dim
        carry = self.carry_dim
        self.embed = EnsembleLinear(e, c.obs_dim + c.action_dim + self.feature_dim, m)
        self.gru = EnsembleGRUCell(e, m, h)
        self.prior_net = EnsembleMLP(e, carry, m, 2 * z, depth=1)
        self.posterior_net = EnsembleMLP(e, carry + d, m, 2 * z, depth=1)
        self.decoder = EnsembleMLP(e, carry + m + z, m, 2 * d, depth=2)
        if c.episode_latent_dim:
            # q(e | window): per-step features of (x_t, Δ̂_t), averaged over the window
            self.episode_embed = EnsembleLinear(e, m + d, m)
            self.episode_head = EnsembleLinear(e, m, 2 * c.episode_latent_dim)
            # p(e): learned (its optimum under the KL is the spread of the posteriors, so that
            # draws from it cover what training encoded; a fixed N(0, I) would not)
            self.episode_prior_raw = nn.Parameter(torch.zeros(e, 2 * c.episode_latent_dim))

    def episode_prior(self) -> tuple[torch.Tensor, torch.Tensor]:
        """p(e) of each member: ``(mean, std)`` each ``[E, Ze]`` (Ze > 0)."""
        return gaussian_head(self.episode_prior_raw, min_std=self.config.latent_min_std)

    @property
    def carry_dim(self) -> int:
        """Size of the recurrent state a rollout carries: h_t (H), then the episode latent e
        (Ze, unchanged over the episode; none when ``episode_latent_dim`` is 0)."""
        return self.config.hidden_dim + self.config.episode_latent_dim

    @property
    def dtype(self) -> torch.dtype:
        """The parameters' floating dtype (inputs must match it)."""
        return self.embed.weight.dtype

    @property
    def device(self) -> torch.device:
        """The parameters' device."""
        return self.embed.weight.device

    def behaviour(self) -> dict[str, Any]:
        """What this model's forecasts are computed from, for a digest
        (:func:`rcvae_torchrl.fingerprint.digest`; a forecast's task holds it): its weights
        and buffers, its config, and the functions it calls by name (the state constraint and
        the input features, their code and the values they read). The same weights loaded
        with another constraint function forecast otherwise, and give another digest."""
        return {
            "weights": dict(self.state_dict()),
            "config": dataclasses.asdict(self.config),
            "state_constraint": self.state_constraint,
            "input_features": self._features,
        }

    # ----------------------------------------------------------------- building blocks
    def initial_hidden(
        self,
        batch_shape: Sequence[int],
        like: torch.Tensor,
        generator: torch.Generator | None = None,
        *,
        mean: bool = False,
    ) -> torch.Tensor:
        """The carried state at t = 0, ``[E, *batch_shape, carry_dim]`` with the dtype/device of
        ``like``: h_0 = 0, then (Ze > 0) the episode latent e ~ p(e), each member's prior
        mean + std ⊙ ε with one noise ε ``[*batch_shape, Ze]`` drawn from ``generator`` and
        shared by the members (the same episode seen by every member), or the prior mean when
        ``mean``. With Ze = 0 nothing is drawn."""
        shape = (self.ensemble_size, *batch_shape, self.config.hidden_dim)
        h0 = like.new_zeros(shape)
        ze = self.config.episode_latent_dim
        if not ze:
            return h0
        view = (self.ensemble_size, *([1] * len(batch_shape)), ze)
        prior_mean, prior_std = (p.to(like.dtype).view(view) for p in self.episode_prior())
        if mean:
            episode = prior_mean.expand(*shape[:-1], ze)
        else:
            episode = prior_mean + prior_std * standard_normal((*batch_shape, ze), like, generator)
        return torch.cat([h0, episode], dim=-1)

    def _split_carry(self, carry: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(h_t, e) from the carried state (e is ``None`` when Ze = 0)."""
        if not self.config.episode_latent_dim:
            return carry, None
        h = self.config.hidden_dim
        return carry[..., :h], carry[..., h:]

    @staticmethod
    def _join_carry(hidden: torch.Tensor, episode: torch.Tensor | None) -> torch.Tensor:
        """[h_t, e] (``episode`` ``[E, *B, Ze]`` broadcast over any step dims of ``hidden``)."""
        if episode is None:
            return hidden
        while episode.dim() < hidden.dim():
            episode = episode.unsqueeze(-2)
        return torch.cat([hidden, episode.expand(*hidden.shape[:-1], episode.shape[-1])], dim=-1)

    def embed_inputs(self, obs_prev: torch.Tensor, action_prev: torch.Tensor) -> torch.Tensor:
        """x_t = SiLU(W [ŝ_{t−1}, â_{t−1}, f̂(s_{t−1})] + b) ``[E, *B, M]`` from ``[E, *B, S]``,
        ``[E, *B, A]``; f̂ are the config's normalised input features, if any."""
        parts = [
            self.normalizer.normalize_state(obs_prev),
            self.normalizer.normalize_action(action_prev),
        ]
        if self._features is not None:
            parts.append(self.normalizer.normalize_features(self._features(obs_prev)))
        return F.silu(self.embed(torch.cat(parts, dim=-1)))

    def recur(
        self, hidden: torch.Tensor, obs_prev: torch.Tensor, action_prev: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One recurrence step: returns ``(h_t [E, *B, H], x_t [E, *B, M])``."""
        x = self.embed_inputs(obs_prev, action_prev)
        return self.gru(x, hidden), x

    def prior(self, hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """p(z_t | h_t): ``[E, *B, carry_dim]`` → ``(mean, std)`` each ``[E, *B, Z]``."""
        return gaussian_head(self.prior_net(hidden), min_std=self.config.latent_min_std)

    def posterior(
        self, hidden: torch.Tensor, target: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """q(z_t | h_t, Δ̂_t): ``[E, *B, carry_dim]``, ``[E, *B, D]`` → ``(mean, std)``
        ``[E, *B, Z]``."""
        # forward_split: the same affine map as on the concatenation, without materialising it
        raw = self.posterior_net.forward_split((hidden, target))
        return gaussian_head(raw, min_std=self.config.latent_min_std)

    def decode(
        self, hidden: torch.Tensor, x: torch.Tensor, latent: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """p(Δ̂_t | h_t, x_t, z_t) → ``(mean, std)`` ``[E, *B, D]``, normalised units."""
        raw = self.decoder.forward_split((hidden, x, latent))
        bounds = (self.config.min_log_std, self.config.max_log_std)
        return gaussian_head(raw, log_std_bounds=bounds)

    def apply_delta(self, obs_prev: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        """s_t from s_{t−1} ``[..., S]`` and a normalised change ``[..., D]``; passthrough exact,
        then the config's known state constraint, if any."""
        head = self._predicted_head
        if head is None:
            change = self.normalizer.denormalize_delta(delta, self.predicted_idx)
            full = obs_prev.new_zeros(obs_prev.shape).index_copy(-1, self.predicted_idx, change)
            state = obs_prev + full
        else:  # predicted dims first: no scatter, the passthrough tail is copied as it is
            norm = self.normalizer
            change = delta * norm.delta_std[:head] + norm.delta_mean[:head]
            state = torch.cat([obs_prev[..., :head] + change, obs_prev[..., head:]], dim=-1)
        if self.state_constraint is None:
            return state
        constrained = self.state_constraint(obs_prev, state)
        if (
            not isinstance(constrained, torch.Tensor)
            or constrained.shape != state.shape
            or constrained.dtype != state.dtype
        ):
            got = (
                f"shape {tuple(constrained.shape)} and dtype {constrained.dtype}"
                if isinstance(constrained, torch.Tensor)
                else type(constrained).__name__
            )
            raise ValueError(
                f"state_constraint {self.config.state_constraint!r}: expected the constrained "
                f"state in the generated state's shape {tuple(state.shape)} and dtype "
                f"{state.dtype} (every dimension, [..., S = {state.shape[-1]}]), got {got}"
            )
        return constrained

    def target_delta(self, obs_prev: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """Normalised state change Δ̂_t of the predicted dims: ``[..., S]`` × 2 → ``[..., D]``."""
        delta = (obs - obs_prev).index_select(-1, self.predicted_idx)
        return self.normalizer.normalize_delta(delta, self.predicted_idx)

    def state_loc_scale(
        self, obs_prev: torch.Tensor, delta_mean: torch.Tensor, delta_std: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The decoder's Gaussian over s_t in state units: ``(loc, scale)`` each ``[..., S]``.

        Passthrough dims get ``loc = s_{t−1}`` and ``scale = 0``.
        """
        loc = self.apply_delta(obs_prev, delta_mean)
        scale_pred = delta_std * self.normalizer.delta_std[self.predicted_idx]
        scale = obs_prev.new_zeros(obs_prev.shape).index_copy(-1, self.predicted_idx, scale_pred)
        return loc, scale

    # ----------------------------------------------------------------- generation
    def step(
        self,
        hidden: torch.Tensor,
        obs_prev: torch.Tensor,
        action_prev: torch.Tensor,
        *,
        noise_latent: torch.Tensor | None = None,
        noise_obs: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> StepOutput:
        """Sample s_t ~ p_θ(s_t | h_{t−1}, s_{t−1}, a_{t−1}) with z_t from the prior.

        Args:
            hidden: the carried state [h_{t−1}, e] ``[E, *B, carry_dim]``.
            obs_prev: s_{t−1} ``[E, *B, S]``.
            action_prev: a_{t−1} ``[E, *B, A]``.
            noise_latent: optional ε_z ``[E, *B, Z]`` (else drawn from ``generator``).
            noise_obs: optional ε_s ``[E, *B, D]`` (else drawn from ``generator``).
            generator: torch generator for the noise not given.
        """
        # shapes and dtypes only (no data read: this is the imagination's hot path)
        lead = obs_prev.shape[:-1]
        if (
            obs_prev.shape[-1] != self.config.obs_dim
            or action_prev.shape[-1] != self.config.action_dim
            or action_prev.shape[:-1] != lead
            or hidden.shape[:-1] != lead
            or hidden.shape[-1] != self.carry_dim
            or lead[:1] != (self.ensemble_size,)
        ):
            self._refuse_step_shapes(hidden, obs_prev, action_prev)
        dtype = self.dtype
        if obs_prev.dtype != dtype or action_prev.dtype != dtype or hidden.dtype != dtype:
            for name, x in (
                ("hidden", hidden),
                ("obs_prev", obs_prev),
                ("action_prev", action_prev),
            ):
                check_dtype(name, check_tensor(name, x), dtype)
        # recur, prior and decode as one hot path (the modules' numbers, fewer ops and calls)
        x = self.embed_inputs(obs_prev, action_prev)
        hidden, episode = self._split_carry(hidden)
        hidden = self._join_carry(gru_step(self.gru, x, hidden), episode)
        prior = ensemble_mlp(self.prior_net, hidden)
        latent = reparameterize(
            *gaussian_head(prior, min_std=self.config.latent_min_std), noise_latent, generator
        )
        raw = ensemble_mlp(self.decoder, torch.cat([hidden, x, latent], dim=-1))
        bounds = (self.config.min_log_std, self.config.max_log_std)
        mean, std = gaussian_head(raw, log_std_bounds=bounds)
        delta = reparameterize(mean, std, noise_obs, generator)
        return StepOutput(hidden, latent, self.apply_delta(obs_prev, delta), mean, std)

    def _refuse_step_shapes(self, *inputs: Any) -> None:
        """:meth:`step`'s inputs whose shapes do not agree, refused naming each one's."""
        for name, x in zip(("hidden", "obs_prev", "action_prev"), inputs, strict=True):
            check_tensor(name, x)
        e, s, a, c = (
            self.ensemble_size,
            self.config.obs_dim,
            self.config.action_dim,
            self.carry_dim,
        )
        hidden, obs_prev, action_prev = inputs
        raise ValueError(
            f"hidden, obs_prev, action_prev: expected [E={e}, *B, {c}], [E={e}, *B, S={s}] and "
            f"[E={e}, *B, A={a}] with the same [*B], got {tuple(hidden.shape)}, "
            f"{tuple(obs_prev.shape)} and {tuple(action_prev.shape)} (initial_hidden gives "
            "the first hidden state)"
        )

    # ----------------------------------------------------------------- training pass
    def forward(
        self,
        observations: torch.Tensor,
        actions: torch.Tensor,
        *,
        next_observations: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        open_loop_steps: int = 0,
        detach_open_loop: bool = False,
        generator: Generators = None,
        validate: bool = True,
    ) -> SequenceOutput:
        """The training pass: windows through the model for the ELBO (teacher forcing,
        optionally open loop).

        Transition t reads state s_t and action a_t and explains s_{t+1}: taken from
        ``next_observations[t]`` when given (L transitions), else from ``observations[t + 1]``
        (L − 1 transitions; the last action is unused). The last ``open_loop_steps``
        transitions (at most all but the first) read the model's own prior sample ŝ_t instead
        of the true s_t, generated from the previous transition; their targets are
        s_{t+1} − ŝ_t. Gradients flow through the fed-back samples unless ``detach_open_loop``.

        Args:
            observations: ``[E, *B, L, S]``.
            actions: ``[E, *B, L, A]``.
            next_observations: optional ``[E, *B, L, S]``, s_{t+1} of each step.
            mask: optional bool ``[E or 1, *B, L]`` of valid steps. The hidden state is reset
                to h_0 after an invalid step, so left-padded windows start fresh; masked steps
                are otherwise computed and must be excluded from the loss by the caller.
            open_loop_steps: number K of trailing transitions fed with model samples.
            detach_open_loop: stop gradients through the fed-back samples.
            generator: torch generator for the latent and fed-back samples, or one per member.
            validate: check that every input value is finite (a read back to the host: on a
                GPU it waits for the queued kernels, under ``torch.compile`` it splits the
                graph). Off for callers that have checked them (the loss checks its windows
                itself, under their tensordict keys). Shapes and dtypes are checked either way.

        Returns:
            a :class:`SequenceOutput` with tensors ``[E, *B, n, ·]``, n = number of transitions.
        """
        check_bool("validate", validate)
        self._check_windows(observations, actions, next_observations, finite=validate)
        self._check_mask(mask, observations)
        check_non_negative_int("open_loop_steps", open_loop_steps)
        if next_observations is None:
            targets = observations[..., 1:, :]
        else:
            targets = next_observations
        n_steps = targets.shape[-2]
        n_open = min(open_loop_steps, max(n_steps - 1, 0))
        hidden, x, prev = self._teacher_forced(observations, actions, mask, n_steps - n_open)
        episode = None
        if self.config.episode_latent_dim:
            episode = self._episode_posterior(observations, actions, targets, x, mask, generator)
        if n_open:
            opened = self._open_loop(
                (hidden[..., -1, :], x[..., -1, :], prev[..., -1, :]),
                actions[..., n_steps - n_open : n_steps, :],
                detach_open_loop,
                generator,
                None if episode is None else episode[2],
            )
            hidden, x, prev = (torch.cat(p, dim=-2) for p in zip((hidden, x, prev), opened))
        out = self._explain(
            hidden, x, prev, targets, generator, None if episode is None else episode[2]
        )
        if episode is None:
            return out
        view = (self.ensemble_size, *([1] * (episode[0].dim() - 2)), -1)
        prior_mean, prior_std = (p.view(view) for p in self.episode_prior())
        return out._replace(
            episode_mean=episode[0],
            episode_std=episode[1],
            episode_prior_mean=prior_mean,
            episode_prior_std=prior_std,
        )

    @torch.no_grad()
    def predict_next(self, observations: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Each member's point prediction of s_{t+1} from the true history (teacher forced).

        The latent at its prior mean and the decoder mean: what the model expects the next
        state to be, without sampling. A self-check of what the model has learned (one-step
        errors against the truth, see :func:`~rcvae_torchrl.training.check_model`).

        Args:
            observations: ``[E, *B, L, S]`` windows of true states.
            actions: ``[E, *B, L, A]``.

        Returns:
            ``[E, *B, L - 1, S]``: the prediction of ``observations[..., 1:, :]``.
        """
        self._check_windows(observations, actions, None)
        n_steps = observations.shape[-2] - 1
        hidden, x, prev = self._teacher_forced(observations, actions, None, n_steps)
        if self.config.episode_latent_dim:  # e at its prior mean
            hidden = self._join_carry(hidden, self.episode_prior()[0])
        latent, _ = self.prior(hidden)
        mean, _ = self.decode(hidden, x, latent)
        return self.apply_delta(prev, mean)

    def _check_windows(
        self,
        observations: torch.Tensor,
        actions: torch.Tensor,
        next_observations: torch.Tensor | None,
        finite: bool = True,
    ) -> None:
        """Windows ``[E, *B, L, S]`` / ``[E, *B, L, A]``: shapes, dtype and (with ``finite``)
        finite values (a NaN would otherwise come out as a NaN loss or prediction)."""
        s, a, e = self.config.obs_dim, self.config.action_dim, self.ensemble_size
        named = [("observations", observations, s), ("actions", actions, a)]
        if next_observations is not None:
            named.append(("next_observations", next_observations, s))
        for name, x, last in named:
            check_tensor(name, x)
            check_floating(name, x)
            check_min_rank(name, x, 3, f"[E={e}, *B, L, {last}]")
            if x.shape[0] != e or x.shape[-1] != last:
                raise ValueError(
                    f"{name}: expected shape [E={e}, *B, L, {last}], got {tuple(x.shape)}"
                )
            if finite:
                check_finite(name, x)
            check_dtype(name, x, self.dtype)
        for name, x, _ in named[1:]:
            if x.shape[:-1] != observations.shape[:-1]:
                raise ValueError(
                    f"{name}: expected the leading shape [E, *B, L] = "
                    f"{tuple(observations.shape[:-1])} of observations, got {tuple(x.shape)}"
                )
        least = 1 if next_observations is not None else 2
        if observations.shape[-2] < least:
            raise ValueError(
                f"observations: expected windows of L >= {least} steps, got L = "
                f"{observations.shape[-2]} (shape {tuple(observations.shape)})"
            )

    def _check_mask(self, mask: torch.Tensor | None, observations: torch.Tensor) -> None:
        """A bool mask ``[E or 1, *B, L]`` of the windows' steps."""
        if mask is None:
            return
        check_tensor("mask", mask)
        expected = observations.shape[1:-1]
        if (
            mask.dtype != torch.bool
            or mask.shape[1:] != expected
            or mask.shape[0] not in (1, self.ensemble_size)
        ):
            raise ValueError(
                f"mask: expected a bool mask [E={self.ensemble_size} or 1, *B, L] = "
                f"[{self.ensemble_size} or 1, {', '.join(map(str, expected))}], got "
                f"{mask.dtype} {tuple(mask.shape)}"
            )

    def _teacher_forced(
        self,
        observations: torch.Tensor,
        actions: torch.Tensor,
        mask: torch.Tensor | None,
        n_steps: int,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """h_1..h_n from true states; embeddings and input gates for all steps in one batch."""
        prev = observations[..., :n_steps, :]
        x = self.embed_inputs(prev, actions[..., :n_steps, :])
        batch = observations.shape[1:-2]
        h0 = observations.new_zeros((self.ensemble_size, *batch, self.config.hidden_dim))
        return gru_scan(self.gru, self.gru.input_proj(x), h0, mask), x, prev

    def _episode_posterior(
        self,
        observations: torch.Tensor,
        actions: torch.Tensor,
        targets: torch.Tensor,
        x: torch.Tensor,
        mask: torch.Tensor | None,
        generator: Generators,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """q(e | window) from the true transitions of the window (masked steps left out):
        ``(mean, std, sample)``, each ``[E, *B, Ze]``."""
        n = targets.shape[-2]
        prev = observations[..., :n, :]
        if x.shape[-2] != n:  # open-loop steps: their true inputs
            x = self.embed_inputs(prev, actions[..., :n, :])
        feats = F.silu(self.episode_embed.forward_split((x, self.target_delta(prev, targets))))
        if mask is None:
            pooled = feats.mean(dim=-2)
        else:  # transition t counts when its steps do (t, and t + 1 without next observations)
            valid = mask if mask.shape[-1] == n else mask[..., 1:] & mask[..., :-1]
            weight = valid.to(feats.dtype).unsqueeze(-1).expand(*feats.shape[:-1], 1)
            pooled = (feats * weight).sum(-2) / weight.sum(-2).clamp_min(1.0)
        mean, std = gaussian_head(self.episode_head(pooled), min_std=self.config.latent_min_std)
        return mean, std, reparameterize(mean, std, generator=generator)

    def _open_loop(
        self,
        last: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        actions: torch.Tensor,
        detach: bool,
        generator: Generators,
        episode: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Continue from the last teacher-forced step, feeding back prior samples."""
        hidden, x, prev = last
        steps: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
        for action in actions.unbind(dim=-2):
            prev = self._sample_next(self._join_carry(hidden, episode), x, prev, generator)
            prev = prev.detach() if detach else prev
            hidden, x = self.recur(hidden, prev, action)
            steps.append((hidden, x, prev))
        return tuple(torch.stack(v, dim=-2) for v in zip(*steps))

    def _sample_next(
        self,
        hidden: torch.Tensor,
        x: torch.Tensor,
        prev: torch.Tensor,
        generator: Generators,
    ) -> torch.Tensor:
        """s_t ~ p(s_t | h_t, x_t, z_t), z_t ~ p(z_t | h_t): the generative half of :meth:`step`."""
        latent = reparameterize(*self.prior(hidden), generator=generator)
        delta = reparameterize(*self.decode(hidden, x, latent), generator=generator)
        return self.apply_delta(prev, delta)

    def _explain(
        self,
        hidden: torch.Tensor,
        x: torch.Tensor,
        prev: torch.Tensor,
        obs_next: torch.Tensor,
        generator: Generators,
        episode: torch.Tensor | None = None,
    ) -> SequenceOutput:
        """Prior, posterior and decoder over all steps at once (none of them is recurrent)."""
        hidden = self._join_carry(hidden, episode)
        target = self.target_delta(prev, obs_next)
        post_mean, post_std = self.posterior(hidden, target)
        latent = reparameterize(post_mean, post_std, generator=generator)
        dec_mean, dec_std = self.decode(hidden, x, latent)
        prior_mean, prior_std = self.prior(hidden)
        return SequenceOutput(prior_mean, prior_std, post_mean, post_std, dec_mean, dec_std, target)

    # ----------------------------------------------------------------- utilities
    def fit_normalizer(
        self,
        observations: torch.Tensor,
        actions: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        next_observations: torch.Tensor | None = None,
    ) -> None:
        """Fit the normalisation statistics; see :meth:`StateNormalizer.fit`.

        For flat TorchRL frames ``[F]`` pass ``next_observations=td["next", "observation"]``,
        so that the jumps between concatenated episodes are not taken for state changes.
        """
        features = None if self._features is None else self._features(observations)
        self.normalizer.fit(observations, actions, mask, next_observations, features)

    def select_members(self, indices: Sequence[int] | torch.Tensor) -> RCVAEEnsemble:
        """A new ensemble holding copies of the chosen members (and the same normaliser and
        novelty check, which depend on the data alone; not the self-checks, which judged the
        whole ensemble, nor the dynamics check, measured with the whole ensemble's mean).

        ``select_members([i])`` is member i as a stand-alone RCVAE.
        """
        idx = torch.as_tensor(indices, device=self.device)
        if idx.dtype.is_floating_point or idx.dtype == torch.bool or idx.dim() != 1:
            raise ValueError(f"indices: expected a sequence of member indices, got {indices!r}")
        if idx.numel() == 0 or bool(((idx < 0) | (idx >= self.ensemble_size)).any()):
            raise ValueError(
                f"indices: expected member indices in [0, {self.ensemble_size}), got {idx.tolist()}"
            )
        idx = idx.long()
        # seeded: its weights are replaced, and torch's own generator is left as it was
        out = RCVAEEnsemble(self.config, int(idx.numel()), functions=self.functions, seed=0)
        out = out.to(self.device, self.dtype)
        params = {name for name, _ in self.named_parameters()}
        state = {k: (v[idx] if k in params else v) for k, v in self.state_dict().items()}
        out.load_state_dict(state)
        out.novelty = self.novelty
        return out

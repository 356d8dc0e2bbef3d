"""The sequence ELBO of an RCVAE ensemble as a TorchRL ``LossModule``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule

from rcvae_torchrl._checks import (
    check_batch_shapes,
    check_bool,
    check_dtype,
    check_finite,
    check_non_negative,
    check_non_negative_int,
    check_trailing,
    check_unit_interval,
)
from rcvae_torchrl.models.functional import Generators
from rcvae_torchrl.models.rcvae import RCVAEEnsemble, SequenceOutput
from rcvae_torchrl.objectives.functional import free_bits, gaussian_kl, gaussian_nll, masked_mean

__all__ = ["RCVAELoss"]


class RCVAELoss(LossModule):
    """Negative sequence ELBO of all ensemble members, summed over members.

    Per window of L steps and per member, for the L − 1 transitions t → t + 1 (Kingma &
    Welling 2014; Chung et al. 2015 for the sequential form)::

        −ELBO = Σ_t E_q[−log p(Δ̂_{t+1} | h, x, z)] + β · max(KL(q(z | h, Δ̂) ‖ p(z | h)), free_nats)

    with Δ̂ the normalised state change of the predicted (non-passthrough) dims. Both terms are
    averaged over valid transitions (windows × steps) per member, then summed over members, so
    one optimiser step on ``loss_reconstruction + loss_kl`` trains every member.

    Input layout: a tensordict of windows with batch ``[E, W, L]`` (member-major: member e sees
    its own windows, e.g. a bootstrap resample) or ``[W, L]`` (the same windows for every member;
    members still differ by their initialisation and noise). Entries: ``observation [..., L, S]``,
    ``action [..., L, A]`` (the last action of a window is unused) and an optional bool mask
    ``[..., L]`` of valid steps (TorchRL's ``SliceSampler(pad_output=True)`` writes
    ``("collector", "mask")``); a transition counts when both of its steps are valid.

    Args:
        ensemble: the world model to train.
        beta: weight of the KL term (β-VAE, Higgins et al. 2017).
        free_nats: per-step free-nats clamp of the KL (0 disables it).
        open_loop_steps: number K of trailing transitions of each window that read the model's
            own sample of the previous state (at most all but the first); may be changed between
            steps for a curriculum. It fights compounding *model* error, but on a stochastic
            system the fed-back sample is independent of the true noise, so the model learns
            to widen its one-step distribution: on the linear-Gaussian test system (σ = 0.1,
            L = 16, K = 8, 400 steps) the one-step std came out 1.24 σ and the 20-step spread
            1.08–1.33 × the analytic one, against 1.03 σ and 0.99–1.03 × with K = 0. Keep K
            small (or 0) where aleatoric calibration matters.
        detach_open_loop: stop gradients through the fed-back samples.
        nll_beta: β of the β-NLL (Seitzer et al. 2022): each element's NLL in the training loss
            is weighted by its detached decoder variance to the power β. With a learned variance
            the plain NLL (β = 0) scales the mean's gradient by 1/σ², so a dimension the model
            finds hard early gets a large σ and then hardly any gradient on its mean: the model
            explains learnable dynamics as noise. β = 0.5 gives the mean a 1/σ gradient, β = 1 an
            MSE-like one. The optimum of σ (the residual's std) is unchanged. The validation
            figures (``loss_per_member``, ``nll``) stay the plain ELBO.
        generator: torch generator for the latent and fed-back samples.
        validate: check that every window entry is finite at every call. The check reads the
            values back to the host, which on a GPU waits for the queued kernels and under
            ``torch.compile`` splits the graph; a caller that has checked all of its data
            before sampling windows from it (as :func:`~rcvae_torchrl.training.train_ensemble`
            does) turns it off. Shapes and dtypes are checked either way.

    Returns (``forward``): a TensorDict with ``loss_reconstruction`` and ``loss_kl`` (scalars
    to sum for the optimiser) and detached diagnostics: ``kl_raw`` (mean unclamped KL per step),
    ``nll`` (mean NLL per step), ``mse`` (mean squared error of the decoder mean, normalised
    units), ``pred_std_mean`` (mean decoder std, normalised units), and per-member
    ``loss_per_member``, ``nll_per_member``, ``kl_per_member`` ``[E]``.

    Example:
        >>> from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
        >>> model = RCVAEEnsemble(RCVAEConfig(3, 1, hidden_dim=8, mlp_dim=8), ensemble_size=2)
        >>> loss = RCVAELoss(model, beta=1.0)
        >>> td = TensorDict(observation=torch.randn(4, 6, 3), action=torch.randn(4, 6, 1),
        ...                 batch_size=[4, 6])
        >>> out = loss(td)
        >>> (out["loss_reconstruction"] + out["loss_kl"]).backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            observation: states ``[..., L, S]``. Defaults to ``"observation"``.
            action: actions ``[..., L, A]``. Defaults to ``"action"``.
            next_observation: optional s_{t+1} of each step ``[..., L, S]``. Defaults to
                ``("next", "observation")``.
            mask: optional bool ``[..., L]`` of valid steps. Defaults to ``("collector", "mask")``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        next_observation: NestedKey = ("next", "observation")
        mask: NestedKey = ("collector", "mask")

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(
        self,
        ensemble: RCVAEEnsemble,
        *,
        beta: float = 1.0,
        free_nats: float = 0.0,
        open_loop_steps: int = 0,
        detach_open_loop: bool = False,
        nll_beta: float = 0.0,
        generator: Generators = None,
        validate: bool = True,
    ) -> None:
        super().__init__()
        if not isinstance(ensemble, RCVAEEnsemble):
            raise TypeError(f"ensemble: expected an RCVAEEnsemble, got {type(ensemble).__name__}")
        check_bool("validate", validate)
        check_non_negative("beta", beta)
        check_non_negative("free_nats", free_nats)
        check_non_negative_int("open_loop_steps", open_loop_steps)
        check_bool("detach_open_loop", detach_open_loop)
        check_unit_interval("nll_beta", nll_beta)
        self.nll_beta = float(nll_beta)
        self.ensemble = ensemble
        self.beta = float(beta)
        self.free_nats = float(free_nats)
        self.open_loop_steps = int(open_loop_steps)
        self.detach_open_loop = detach_open_loop
        self.generator = generator
        self.validate = validate
        self._set_in_keys()

    def _set_in_keys(self) -> None:
        keys = self.tensor_keys
        self._in_keys = [keys.observation, keys.action, keys.next_observation, keys.mask]
        self._out_keys = ["loss_reconstruction", "loss_kl"]

    @property
    def in_keys(self) -> list[NestedKey]:
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values: list[NestedKey]) -> None:
        self._in_keys = values

    @property
    def out_keys(self) -> list[NestedKey]:
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values: list[NestedKey]) -> None:
        self._out_keys = values

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self._set_in_keys()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, action, next_obs, mask = self._read(tensordict)
        seq = self.ensemble(
            obs,
            action,
            next_observations=next_obs,
            mask=mask,
            open_loop_steps=self.open_loop_steps,
            detach_open_loop=self.detach_open_loop,
            generator=self.generator,
            validate=False,  # _read checked the windows (when self.validate), under their keys
        )
        return self._reduce(seq, _transition_mask(mask, with_next=next_obs is not None))

    def _reduce(self, seq: SequenceOutput, valid: torch.Tensor | None) -> TensorDict:
        """Per-step terms ``[E, W, L−1]`` → per-member means ``[E]`` → scalars."""
        nll_elem = gaussian_nll(seq.target, seq.decoder_mean, seq.decoder_std)
        nll = nll_elem.sum(-1)
        kl = gaussian_kl(seq.posterior_mean, seq.posterior_std, seq.prior_mean, seq.prior_std)
        kl = kl.sum(-1)
        dims = tuple(range(1, nll.dim()))
        nll_m = masked_mean(nll, valid, dims)
        kl_m = masked_mean(free_bits(kl, self.free_nats), valid, dims)
        if seq.episode_mean is not None:  # KL(q(e | window) ‖ p(e)), once per window
            episode = _episode_kl_per_step(seq, valid, kl.shape)
            kl_m, kl = kl_m + episode.mean(dims[:-1]), kl + episode.detach().unsqueeze(-1)
        if self.nll_beta > 0:
            weight = seq.decoder_std.detach().pow(2.0 * self.nll_beta)
            train_nll_m = masked_mean((nll_elem * weight).sum(-1), valid, dims)
        else:
            train_nll_m = nll_m
        with torch.no_grad():
            mse = masked_mean((seq.decoder_mean - seq.target).square().mean(-1), valid, dims)
            std = masked_mean(seq.decoder_std.mean(-1), valid, dims)
            kl_raw = masked_mean(kl, valid, dims)
        return TensorDict(
            loss_reconstruction=train_nll_m.sum(),
            loss_kl=self.beta * kl_m.sum(),
            kl_raw=kl_raw.mean(),
            nll=nll_m.detach().mean(),
            mse=mse.mean(),
            pred_std_mean=std.mean(),
            loss_per_member=(nll_m + self.beta * kl_m).detach(),
            nll_per_member=nll_m.detach(),
            kl_per_member=kl_raw,
        )

    def _read(
        self, td: TensorDictBase
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """Fetch and check the windows; return them member-major ``[E, W, L, ·]``."""
        keys, e = self.tensor_keys, self.ensemble.ensemble_size
        if td.batch_dims not in (2, 3) or (td.batch_dims == 3 and td.batch_size[0] != e):
            raise ValueError(
                f"RCVAELoss: expected a tensordict with batch [W, L] or [E={e}, W, L], "
                f"got batch {tuple(td.batch_size)}."
            )
        next_obs = td.get(keys.next_observation, None)
        if td.batch_size[-1] < (1 if next_obs is not None else 2):
            raise ValueError(
                f"RCVAELoss: windows need at least one transition, got L={td.batch_size[-1]}"
                f"{'' if next_obs is not None else ' without next observations'}."
            )
        tensors = [td.get(keys.observation, None), td.get(keys.action, None), next_obs]
        for key, x in zip((keys.observation, keys.action), tensors, strict=False):
            if x is None:
                raise KeyError(
                    f"RCVAELoss: expected an entry {key!r} in the windows, got the entries "
                    f"{sorted(map(str, td.keys(True, True)))}"
                )
        if td.batch_size[-2] == 0:
            raise ValueError(
                f"RCVAELoss: expected at least one window, got batch {tuple(td.batch_size)}"
            )
        self._check(tensors)
        mask = self._read_mask(td)
        if td.batch_dims == 2:
            tensors = [None if x is None else x.expand(e, *x.shape) for x in tensors]
            mask = None if mask is None else mask.unsqueeze(0)
        return (*tensors, mask)

    def _check(self, tensors: list[torch.Tensor | None]) -> None:
        keys, cfg = self.tensor_keys, self.ensemble.config
        dtype = self.ensemble.dtype
        obs_key, act_key, next_key = map(
            str, (keys.observation, keys.action, keys.next_observation)
        )
        for key, x, size, what in (
            (obs_key, tensors[0], cfg.obs_dim, f"[..., L, S={cfg.obs_dim}]"),
            (act_key, tensors[1], cfg.action_dim, f"[..., L, A={cfg.action_dim}]"),
            (next_key, tensors[2], cfg.obs_dim, f"[..., L, S={cfg.obs_dim}]"),
        ):
            if x is None:
                continue
            check_trailing(key, x, (size,), what)
            check_batch_shapes((obs_key, key), tensors[0].shape[:-1], x.shape[:-1])
            if self.validate:
                check_finite(key, x)
            check_dtype(key, x, dtype)

    def _read_mask(self, td: TensorDictBase) -> torch.Tensor | None:
        mask = td.get(self.tensor_keys.mask, None)
        if mask is not None and (mask.dtype != torch.bool or mask.shape != td.batch_size):
            raise ValueError(
                f"{self.tensor_keys.mask}: expected a bool mask of shape "
                f"{tuple(td.batch_size)}, got {mask.dtype} {tuple(mask.shape)}."
            )
        if mask is not None and not bool(mask.any()):
            raise ValueError(
                f"{self.tensor_keys.mask}: expected some valid steps, got a mask that is all "
                "False (the loss would be 0 and teach nothing)"
            )
        return mask


def _episode_kl_per_step(
    seq: SequenceOutput, valid: torch.Tensor | None, shape: torch.Size
) -> torch.Tensor:
    """KL(q(e | window) ‖ p(e)) of the episode latent, per window ``[E, *B]``, spread over the
    window's valid transitions (the per-step terms are averaged over them)."""
    q = (seq.episode_mean, seq.episode_std)
    kl = gaussian_kl(*q, seq.episode_prior_mean, seq.episode_prior_std).sum(-1)
    if valid is None:
        return kl / shape[-1]
    steps = valid.to(kl.dtype).expand(shape).sum(-1)
    return kl / steps.clamp_min(1.0)


def _transition_mask(mask: torch.Tensor | None, with_next: bool) -> torch.Tensor | None:
    """Which transitions count: step t's own (with next observations), else t and t + 1."""
    if mask is None or with_next:
        return mask
    return mask[..., 1:] & mask[..., :-1]

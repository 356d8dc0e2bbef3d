"""Normalisation statistics of states, actions and state changes, fitted from data.

The statistics are buffers, so they travel with ``state_dict()`` and ``.to(device)``.
"""

from __future__ import annotations

import torch
from torch import nn

from rcvae_torchrl._checks import check_finite, check_floating, check_tensor, check_trailing

__all__ = ["StateNormalizer", "masked_mean_std"]


def masked_mean_std(
    x: torch.Tensor, mask: torch.Tensor | None = None, min_std: float = 1e-6
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-feature mean and std over all leading dimensions.

    Args:
        x: samples ``[..., F]``.
        mask: optional bool ``[...]`` selecting the samples that count.
        min_std: stds below this (constant features) are replaced by 1, so normalising
            leaves such a feature centred but unscaled instead of dividing by ~0.

    Returns:
        ``(mean [F], std [F])``.
    """
    flat = x.reshape(-1, x.shape[-1])
    if mask is not None:
        flat = flat[mask.reshape(-1)]
    if flat.shape[0] == 0:
        raise ValueError("masked_mean_std: no samples to fit (empty input or all masked out).")
    mean = flat.mean(0)
    std = flat.std(0, correction=0) if flat.shape[0] > 1 else torch.ones_like(mean)
    return mean, torch.where(std < min_std, torch.ones_like(std), std)


def _state_changes(
    observations: torch.Tensor,
    mask: torch.Tensor | None,
    next_observations: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """State changes and their validity mask, from transitions or from trajectories."""
    if next_observations is not None:
        if next_observations.shape != observations.shape:
            raise ValueError(
                f"next_observations: expected shape {tuple(observations.shape)} (that of "
                f"observations), got {tuple(next_observations.shape)}."
            )
        return next_observations - observations, mask
    if observations.dim() < 2 or observations.shape[-2] < 2:
        raise ValueError(
            "observations: expected trajectories [..., T, S] with T >= 2 (or pass "
            f"next_observations), got shape {tuple(observations.shape)}."
        )
    delta = observations[..., 1:, :] - observations[..., :-1, :]
    return delta, None if mask is None else mask[..., 1:] & mask[..., :-1]


class StateNormalizer(nn.Module):
    """Affine normalisers for states s, actions a and state changes Δ = s_t − s_{t−1}.

    Until :meth:`fit` is called the maps are identities (mean 0, std 1); ``fitted`` says
    whether it has been called.

    Args:
        obs_dim: state dimension S.
        action_dim: action dimension A.
        feature_dim: number F of input features (their statistics exist only when F > 0, so
            checkpoints of models without features keep their layout).

    Example:
        >>> norm = StateNormalizer(3, 1)
        >>> norm.fit(torch.randn(10, 50, 3), torch.randn(10, 50, 1))
        >>> norm.normalize_state(torch.zeros(3)).shape
        torch.Size([3])
    """

    def __init__(self, obs_dim: int, action_dim: int, feature_dim: int = 0) -> None:
        super().__init__()
        self.feature_dim = feature_dim
        if feature_dim:
            self.register_buffer("feature_mean", torch.zeros(feature_dim))
            self.register_buffer("feature_std", torch.ones(feature_dim))
        self.register_buffer("state_mean", torch.zeros(obs_dim))
        self.register_buffer("state_std", torch.ones(obs_dim))
        self.register_buffer("action_mean", torch.zeros(action_dim))
        self.register_buffer("action_std", torch.ones(action_dim))
        self.register_buffer("delta_mean", torch.zeros(obs_dim))
        self.register_buffer("delta_std", torch.ones(obs_dim))
        self.register_buffer("_fitted", torch.zeros((), dtype=torch.bool))

    @property
    def fitted(self) -> bool:
        """Whether :meth:`fit` has set the statistics."""
        return bool(self._fitted)

    @torch.no_grad()
    def fit(
        self,
        observations: torch.Tensor,
        actions: torch.Tensor | None = None,
        mask: torch.Tensor | None = None,
        next_observations: torch.Tensor | None = None,
        features: torch.Tensor | None = None,
    ) -> None:
        """Fit all statistics from trajectories or from transitions.

        Args:
            observations: states. Without ``next_observations``: trajectories ``[..., T, S]``
                with time on dim −2 (T ≥ 2); state changes are taken between consecutive steps,
                so a flat batch of concatenated episodes would count the jumps between episodes.
                With ``next_observations``: any ``[..., S]`` (e.g. flat TorchRL frames).
            actions: optional actions ``[..., T, A]`` / ``[..., A]``; if omitted the action map
                stays as is.
            mask: optional bool ``[..., T]`` / ``[...]`` of valid steps. For trajectories a state
                change counts only when both of its steps are valid.
            next_observations: optional s_{t+1} ``[..., S]`` of each step (TorchRL's
                ``("next", "observation")``); state changes are ``next − observation``.
            features: the input features of ``observations`` ``[..., F]``; required when
                ``feature_dim > 0``.

        Raises:
            ValueError / TypeError naming the argument: a non-floating input, a last dimension
            other than S / A / F, or a NaN or infinite entry among the steps that count (the
            statistics would be NaN, and so would every later prediction with them).
        """
        obs_dim, action_dim = self.state_mean.shape[0], self.action_mean.shape[0]
        for name, x, size in (
            ("observations", observations, obs_dim),
            ("actions", actions, action_dim),
            ("next_observations", next_observations, obs_dim),
            ("features", features, self.feature_dim or None),
        ):
            if x is None:
                continue
            check_tensor(name, x)
            check_floating(name, x)
            if size is not None:
                check_trailing(name, x, (size,), f"[..., {size}]")
            counted = x[mask] if mask is not None and mask.shape == x.shape[:-1] else x
            check_finite(name, counted)
        if self.feature_dim:
            if features is None or features.shape[-1] != self.feature_dim:
                got = None if features is None else tuple(features.shape)
                raise ValueError(
                    f"features: expected [..., F={self.feature_dim}] input features, got {got}."
                )
            self._copy(self.feature_mean, self.feature_std, masked_mean_std(features, mask))
        self._copy(self.state_mean, self.state_std, masked_mean_std(observations, mask))
        delta, delta_mask = _state_changes(observations, mask, next_observations)
        self._copy(self.delta_mean, self.delta_std, masked_mean_std(delta, delta_mask))
        if actions is not None:
            self._copy(self.action_mean, self.action_std, masked_mean_std(actions, mask))
        self._fitted.fill_(True)

    @staticmethod
    def _copy(mean: torch.Tensor, std: torch.Tensor, stats: tuple[torch.Tensor, ...]) -> None:
        mean.copy_(stats[0])
        std.copy_(stats[1])

    def normalize_state(self, s: torch.Tensor) -> torch.Tensor:
        """``[..., S]`` → ``[..., S]``."""
        return (s - self.state_mean) / self.state_std

    def normalize_features(self, f: torch.Tensor) -> torch.Tensor:
        """``[..., F]`` → ``[..., F]``."""
        return (f - self.feature_mean) / self.feature_std

    def normalize_action(self, a: torch.Tensor) -> torch.Tensor:
        """``[..., A]`` → ``[..., A]``."""
        return (a - self.action_mean) / self.action_std

    def normalize_delta(self, delta: torch.Tensor, dims: torch.Tensor) -> torch.Tensor:
        """Normalise the state changes of the state dimensions ``dims`` (``[..., len(dims)]``)."""
        return (delta - self.delta_mean[dims]) / self.delta_std[dims]

    def denormalize_delta(self, delta: torch.Tensor, dims: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`normalize_delta`."""
        return delta * self.delta_std[dims] + self.delta_mean[dims]

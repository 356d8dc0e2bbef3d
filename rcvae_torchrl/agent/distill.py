"""Behaviour cloning: distil an expensive policy (the MPC planner) into an :class:`MLPPolicy`."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tqdm.auto import tqdm

from rcvae_torchrl._checks import check_non_negative_int, check_positive, check_tensor

from .policy import MLPPolicy

__all__ = ["DistillConfig", "distill_policy"]


@dataclass(frozen=True)
class DistillConfig:
    """Budget of :func:`distill_policy`.

    Args:
        epochs: passes over the training pairs at most.
        batch_size: pairs per step.
        lr: Adam learning rate.
        val_fraction: pairs held out for early stopping.
        patience: epochs without validation improvement before stopping.
        seed: seeds the split, the shuffling and the initialisation.
    """

    epochs: int = 200
    batch_size: int = 256
    lr: float = 1e-3
    val_fraction: float = 0.1
    patience: int = 20
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("epochs", "batch_size", "patience"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {value!r}")
        check_positive("lr", self.lr)
        check_non_negative_int("seed", self.seed)
        if isinstance(self.val_fraction, bool) or not isinstance(self.val_fraction, (int, float)):
            raise TypeError(f"val_fraction: expected a float in (0, 1), got {self.val_fraction!r}")
        if not 0.0 < self.val_fraction < 1.0:
            raise ValueError(
                f"val_fraction: expected a fraction in (0, 1), got {self.val_fraction!r}"
            )


def _check_pairs(
    observations: torch.Tensor, actions: torch.Tensor, dtype: torch.dtype = torch.float32
) -> None:
    for name, x in (("observations", observations), ("actions", actions)):
        check_tensor(name, x)
        if x.dtype != dtype:
            raise TypeError(
                f"{name}: expected {dtype} values (the policy's dtype), got {x.dtype}; cast "
                f"them with .to({dtype})"
            )
    if observations.ndim != 2 or actions.ndim != 2 or len(observations) != len(actions):
        raise ValueError(
            f"observations, actions: expected [N, S] and [N, A] with the same N, got "
            f"{tuple(observations.shape)} and {tuple(actions.shape)}"
        )
    if len(observations) < 10:
        raise ValueError(f"observations: expected at least 10 pairs, got {len(observations)}")
    if not (torch.isfinite(observations).all() and torch.isfinite(actions).all()):
        raise ValueError("observations, actions: expected finite values, got NaN or inf")
    low, high = float(actions.min()), float(actions.max())
    if low < -1.0 or high > 1.0:
        raise ValueError(
            f"actions: expected labels in [-1, 1] (the policy's tanh range: scale the actions "
            f"first), got values in [{low:.3g}, {high:.3g}]"
        )


def distill_policy(
    observations: torch.Tensor,
    actions: torch.Tensor,
    config: DistillConfig = DistillConfig(),
    *,
    policy: MLPPolicy | None = None,
    progress: bool = True,
) -> tuple[MLPPolicy, dict[str, float]]:
    """Fit ``policy`` (a new :class:`MLPPolicy` by default) to ``actions [N, A]`` given
    ``observations [N, S]`` by mean squared error, keeping the weights of the best validation
    epoch. Returns the policy and ``{"train_mse", "val_mse", "epochs"}``.
    """
    dtype = torch.float32 if policy is None else next(policy.parameters()).dtype
    _check_pairs(observations, actions, dtype)
    if policy is not None:
        with torch.no_grad():
            out = policy(observations[:1])
        if out.shape[-1] != actions.shape[-1]:
            raise ValueError(
                f"policy: expected actions of A={actions.shape[-1]} (those of the labels), "
                f"got a policy of A={out.shape[-1]}"
            )
    g = torch.Generator().manual_seed(config.seed)
    torch.manual_seed(config.seed)
    if policy is None:
        policy = MLPPolicy(observations.shape[-1], actions.shape[-1])
        policy.fit_normalizer(observations)
    perm = torch.randperm(len(observations), generator=g)
    n_val = max(1, int(config.val_fraction * len(observations)))
    val, train = perm[:n_val], perm[n_val:]
    optimizer = torch.optim.Adam(policy.parameters(), lr=config.lr)
    best = (float("inf"), {k: v.clone() for k, v in policy.state_dict().items()}, 0)
    stats = {"train_mse": float("nan")}
    for epoch in tqdm(
        range(config.epochs), desc="distil policy", disable=not progress, leave=False
    ):
        stats["train_mse"] = _epoch(policy, optimizer, observations, actions, train, config, g)
        with torch.no_grad():
            val_mse = (policy(observations[val]) - actions[val]).square().mean().item()
        if val_mse < best[0]:
            best = (val_mse, {k: v.clone() for k, v in policy.state_dict().items()}, epoch)
        elif epoch - best[2] >= config.patience:
            break
    policy.load_state_dict(best[1])
    return policy, {**stats, "val_mse": best[0], "epochs": float(epoch + 1)}


def _epoch(policy, optimizer, observations, actions, idx, config, g) -> float:
    total, count = 0.0, 0
    for batch in idx[torch.randperm(len(idx), generator=g)].split(config.batch_size):
        loss = (policy(observations[batch]) - actions[batch]).square().mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        total, count = total + loss.item() * len(batch), count + len(batch)
    return total / count

"""An amortised policy: a small MLP that maps observations to actions in [-1, 1].

It stands in for the MPC planner where planning at every step is too slow: inside imagined
rollouts of thousands of particles (closed-loop competency forecasts) and as a real-time agent.
Observations are normalised with statistics fitted from data and saved with the weights
(:func:`save_policy` / :func:`load_policy`, a versioned file like the ensemble checkpoints).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torch import nn

from rcvae_torchrl._checks import check_positive_int
from rcvae_torchrl.io import StoredFileError, load_torch, save_torch

__all__ = [
    "POLICY_FORMAT_VERSION",
    "FixedRowsPolicy",
    "MLPPolicy",
    "ResidualPolicy",
    "load_policy",
    "save_policy",
]

POLICY_FORMAT_VERSION = 1
_KIND = "rcvae_torchrl.MLPPolicy"


class MLPPolicy(nn.Module):
    """``a = tanh(MLP((s - mean) / std))``, ``[..., S] -> [..., A]``.

    Args:
        obs_dim: S.
        action_dim: A.
        hidden: width of the two hidden layers.
    """

    def __init__(self, obs_dim: int, action_dim: int, hidden: int = 256) -> None:
        for name, value in (("obs_dim", obs_dim), ("action_dim", action_dim), ("hidden", hidden)):
            check_positive_int(name, value)
        super().__init__()
        self.obs_dim, self.action_dim, self.hidden = obs_dim, action_dim, hidden
        self.net = nn.Sequential(
            nn.Linear(obs_dim, hidden),
            nn.ELU(),
            nn.Linear(hidden, hidden),
            nn.ELU(),
            nn.Linear(hidden, action_dim),
        )
        self.register_buffer("obs_mean", torch.zeros(obs_dim))
        self.register_buffer("obs_std", torch.ones(obs_dim))

    def fit_normalizer(self, observations: torch.Tensor) -> None:
        """Set the input statistics from observations ``[..., S]`` (std floored at 1e-3)."""
        if observations.shape[-1] != self.obs_dim or observations.numel() < 2 * self.obs_dim:
            raise ValueError(
                f"observations: expected at least two rows [..., S={self.obs_dim}], got shape "
                f"{tuple(observations.shape)}"
            )
        if not bool(torch.isfinite(observations).all()):
            raise ValueError("observations: expected finite values, got NaN or inf")
        flat = observations.reshape(-1, self.obs_dim)
        self.obs_mean.copy_(flat.mean(0))
        self.obs_std.copy_(flat.std(0).clamp_min(1e-3))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        if observation.shape[-1] != self.obs_dim:
            raise ValueError(
                f"observation: expected shape [..., {self.obs_dim}], got {tuple(observation.shape)}"
            )
        return torch.tanh(self.net((observation - self.obs_mean) / self.obs_std))


class ResidualPolicy(nn.Module):
    """``a = clamp(base(s) + residual(s), -1, 1)``: a fixed prior policy plus a learned correction.

    Distilling a planner that refines a prior policy (policy-guided CEM) into the residual is far
    easier than into a whole policy: the correction is small and smooth where the prior switches
    modes abruptly (residual policy learning, Silver et al. 2018; Johannink et al. 2019). The
    base is code, not weights: :func:`save_policy` stores the residual and :func:`load_policy`
    takes the base again.
    """

    def __init__(self, base: nn.Module, residual: MLPPolicy) -> None:
        super().__init__()
        if not isinstance(residual, MLPPolicy):
            raise TypeError(
                f"residual: expected an MLPPolicy (what distill_policy fits), got "
                f"{type(residual).__name__}"
            )
        if not callable(base):
            raise TypeError(f"base: expected a policy observation -> action, got {base!r}")
        try:
            with torch.no_grad():  # the base's action size, on one zero state
                probe = base(torch.zeros(1, residual.obs_dim))
        except Exception:  # a base not written for that state: its first call will tell
            probe = None
        if probe is not None and (
            not isinstance(probe, torch.Tensor) or probe.shape != (1, residual.action_dim)
        ):
            got = tuple(probe.shape) if isinstance(probe, torch.Tensor) else type(probe).__name__
            raise ValueError(
                f"base: expected actions [B, A={residual.action_dim}] (the residual's) for states "
                f"[B, S={residual.obs_dim}], got {got} for one state"
            )
        self.base, self.residual = base, residual
        self.obs_dim, self.action_dim = residual.obs_dim, residual.action_dim

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return (self.base(observation) + self.residual(observation)).clamp(-1.0, 1.0)


class FixedRowsPolicy:
    """A stateless TensorDict policy called on blocks of exactly ``rows`` rows, so that each
    row's action does not depend on the batch it comes in.

    A matrix product's float32 rounding can depend on the number of rows (the BLAS picks its
    kernels by shape; one row is a matrix-vector product), and so can an elementwise function's
    (a vectorised kernel, of ``atan2`` say, rounds some values otherwise than the scalar loop
    that takes a short tensor or the tail of a long one), so the same state can get a slightly
    different action in a batch of 40 envs than in one of 100 or alone, and a contact-rich
    episode amplifies the difference. A multiple of 32 rows (the default 64) leaves such
    kernels no short tail in a block. Here every call flattens the input's batch, splits it
    into blocks of ``rows`` (the last one padded with repeats of its last row, whose results
    are dropped), calls ``policy`` on each and writes the results back: an episode's actions
    then come out the same whether it runs alone, in a batched env of any size, in worker
    processes or on other ranks (on the same machine and device).

    Only for policies without state across calls (a planner's warm start would leak between
    blocks). ``reset()`` is passed on to ``policy`` where it has one.
    """

    def __init__(self, policy: Callable[[TensorDictBase], TensorDictBase], rows: int = 64) -> None:
        if not callable(policy):
            raise TypeError(f"policy: expected a TensorDict policy, got {type(policy).__name__}")
        check_positive_int("rows", rows)
        self.policy, self.rows = policy, rows

    def reset(self) -> None:
        if hasattr(type(self.policy), "reset"):
            self.policy.reset()

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        flat = tensordict.reshape(-1)
        n, parts = flat.shape[0], []
        for low in range(0, n, self.rows):
            block = flat[torch.arange(low, low + self.rows).clamp_max(n - 1)]
            parts.append(self.policy(block)[: min(self.rows, n - low)])
        tensordict.update(torch.cat(parts).reshape(tensordict.shape))
        return tensordict


def save_policy(policy: MLPPolicy | ResidualPolicy, path: str | Path) -> Path:
    """Write the policy's weights, sizes and normaliser (and whether it is a residual on a base
    policy) to ``path`` atomically, with a kind and a format version."""
    mlp = policy.residual if isinstance(policy, ResidualPolicy) else policy
    if not isinstance(mlp, MLPPolicy):
        raise TypeError(
            f"policy: expected an MLPPolicy or a ResidualPolicy, got {type(policy).__name__}"
        )
    payload = {
        "kind": _KIND,
        "format_version": POLICY_FORMAT_VERSION,
        "obs_dim": mlp.obs_dim,
        "action_dim": mlp.action_dim,
        "hidden": mlp.hidden,
        "residual": isinstance(policy, ResidualPolicy),
        "state_dict": {k: v.detach().cpu() for k, v in mlp.state_dict().items()},
    }
    return save_torch(path, payload)


def load_policy(path: str | Path, *, base: nn.Module | None = None) -> MLPPolicy | ResidualPolicy:
    """Rebuild the policy :func:`save_policy` wrote (in eval mode).

    Args:
        path: the policy file.
        base: the base policy, required when the file holds a residual policy.

    Raises:
        StoredFileError: a missing, truncated, corrupt or foreign file, an unknown format
            version, or weights that do not match.
        ValueError: a residual policy without ``base``.
    """
    payload = load_torch(path, "policy file")
    where = f"policy file {str(path)!r}"
    if not isinstance(payload, dict) or payload.get("kind") != _KIND:
        raise StoredFileError(f"{where}: expected a policy saved by save_policy", path)
    if payload.get("format_version") != POLICY_FORMAT_VERSION:
        raise StoredFileError(
            f"{where}: expected format version {POLICY_FORMAT_VERSION}, "
            f"got {payload.get('format_version')!r}",
            path,
        )
    mlp = MLPPolicy(payload["obs_dim"], payload["action_dim"], payload["hidden"])
    try:
        mlp.load_state_dict(payload["state_dict"])
    except RuntimeError as err:
        raise StoredFileError(f"{where}: weights do not match: {err}", path) from err
    if not payload["residual"]:
        return mlp.eval()
    if base is None:
        raise ValueError(f"base: {where} holds a residual policy; pass its base policy")
    return ResidualPolicy(base, mlp).eval()

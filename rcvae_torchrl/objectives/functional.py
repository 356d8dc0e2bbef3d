"""Pure tensor functions of the sequence ELBO (Gaussian NLL, Gaussian KL, free bits)."""

from __future__ import annotations

import math

import torch

from rcvae_torchrl._checks import broadcasts_to, check_non_negative

__all__ = ["free_bits", "gaussian_kl", "gaussian_nll", "masked_mean"]

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


def gaussian_nll(x: torch.Tensor, mean: torch.Tensor, std: torch.Tensor) -> torch.Tensor:
    """Elementwise −log N(x; mean, std²) in nats, constant included. Shapes broadcast.

    ``std`` must be positive (not checked: the loss's hot path; 0 gives inf or NaN)."""
    return 0.5 * ((x - mean) / std).square() + std.log() + _HALF_LOG_2PI


def gaussian_kl(
    mean_q: torch.Tensor, std_q: torch.Tensor, mean_p: torch.Tensor, std_p: torch.Tensor
) -> torch.Tensor:
    """Elementwise KL(N(mean_q, std_q²) ‖ N(mean_p, std_p²)) in nats. Shapes broadcast.

    ``log(σp/σq) + (σq² + (μq − μp)²) / (2σp²) − 1/2``. Both stds must be positive (not
    checked: the loss's hot path).
    """
    var_ratio = (std_q / std_p).square()
    mahalanobis = ((mean_q - mean_p) / std_p).square()
    return 0.5 * (var_ratio + mahalanobis - 1.0 - var_ratio.log())


def free_bits(kl: torch.Tensor, free_nats: float) -> torch.Tensor:
    """Per-element free-nats clamp ``max(kl, free_nats)`` (Kingma et al. 2016; Dreamer).

    Below ``free_nats`` the KL gives no gradient to prior or posterior, so keep it small
    when prior samples must match the data (generation). ``free_nats = 0`` is the plain KL.
    """
    check_non_negative("free_nats", free_nats)
    return kl.clamp_min(free_nats) if free_nats > 0 else kl


def masked_mean(x: torch.Tensor, mask: torch.Tensor | None, dims: tuple[int, ...]) -> torch.Tensor:
    """Mean of ``x`` over ``dims`` counting only entries where ``mask`` (broadcastable) is true.

    Entries with no valid element get 0.
    """
    if mask is None:
        return x.mean(dim=dims)
    if not broadcasts_to(mask.shape, x.shape):
        raise ValueError(
            f"mask: expected a shape that broadcasts to x's {tuple(x.shape)}, got "
            f"{tuple(mask.shape)}"
        )
    weight = mask.to(x.dtype).expand_as(x)
    return (x * weight).sum(dim=dims) / weight.sum(dim=dims).clamp_min(1.0)

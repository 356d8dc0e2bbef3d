"""Pure tensor functions of the RCVAE's Gaussian heads."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

__all__ = ["Generators", "gaussian_head", "reparameterize", "soft_clamp", "standard_normal"]


def soft_clamp(x: torch.Tensor, low: float, high: float) -> torch.Tensor:
    """Smoothly bound ``x`` to ``(low, high)`` with two softplus hinges (PETS, Chua et al. 2018).

    ``y = high − softplus(high − x)``, then ``low + softplus(y − low)``. Identity far inside
    the bounds, never a zero gradient at them. Elementwise, any shape.
    """
    x = high - F.softplus(high - x)
    return low + F.softplus(x - low)


def gaussian_head(
    raw: torch.Tensor,
    *,
    min_std: float | None = None,
    log_std_bounds: tuple[float, float] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Split a network output ``[..., 2F]`` into a Gaussian's ``(mean [..., F], std [..., F])``.

    Exactly one of ``min_std`` (std = softplus(raw) + min_std, the latent heads, as Dreamer's
    RSSM) or ``log_std_bounds`` (std = exp(soft_clamp(raw, low, high)), the decoder, as PETS)
    must be given.
    """
    mean, raw_std = raw.chunk(2, dim=-1)
    if (min_std is None) == (log_std_bounds is None):
        raise ValueError("gaussian_head: give exactly one of min_std or log_std_bounds.")
    if min_std is not None:
        # softplus of the strided half is unvectorised on CPU (~10x slower): copy it first
        return mean, F.softplus(raw_std.contiguous()) + min_std
    return mean, soft_clamp(raw_std, *log_std_bounds).exp()


#: A generator, or one per ensemble member: row ``m`` of member-major noise ``[E, ...]`` comes
#: from the ``m``-th (so a member's noise does not depend on the other members it runs with).
Generators = torch.Generator | Sequence[torch.Generator] | None


def standard_normal(
    shape: torch.Size | tuple[int, ...],
    like: torch.Tensor,
    generator: Generators = None,
) -> torch.Tensor:
    """Draw N(0, I) noise of ``shape`` with the dtype and device of ``like``.

    ``generator`` may be a sequence of ``shape[0]`` generators, one per leading row.
    """
    if generator is None or isinstance(generator, torch.Generator):
        return torch.randn(shape, generator=generator, dtype=like.dtype, device=like.device)
    if not isinstance(generator, Sequence) or not all(
        isinstance(g, torch.Generator) for g in generator
    ):
        raise TypeError(
            "generator: expected a torch.Generator, one per leading row, or None, got "
            f"{type(generator).__name__}"
        )
    if len(generator) != shape[0]:
        raise ValueError(
            f"generator: expected one generator per leading row ({shape[0]}), got {len(generator)}"
        )
    rows = [
        torch.randn(shape[1:], generator=g, dtype=like.dtype, device=like.device) for g in generator
    ]
    return torch.stack(rows)


def reparameterize(
    mean: torch.Tensor,
    std: torch.Tensor,
    noise: torch.Tensor | None = None,
    generator: Generators = None,
) -> torch.Tensor:
    """A reparameterised Gaussian sample ``mean + std ⊙ ε`` (Kingma & Welling 2014).

    ``noise`` (ε, same shape as ``mean``) is drawn from ``generator`` when not given.
    """
    if noise is None:
        noise = standard_normal(mean.shape, mean, generator)
    elif noise.shape != mean.shape:
        raise ValueError(f"noise: expected shape {tuple(mean.shape)}, got {tuple(noise.shape)}.")
    return mean + std * noise

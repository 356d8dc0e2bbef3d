"""Batched-matmul ensemble layers: E independent members as one computation.

Members are stacked on a leading dimension. Inputs are member-major ``[E, B, in]``; one
``torch.baddbmm`` evaluates all members, so there is no Python loop over members and no
``torch.vmap`` (which has no batching rule for ``nn.GRUCell`` and draws the same noise for
every member unless told otherwise).

:func:`ensemble_linear` and :func:`ensemble_mlp` compute what the modules compute (the same
kernels on the same operands, so the same bits) without the ``nn.Module`` call overhead: a
planner steps a few hundred particles at a time, where every call costs microseconds whatever
its size.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["EnsembleLinear", "EnsembleMLP", "ensemble_linear", "ensemble_mlp"]


class EnsembleLinear(nn.Module):
    """E independent affine maps ``y[e] = x[e] @ W[e] + b[e]``.

    Each member is initialised like ``nn.Linear`` (kaiming-uniform with a = √5, i.e.
    U(−1/√in, 1/√in) for weights and biases), independently per member.

    Args:
        ensemble_size: number of members E.
        in_features: input size.
        out_features: output size.

    Shapes:
        input ``[E, *B, in]`` → output ``[E, *B, out]`` (any number of batch dims, flattened
        for one ``baddbmm``); ``weight`` is ``[E, in, out]`` and ``bias`` is ``[E, out]``.

    Example:
        >>> layer = EnsembleLinear(5, 3, 4)
        >>> layer(torch.randn(5, 7, 3)).shape
        torch.Size([5, 7, 4])
    """

    def __init__(self, ensemble_size: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.ensemble_size = ensemble_size
        self.in_features = in_features
        self.out_features = out_features
        self.weight = nn.Parameter(torch.empty(ensemble_size, in_features, out_features))
        self.bias = nn.Parameter(torch.empty(ensemble_size, out_features))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Draw every member's weights and biases from U(−1/√in, 1/√in)."""
        bound = 1.0 / math.sqrt(self.in_features)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() == 3:
            return torch.baddbmm(self.bias.unsqueeze(1), x, self.weight)
        flat = x.reshape(x.shape[0], -1, x.shape[-1])
        out = torch.baddbmm(self.bias.unsqueeze(1), flat, self.weight)
        return out.view(*x.shape[:-1], self.out_features)

    def forward_split(self, parts: Sequence[torch.Tensor]) -> torch.Tensor:
        """``forward(torch.cat(parts, dim=-1))`` without the concatenation.

        Each part multiplies its own rows of ``weight`` (one ``baddbmm`` per part, summed), so
        neither the concatenated input nor, in backward, its split gradient is materialised.
        Parts are ``[E, *B, in_i]`` with the same ``*B`` and ``Σ in_i = in``.
        """
        if sum(p.shape[-1] for p in parts) != self.in_features:
            raise ValueError(
                f"forward_split: part sizes {[p.shape[-1] for p in parts]} do not sum to "
                f"in={self.in_features}."
            )
        batch = parts[0].shape[:-1]
        out, start = self.bias.unsqueeze(1), 0
        for i, part in enumerate(parts):
            size = part.shape[-1]
            flat = part.reshape(part.shape[0], -1, size)
            weight = self.weight[:, start : start + size]
            # accumulate in place after the first part (baddbmm's backward needs neither sum)
            out = torch.baddbmm(out, flat, weight) if i == 0 else out.baddbmm_(flat, weight)
            start += size
        return out.view(*batch, self.out_features)

    def extra_repr(self) -> str:
        return f"ensemble_size={self.ensemble_size}, in={self.in_features}, out={self.out_features}"


class EnsembleMLP(nn.Sequential):
    """An MLP of :class:`EnsembleLinear` layers with SiLU activations between them.

    Args:
        ensemble_size: number of members E.
        in_features: input size.
        hidden_features: width of each hidden layer.
        out_features: output size.
        depth: number of hidden layers (0 gives a single affine map).

    Shapes:
        ``[E, *B, in]`` → ``[E, *B, out]``.
    """

    def __init__(
        self,
        ensemble_size: int,
        in_features: int,
        hidden_features: int,
        out_features: int,
        depth: int = 1,
    ) -> None:
        sizes = [in_features] + [hidden_features] * depth + [out_features]
        layers: list[nn.Module] = []
        for i, (n_in, n_out) in enumerate(itertools.pairwise(sizes)):
            layers.append(EnsembleLinear(ensemble_size, n_in, n_out))
            if i < depth:
                layers.append(nn.SiLU())
        super().__init__(*layers)

    def forward_split(self, parts: Sequence[torch.Tensor]) -> torch.Tensor:
        """``self(torch.cat(parts, dim=-1))`` without the concatenation (see
        :meth:`EnsembleLinear.forward_split`)."""
        x = self[0].forward_split(parts)
        for layer in list(self)[1:]:
            x = layer(x)
        return x


def ensemble_linear(layer: EnsembleLinear, x: torch.Tensor) -> torch.Tensor:
    """``layer(x)`` without the module call (the same numbers)."""
    if x.dim() == 3:
        return torch.baddbmm(layer.bias.unsqueeze(1), x, layer.weight)
    return layer.forward(x)


def ensemble_mlp(net: EnsembleMLP, x: torch.Tensor) -> torch.Tensor:
    """``net(x)`` without the module calls (its layers are EnsembleLinear and SiLU)."""
    for layer in net:
        x = ensemble_linear(layer, x) if isinstance(layer, EnsembleLinear) else F.silu(x)
    return x

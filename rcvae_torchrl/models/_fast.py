"""The generation step's hot path: the modules' numbers with fewer small tensor ops.

A planner steps a few hundred particles at a time, where every tensor op costs microseconds of
dispatch whatever its size. These functions compute exactly what the modules compute (the same
kernels on the same operands, so the same bits), minus the ``nn.Module`` call overhead and a few
ops: the GRU's reset and update gates share one add and one sigmoid. The training path keeps
using the modules.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from rcvae_torchrl.models.ensemble_gru import EnsembleGRUCell
from rcvae_torchrl.models.ensemble_layers import EnsembleLinear, EnsembleMLP

__all__ = ["gru_step", "linear", "mlp"]


def linear(layer: EnsembleLinear, x: torch.Tensor) -> torch.Tensor:
    """``layer(x)`` without the module call."""
    if x.dim() == 3:
        return torch.baddbmm(layer.bias.unsqueeze(1), x, layer.weight)
    return layer.forward(x)


def mlp(net: EnsembleMLP, x: torch.Tensor) -> torch.Tensor:
    """``net(x)`` without the module calls (its layers are EnsembleLinear and SiLU)."""
    for layer in net:
        x = linear(layer, x) if isinstance(layer, EnsembleLinear) else F.silu(x)
    return x


def gru_step(cell: EnsembleGRUCell, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """``cell(x, h)``: :func:`~rcvae_torchrl.models.ensemble_gru.gru_update` with the reset and
    update gates computed by one add and one sigmoid."""
    gates_x, gates_h = linear(cell.input_proj, x), linear(cell.hidden_proj, h)
    size = h.shape[-1]
    reset_update = torch.sigmoid(gates_x[..., : 2 * size] + gates_h[..., : 2 * size])
    new = torch.tanh(gates_x[..., 2 * size :] + reset_update[..., :size] * gates_h[..., 2 * size :])
    return torch.lerp(new, h, reset_update[..., size:])

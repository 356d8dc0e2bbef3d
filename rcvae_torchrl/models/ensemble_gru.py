"""A GRU cell for E stacked members, written from :class:`EnsembleLinear` ops.

``nn.GRUCell`` has no ``torch.vmap`` batching rule; this cell is batched by construction.
"""

from __future__ import annotations

import torch
from torch import nn

from rcvae_torchrl.models.ensemble_layers import EnsembleLinear, ensemble_linear

__all__ = ["EnsembleGRUCell", "gru_scan", "gru_step", "gru_update"]


def gru_update(gates_x: torch.Tensor, gates_h: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """The GRU update from precomputed input and hidden projections (Cho et al. 2014).

    Same equations and gate order (reset, update, new) as ``torch.nn.GRUCell``::

        r = σ(x_r + h_r),  u = σ(x_u + h_u),  n = tanh(x_n + r ⊙ h_n),  h' = (1 − u) ⊙ n + u ⊙ h

    Args:
        gates_x: input projection ``W_x x + b_x``, ``[..., 3H]``.
        gates_h: hidden projection ``W_h h + b_h``, ``[..., 3H]``.
        h: previous hidden state ``[..., H]``.

    Returns:
        the new hidden state ``[..., H]``.
    """
    x_r, x_u, x_n = gates_x.chunk(3, dim=-1)
    h_r, h_u, h_n = gates_h.chunk(3, dim=-1)
    reset = torch.sigmoid(x_r + h_r)
    update = torch.sigmoid(x_u + h_u)
    new = torch.tanh(x_n + reset * h_n)
    return torch.lerp(new, h, update)


class EnsembleGRUCell(nn.Module):
    """E independent GRU cells evaluated together.

    Initialised per member like ``nn.GRUCell`` (U(−1/√H, 1/√H) for every weight and bias).

    Args:
        ensemble_size: number of members E.
        input_size: input size I.
        hidden_size: hidden size H.

    Shapes:
        ``x [E, B, I]``, ``h [E, B, H]`` → ``[E, B, H]``.
    """

    def __init__(self, ensemble_size: int, input_size: int, hidden_size: int) -> None:
        super().__init__()
        self.hidden_size = hidden_size
        self.input_proj = EnsembleLinear(ensemble_size, input_size, 3 * hidden_size)
        self.hidden_proj = EnsembleLinear(ensemble_size, hidden_size, 3 * hidden_size)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Draw all weights and biases from U(−1/√H, 1/√H), as ``nn.GRUCell`` does."""
        bound = self.hidden_size**-0.5
        for param in self.parameters():
            nn.init.uniform_(param, -bound, bound)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        return gru_update(self.input_proj(x), self.hidden_proj(h), h)


def gru_step(cell: EnsembleGRUCell, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """``cell(x, h)`` on the generation hot path: :func:`gru_update`'s numbers with the reset and
    update gates computed by one add and one sigmoid, and no module calls."""
    gates_x, gates_h = ensemble_linear(cell.input_proj, x), ensemble_linear(cell.hidden_proj, h)
    size = h.shape[-1]
    reset_update = torch.sigmoid(gates_x[..., : 2 * size] + gates_h[..., : 2 * size])
    new = torch.tanh(gates_x[..., 2 * size :] + reset_update[..., :size] * gates_h[..., 2 * size :])
    return torch.lerp(new, h, reset_update[..., size:])


def gru_scan(
    cell: EnsembleGRUCell,
    gates_x: torch.Tensor,
    hidden: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """``cell`` stepped over a whole sequence whose input projections are precomputed (the
    training pass's recurrence), with :func:`gru_step`'s numbers.

    Only the recurrent part runs per step: the input gates are split into their reset/update
    and new parts once for all steps, and the reset and update gates take one add and one
    sigmoid, so a step is 10 ops forward and 10 autograd nodes backward (12 and 12 through
    :func:`gru_update` and a module call). What each op costs besides its arithmetic does
    not grow with E, so it is a fixed cost of every training step, whatever the members.

    Args:
        cell: the GRU cell.
        gates_x: ``cell.input_proj(x)`` of every step, ``[E, *B, L, 3H]``.
        hidden: h_0 ``[E, *B, H]``.
        mask: optional bool ``[E or 1, *B, L]`` of valid steps: the hidden state is reset to
            zero after an invalid step (step t > 0 reads ``h_{t-1} * mask[t - 1]``).

    Returns:
        h_1..h_L, ``[E, *B, L, H]``.
    """
    batch, size = hidden.shape[:-1], hidden.shape[-1]
    h = hidden.reshape(batch[0], -1, size)  # [E, N, H]: one baddbmm per step
    gates = gates_x.reshape(*h.shape[:2], *gates_x.shape[-2:])
    reset_update_x, new_x = (g.unbind(dim=-2) for g in gates.split([2 * size, size], dim=-1))
    # the bias unsqueezed per step, as in a module call: its gradient then sums step by step,
    # in the same order as when open-loop steps (module calls) follow
    bias, weight = cell.hidden_proj.bias, cell.hidden_proj.weight
    keep = None
    if mask is not None:
        keep = mask.to(h.dtype).expand(mask.shape[0], *batch[1:], mask.shape[-1])
        keep = keep.reshape(mask.shape[0], -1, mask.shape[-1], 1).unbind(dim=-2)
    states = []
    for t, (ru_x, n_x) in enumerate(zip(reset_update_x, new_x, strict=True)):
        if keep is not None and t > 0:
            h = h * keep[t - 1]
        ru_h, n_h = torch.baddbmm(bias.unsqueeze(1), h, weight).split([2 * size, size], dim=-1)
        reset, update = torch.sigmoid(ru_x + ru_h).chunk(2, dim=-1)
        h = torch.lerp(torch.tanh(n_x + reset * n_h), h, update)
        states.append(h)
    return torch.stack(states, dim=-2).view(*batch, len(states), size)

"""A GRU cell for E stacked members, written from :class:`EnsembleLinear` ops.

``nn.GRUCell`` has no ``torch.vmap`` batching rule; this cell is batched by construction.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.autograd.function import once_differentiable

from rcvae_torchrl.models.ensemble_layers import EnsembleLinear, ensemble_linear

__all__ = ["EnsembleGRUCell", "gru_scan", "gru_scan_stepwise", "gru_step", "gru_update"]

_tanh_backward = torch.ops.aten.tanh_backward.grad_input  # grad * (1 - y^2), y = tanh(x)
_sigmoid_backward = torch.ops.aten.sigmoid_backward.grad_input  # grad * y (1 - y), y = sigmoid(x)


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
    sigmoid (10 ops a step). When a gradient is needed (and not under ``torch.compile``, which
    traces :func:`gru_scan_stepwise`), the scan is one autograd node whose backward pass is
    written out: per step the gate gradients from the gates the forward pass kept, each written
    straight into the input gates' and the hidden projection's gradients (10 ops, no
    concatenation, and one ``baddbmm`` for the carried gradient, no autograd node), the reset
    and update gates' copied over for all steps at once, and the hidden weights'
    gradient as one ``bmm`` over all steps, in place of about 20 autograd nodes a step. What
    each op costs besides its arithmetic does not grow with E, so the op count is a fixed cost
    of every training step, whatever the members. The outputs are :func:`gru_scan_stepwise`'s
    bits; the gradients are its values up to float rounding (another summation order).

    Args:
        cell: the GRU cell.
        gates_x: ``cell.input_proj(x)`` of every step, ``[E, *B, L, 3H]``.
        hidden: h_0 ``[E, *B, H]``.
        mask: optional bool ``[E or 1, *B, L]`` of valid steps: the hidden state is reset to
            zero after an invalid step (step t > 0 reads ``h_{t-1} * mask[t - 1]``).

    Returns:
        h_1..h_L, ``[E, *B, L, H]``.
    """
    needs_grad = torch.is_grad_enabled() and any(
        t.requires_grad for t in (gates_x, hidden, *cell.hidden_proj.parameters())
    )
    if not needs_grad or torch.compiler.is_compiling():
        return gru_scan_stepwise(cell, gates_x, hidden, mask)
    batch, size = hidden.shape[:-1], hidden.shape[-1]
    h = hidden.reshape(batch[0], -1, size)  # [E, N, H]: one baddbmm per step
    gates = gates_x.reshape(*h.shape[:2], *gates_x.shape[-2:])
    weight, bias = cell.hidden_proj.weight, cell.hidden_proj.bias
    out = _GRUScan.apply(gates, h, weight, bias, _keep(mask, batch, h.dtype))
    return out.reshape(*batch, out.shape[-2], size)


def gru_scan_stepwise(
    cell: EnsembleGRUCell,
    gates_x: torch.Tensor,
    hidden: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`gru_scan` as plain autograd ops, one step after the other: the reference its
    written-out backward pass is tested against, what ``torch.compile`` traces, and the pass
    when no gradient is needed."""
    batch, size = hidden.shape[:-1], hidden.shape[-1]
    h = hidden.reshape(batch[0], -1, size)  # [E, N, H]: one baddbmm per step
    gates = gates_x.reshape(*h.shape[:2], *gates_x.shape[-2:])
    reset_update_x, new_x = (g.unbind(dim=-2) for g in gates.split([2 * size, size], dim=-1))
    bias, weight = cell.hidden_proj.bias, cell.hidden_proj.weight
    keep = _keep(mask, batch, h.dtype)
    states = []
    for t, (ru_x, n_x) in enumerate(zip(reset_update_x, new_x, strict=True)):
        if keep is not None and t > 0:
            h = h * keep[t - 1]
        ru_h, n_h = torch.baddbmm(bias.unsqueeze(1), h, weight).split([2 * size, size], dim=-1)
        reset, update = torch.sigmoid(ru_x + ru_h).chunk(2, dim=-1)
        h = torch.lerp(torch.tanh(n_x + reset * n_h), h, update)
        states.append(h)
    return torch.stack(states, dim=-2).view(*batch, len(states), size)


def _keep(
    mask: torch.Tensor | None, batch: torch.Size, dtype: torch.dtype
) -> tuple[torch.Tensor, ...] | None:
    """The mask as one ``[E or 1, N, 1]`` multiplier per step (``N`` = the flattened batch)."""
    if mask is None:
        return None
    keep = mask.to(dtype).expand(mask.shape[0], *batch[1:], mask.shape[-1])
    return keep.reshape(mask.shape[0], -1, mask.shape[-1], 1).unbind(dim=-2)


class _GRUScan(torch.autograd.Function):
    """The scan of :func:`gru_scan` as one autograd node: ``gates [E, N, L, 3H]``, ``h_0
    [E, N, H]``, the hidden projection's ``weight [E, H, 3H]`` and ``bias [E, 3H]``, the per-step
    mask multipliers or ``None`` → h_1..h_L as a ``[E, N, L, H]`` view.

    The forward pass computes :func:`gru_scan_stepwise`'s ops (the same bits) and keeps each
    step's input state, gates and hidden projection of the new gate; the backward pass runs the
    steps in reverse with ``r, u, n`` the reset, update and new gates and ``h`` the step's input
    state (``h' = n + u (h - n)``, ``n = tanh(x_n + r h_n)``)::

        dn_pre = (1 - n^2) (1 - u) dh'        du_pre = u (1 - u) (h - n) dh'
        dr_pre = r (1 - r) h_n dn_pre         dh = u dh' + [dr_pre, du_pre, r dn_pre] W^T

    (the input gates' gradient is ``[dr_pre, du_pre, dn_pre]``), then ``dW = Σ_t h_t^T
    [dr_pre, du_pre, r dn_pre]_t`` in one ``bmm`` and ``db`` as its row sum.
    """

    @staticmethod
    def forward(ctx, gates, h, weight, bias, keep):
        size, steps = h.shape[-1], gates.shape[-2]
        reset_update_x, new_x = (g.unbind(dim=-2) for g in gates.split([2 * size, size], dim=-1))
        # h_0..h_L step-major per member, so that each step's state is one block per member
        # and the states read by the steps are one [E, L N, H] matrix for the weights' gradient
        seq = h.new_empty(h.shape[0], steps + 1, *h.shape[1:])
        seq[:, 0] = h
        states = seq.unbind(dim=1)
        read = seq[:, :steps] if keep is None else h.new_empty(h.shape[0], steps, *h.shape[1:])
        reads, gate_outputs, news, hidden_news = read.unbind(dim=1), [], [], []
        bias = bias.unsqueeze(1)
        for t, (ru_x, n_x) in enumerate(zip(reset_update_x, new_x, strict=True)):
            h = states[t]
            if keep is not None:  # the masked state, kept where the weights' gradient reads it
                h = torch.mul(h, keep[t - 1], out=reads[t]) if t > 0 else reads[t].copy_(h)
            ru_h, n_h = torch.baddbmm(bias, h, weight).split([2 * size, size], dim=-1)
            reset_update = torch.sigmoid(ru_x + ru_h)
            reset, update = reset_update.chunk(2, dim=-1)
            new = torch.tanh(n_x + reset * n_h)
            torch.lerp(new, h, update, out=states[t + 1])
            gate_outputs.append(reset_update)
            news.append(new)
            hidden_news.append(n_h)
        ctx.steps = (read, gate_outputs, news, hidden_news, keep)
        ctx.save_for_backward(weight)
        return seq[:, 1:].transpose(1, 2)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        (weight,) = ctx.saved_tensors
        read, gate_outputs, news, hidden_news, keep = ctx.steps
        members, steps, rows, size = read.shape
        reads, grads = read.unbind(dim=1), grad.unbind(dim=-2)
        weight_t = weight.transpose(1, 2)
        grad_gates = grad.new_empty(members, rows, steps, 3 * size)
        grad_hidden = grad.new_empty(members, steps, rows, 3 * size)  # step-major, as `read`
        # each gate's gradient is written where it goes (no concatenation a step): the reset and
        # update gates' into the hidden projection's gradient (copied to the input gates' after
        # the loop), the new gate's into the input gates' and, times r, into the hidden's
        d_resets, d_updates, d_news_h = grad_hidden.split(size, dim=-1)
        d_resets, d_updates, d_news_h = (g.unbind(dim=1) for g in (d_resets, d_updates, d_news_h))
        d_news, hidden_at = grad_gates[..., 2 * size :].unbind(dim=2), grad_hidden.unbind(dim=1)
        dh = None
        for t in range(steps - 1, -1, -1):
            dh = grads[t] if dh is None else grads[t] + dh
            reset, update = gate_outputs[t].chunk(2, dim=-1)
            through = dh * update
            d_new = _tanh_backward(dh - through, news[t], grad_input=d_news[t])
            _sigmoid_backward(d_new * hidden_news[t], reset, grad_input=d_resets[t])
            _sigmoid_backward(dh * (reads[t] - news[t]), update, grad_input=d_updates[t])
            torch.mul(d_new, reset, out=d_news_h[t])
            dh = torch.baddbmm(through, hidden_at[t], weight_t)
            if keep is not None and t > 0:
                dh = dh * keep[t - 1]
        grad_gates[..., : 2 * size].copy_(grad_hidden[..., : 2 * size].transpose(1, 2))
        flat = grad_hidden.view(members, -1, 3 * size)
        grad_weight = torch.bmm(read.reshape(members, -1, size).transpose(1, 2), flat)
        return grad_gates, dh, grad_weight, flat.sum(dim=1), None

"""EnsembleLinear, EnsembleGRUCell and MemberLayout against per-member references."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from rcvae_torchrl.models import (
    EnsembleGRUCell,
    EnsembleLinear,
    EnsembleMLP,
    gru_scan,
    gru_scan_stepwise,
    gru_update,
)
from rcvae_torchrl.rollout import MemberLayout


def test_ensemble_linear_matches_per_member_affine_maps():
    torch.manual_seed(0)
    layer = EnsembleLinear(3, 4, 5)
    x = torch.randn(3, 2, 7, 4)
    y = layer(x)
    assert y.shape == (3, 2, 7, 5)
    for e in range(3):
        torch.testing.assert_close(y[e], x[e] @ layer.weight[e] + layer.bias[e])


def test_ensemble_linear_init_is_independent_and_bounded():
    torch.manual_seed(0)
    layer = EnsembleLinear(4, 16, 8)
    assert layer.weight.abs().max() <= 16**-0.5
    assert layer.bias.abs().max() <= 16**-0.5
    flat = layer.weight.flatten(1)
    for i in range(4):
        for j in range(i + 1, 4):
            assert not torch.equal(flat[i], flat[j])


def test_ensemble_mlp_depth_and_shapes():
    mlp = EnsembleMLP(2, 3, 8, 4, depth=2)
    assert sum(isinstance(m, EnsembleLinear) for m in mlp) == 3
    assert mlp(torch.randn(2, 5, 3)).shape == (2, 5, 4)


def test_forward_split_matches_forward_on_the_concatenation():
    torch.manual_seed(0)
    mlp = EnsembleMLP(3, 4 + 2 + 1, 8, 5, depth=2)
    parts = [torch.randn(3, 2, 6, n, requires_grad=True) for n in (4, 2, 1)]
    split = mlp.forward_split(parts)
    whole = mlp(torch.cat(parts, dim=-1))
    torch.testing.assert_close(split, whole)
    weights = torch.randn_like(whole)
    grads_split = torch.autograd.grad((split * weights).sum(), [*parts, *mlp.parameters()])
    grads_whole = torch.autograd.grad((whole * weights).sum(), [*parts, *mlp.parameters()])
    for got, want in zip(grads_split, grads_whole, strict=True):
        torch.testing.assert_close(got, want)
    with pytest.raises(ValueError, match="do not sum"):
        mlp.forward_split(parts[:2])


def test_gru_cell_matches_torch_gru_cell():
    torch.manual_seed(0)
    cell = EnsembleGRUCell(2, 3, 6)
    for e in range(2):
        ref = nn.GRUCell(3, 6)
        with torch.no_grad():
            ref.weight_ih.copy_(cell.input_proj.weight[e].T)
            ref.weight_hh.copy_(cell.hidden_proj.weight[e].T)
            ref.bias_ih.copy_(cell.input_proj.bias[e])
            ref.bias_hh.copy_(cell.hidden_proj.bias[e])
        x, h = torch.randn(2, 9, 3), torch.randn(2, 9, 6)
        torch.testing.assert_close(cell(x, h)[e], ref(x[e], h[e]))


@pytest.mark.parametrize(
    "member",
    [
        torch.tensor([0, 1, 2, 0, 1, 2]),  # round robin, no padding
        torch.tensor([2, 2, 0, 2, 0]),  # uneven, member 1 empty
        torch.tensor([1]),
    ],
)
def test_member_layout_round_trip(member):
    layout = MemberLayout(member, ensemble_size=3)
    x = torch.randn(member.shape[0], 2, 4)
    packed = layout.pack(x)
    assert packed.shape == (3, layout.capacity, 2, 4)
    assert torch.equal(layout.unpack(packed), x)
    for i, m in enumerate(member.tolist()):  # particle i sits in its member's row
        assert any(torch.equal(packed[m, c], x[i]) for c in range(layout.capacity))


def test_member_layout_round_robin_has_no_padding():
    layout = MemberLayout(torch.arange(20) % 5, ensemble_size=5)
    assert layout.capacity == 4


def test_member_layout_rejects_non_flat_member():
    with pytest.raises(ValueError, match="member must be 1-D"):
        MemberLayout(torch.zeros(2, 2, dtype=torch.long), 3)


def _stepped(cell, gates_x, h0, mask):
    h, stepped = h0, []
    for t in range(gates_x.shape[-2]):
        if t > 0:
            h = h * mask[..., t - 1, None].to(h.dtype)
        h = gru_update(gates_x[..., t, :], cell.hidden_proj(h), h)
        stepped.append(h)
    return torch.stack(stepped, dim=-2)


def test_gru_scan_stepwise_matches_stepping_the_cell_bit_for_bit():
    # E * B * H a multiple of 32, so that no gate falls in the scalar tail of torch's vectorised
    # loops (32 floats at a time): its scalar sigmoid differs from the vectorised one in the
    # last bit
    torch.manual_seed(0)
    cell = EnsembleGRUCell(3, 4, 16)
    x = torch.randn(3, 2, 5, 7, 4, requires_grad=True)  # [E, *B, L, I] with two batch dims
    h0 = torch.randn(3, 2, 5, 16, requires_grad=True)
    mask = torch.rand(1, 2, 5, 7) > 0.3
    gates_x = cell.input_proj(x)
    scanned = gru_scan_stepwise(cell, gates_x, h0, mask)
    stepped = _stepped(cell, gates_x, h0, mask)
    assert scanned.shape == (3, 2, 5, 7, 16) and torch.equal(scanned, stepped)
    weights = torch.randn_like(scanned)
    inputs = [x, h0, *cell.parameters()]
    got = torch.autograd.grad((scanned * weights).sum(), inputs, retain_graph=True)
    want = torch.autograd.grad((stepped * weights).sum(), inputs)
    for a, b in zip(got, want, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gru_scan_backward_matches_autograd_through_the_steps(masked, dtype):
    """The written-out backward pass: the stepwise scan's outputs bit for bit, its gradients
    (every input, both parameters of both projections) to float rounding."""
    torch.manual_seed(1)
    cell = EnsembleGRUCell(3, 4, 16).to(dtype)
    x = torch.randn(3, 2, 5, 7, 4, dtype=dtype, requires_grad=True)
    h0 = torch.randn(3, 2, 5, 16, dtype=dtype, requires_grad=True)
    mask = torch.rand(3, 2, 5, 7) > 0.3 if masked else None
    gates_x = cell.input_proj(x)
    fused = gru_scan(cell, gates_x, h0, mask)
    reference = gru_scan_stepwise(cell, gates_x, h0, mask)
    assert fused.grad_fn is not None and type(fused.grad_fn) is not type(reference.grad_fn)
    assert torch.equal(fused, reference)
    weights = torch.randn_like(fused)
    inputs = [x, h0, *cell.parameters()]
    got = torch.autograd.grad((fused * weights).sum(), inputs, retain_graph=True)
    want = torch.autograd.grad((reference * weights).sum(), inputs)
    tol = {"rtol": 1e-5, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-12}
    for a, b in zip(got, want, strict=True):
        assert a.shape == b.shape
        torch.testing.assert_close(a, b, **tol)


def test_gru_scan_gradients_pass_gradcheck():
    """Finite differences, in float64, through the gates, h_0 and the hidden projection (a
    masked batch: the reset after an invalid step included)."""
    torch.manual_seed(2)
    cell = EnsembleGRUCell(2, 3, 4).double()
    gates = torch.randn(2, 3, 5, 12, dtype=torch.float64, requires_grad=True)
    h0 = torch.randn(2, 3, 4, dtype=torch.float64, requires_grad=True)
    mask = torch.tensor([True, False, True, True, False]).expand(1, 3, 5)
    names = ("hidden_proj.weight", "hidden_proj.bias")

    def scan(gates, h0, weight, bias):  # the cell's hidden projection swapped for the inputs
        swapped = dict(zip(names, (weight, bias), strict=True))
        return torch.func.functional_call(cell, swapped, (gates, h0, mask), strict=False)

    cell.forward = lambda gates, h0, mask: gru_scan(cell, gates, h0, mask)
    params = [cell.get_parameter(n).detach().clone().requires_grad_() for n in names]
    assert torch.autograd.gradcheck(scan, (gates, h0, *params))


def test_gru_scan_without_gradient_is_the_stepwise_pass():
    torch.manual_seed(3)
    cell = EnsembleGRUCell(2, 3, 8)
    gates, h0 = torch.randn(2, 4, 6, 24), torch.zeros(2, 4, 8)
    with torch.no_grad():
        out = gru_scan(cell, gates, h0)
    assert out.grad_fn is None
    assert torch.equal(out, gru_scan_stepwise(cell, gates, h0))

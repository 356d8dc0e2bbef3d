"""The CEM math: prior from bounds, clamped sampling, elite selection, momentum update, shift."""

from __future__ import annotations

import pytest
import torch

from rcvae_torchrl.planners import (
    action_prior,
    cem_update,
    elite_mask,
    sample_candidates,
    shift_plan,
)

NAN, INF = float("nan"), float("inf")


def test_action_prior_bounded_and_unbounded():
    low = torch.tensor([-1.0, 0.0, torch.finfo(torch.float32).min])
    high = torch.tensor([1.0, 2.0, torch.finfo(torch.float32).max])
    mean, std = action_prior(low, high)
    torch.testing.assert_close(mean, torch.tensor([0.0, 1.0, 0.0]))
    torch.testing.assert_close(std, torch.tensor([0.5, 0.5, 1.0]))
    _, std = action_prior(low, high, init_std=0.3)
    torch.testing.assert_close(std, torch.full((3,), 0.3))


def test_sample_candidates_shape_and_bounds():
    low, high = torch.tensor([-0.5, -2.0, 0.0]), torch.tensor([1.5, 1.0, 1.0])
    mean, std = torch.zeros(4, 6, 3), torch.full((4, 6, 3), 10.0)
    g = torch.Generator().manual_seed(0)
    cands = sample_candidates(mean, std, 50, low, high, g)
    assert cands.shape == (4, 50, 6, 3)
    assert bool((cands >= low).all() and (cands <= high).all())
    assert bool((cands == low).any() and (cands == high).any())  # clamped, not resampled
    again = sample_candidates(mean, std, 50, low, high, torch.Generator().manual_seed(0))
    assert torch.equal(cands, again)


def test_elite_mask_ranks_nonfinite_last():
    scores = torch.tensor([[NAN, 1.0, INF, -INF, 0.5, 2.0]])
    assert elite_mask(scores, 2).tolist() == [[False, True, False, False, False, True]]
    # asking for more elites than finite scores returns only the finite ones
    assert elite_mask(torch.tensor([NAN, 3.0, -INF]), 2).tolist() == [False, True, False]


def test_cem_update_hand_computed():
    mean, std = torch.zeros(1), torch.ones(1)
    cands = torch.tensor([[0.0], [1.0], [3.0], [9.0]])
    scores = torch.tensor([0.0, 1.0, NAN, INF])
    new_mean, new_std = cem_update(mean, std, cands, scores, top_k=2, momentum=0.5)
    # elites {0, 1}: mean 0.5, population std 0.5
    torch.testing.assert_close(new_mean, torch.tensor([0.25]))
    torch.testing.assert_close(new_std, torch.tensor([0.75]))
    no_momentum = cem_update(mean, std, cands, scores, top_k=1, momentum=0.0)
    torch.testing.assert_close(no_momentum, (torch.tensor([1.0]), torch.tensor([0.0])))


def test_cem_update_batched_and_all_nonfinite_keeps_plan():
    mean, std = torch.tensor([[1.0], [2.0]]), torch.tensor([[0.3], [0.4]])
    cands = torch.tensor([[[5.0], [6.0]], [[7.0], [8.0]]])
    scores = torch.tensor([[NAN, NAN], [1.0, 0.0]])
    new_mean, new_std = cem_update(mean, std, cands, scores, top_k=1, momentum=0.0)
    torch.testing.assert_close(new_mean, torch.tensor([[1.0], [7.0]]))
    torch.testing.assert_close(new_std, torch.tensor([[0.3], [0.0]]))


def test_cem_update_shape_errors():
    mean, std = torch.zeros(3, 2), torch.ones(3, 2)
    with pytest.raises(ValueError, match=r"candidates: expected shape \[\*B, C, \*D\]"):
        cem_update(mean, std, torch.zeros(5, 3, 3), torch.zeros(5), 2, 0.1)
    with pytest.raises(ValueError, match="std: expected shape"):
        cem_update(mean, torch.ones(3), torch.zeros(5, 3, 2), torch.zeros(5), 2, 0.1)
    with pytest.raises(ValueError, match="top_k: expected at most num_candidates = 5"):
        cem_update(mean, std, torch.zeros(5, 3, 2), torch.zeros(5), 6, 0.1)


def test_shift_plan():
    plan = torch.arange(12.0).reshape(2, 3, 2)  # [B=2, H=3, A=2]
    out = shift_plan(plan, torch.tensor([-1.0, -2.0]), time_dim=1)
    torch.testing.assert_close(out[:, :2], plan[:, 1:])
    torch.testing.assert_close(out[:, 2], torch.tensor([[-1.0, -2.0], [-1.0, -2.0]]))

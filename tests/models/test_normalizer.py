"""StateNormalizer: fitted statistics, masks, constant dims, state_dict."""

from __future__ import annotations

import math

import pytest
import torch

from rcvae_torchrl.models import StateNormalizer


def test_fit_statistics_and_inverse():
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(6, 30, 3, generator=g) * torch.tensor([1.0, 2.0, 0.5]) + 3.0
    act = torch.rand(6, 30, 2, generator=g)
    norm = StateNormalizer(3, 2)
    assert not norm.fitted
    norm.fit(obs, act)
    assert norm.fitted
    torch.testing.assert_close(norm.state_mean, obs.reshape(-1, 3).mean(0))
    torch.testing.assert_close(norm.state_std, obs.reshape(-1, 3).std(0, correction=0))
    delta = obs[:, 1:] - obs[:, :-1]
    torch.testing.assert_close(norm.delta_mean, delta.reshape(-1, 3).mean(0))
    torch.testing.assert_close(norm.action_mean, act.reshape(-1, 2).mean(0))
    dims = torch.tensor([0, 2])
    d = torch.randn(4, 2)
    torch.testing.assert_close(norm.denormalize_delta(norm.normalize_delta(d, dims), dims), d)


def test_constant_dims_get_unit_std():
    obs = torch.randn(4, 10, 2)
    obs[..., 1] = 7.0  # constant within and across episodes (a passthrough-like dim)
    norm = StateNormalizer(2, 1)
    norm.fit(obs)
    assert norm.state_std[1] == 1.0 and norm.delta_std[1] == 1.0
    assert norm.state_mean[1] == 7.0
    assert torch.isfinite(norm.normalize_state(obs)).all()


def test_mask_excludes_padded_steps():
    obs = torch.zeros(1, 4, 1)
    obs[0, :3, 0] = torch.tensor([0.0, 1.0, 2.0])
    obs[0, 3, 0] = 1000.0  # padding
    mask = torch.tensor([[True, True, True, False]])
    norm = StateNormalizer(1, 1)
    norm.fit(obs, mask=mask)
    assert norm.state_mean.item() == pytest.approx(1.0)
    assert norm.delta_mean.item() == pytest.approx(1.0)
    assert norm.delta_std.item() == 1.0  # zero spread → unit std


def test_state_dict_round_trip():
    norm = StateNormalizer(3, 2)
    norm.fit(torch.randn(2, 5, 3), torch.randn(2, 5, 2))
    other = StateNormalizer(3, 2)
    other.load_state_dict(norm.state_dict())
    assert other.fitted
    for name, buf in norm.named_buffers():
        assert torch.equal(buf, getattr(other, name))


def test_fit_from_flat_transitions_ignores_episode_jumps():
    """Two episodes concatenated as flat frames: with next observations, the jump between
    them is not a state change."""
    episode = torch.arange(5.0)[:, None]  # s_t = t, state change 1 every step
    frames = torch.cat([episode, episode + 100.0])  # [10, 1]
    next_frames = frames + 1.0
    norm = StateNormalizer(1, 1)
    norm.fit(frames, next_observations=next_frames)
    assert norm.delta_mean.item() == 1.0 and norm.delta_std.item() == 1.0  # zero spread
    norm.fit(frames)  # as one trajectory: the jump of 96 counts
    assert norm.delta_mean.item() > 1.0


def test_fit_errors():
    with pytest.raises(ValueError, match=r"T >= 2"):
        StateNormalizer(3, 1).fit(torch.randn(4, 1, 3))
    with pytest.raises(ValueError, match=r"next_observations: expected shape \[\.\.\., 3\]"):
        StateNormalizer(3, 1).fit(torch.randn(4, 3), next_observations=torch.randn(4, 2))
    with pytest.raises(ValueError, match=r"next_observations: expected shape \(4, 3\)"):
        StateNormalizer(3, 1).fit(torch.randn(4, 3), next_observations=torch.randn(5, 3))
    with pytest.raises(ValueError, match=r"actions: expected shape \[\.\.\., 1\], got \(4, 5, 2\)"):
        StateNormalizer(3, 1).fit(torch.randn(4, 5, 3), torch.randn(4, 5, 2))
    with pytest.raises(TypeError, match="observations: expected a floating-point tensor"):
        StateNormalizer(3, 1).fit(torch.ones(4, 5, 3, dtype=torch.int64))


@pytest.mark.parametrize("name", ["observations", "actions", "next_observations"])
def test_fit_refuses_non_finite_and_keeps_the_statistics(name):
    """A NaN would make every statistic NaN with ``fitted`` True: refused, nothing changed."""
    norm = StateNormalizer(3, 1)
    data = {
        "observations": torch.randn(6, 3),
        "actions": torch.randn(6, 1),
        "next_observations": torch.randn(6, 3),
    }
    data[name][2, 0] = math.nan
    with pytest.raises(ValueError, match=f"{name}: expected finite values, got 1 NaN"):
        norm.fit(**data)
    assert not norm.fitted and norm.state_mean.eq(0).all() and norm.delta_std.eq(1).all()


def test_fit_ignores_non_finite_steps_the_mask_leaves_out():
    obs = torch.randn(2, 5, 3)
    obs[1, 4] = math.nan  # padding after a shorter episode
    mask = torch.ones(2, 5, dtype=torch.bool)
    mask[1, 4] = False
    norm = StateNormalizer(3, 1)
    norm.fit(obs, mask=mask)
    assert torch.allclose(norm.state_mean, obs[mask].mean(0))

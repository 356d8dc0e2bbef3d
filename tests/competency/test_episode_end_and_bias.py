"""Ended episodes as an absorbing terminal bin, and the shuffle correction of the epistemic bias."""

import math

import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.competency import SuccessBoundary, UncertaintyMetric, decompose_uncertainty


def _h2(p: float) -> float:
    return 0.0 if p in (0.0, 1.0) else -(p * math.log2(p) + (1 - p) * math.log2(1 - p))


def test_ended_samples_share_one_terminal_bin():
    # Live samples all in one bin: the only uncertainty is whether the episode has ended.
    samples = torch.zeros(2, 40, 3, 2)
    ended = torch.zeros(2, 40, 3, dtype=torch.bool)
    ended[:, :10, 0] = True  # a quarter ended, same in both members
    ended[:, :, 1] = True  # all ended: nothing left to be uncertain about
    ended[0, :, 2] = True  # members disagree completely on whether the episode is over
    u = decompose_uncertainty(samples, "histogram", bin_width=0.1, ended=ended)
    assert torch.allclose(u.total[0], torch.full((2,), _h2(0.25)), atol=1e-6)
    assert torch.allclose(u.epistemic[0], torch.zeros(2), atol=1e-6)
    assert u.total[1].abs().max().item() < 1e-9
    assert torch.allclose(u.epistemic[2], torch.ones(2), atol=1e-6)  # JS of δ0, δ1 = 1 bit
    assert u.aleatoric[2].abs().max().item() < 1e-9


def test_ended_mixture_entropy_is_h2_plus_live_share_of_live_entropy():
    # H[ended ∪ states] = H2(q) + (1 - q)·H[live states] for a terminal bin of mass q.
    live = torch.arange(32, dtype=torch.float32).repeat(3)  # 32 equally likely bins
    samples = torch.cat([live, torch.zeros(32)]).view(1, 128, 1).expand(2, 128, 1).unsqueeze(2)
    ended = torch.zeros(2, 128, 1, dtype=torch.bool)
    ended[:, 96:] = True  # q = 1/4
    u = decompose_uncertainty(samples, "histogram", bin_width=1.0, ended=ended)
    assert u.total.item() == pytest.approx(_h2(0.25) + 0.75 * 5.0, abs=1e-6)


def test_ended_values_are_ignored():
    samples = torch.randn(3, 50, 4, 2)
    ended = torch.rand(3, 50, 4) < 0.3
    other = torch.where(ended.unsqueeze(-1), torch.full_like(samples, 1e6), samples)
    a = decompose_uncertainty(samples, "histogram", bin_width=0.2, ended=ended)
    b = decompose_uncertainty(other, "histogram", bin_width=0.2, ended=ended)
    assert torch.equal(a.total, b.total) and torch.equal(a.epistemic, b.epistemic)


def test_shuffle_correction_removes_the_bias_of_undersampled_identical_members():
    generator = torch.Generator().manual_seed(0)
    samples = 10.0 * torch.randn(5, 50, 64, 1)  # ~400 bins for 50 samples per member
    plug_in = decompose_uncertainty(samples, "histogram", bin_width=0.1)
    corrected = decompose_uncertainty(
        samples, "histogram", bin_width=0.1, bias_correction="shuffle", generator=generator
    )
    assert plug_in.epistemic.mean().item() > 1.5  # close to log2 5 without any disagreement
    assert corrected.epistemic.mean().item() < 0.05
    assert torch.equal(corrected.total, plug_in.total)
    assert torch.allclose(corrected.aleatoric + corrected.epistemic, corrected.total)


def test_shuffle_correction_vanishes_for_well_sampled_members():
    generator = torch.Generator().manual_seed(1)
    shift = 0.5 * torch.arange(4, dtype=torch.float32).view(4, 1, 1, 1)
    samples = torch.randn(4, 4000, 8, 1) + shift
    plug_in = decompose_uncertainty(samples, "histogram", bin_width=0.5)
    corrected = decompose_uncertainty(
        samples, "histogram", bin_width=0.5, bias_correction="shuffle", generator=generator
    )
    assert plug_in.epistemic.mean().item() > 0.15
    assert torch.allclose(corrected.epistemic, plug_in.epistemic, atol=0.01)


def test_shuffle_correction_is_reproducible_under_a_generator():
    samples = torch.randn(3, 30, 5, 2)

    def run(seed: int) -> torch.Tensor:
        g = torch.Generator().manual_seed(seed)
        return decompose_uncertainty(
            samples, "histogram", bin_width=0.3, bias_correction="shuffle", generator=g
        ).epistemic

    assert torch.equal(run(3), run(3))


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"bias_correction": "jackknife"}, ValueError, "bias_correction"),
        ({"bias_correction": "shuffle", "shuffles": 0}, ValueError, "shuffles"),
        ({"ended": torch.zeros(3, 30, 5)}, TypeError, "ended: expected a bool tensor"),
        ({"ended": torch.zeros(3, 30, dtype=torch.bool)}, ValueError, r"ended: expected shape"),
    ],
)
def test_bad_histogram_options_are_named(kwargs, error, match):
    with pytest.raises(error, match=match):
        decompose_uncertainty(torch.randn(3, 30, 5, 2), "histogram", bin_width=0.3, **kwargs)


def test_ended_needs_the_histogram_estimator():
    ended = torch.zeros(3, 30, 5, dtype=torch.bool)
    with pytest.raises(ValueError, match="ended: only the histogram"):
        decompose_uncertainty(torch.randn(3, 30, 5, 2), "gaussian", ended=ended)
    with pytest.raises(ValueError, match="episode_end: only the histogram"):
        UncertaintyMetric(estimator="gaussian", episode_end=True)


def test_boundary_marks_steps_after_success_failure_and_time_limit():
    x = torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.0, 0.0, 0.0]])
    obs = x.unsqueeze(-1)  # [2, T=6, D=1]
    boundary = SuccessBoundary(lambda o: o[..., 0] > 0.5, failure=lambda o: o[..., 0] < -0.5)
    ended = boundary.ended_over_time(obs)
    assert ended.tolist() == [
        [False, False, False, True, True, True],  # success at step 2
        [False, False, True, True, True, True],  # failure at step 1, before the success
    ]
    limited = SuccessBoundary(lambda o: o[..., 0] > 5.0, time_limit=4).ended_over_time(obs)
    assert limited.tolist() == [[False] * 4 + [True] * 2] * 2


def test_metric_reads_the_ended_entry():
    obs = torch.randn(2, 20, 3, 5, 2)
    ended = torch.zeros(2, 20, 3, 5, dtype=torch.bool)
    ended[..., 2:] = True
    td = TensorDict({"observation": obs, "ended": ended}, batch_size=obs.shape[:-1])
    out = UncertaintyMetric(bin_width=0.1, episode_end=True)(td)["uncertainty"]
    assert out["total"][:, 2:].abs().max().item() < 1e-9
    assert out["total"][:, :2].min().item() > 1.0
    with pytest.raises(KeyError, match="'ended' entry"):
        UncertaintyMetric(bin_width=0.1, episode_end=True)(td.exclude("ended"))


def test_bits_per_live_step_do_not_depend_on_how_long_episodes_last():
    # The same spread while an episode runs, for 2 steps in one start and 4 in another: the
    # time means differ by the episodes' lengths, the bits per live step do not.
    obs = torch.randn(2, 40, 1, 6, 2, generator=torch.Generator().manual_seed(0)).expand(
        2, 40, 2, 6, 2
    )
    ended = torch.zeros(2, 40, 2, 6, dtype=torch.bool)
    ended[:, :, 0, 2:] = True
    ended[:, :, 1, 4:] = True
    td = TensorDict({"observation": obs, "ended": ended}, batch_size=obs.shape[:-1])
    out = UncertaintyMetric(bin_width=0.1, episode_end=True)(td)["uncertainty"]
    assert torch.equal(out["live"], (~ended[0, 0]).float())
    for kind in ("total", "aleatoric", "epistemic"):
        by_step = out[kind].sum(-1)  # [B, T] summed over dimensions
        want = by_step.sum(-1) / torch.tensor([2.0, 4.0])  # the time sum over the live steps
        torch.testing.assert_close(out["per_live_step", kind], want)
        torch.testing.assert_close(out["summary", kind], by_step.mean(-1))
    # alike while they run: per live step within 1 %, the time means 2x apart
    live = out["per_live_step", "total"]
    assert abs(live[1] / live[0] - 1) < 0.01
    assert out["summary", "total"][1] > 1.9 * out["summary", "total"][0]
    plain = UncertaintyMetric(bin_width=0.1)(td)["uncertainty"]
    assert "per_live_step" not in plain.keys() and "live" not in plain.keys()

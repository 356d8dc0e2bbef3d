"""P(success), its binary-entropy decomposition, time to success and intervals."""

import math

import pytest
import torch
from scipy import stats

from rcvae_torchrl.competency import (
    binary_entropy,
    binomial_interval,
    first_success_step,
    outcome_uncertainty,
    success_probability,
    time_to_success,
)


def test_success_probability_pooled_and_per_member():
    success = torch.zeros(3, 4, 2, dtype=torch.bool)
    success[0, :, 0] = True
    success[1, :2, 0] = True
    p, p_member = success_probability(success)
    assert p.tolist() == pytest.approx([0.5, 0.0])
    assert p_member[:, 0].tolist() == pytest.approx([1.0, 0.5, 0.0])
    assert p_member.shape == (3, 2)


def test_binary_entropy_values_and_endpoints():
    p = torch.tensor([0.0, 0.25, 0.5, 1.0])
    expected = [0.0, -(0.25 * math.log2(0.25) + 0.75 * math.log2(0.75)), 1.0, 0.0]
    assert binary_entropy(p).tolist() == pytest.approx(expected, abs=1e-6)
    assert not torch.isnan(binary_entropy(p)).any()


def test_outcome_uncertainty_splits_binary_entropy():
    success = torch.zeros(2, 4, 3, dtype=torch.bool)
    success[0, :, 0] = True  # members disagree completely: 1 bit epistemic
    success[:, :2, 1] = True  # both members at p = ½: 1 bit aleatoric
    success[0, :1, 2] = True  # p_m = (¼, 0)
    u = outcome_uncertainty(success)
    assert u.total.tolist() == pytest.approx([1.0, 1.0, binary_entropy(torch.tensor(0.125)).item()])
    assert u.aleatoric.tolist() == pytest.approx(
        [0.0, 1.0, binary_entropy(torch.tensor(0.25)).item() / 2]
    )
    assert torch.allclose(u.total, u.aleatoric + u.epistemic)
    assert (u.epistemic >= 0).all()


def test_first_success_step_with_never():
    s = torch.tensor([[False, False, True, True], [False] * 4, [True] * 4])
    assert first_success_step(s).tolist() == [2, 4, 0]


def test_time_to_success_distribution():
    s = torch.zeros(2, 2, 1, 5, dtype=torch.bool)
    s[0, 0, 0, 1:] = True  # first success at 1
    s[0, 1, 0, 3] = True  # at 3
    s[1, 0, 0, 3:] = True  # at 3; s[1, 1] never
    tts = time_to_success(s)
    assert tts.first_step[..., 0].tolist() == [[1, 3], [3, 5]]
    assert tts.step_probability[0].tolist() == pytest.approx([0, 0.25, 0, 0.5, 0])
    assert tts.success_by_step[0].tolist() == pytest.approx([0, 0.25, 0.25, 0.75, 0.75])
    assert tts.mean_steps.item() == pytest.approx(7 / 3)
    assert tts.median_steps.item() == 3.0
    never = time_to_success(torch.zeros(2, 3, 4, dtype=torch.bool))
    assert math.isinf(never.mean_steps.item()) and math.isinf(never.median_steps.item())
    assert never.success_by_step.sum().item() == 0


def test_success_by_step_ends_at_p_success():
    s = torch.rand(3, 20, 4, 10) < 0.05
    p, _ = success_probability(s.any(dim=-1))
    assert torch.allclose(time_to_success(s).success_by_step[..., -1], p)


def test_jeffreys_interval_matches_beta_quantiles():
    k = torch.tensor([0, 3, 10, 20])
    low, high = binomial_interval(k, 20, confidence=0.9)
    assert low[0].item() == 0.0 and high[-1].item() == 1.0
    assert low[1].item() == pytest.approx(stats.beta.ppf(0.05, 3.5, 17.5), abs=1e-6)
    assert high[2].item() == pytest.approx(stats.beta.ppf(0.95, 10.5, 10.5), abs=1e-6)


def test_wilson_interval_closed_form():
    low, high = binomial_interval(torch.tensor(8), 10, confidence=0.95, method="wilson")
    z = stats.norm.ppf(0.975)
    centre = (0.8 + z * z / 20) / (1 + z * z / 10)
    half = z / (1 + z * z / 10) * math.sqrt(0.8 * 0.2 / 10 + z * z / 400)
    assert (low.item(), high.item()) == pytest.approx((centre - half, centre + half), abs=1e-6)


@pytest.mark.parametrize("n", [10, 30, 100, 101])
def test_the_median_first_success_step_is_the_lower_median_whatever_the_count(n):
    """Trajectory i first succeeds at step i: the lower median of 0..n-1 is (n-1)//2. Float sums
    of probabilities decided the tie at exactly half (100 trajectories gave 50, not 49)."""
    tts = time_to_success(torch.eye(n, dtype=torch.bool)[None])
    assert tts.median_steps.item() == (n - 1) // 2


def test_the_median_first_success_step_matches_the_sorted_steps():
    g = torch.Generator().manual_seed(0)
    for _ in range(300):
        members, samples, horizon = 2, int(torch.randint(1, 9, (1,), generator=g)), 7
        success = torch.rand(members, samples, horizon, generator=g) < 0.2
        first = first_success_step(success).reshape(-1)
        hits = first[first < horizon].sort().values
        tts = time_to_success(success)
        want = float(hits[(hits.numel() - 1) // 2]) if hits.numel() else math.inf
        assert tts.median_steps.item() == want, success

"""SuccessBoundary and the LossModule-style metrics: keys, shapes, set_keys, numbers."""

import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.competency import (
    SuccessBoundary,
    SuccessMetric,
    UncertaintyMetric,
    binomial_interval,
    decompose_uncertainty,
    outcome_uncertainty,
    success_probability,
    time_to_success,
)

E, N, B, T, D = 3, 16, 2, 6, 4


@pytest.fixture
def rollout() -> TensorDict:
    obs = torch.randn(E, N, B, T, D)
    return TensorDict({"observation": obs}, batch_size=[E, N, B, T])


def test_uncertainty_metric_keys_shapes_and_values(rollout):
    metric = UncertaintyMetric(bin_width=0.5, dim_names=["a", "b", "c", "d"])
    out = metric(rollout)
    expected = decompose_uncertainty(rollout["observation"], bin_width=0.5)
    for name in ("total", "aleatoric", "epistemic"):
        per_step = out["uncertainty", name]
        assert per_step.shape == (B, T, D)
        assert torch.equal(per_step, getattr(expected, name))
        assert torch.allclose(out["uncertainty", "time_mean", name], per_step.mean(dim=1))
        summary = out["uncertainty", "summary", name]
        assert summary.shape == (B,)
        assert torch.allclose(summary, per_step.sum(dim=-1).mean(dim=-1))
        assert torch.equal(out["uncertainty", "by_dim", "c", name], per_step[..., 2])


def test_uncertainty_metric_joint_estimator_and_dim_mean(rollout):
    out = UncertaintyMetric(estimator="knn", k=2)(rollout)
    assert out["uncertainty", "total"].shape == (B, T)
    assert out["uncertainty", "time_mean", "total"].shape == (B,)
    mixture = UncertaintyMetric(estimator="mixture", bound="lower")(rollout)["uncertainty"]
    expected = decompose_uncertainty(rollout["observation"], "mixture", bound="lower")
    assert torch.equal(mixture["epistemic"], expected.epistemic)
    assert torch.allclose(mixture["summary", "epistemic"], expected.epistemic.mean(dim=-1))
    mean_metric = UncertaintyMetric(bin_width=0.5, dim_reduction="mean")
    per_step = mean_metric(rollout)["uncertainty", "total"]
    summary = mean_metric(rollout)["uncertainty", "summary", "total"]
    assert torch.allclose(summary, per_step.mean(dim=(-2, -1)))


def test_uncertainty_metric_set_keys(rollout):
    metric = UncertaintyMetric(bin_width=torch.full((D,), 0.5))
    metric.set_keys(observation=("imagined", "obs"), uncertainty=("metrics", "bits"))
    td = TensorDict({("imagined", "obs"): rollout["observation"]}, batch_size=[E, N, B, T])
    out = metric(td)
    assert out["metrics", "bits", "epistemic"].shape == (B, T, D)
    with pytest.raises(ValueError, match="reward: not a key of"):
        metric.set_keys(reward="r")


def test_bins_too_narrow_for_the_samples_are_named(rollout):
    """A width far below the samples' spread gives each member's samples bins of their own:
    the bits are log2 N, a count; the metric names the dimension (only the dimensions where
    that holds at most running steps)."""
    import math
    import warnings

    widths = torch.tensor([1e-9, 0.5, 0.5, 1e-9])
    narrow = UncertaintyMetric(bin_width=widths, dim_names=["a", "b", "c", "d"])
    with pytest.warns(UserWarning) as caught:
        out = narrow(rollout)
    (warning,) = caught
    assert str(warning.message).startswith(
        "bin_width: in a (width 1e-09, at 100% of the steps), d (width 1e-09, at 100% of the "
        "steps), each member's 16 samples fall in bins of their own: the bits there are "
        "log2 16 = 4.00"
    )
    assert torch.allclose(out["uncertainty", "aleatoric"][..., 0], torch.tensor(math.log2(N)))
    # no start state: nothing to look at, no word and no error (empty bits)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        empty = rollout[:, :, :0]
        bits = UncertaintyMetric(bin_width=widths)(empty)["uncertainty", "total"]
        assert bits.shape[0] == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        narrow(rollout)  # said once per metric: an assessor's every call would repeat it
        UncertaintyMetric(bin_width=0.5)(rollout)  # samples share bins: no word
        # only the steps where every sample still runs count: here the first, where the
        # samples start together (ended samples share a bin of their own)
        ended = torch.zeros(E, N, B, T, dtype=torch.bool)
        ended[:, : N // 2, :, 1:] = True
        rollout["observation"][..., 0, :] = 0.0
        metric = UncertaintyMetric(bin_width=widths, episode_end=True)
        metric(rollout.set("ended", ended))
    ended[:, : N // 2, :, 4:] = False  # steps 0, 4 and 5 run with every sample
    with pytest.warns(UserWarning, match=r"in obs\[0\] \(width 1e-09, at 67% of the steps\)"):
        metric(rollout.set("ended", ended))


def test_uncertainty_metric_bin_width_is_a_buffer():
    metric = UncertaintyMetric(bin_width=[0.1, 0.2])
    assert "bin_width" in dict(metric.named_buffers())


def test_boundary_ball_time_limit_and_failure():
    obs = torch.zeros(1, 5, 3)  # [batch, T, D]: position at index 0, target at index 1
    obs[0, :, 1] = 1.0
    obs[0, 3:, 0] = 1.0  # reaches the target at step 3
    boundary = SuccessBoundary.ball(position=[0], target=[1], radius=0.1)
    assert boundary.success_over_time(obs).tolist() == [[False, False, False, True, True]]
    late = SuccessBoundary.ball(position=[0], target=[1], radius=0.1, time_limit=3)
    assert late.outcome(obs)[1].tolist() == [False]
    fixed = SuccessBoundary.ball(
        position=[0], target=torch.tensor([1.0]), radius=0.1, time_limit_s=0.2, dt=0.05
    )
    assert fixed.time_limit == 4 and fixed.outcome(obs)[1].tolist() == [True]
    crash = SuccessBoundary.ball(
        position=[0], target=[1], radius=0.1, failure=lambda o: o[..., 2] > 0.5
    )
    obs_fail = obs.clone()
    obs_fail[0, 2, 2] = 1.0  # fails at step 2, before reaching the target
    _, success, failure = crash.outcome(obs_fail)
    assert success.tolist() == [False] and failure.tolist() == [True]
    obs_late_fail = obs.clone()
    obs_late_fail[0, 4, 2] = 1.0  # fails after succeeding: still a success
    _, success, failure = crash.outcome(obs_late_fail)
    assert success.tolist() == [True] and failure.tolist() == [False]


def test_boundary_survival_lasts_the_time_limit():
    # [4, T=5, D=1]: a failure is |x| > 0.5; the limit is 3 steps (decided at step 2)
    obs = torch.zeros(4, 5, 1)
    obs[1, 1, 0] = 1.0  # fails at step 1
    obs[2, 2, 0] = -1.0  # fails at step 2, the deciding step: a failure
    obs[3, 3, 0] = 1.0  # fails at step 3, after the limit: it lasted
    boundary = SuccessBoundary.survival(lambda o: o[..., 0].abs() > 0.5, time_limit=3)
    assert boundary.is_survival and not SuccessBoundary(lambda o: o[..., 0] > 0).is_survival
    over_time, success, failure = boundary.outcome(obs)
    assert over_time.tolist() == [
        [False, False, True, False, False],
        [False] * 5,
        [False] * 5,
        [False, False, True, False, False],
    ]
    assert success.tolist() == [True, False, False, True]
    assert failure.tolist() == [False, True, True, False]
    # an episode ends after its first failure or at the limit, whichever comes first
    assert boundary.ended_over_time(obs).tolist() == [
        [False, False, False, True, True],
        [False, False, True, True, True],
        [False, False, False, True, True],
        [False, False, False, True, True],
    ]
    # a trajectory shorter than the limit has not lasted it yet: neither outcome
    _, success, failure = boundary.outcome(obs[:2, :2])
    assert success.tolist() == [False, False] and failure.tolist() == [False, True]
    # the same boundary by the constructor, in seconds
    seconds = SuccessBoundary(
        None, failure=lambda o: o[..., 0].abs() > 0.5, time_limit_s=0.3, dt=0.1
    )
    assert seconds.time_limit == 3 and torch.equal(
        seconds.outcome(obs)[1], boundary.outcome(obs)[1]
    )
    assert "survival" in repr(boundary)


def test_boundary_survival_errors_name_the_argument():
    with pytest.raises(TypeError, match="success, failure: expected a success predicate"):
        SuccessBoundary(None, time_limit=3)
    with pytest.raises(ValueError, match="time_limit, time_limit_s: expected how long to last"):
        SuccessBoundary.survival(lambda o: o[..., 0] > 0)
    with pytest.raises(TypeError, match="failure: expected a callable predicate, got int"):
        SuccessBoundary.survival(3, time_limit=3)
    with pytest.raises(TypeError, match=r"success: expected a callable predicate .*got str"):
        SuccessBoundary("x", time_limit=3)


def test_success_metric_keys_shapes_and_values(rollout):
    boundary = SuccessBoundary(lambda o: o[..., 0] > 1.0, time_limit=4, dt=0.5)
    out = SuccessMetric(boundary)(rollout)["competency"]
    success_over_time = (rollout["observation"][..., 0] > 1.0) & (torch.arange(T) < 4)
    success = success_over_time.any(dim=-1)
    p, p_member = success_probability(success)
    assert torch.equal(out["success"], success)
    assert out["failure"].shape == (E, N, B) and not out["failure"].any()
    assert torch.allclose(out["p_success"], p) and torch.allclose(out["p_success_member"], p_member)
    low, high = binomial_interval(success.sum(dim=(0, 1)), E * N)
    assert torch.allclose(out["p_success_low"], low) and torch.allclose(out["p_success_high"], high)
    assert (out["p_success_low"] <= p).all() and (p <= out["p_success_high"]).all()
    u = outcome_uncertainty(success)
    assert torch.allclose(out["outcome_uncertainty", "epistemic"], u.epistemic)
    tts = time_to_success(success_over_time)
    assert out["time_to_success", "success_by_step"].shape == (B, T)
    assert torch.allclose(out["time_to_success", "success_by_step"], tts.success_by_step)
    # index t holds the state after t + 1 steps
    assert torch.allclose(out["time_to_success", "mean_s"], (tts.mean_steps + 1) * 0.5)


def test_success_metric_set_keys_and_wilson(rollout):
    metric = SuccessMetric(SuccessBoundary(lambda o: o[..., 1] > 0.0), interval="wilson")
    metric.set_keys(observation="obs", competency=("eval", "competency"))
    td = TensorDict({"obs": rollout["observation"]}, batch_size=[E, N, B, T])
    out = metric(td)["eval", "competency"]
    success = (rollout["observation"][..., 1] > 0.0).any(dim=-1)
    assert torch.allclose(out["p_success"], success.float().mean(dim=(0, 1)))
    assert out["p_success_member"].shape == (E, B)
    low, high = binomial_interval(success.sum(dim=(0, 1)), E * N, method="wilson")
    assert torch.allclose(out["p_success_low"], low) and torch.allclose(out["p_success_high"], high)
    assert "mean_s" not in out["time_to_success"].keys()  # no dt given

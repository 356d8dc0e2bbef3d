"""Scoring action sequences: the rollout path, the fast path and what the seam accepts."""

from __future__ import annotations

import pytest
import torch
from planner_envs import AnalyticPointMassEnv, PointMassEnv, RiskyChoiceEnv
from tensordict import TensorDict
from torchrl.envs import RewardScaling, TransformedEnv

from rcvae_torchrl.planners import (
    ActionSequenceEvaluator,
    SuccessAwareEvaluator,
    env_returns,
    has_fast_path,
    rollout_returns,
    supports_success,
)


def _starts(env, batch=(2,)):
    td = env.reset(TensorDict(batch_size=batch))
    td["position"] = torch.linspace(-0.9, 0.9, td["position"].numel()).reshape(td["position"].shape)
    return td


def test_rollout_path_equals_analytic_fast_path():
    env = AnalyticPointMassEnv(double=False, terminate_on_success=True, success_radius=0.3)
    td = _starts(env)
    actions = torch.rand(2, 5, 4, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    actions[:, 0] = (-1.25 * td["position"]).clamp(-1, 1).unsqueeze(1)  # candidate 0 arrives
    fast = env_returns(env, td, actions, 3, return_success=True)
    slow = rollout_returns(env, td, actions, 3, success_key="success")
    assert fast.returns.shape == slow.returns.shape == (2, 5, 3)
    torch.testing.assert_close(slow.returns, fast.returns)
    assert torch.equal(slow.success, fast.success)
    assert bool(slow.success.any()) and not bool(slow.success.all())


def test_rewards_after_done_are_ignored():
    env = PointMassEnv(double=False, success_radius=0.25, terminate_on_success=True)
    td = env.reset()
    td["position"] = torch.tensor([0.3, 0.0])
    # step 0 reaches x = 0.1 (done, reward -0.1); then the particle walks away
    actions = torch.tensor([-1.0, 0.0]).repeat(1, 1, 1) * torch.tensor([1.0, -5.0, -5.0]).reshape(
        1, 3, 1
    )
    out = rollout_returns(env, td, actions, 1, success_key="success")
    torch.testing.assert_close(out.returns, torch.tensor([[-0.1]]))
    assert out.success.tolist() == [[True]]


def test_discount():
    env = PointMassEnv(double=False)
    td = env.reset()
    actions = torch.zeros(2, 3, 2)  # stand still at distance 0.8·√2
    out = rollout_returns(env, td, actions, 1, discount=0.5)
    expected = -0.8 * 2**0.5 * (1 + 0.5 + 0.25)
    torch.testing.assert_close(out.returns, torch.full((2, 1), expected))
    assert out.success is None


def test_rollout_respects_a_nested_action_key():
    env = PointMassEnv(action_key=("agent", "action"), double=False)
    td = env.reset()
    actions = torch.full((1, 1, 2), -1.0)
    out = rollout_returns(env, td, actions, 2, action_key=("agent", "action"))
    torch.testing.assert_close(out.returns, torch.full((1, 2), -0.6 * 2**0.5))


def test_rollout_goes_through_transforms():
    env = TransformedEnv(PointMassEnv(double=False), RewardScaling(loc=0.0, scale=2.0))
    td = env.reset()
    out = rollout_returns(env, td, torch.zeros(1, 1, 2), 1)
    torch.testing.assert_close(out.returns, torch.tensor([[-1.6 * 2**0.5]]))


def test_fast_path_detection():
    analytic = AnalyticPointMassEnv()
    assert has_fast_path(analytic) and supports_success(analytic)
    assert isinstance(analytic, ActionSequenceEvaluator)
    assert isinstance(analytic, SuccessAwareEvaluator)
    assert not has_fast_path(PointMassEnv())
    # a TransformedEnv forwards attributes to its base env, but scoring there would skip transforms
    assert not has_fast_path(TransformedEnv(analytic, RewardScaling(0.0, 2.0)))
    risky = RiskyChoiceEnv()
    assert has_fast_path(risky) and not supports_success(risky)


def test_env_returns_accepts_bc_and_rejects_wrong_shapes():
    env = RiskyChoiceEnv()
    td = env.reset(TensorDict(batch_size=(3,)))
    actions = torch.zeros(3, 4, 2, 2)
    assert env_returns(env, td, actions, 5).returns.shape == (3, 4, 5)

    class Flat(PointMassEnv):
        def evaluate_action_sequences(self, td_start, actions, particles):
            return torch.zeros(actions.shape[:2])

    assert env_returns(Flat(), td, actions, 5).returns.shape == (3, 4, 1)

    class Wrong(PointMassEnv):
        def evaluate_action_sequences(self, td_start, actions, particles, *, return_success=False):
            return (
                (torch.zeros(3, 4, 5), torch.zeros(3, 4, 2))
                if return_success
                else torch.zeros(4, 3)
            )

    with pytest.raises(
        ValueError, match=r"Wrong\.evaluate_action_sequences result: expected shape"
    ):
        env_returns(Wrong(), td, actions, 5)
    with pytest.raises(ValueError, match=r"Wrong\.evaluate_action_sequences success: expected"):
        env_returns(Wrong(), td, actions, 5, return_success=True)

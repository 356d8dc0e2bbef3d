"""The model env drops into planners: TorchRL's CEM / MPPI and ours, acting in the real Pusher."""

from __future__ import annotations

import pytest
import torch
from model_env_utils import at_target
from tensordict import TensorDict
from torchrl.envs import Compose, InitTracker, RewardScaling, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import MLP, MPPIPlanner, ValueOperator
from torchrl.modules import CEMPlanner as TorchRLCEMPlanner
from torchrl.objectives.value import TDLambdaEstimator

from rcvae_torchrl.planners import CEMPlanner, has_fast_path, rollout_returns

STEPS = 3


def _acts_in_bounds(rollout, real_env) -> bool:
    action = rollout["action"]
    spec = real_env.action_spec
    return bool(((action >= spec.space.low) & (action <= spec.space.high)).all())


def _stock_cem(env):
    return TorchRLCEMPlanner(env, planning_horizon=4, optim_steps=2, num_candidates=16, top_k=4)


def _mppi(env):
    torch.manual_seed(0)
    value = ValueOperator(MLP(in_features=14, out_features=1, num_cells=[8]), ["observation"])
    advantage = TDLambdaEstimator(gamma=0.99, lmbda=0.95, value_network=value)
    return MPPIPlanner(
        env,
        advantage,
        temperature=1.0,
        planning_horizon=4,
        optim_steps=2,
        num_candidates=16,
        top_k=4,
    )


@pytest.mark.parametrize("make_planner", [_stock_cem, _mppi], ids=["cem", "mppi"])
@pytest.mark.parametrize("start_states", [True, False])
def test_torchrl_planners_act_in_the_real_env(make_env, real_env, make_planner, start_states):
    env = make_env() if start_states else make_env(start_states=None)
    rollout = real_env.rollout(STEPS, make_planner(env))
    assert rollout.batch_size == (STEPS,)
    assert _acts_in_bounds(rollout, real_env)
    assert torch.isfinite(rollout["action"]).all()


@pytest.mark.parametrize("make_planner", [_stock_cem, _mppi], ids=["cem", "mppi"])
@pytest.mark.parametrize("start_states", [True, False])
def test_torchrl_planners_through_imagined_success(
    still_ball_env, real_env, starts, make_planner, start_states, monkeypatch
):
    """The ball lies on the target: every imagined episode ends at its first step, and the
    planners' rollouts auto-reset the done particles (from start_states, or from their last
    state without) and go on."""
    env = still_ball_env(start_states=starts if start_states else None)
    resets = []
    reset = env._reset
    monkeypatch.setattr(env, "_reset", lambda td=None, **kw: resets.append(1) or reset(td, **kw))
    td = real_env.reset()
    td["observation"] = at_target(td["observation"])
    action = make_planner(env)(td)["action"]
    assert action.shape == (2,) and torch.isfinite(action).all()
    assert resets  # the imagined success did end episodes


def test_under_transformed_env(make_env, real_env, starts):
    tenv = TransformedEnv(make_env(), Compose(InitTracker(), StepCounter(4), RewardSum()))
    check_env_specs(tenv, seed=0)
    rollout = tenv.rollout(6, break_when_any_done=False)
    assert rollout["next", "step_count"].max() <= 4
    # batched: transforms that keep per-element state (StepCounter, RewardScaling)
    scaled = TransformedEnv(make_env(), Compose(StepCounter(10), RewardScaling(0.0, 2.0)))
    start = scaled.reset(TensorDict({"observation": starts[:4]}, batch_size=[4]))
    td = scaled.rollout(3, tensordict=start, auto_reset=False, break_when_any_done=False)
    assert torch.equal(td["observation"][:, 0], starts[:4])
    assert td["next", "step_count"][:, -1].squeeze(-1).tolist() == [3, 3, 3, 3]
    # planners start from the real env's tensordict: transforms that need a reset (StepCounter)
    # cannot step it, stateless ones can
    rescaled = TransformedEnv(make_env(), RewardScaling(0.0, 2.0))
    planner = CEMPlanner(
        rescaled, horizon=3, num_candidates=16, top_k=4, iterations=2, particles=3, seed=0
    )
    assert planner.evaluation == "rollout"
    assert _acts_in_bounds(real_env.rollout(2, planner), real_env)
    assert _acts_in_bounds(real_env.rollout(2, _stock_cem(rescaled)), real_env)


def _ours(env, evaluation, **kwargs):
    return CEMPlanner(
        env,
        horizon=5,
        num_candidates=24,
        top_k=4,
        iterations=2,
        particles=3,
        seed=0,
        evaluation=evaluation,
        **kwargs,
    )


@pytest.mark.parametrize("objective", ["mean", "success"])
def test_our_planner_fast_and_generic_paths(make_env, real_env, objective):
    env = make_env()
    assert has_fast_path(env)
    kwargs = {"objective": objective}
    if objective == "success":
        kwargs["success_key"] = "success"
    fast, generic = _ours(env, "env", **kwargs), _ours(env, "rollout", **kwargs)
    for planner in (fast, generic):
        rollout = real_env.rollout(STEPS, planner)
        assert _acts_in_bounds(rollout, real_env)


def test_fast_and_generic_paths_choose_the_same_actions_when_deterministic(make_env, real_env):
    """With the deterministic "mean" propagation both paths compute the same returns, so the
    planners (same seed, same candidates) make the same choices."""
    env = make_env(trajectory_sampling="mean", terminate_on_success=False)
    td = real_env.reset()
    actions = torch.rand(7, 5, 2) * 2 - 1
    fast = env.evaluate_action_sequences(td, actions, 3)
    generic = rollout_returns(env, td, actions, 3).returns
    torch.testing.assert_close(fast, generic)
    chosen = [_ours(env, evaluation)(td.clone())["action"] for evaluation in ("env", "rollout")]
    torch.testing.assert_close(chosen[0], chosen[1])

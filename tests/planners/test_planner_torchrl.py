"""The planner under TorchRL's stock API: rollouts, transforms, collectors, the stock CEMPlanner."""

from __future__ import annotations

import pytest
import torch
from planner_envs import AnalyticPointMassEnv, PointMassEnv
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs import InitTracker, PendulumEnv, RewardScaling, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs
from torchrl.modules import CEMPlanner as StockCEMPlanner

from rcvae_torchrl.planners import CEMPlanner

SMALL = {"num_candidates": 64, "top_k": 8, "iterations": 3}
LOW = torch.tensor([[-0.5, -2.0], [-1.0, -0.25]])
HIGH = torch.tensor([[1.5, 1.0], [0.5, 2.0]])


def _episodic(max_steps: int) -> TransformedEnv:
    env = TransformedEnv(PointMassEnv(), InitTracker())
    env.append_transform(StepCounter(max_steps))
    return env


@pytest.mark.parametrize(
    "env",
    [
        PointMassEnv(),
        AnalyticPointMassEnv(),
        PointMassEnv((2, 2), LOW, HIGH, action_key=("agent", "action")),
        _episodic(5),
    ],
    ids=["point", "analytic", "nested-2x2", "transformed"],
)
def test_toy_env_specs(env):
    check_env_specs(env)


def test_toy_env_partial_reset():
    env = PointMassEnv()
    only_reset = TensorDict({"_reset": torch.tensor([[True], [False]])}, batch_size=(2,))
    assert env.reset(only_reset)["position"][0].tolist() == pytest.approx([0.8, 0.8])
    td = env.reset(TensorDict(batch_size=(2,)))
    td["position"] = torch.tensor([[0.1, 0.2], [0.3, 0.4]])
    td["_reset"] = torch.tensor([[True], [False]])
    out = env.reset(td)["position"]
    torch.testing.assert_close(out, torch.tensor([[0.8, 0.8], [0.3, 0.4]]))


def test_init_tracker_clears_the_plan_at_each_episode_start():
    env = _episodic(max_steps=8)
    planner = CEMPlanner(PointMassEnv(), horizon=6, seed=0, **SMALL)
    rollout = env.rollout(24, planner, break_when_any_done=False)
    assert rollout["is_init"].squeeze(-1).nonzero().squeeze(-1).tolist() == [0, 8, 16]

    reference = CEMPlanner(PointMassEnv(), horizon=6, seed=0, **SMALL)
    episodes = []
    for _ in range(3):
        reference.reset()
        episodes.append(PointMassEnv().rollout(8, reference)["action"])
    torch.testing.assert_close(rollout["action"], torch.cat(episodes))


def test_collector_runs_whole_episodes():
    env = _episodic(max_steps=15)
    planner = CEMPlanner(PointMassEnv(), horizon=8, seed=0, **SMALL)
    collector = Collector(env, planner, frames_per_batch=15, total_frames=30)
    try:
        batches = list(collector)
    finally:
        collector.shutdown()
    assert len(batches) == 2
    for batch in batches:
        assert batch["is_init"][0].item() and bool((batch["action"].abs() <= 1).all())
        assert float(batch["next", "position"][-1].norm()) < 0.05


def test_plans_inside_a_transformed_model_env():
    model = TransformedEnv(AnalyticPointMassEnv(), RewardScaling(loc=0.0, scale=2.0))
    planner = CEMPlanner(model, horizon=8, seed=0, **SMALL)
    assert planner.evaluation == "rollout"  # the transforms are not skipped
    rollout = _episodic(max_steps=30).rollout(25, planner)
    assert float(rollout["next", "position"][-1].norm()) < 0.05
    assert model.base_env.calls == 0


def test_similar_quality_to_the_stock_cem_planner():
    env = PointMassEnv()
    stock = StockCEMPlanner(env, planning_horizon=8, optim_steps=3, num_candidates=64, top_k=8)
    ours = CEMPlanner(env, horizon=8, seed=0, **SMALL)
    stock_distance = env.rollout(25, stock)["next", "position"][-5:].norm(dim=-1)
    our_distance = env.rollout(25, ours)["next", "position"][-5:].norm(dim=-1)
    assert float(stock_distance.max()) < 0.1 and float(our_distance.max()) < 0.1
    assert float(our_distance.mean()) <= max(2 * float(stock_distance.mean()), 0.02)


def test_stock_pendulum_env():
    env = PendulumEnv()
    planner = CEMPlanner(env, horizon=5, seed=0, **SMALL)
    rollout = env.rollout(4, planner)
    assert rollout["action"].shape == (4, 1) and bool((rollout["action"].abs() <= 2).all())

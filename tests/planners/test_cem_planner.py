"""CEMPlanner: closed-loop control, bounds for any action shape, warm start, resets, batch, NaN."""

from __future__ import annotations

import pytest
import torch
from planner_envs import (
    AnalyticPointMassEnv,
    NaNAnalyticPointMassEnv,
    NaNPointMassEnv,
    PointMassEnv,
    RiskyChoiceEnv,
)
from tensordict import TensorDict

from rcvae_torchrl.planners import CEMPlanner, make_cem_planner
from rcvae_torchrl.planners.cem import _device_of

SMALL = {"num_candidates": 64, "top_k": 8, "iterations": 3}
LOW3, HIGH3 = torch.tensor([-0.5, -2.0, -0.2]), torch.tensor([1.5, 1.0, 0.3])
LOW22 = torch.tensor([[-0.5, -2.0], [-1.0, -0.25]])
HIGH22 = torch.tensor([[1.5, 1.0], [0.5, 2.0]])


def _distance(position: torch.Tensor, action_dims: int) -> torch.Tensor:
    return position.flatten(-action_dims).norm(dim=-1)


@pytest.mark.parametrize("env_cls", [PointMassEnv, AnalyticPointMassEnv])
def test_drives_the_point_mass_to_the_goal(env_cls):
    env = env_cls()
    planner = CEMPlanner(env, horizon=8, seed=0, **SMALL)
    rollout = env.rollout(25, planner)
    distance = _distance(rollout["next", "position"], 1)
    assert distance[0] > 1.0 and float(distance[-5:].max()) < 0.05


@pytest.mark.parametrize(("shape", "low", "high"), [((3,), LOW3, HIGH3), ((2, 2), LOW22, HIGH22)])
def test_any_action_shape_stays_in_bounds_and_reaches_the_goal(shape, low, high):
    env = PointMassEnv(shape, low, high, double=False, start=torch.full(shape, 0.3))
    # each call searches with the prior std (a warm start keeps the mean alone): to come
    # within 5 cm the search needs the budget to narrow it within a call
    budget = {**SMALL, "num_candidates": 256, "top_k": 16, "iterations": 5}
    planner = CEMPlanner(env, horizon=5, seed=0, **budget)
    rollout = env.rollout(20, planner)
    actions = rollout["action"]
    assert actions.shape == (20, *shape)
    assert bool((actions >= low).all() and (actions <= high).all())
    assert float(_distance(rollout["next", "position"], len(shape))[-1]) < 0.05
    assert env.action_spec.is_in(actions[0])


def test_nested_action_key():
    env = PointMassEnv(action_key=("agent", "action"))
    planner = CEMPlanner(env, horizon=8, seed=0, **SMALL)
    assert planner.out_keys == [("agent", "action")]
    rollout = env.rollout(25, planner)
    assert "action" not in rollout.keys()
    assert bool((rollout["agent", "action"].abs() <= 1).all())
    assert float(rollout["next", "position"].norm(dim=-1)[-1]) < 0.05


def test_rollout_and_fast_path_give_the_same_plan():
    env = AnalyticPointMassEnv()
    fast = CEMPlanner(env, horizon=6, particles=2, seed=3, **SMALL)
    slow = CEMPlanner(env, horizon=6, particles=2, seed=3, evaluation="rollout", **SMALL)
    assert (fast.evaluation, slow.evaluation) == ("env", "rollout")
    td = env.reset()
    for _ in range(3):  # warm starts included
        a_fast, a_slow = fast(td.clone())["action"], slow(td.clone())["action"]
        torch.testing.assert_close(a_fast, a_slow)
        td = env.step_mdp(env.step(td.set("action", a_fast)))
    assert env.calls == 3 * SMALL["iterations"]


def test_same_seed_same_actions_other_seed_other_actions():
    env = PointMassEnv()
    runs = [
        env.rollout(5, CEMPlanner(env, horizon=6, seed=s, **SMALL))["action"] for s in (0, 0, 1)
    ]
    assert torch.equal(runs[0], runs[1]) and not torch.equal(runs[0], runs[2])


def test_warm_start_keeps_the_shifted_plan():
    env = PointMassEnv()
    planner = CEMPlanner(env, horizon=6, seed=0, **SMALL)
    td = env.reset()
    assert planner.plan is None
    state = planner.generator.get_state()
    mean, _ = planner.optimize(td, *planner.initial_plan(td))
    planner.generator.set_state(state)
    action = planner(td.clone())["action"]
    torch.testing.assert_close(action, mean[0])
    kept_mean, kept_std = planner.plan
    torch.testing.assert_close(kept_mean[:-1], mean[1:])
    torch.testing.assert_close(kept_mean[-1], planner.prior_mean)
    # the std is the prior's again: a kept one shrinks at every call (a pendulum's search fell
    # to 0.005 wide within 10 calls, and never found the swing-up again)
    torch.testing.assert_close(kept_std, planner.prior_std.expand(6, 2))
    # the next call starts from the kept plan, unless the state is an episode start
    torch.testing.assert_close(planner.initial_plan(td)[0], kept_mean)
    fresh = planner.initial_plan(td.clone().set("is_init", torch.tensor([True])))
    torch.testing.assert_close(fresh[0], planner.prior_mean.expand(6, 2))
    for _ in range(10):
        planner(td.clone())
    torch.testing.assert_close(planner.initial_plan(td)[1], planner.prior_std.expand(6, 2))
    planner.reset()
    assert planner.plan is None


def test_is_init_resets_only_flagged_batch_elements():
    env = PointMassEnv()
    planner = CEMPlanner(env, horizon=4, seed=0, **SMALL)
    td = env.reset(TensorDict(batch_size=(2,)))
    planner(td.clone())
    kept_mean, kept_std = planner.plan
    td["is_init"] = torch.tensor([[True], [False]])
    mean, std = planner.initial_plan(td)
    torch.testing.assert_close(mean[0], planner.prior_mean.expand(4, 2))
    torch.testing.assert_close(std[0], planner.prior_std.expand(4, 2))
    torch.testing.assert_close(mean[1], kept_mean[1])
    torch.testing.assert_close(std[1], kept_std[1])
    # a new batch shape starts from the prior
    mean, _ = planner.initial_plan(env.reset(TensorDict(batch_size=(3,))))
    torch.testing.assert_close(mean, planner.prior_mean.expand(3, 4, 2))


def test_no_warm_start_keeps_nothing():
    env = PointMassEnv()
    planner = CEMPlanner(env, horizon=4, warm_start=False, seed=0, **SMALL)
    planner(env.reset())
    assert planner.plan is None


def _episode(env, planner, start, steps=6):
    td = env.reset()
    td["position"] = start
    return env.rollout(steps, planner, auto_reset=False, tensordict=td)["action"]


def test_reset_stops_the_plan_leaking_into_the_next_episode():
    env = PointMassEnv()
    planner = CEMPlanner(env, horizon=6, seed=0, **SMALL)
    _episode(env, planner, torch.tensor([0.9, -0.9]))
    state = planner.generator.get_state()
    leaked = _episode(env, planner, torch.tensor([-0.5, 0.5]))

    fresh = CEMPlanner(env, horizon=6, seed=0, **SMALL)
    fresh.generator.set_state(state)
    clean = _episode(env, fresh, torch.tensor([-0.5, 0.5]))
    assert not torch.equal(leaked, clean)  # without a reset signal the old plan leaks in

    _episode(env, planner, torch.tensor([0.9, -0.9]))
    planner.reset()
    planner.generator.set_state(state)
    assert torch.equal(_episode(env, planner, torch.tensor([-0.5, 0.5])), clean)


def test_batch_of_states_plans_each_independently():
    env = PointMassEnv()
    starts = torch.tensor([[0.8, 0.8], [-0.9, 0.2], [0.1, -0.7], [0.5, 0.0]])
    td = env.reset(TensorDict(batch_size=(4,)))
    td["position"] = starts
    planner = CEMPlanner(env, horizon=8, seed=0, **SMALL)
    rollout = env.rollout(25, planner, auto_reset=False, tensordict=td)
    assert rollout.batch_size == (4, 25)
    assert float(rollout["next", "position"][:, -1].norm(dim=-1).max()) < 0.05

    # changing one start state does not change another element's plan (same noise)
    def first_action(positions):
        fresh = env.reset(TensorDict(batch_size=(2,))).set("position", positions)
        return CEMPlanner(env, horizon=6, seed=1, **SMALL)(fresh)["action"]

    a = first_action(torch.tensor([[0.8, 0.8], [-0.9, 0.2]]))
    b = first_action(torch.tensor([[0.8, 0.8], [0.3, 0.3]]))
    torch.testing.assert_close(a[0], b[0])
    assert not torch.allclose(a[1], b[1])


def test_single_state_equals_batch_of_one():
    env = PointMassEnv()
    td = env.reset()
    single = CEMPlanner(env, horizon=6, seed=2, **SMALL)(td.clone())["action"]
    batched = CEMPlanner(env, horizon=6, seed=2, **SMALL)(td.unsqueeze(0).clone())["action"]
    torch.testing.assert_close(batched[0], single)


def test_multi_dim_batch():
    env = PointMassEnv()
    td = env.reset(TensorDict(batch_size=(2, 3)))
    out = CEMPlanner(env, horizon=4, seed=0, **SMALL)(td)
    assert out["action"].shape == (2, 3, 2) and bool((out["action"].abs() <= 1).all())


@pytest.mark.parametrize("env_cls", [NaNPointMassEnv, NaNAnalyticPointMassEnv])
def test_nan_returns_never_win(env_cls):
    # the goal lies at +x, but every sequence with a positive x-action has NaN return
    start = torch.tensor([-0.8, 0.0])
    env = env_cls(start=start)
    planner = CEMPlanner(env, horizon=5, seed=0, **SMALL)
    td = env.reset()
    candidates = torch.tensor([[0.5, 0.0], [-0.5, 0.0]]).unsqueeze(1).expand(2, 5, 2)
    scores = planner.score(td, candidates)
    assert torch.isnan(scores[0]) and torch.isfinite(scores[1])
    actions = env.rollout(5, planner)["action"]
    assert bool((actions[:, 0] <= 0).all()) and bool(torch.isfinite(actions).all())
    # without the NaNs the planner heads for +x
    clean = PointMassEnv(start=start)
    assert bool(clean.rollout(1, CEMPlanner(clean, horizon=5, seed=0, **SMALL))["action"][0, 0] > 0)


@pytest.mark.parametrize(
    ("objective", "risk_level", "risky"),
    [("mean", 0.1, True), ("quantile", 0.1, False), ("cvar", 0.2, False)],
)
def test_risk_averse_objective_prefers_the_safe_plan(objective, risk_level, risky):
    env = RiskyChoiceEnv()
    planner = CEMPlanner(
        env, horizon=3, particles=20, objective=objective, risk_level=risk_level, seed=0, **SMALL
    )
    action = planner(env.reset())["action"]
    assert bool(action[0] > 0) is risky


def test_success_objective_on_both_paths():
    env = AnalyticPointMassEnv(double=False, success_radius=0.15, start=torch.tensor([0.5, 0.0]))
    kwargs = {"horizon": 4, "objective": "success", "seed": 0, **SMALL}
    fast = CEMPlanner(env, **kwargs)
    slow = make_cem_planner(env, evaluation="rollout", **kwargs)
    assert slow.success_key == "success"
    td = env.reset()
    torch.testing.assert_close(fast(td.clone())["action"], slow(td.clone())["action"])
    rollout = env.rollout(6, CEMPlanner(env, **kwargs))
    assert bool(rollout["next", "success"].any())


def test_proposal_joins_the_candidates_and_wins_when_best():
    env = AnalyticPointMassEnv()
    td = env.reset()
    # The best plan pushes straight to the goal; a tiny population rarely samples it.
    best = -torch.sign(td["position"]).expand(6, *td["position"].shape).clone()
    planner = CEMPlanner(
        env,
        horizon=6,
        num_candidates=2,
        top_k=1,
        iterations=1,
        momentum=0.0,
        seed=0,
        proposal=lambda t: best,
    )
    torch.testing.assert_close(planner(td.clone())["action"], best[0])
    blind = CEMPlanner(
        env, horizon=6, num_candidates=2, top_k=1, iterations=1, momentum=0.0, seed=0
    )
    assert not torch.allclose(blind(td.clone())["action"], best[0])
    with pytest.raises(ValueError, match="proposal: expected a plan of shape"):
        CEMPlanner(env, horizon=6, seed=0, proposal=lambda t: best[:3])(td.clone())
    with pytest.raises(TypeError, match="proposal: expected a callable"):
        CEMPlanner(env, horizon=6, seed=0, proposal=3)


def test_device_of_is_the_tensordicts_or_its_first_tensors():
    on_cpu = torch.device("cpu")
    assert _device_of(TensorDict(a=torch.zeros(2), batch_size=[2], device="cpu")) == on_cpu
    assert _device_of(TensorDict(a=torch.zeros(2), batch_size=[2])) == on_cpu
    assert _device_of(TensorDict({}, batch_size=[])) is None


def test_an_input_on_the_envs_device_is_planned_in_place():
    td = PointMassEnv().reset()
    out = CEMPlanner(PointMassEnv(), horizon=5, seed=0, **SMALL)(td)
    assert out is td and out["action"].device == torch.device("cpu")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the env on a GPU needs CUDA")
@pytest.mark.parametrize("env_cls", [PointMassEnv, AnalyticPointMassEnv])
def test_a_cpu_state_is_planned_on_the_envs_device_and_answered_on_its_own(env_cls):
    """A CPU simulator's state with the model env on a GPU: the same plan as on the GPU."""
    td = env_cls().reset()
    out = CEMPlanner(env_cls(device="cuda"), horizon=5, seed=0, **SMALL)(td.clone())
    assert out["action"].device == torch.device("cpu")
    on_gpu = CEMPlanner(env_cls(device="cuda"), horizon=5, seed=0, **SMALL)(td.to("cuda"))
    torch.testing.assert_close(out["action"], on_gpu["action"].cpu(), rtol=0, atol=0)


@pytest.mark.parametrize("env_cls", [PointMassEnv, AnalyticPointMassEnv])
def test_an_input_on_another_device_takes_the_copy_path(env_cls):
    """An input whose device differs from the env's (``cpu:0`` against ``cpu`` on any machine)
    is copied to the env's device for the plan: the same action, written into the input."""
    td = env_cls().reset()
    elsewhere = td.clone().to("cpu:0")
    assert elsewhere.device != torch.device("cpu")
    out = CEMPlanner(env_cls(), horizon=5, seed=0, **SMALL)(elsewhere)
    in_place = CEMPlanner(env_cls(), horizon=5, seed=0, **SMALL)(td)
    assert out is elsewhere and out.device == torch.device("cpu:0")
    torch.testing.assert_close(out["action"], in_place["action"], rtol=0, atol=0)

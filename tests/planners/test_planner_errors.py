"""Bad input gives errors that name the argument, what was expected and what was given."""

from __future__ import annotations

import math

import pytest
import torch
from planner_envs import AnalyticPointMassEnv, PointMassEnv, RiskyChoiceEnv
from tensordict import TensorDict
from torchrl.data import Categorical, Composite

from rcvae_torchrl.planners import CEMPlanner


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"horizon": 0}, "horizon: expected a positive integer, got 0"),
        ({"horizon": -3}, "horizon: expected a positive integer, got -3"),
        ({"horizon": 2.5}, "horizon: expected a positive integer, got 2.5"),
        ({"num_candidates": 0}, "num_candidates: expected a positive integer, got 0"),
        ({"top_k": 11}, "top_k: expected at most num_candidates = 10 elites, got 11"),
        ({"top_k": 0}, "top_k: expected a positive integer, got 0"),
        ({"iterations": 0}, "iterations: expected a positive integer, got 0"),
        ({"particles": 0}, "particles: expected a positive integer, got 0"),
        ({"momentum": 1.0}, r"momentum: expected a float in \[0, 1\), got 1.0"),
        ({"momentum": -0.1}, r"momentum: expected a float in \[0, 1\), got -0.1"),
        ({"objective": "median"}, "objective: expected one of .*, got 'median'"),
        ({"objective": "cvar", "risk_level": 0.0}, r"risk_level: expected a float in \(0, 1\]"),
        ({"objective": "quantile", "risk_level": 1.5}, r"risk_level: expected a float in \[0, 1\]"),
        ({"evaluation": "fast"}, "evaluation: expected one of .*, got 'fast'"),
        ({"evaluation": "env"}, "evaluation: 'env' needs an env with evaluate_action_sequences"),
        ({"objective": "success"}, "success_key: expected the key of a success flag"),
        ({"seed": 0, "generator": torch.Generator()}, "seed: expected None when a generator"),
        ({"init_std": -1.0}, "init_std: expected positive finite values, got -1.0"),
        (
            {"init_std": torch.ones(3)},
            r"init_std: expected a scalar or shape \[\*A\] = \(2,\), got shape \(3,\)",
        ),
        ({"proposal": lambda td: td, "proposal_std": math.inf}, "proposal_std: expected a pos"),
        ({"action_key": "act"}, r"action_key: expected one of the env's action keys \['action'\]"),
    ],
)
def test_bad_arguments(kwargs, message):
    args = {"horizon": 4, "num_candidates": 10, "top_k": 2, **kwargs}
    with pytest.raises(ValueError, match=message):
        CEMPlanner(PointMassEnv(), **args)


def test_momentum_type():
    with pytest.raises(TypeError, match="momentum: expected a float in"):
        CEMPlanner(PointMassEnv(), horizon=4, momentum="0.1")


def test_fast_path_conflicts():
    with pytest.raises(
        ValueError, match=r"discount: expected 1\.0 when the env scores plans itself"
    ):
        CEMPlanner(AnalyticPointMassEnv(), horizon=4, discount=0.9)
    with pytest.raises(ValueError, match="objective: 'success' needs RiskyChoiceEnv"):
        CEMPlanner(RiskyChoiceEnv(), horizon=4, objective="success")


def test_unsupported_envs():
    class Locked(PointMassEnv):
        """Batch-locked, like most real envs (EnvBase.__new__ keeps the flag on the class)."""

    locked = Locked()
    Locked._batch_locked = True
    assert locked.batch_locked
    with pytest.raises(
        ValueError,
        match=r"env: expected an env that steps any batch .*make_rcvae_env.*got Locked, whose "
        r"batch is locked \(a real env",
    ):
        CEMPlanner(locked, horizon=4)
    env = PointMassEnv()
    env.full_action_spec = Composite(action=Categorical(3))
    with pytest.raises(TypeError, match=r"env.full_action_spec\['action'\]: expected a continuous"):
        CEMPlanner(env, horizon=4)


def test_nan_in_the_state():
    env = PointMassEnv()
    planner = CEMPlanner(env, horizon=4, num_candidates=10, top_k=2, seed=0)
    td = env.reset()
    td["velocity"] = torch.tensor([0.0, float("nan")])
    with pytest.raises(
        ValueError, match=r"tensordict\['velocity'\]: expected finite values, got 1 NaN"
    ):
        planner(td)


def test_wrong_action_shape_given_to_evaluate():
    env = PointMassEnv()
    planner = CEMPlanner(env, horizon=4, num_candidates=10, top_k=2, seed=0)
    td = env.reset(TensorDict(batch_size=(3,)))
    planner.evaluate(td, torch.zeros(3, 5, 4, 2))
    for bad in (torch.zeros(3, 5, 4, 3), torch.zeros(2, 5, 4, 2), torch.zeros(3, 4, 2)):
        with pytest.raises(
            ValueError, match=r"actions: expected shape \[\*B, C, H, \*A\] with B = \(3,\)"
        ):
            planner.evaluate(td, bad)


def test_wrong_returns_shape_from_the_env():
    class Wrong(PointMassEnv):
        def evaluate_action_sequences(self, td_start, actions, particles):
            return torch.zeros(actions.shape[0] + 1)

    planner = CEMPlanner(Wrong(), horizon=4, num_candidates=10, top_k=2, seed=0)
    with pytest.raises(
        ValueError, match=r"Wrong\.evaluate_action_sequences result: expected shape"
    ):
        planner(Wrong().reset())


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"discount": math.nan}, ValueError, r"discount: expected a float in \(0, 1\], got nan"),
        ({"discount": -1.0}, ValueError, r"discount: expected a float in \(0, 1\], got -1.0"),
        ({"warm_start": "no"}, TypeError, "warm_start: expected True or False, got 'no'"),
    ],
)
def test_bad_discount_and_flags(kwargs, error, message):
    with pytest.raises(error, match=message):
        CEMPlanner(PointMassEnv(), horizon=4, evaluation="rollout", **kwargs)


def test_env_must_be_an_env():
    with pytest.raises(TypeError, match="env: expected a TorchRL EnvBase, got str"):
        CEMPlanner("point_mass", horizon=4)


class _NaNReward(PointMassEnv):
    """A task whose reward is NaN whenever the point moves off the axis (every plan here)."""

    def reward(self, position, action):
        return super().reward(position, action) * torch.nan


def test_a_plan_no_finite_score_chose_is_refused():
    """Every candidate scores NaN (a broken model or reward): the prior's mean would come back
    as if planned; the planner says so instead."""
    env = _NaNReward()
    planner = CEMPlanner(env, horizon=4, num_candidates=10, top_k=2, seed=0)
    with pytest.raises(FloatingPointError, match=r"every candidate plan of 1 of 1 start state"):
        planner(env.reset())
    # the same planner on a sound task plans
    sound = CEMPlanner(PointMassEnv(), horizon=4, num_candidates=10, top_k=2, seed=0)
    assert torch.isfinite(sound(PointMassEnv().reset())["action"]).all()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"init_std": "big"}, "init_std: expected a positive number or a tensor"),
        ({"proposal": lambda td: td, "proposal_std": "x"}, "proposal_std: expected a positive"),
        ({"generator": 3}, "generator: expected a torch.Generator or None, got int"),
    ],
)
def test_arguments_of_another_type(kwargs, message):
    with pytest.raises((TypeError, ValueError)) as info:
        CEMPlanner(PointMassEnv(), horizon=4, **kwargs)
    assert message in str(info.value)


def test_init_std_may_be_a_list_per_action_dimension():
    planner = CEMPlanner(PointMassEnv(), horizon=4, init_std=[0.3, 0.4])
    assert planner.prior_std.tolist() == pytest.approx([0.3, 0.4])


def test_a_nan_candidate_is_never_an_elite_and_a_nan_proposal_is_refused():
    """A NaN candidate scored NaN added 0 x NaN = NaN to the elites' mean: the whole plan was
    NaN. A proposal of NaN actions was taken in."""
    from rcvae_torchrl.planners import cem_update

    nan = float("nan")
    candidates = torch.tensor([[0.0], [1.0], [nan]])
    mean, std = cem_update(
        torch.zeros(1), torch.ones(1), candidates, torch.tensor([0.0, 1.0, nan]), 2, 0.5
    )
    assert torch.equal(mean, torch.tensor([0.25])) and torch.equal(std, torch.tensor([0.75]))
    env = PointMassEnv()
    planner = CEMPlanner(
        env, horizon=3, num_candidates=8, top_k=2, proposal=lambda td: torch.full((3, 2), nan)
    )
    with pytest.raises(ValueError, match=r"proposal: expected a finite plan, got non-finite"):
        planner.planning(env.reset())


def test_success_outside_0_1_is_refused_and_a_nan_ranks_lowest():
    from rcvae_torchrl.planners import lexicographic_score, reduce_particles

    returns = torch.tensor([[[1.0, 1.0], [5.0, 5.0], [2.0, 2.0]]])
    for bad in (float("nan"), 7.0, -1.0):
        success = torch.tensor([[[bad, 0.0], [1.0, 1.0], [0.5, 0.5]]])
        with pytest.raises(ValueError, match=r"success: expected a bool indicator or values in"):
            reduce_particles(returns, "success", success=success)
    score = lexicographic_score(
        torch.tensor([[float("nan"), 1.0, 0.5]]), torch.tensor([[9, 5, 2.0]])
    )
    assert score.argmax().item() == 1 and score.argmin().item() == 0


def test_crossed_or_nan_bounds_and_bad_counts_are_named():
    from rcvae_torchrl.planners import action_prior, sample_candidates

    with pytest.raises(ValueError, match=r"low, high: expected low <= high \(and no NaN\)"):
        action_prior(torch.ones(2), -torch.ones(2))
    with pytest.raises(ValueError, match=r"low, high: expected low <= high \(and no NaN\)"):
        action_prior(torch.tensor([float("nan"), 0.0]), torch.ones(2))
    with pytest.raises(ValueError, match="num_candidates: expected a positive integer, got 0"):
        sample_candidates(torch.zeros(3, 2), torch.ones(3, 2), 0, -torch.ones(2), torch.ones(2))
    # crossed bounds would clamp every candidate to high; bounds of two shapes, to torch's error
    with pytest.raises(ValueError, match=r"low, high: expected low <= high \(and no NaN\)"):
        sample_candidates(torch.zeros(3, 2), torch.ones(3, 2), 4, torch.ones(2), -torch.ones(2))
    with pytest.raises(
        ValueError, match=r"high: expected shape \[\*A\] \(the shape of low\) = \(2,\), got \(1,\)"
    ):
        sample_candidates(torch.zeros(3, 2), torch.ones(3, 2), 4, -torch.ones(2), torch.ones(1))


def test_rollout_returns_names_its_arguments():
    from rcvae_torchrl.planners import rollout_returns

    env = PointMassEnv()
    start, actions = env.reset(), torch.zeros(4, 3, 2)
    with pytest.raises(ValueError, match=r"discount: expected a float in \(0, 1\], got nan"):
        rollout_returns(env, start, actions, 1, discount=math.nan)
    with pytest.raises(ValueError, match=r"discount: expected a float in \(0, 1\], got -2"):
        rollout_returns(env, start, actions, 1, discount=-2)
    for particles in (0, -1, 1.5):
        with pytest.raises(ValueError, match="particles: expected a positive integer"):
            rollout_returns(env, start, actions, particles)
    with pytest.raises(KeyError, match=r"reward_key: the env's step wrote no \('next', 'rew'\)"):
        rollout_returns(env, start, actions, reward_key="rew")
    with pytest.raises(KeyError, match=r"success_key: the env's step wrote no"):
        rollout_returns(env, start, actions, success_key="won")
    with pytest.raises(TypeError, match="td_start: expected a TensorDict, got dict"):
        rollout_returns(env, {}, actions)
    with pytest.raises(ValueError, match=r"actions: expected \[\*B, C, H, \*A\] with the batch"):
        rollout_returns(env, start.expand(2).clone(), torch.zeros(3, 4, 3, 2))
    with pytest.raises(ValueError, match="actions: expected finite values"):
        rollout_returns(env, start, torch.full((4, 3, 2), math.nan))


def test_optimize_checks_the_plan_it_starts_from():
    env = PointMassEnv()
    planner = CEMPlanner(env, horizon=3, num_candidates=8, top_k=2)
    td = env.reset()
    mean, std = planner.initial_plan(td)
    with pytest.raises(ValueError, match=r"mean: expected a plan \[\*B, H, \*A\] = \(3, 2\)"):
        planner.optimize(td, torch.zeros(4, 2), std)
    with pytest.raises(ValueError, match="mean: expected finite values"):
        planner.optimize(td, torch.full_like(mean, math.nan), std)
    with pytest.raises(ValueError, match="std: expected positive values"):
        planner.optimize(td, mean, -std)
    planner.optimize(td, mean, std)


def test_reductions_and_plan_helpers_name_empty_or_misshaped_inputs():
    """An empty particle axis gave NaN scores or torch's "quantile() input tensor must be
    non-empty"; a bad time_dim, fill or scalar scores failed inside torch."""
    from rcvae_torchrl.planners import (
        cvar_return,
        elite_mask,
        expected_return,
        lexicographic_score,
        quantile_return,
        sample_candidates,
        shift_plan,
    )

    empty = torch.zeros(2, 0)
    for reduce in (expected_return, lambda r: quantile_return(r, 0.5), lambda r: cvar_return(r, 1)):
        with pytest.raises(ValueError, match=r"returns: expected .* with P >= 1, got .* \(2, 0\)"):
            reduce(empty)
    with pytest.raises(TypeError, match=r"returns: expected a tensor \[\*B, C, P\], got list"):
        expected_return([[1.0, 2.0]])
    with pytest.raises(ValueError, match=r"time_dim: expected the index of H >= 1 in plan"):
        shift_plan(torch.zeros(3, 2), torch.zeros(2), 5)
    with pytest.raises(ValueError, match=r"fill: expected a tensor that broadcasts to \(2,\)"):
        shift_plan(torch.zeros(3, 2), torch.zeros(3), 0)
    with pytest.raises(ValueError, match=r"scores: expected a floating tensor \[\*B, C\]"):
        elite_mask(torch.tensor(1.0), 1)
    with pytest.raises(ValueError, match=r"primary: expected a tensor \[\*B, C\], got \(\)"):
        lexicographic_score(torch.tensor(1.0), torch.tensor(1.0))
    with pytest.raises(ValueError, match=r"mean: expected \[\*B, H, \*A\] with \*A = \(2,\)"):
        sample_candidates(torch.zeros(3), torch.ones(3), 4, -torch.ones(2), torch.ones(2))
    shifted = shift_plan(torch.arange(6.0).reshape(3, 2), torch.full((2,), -1.0), 0)
    assert shifted.tolist() == [[2.0, 3.0], [4.0, 5.0], [-1.0, -1.0]]


def test_rollout_returns_names_an_action_of_another_width():
    from rcvae_torchrl.planners import rollout_returns

    env = PointMassEnv()
    with pytest.raises(ValueError, match=r"actions: expected \[\*B, C, H, \*A\] with \*A = \(2,\)"):
        rollout_returns(env, env.reset(), torch.zeros(4, 3, 3))


def test_rollout_returns_names_an_action_key_the_env_lacks():
    from rcvae_torchrl.planners import rollout_returns

    env = PointMassEnv(action_key=("agent", "action"), double=False)
    with pytest.raises(KeyError, match=r"action_key: the env has no action 'action'; its actions"):
        rollout_returns(env, env.reset(), torch.zeros(1, 1, 2))
    out = rollout_returns(env, env.reset(), torch.zeros(1, 1, 2), action_key=("agent", "action"))
    assert out.returns.shape == (1, 1)

"""A stochastic TorchRL policy (a ``ProbabilisticActor``) acts in one known exploration mode in
collection, imagination and real episodes; the mode is recorded, the same seed gives the same
draws, and a forecast of the policy acting one way is not judged by episodes of another.

A cheetah trial: a ``ProbabilisticActor`` whose model learned from sampled episodes (TorchRL's
collector samples) was imagined and run by its mean (TorchRL's default outside a context):
forecast 0.31, real 0.85 by the mean, 0.39 sampled, and nothing said which agent was judged.
"""

from __future__ import annotations

import warnings

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal
from torchrl.modules.planners import MPCPlannerBase

from rcvae_torchrl.agent import RealOutcomes, real_outcomes, score_forecast
from rcvae_torchrl.data import (
    GaussianExploration,
    collect_episodes,
    exploration_mode,
    make_policy_module,
    prepare_env,
)
from rcvae_torchrl.training import OutcomeCheck
from tests.agent.worker_envs import plain_reset
from tests.competency.test_assessor import make_assessor, make_ensemble, make_env
from tests.planners.planner_envs import PointMassEnv

STEPS = 12


class _Toward(nn.Module):
    """Toward the origin from a point mass's (position, velocity), with a wide spread: the mean
    always arrives, samples only sometimes."""

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        half = observation.shape[-1] // 2
        loc = -2.0 * observation[..., :2] - 2.0 * observation[..., half : half + 2]
        return loc, torch.full_like(loc, 1.5)


def stochastic_actor() -> ProbabilisticActor:
    net = TensorDictModule(_Toward(), in_keys=["observation"], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        net,
        in_keys=["loc", "scale"],
        out_keys=["action"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0},
    )


def point_mass():
    return prepare_env(PointMassEnv())[0]


def _near(observation: torch.Tensor) -> torch.Tensor:
    return observation[..., :2].norm(dim=-1) < 0.25


def _outcomes(env, **kwargs) -> RealOutcomes:
    starts = env.reset()["observation"].expand(3, -1).clone()
    args = dict(runs_per_start=6, reset_to_state=plain_reset, max_steps=STEPS, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # copies, where the mean policy acts
        return real_outcomes(env, stochastic_actor(), starts, success=_near, **args, **kwargs)


def test_the_mode_is_the_argument_else_the_caller_s_else_sampled():
    assert exploration_mode() is ExplorationType.RANDOM  # as TorchRL's collectors
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert exploration_mode() is ExplorationType.DETERMINISTIC
        assert exploration_mode("Random") is ExplorationType.RANDOM
    assert exploration_mode(ExplorationType.MEAN) is ExplorationType.MEAN
    with pytest.raises(ValueError, match=r"^exploration_type: expected one of \[.*'random'"):
        exploration_mode("sampled")
    with pytest.raises(TypeError, match=r"^exploration_type: expected a torchrl ExplorationType"):
        exploration_mode(1)


def test_real_episodes_sample_by_default_and_repeat_under_their_seed():
    env = point_mass()
    before = torch.get_rng_state()
    sampled = _outcomes(env)
    assert torch.equal(torch.get_rng_state(), before)  # the caller's stream is left as it was
    assert sampled.acting == "random"
    assert 0.1 < float(sampled.success.float().mean()) < 0.9  # draws: some arrive, some not
    again = _outcomes(env)
    assert torch.equal(again.steps, sampled.steps) and torch.equal(again.success, sampled.success)
    other = _outcomes(env, seed=1)
    assert not torch.equal(other.steps, sampled.steps)
    # the mean: every run arrives, one episode repeated; asked for, or by the caller's context
    mean = _outcomes(env, exploration_type="deterministic")
    assert mean.acting == "deterministic" and bool(mean.success.all())
    assert (mean.steps == mean.steps[0, 0]).all()
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert torch.equal(_outcomes(env).steps, mean.steps)
        assert _outcomes(env, exploration_type="random").acting == "random"


class _Mean(nn.Module):
    """:class:`_Toward`'s mean alone."""

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return _Toward()(observation)[0]


class _NoisyPlanner(MPCPlannerBase):
    """Toward the origin, with noise from its own generator and from that of the env it plans
    in, as a planner draws its candidates and scores them (TorchRL's planners hold it as
    ``env``)."""

    def __init__(self) -> None:
        planned_in = PointMassEnv()
        planned_in.generator = torch.Generator().manual_seed(1)
        super().__init__(planned_in)
        self.generator = torch.Generator().manual_seed(0)

    def planning(self, td):
        observation = td["observation"]
        half = observation.shape[-1] // 2
        loc = -2.0 * observation[..., :2] - 2.0 * observation[..., half : half + 2]
        noise = torch.randn(loc.shape, generator=self.generator)
        noise += torch.randn(loc.shape, generator=self.env.generator)
        return (loc + noise).clamp(-1.0, 1.0)


def test_a_planner_s_generators_are_seeded_per_episode_and_left_as_they_were():
    """Real episodes of a planner repeat under their seeds whatever its generators (its own
    and its model env's) drew before, and the generators are left as they were (a Reacher
    trial's MPPI agent gave real rates of 0.9 and 0.4 from one start, with one seed). An
    exploration policy's own generator runs on from where it was seeded, as in collection."""
    env = point_mass()
    planner = _NoisyPlanner()
    starts = env.reset()["observation"].expand(3, -1).clone()
    args = dict(runs_per_start=6, reset_to_state=plain_reset, max_steps=STEPS, progress=False)

    def outcomes(policy, **kwargs) -> RealOutcomes:
        return real_outcomes(env, policy, starts, success=_near, **args, **kwargs)

    first = outcomes(planner)
    states = [planner.generator.get_state(), planner.env.generator.get_state()]
    assert torch.equal(states[0], torch.Generator().manual_seed(0).get_state())
    assert torch.equal(states[1], torch.Generator().manual_seed(1).get_state())
    assert 0.1 < float(first.success.float().mean()) < 0.9  # the noise decides some runs
    torch.randn(5, generator=planner.generator)  # drawn from before the second call
    torch.randn(7, generator=planner.env.generator)
    again = outcomes(planner)
    assert torch.equal(again.steps, first.steps) and torch.equal(again.success, first.success)
    assert not torch.equal(outcomes(planner, seed=1).steps, first.steps)
    explorer = make_policy_module(GaussianExploration(_Mean(), 1.0, seed=0))
    before = explorer.module.generator.get_state()
    outcomes(explorer)
    assert not torch.equal(explorer.module.generator.get_state(), before)  # it ran on


def test_copies_from_a_policy_acting_by_its_mean_are_said_to_be_so():
    env = point_mass()
    starts = env.reset()["observation"].expand(2, -1).clone()
    with pytest.warns(UserWarning, match=r"copies of one outcome.*acting 'deterministic', as here"):
        real_outcomes(
            env,
            stochastic_actor(),
            starts,
            runs_per_start=2,
            reset_to_state=plain_reset,
            max_steps=STEPS,
            success=_near,
            progress=False,
            exploration_type="deterministic",
        )


def test_collection_acts_in_the_mode_asked_and_repeats_under_its_seed():
    args = dict(num_episodes=2, max_frames=400, progress=False)

    def bounded():  # episodes of STEPS steps
        from torchrl.envs import StepCounter

        return point_mass().append_transform(StepCounter(STEPS))

    sampled = collect_episodes(bounded, stochastic_actor(), **args)
    again = collect_episodes(bounded, stochastic_actor(), **args)
    assert torch.equal(sampled["action"], again["action"])
    mean = collect_episodes(bounded, stochastic_actor(), exploration_type="deterministic", **args)
    loc, _ = _Toward()(mean["observation"])
    assert torch.allclose(mean["action"], torch.tanh(loc), atol=1e-6)
    assert not torch.allclose(sampled["action"], torch.tanh(_Toward()(sampled["observation"])[0]))


def test_a_forecast_repeats_under_its_seed_and_keeps_how_the_policy_acted():
    assessor = make_assessor(make_env(make_ensemble()))
    starts = torch.randn(4, 14, generator=torch.Generator().manual_seed(1)) * 0.1
    before = torch.get_rng_state()
    one = assessor.assess(starts, policy=stochastic_actor(), seed=3, return_rollouts=True)
    assert torch.equal(torch.get_rng_state(), before)
    two = assessor.assess(starts, policy=stochastic_actor(), seed=3, return_rollouts=True)
    actions = ("rollout", "action")
    assert torch.equal(one.data.get(actions), two.data.get(actions))
    assert one.acting == "random"
    mean = assessor.assess(
        starts, policy=stochastic_actor(), seed=3, return_rollouts=True, exploration_type="mean"
    )
    assert mean.acting == "mean" and not torch.equal(mean.data.get(actions), one.data.get(actions))
    plan = torch.zeros(4, 6, 2)
    assert assessor.assess(starts, actions=plan, seed=3).acting is None  # open loop: no policy


def test_a_forecast_is_not_judged_by_episodes_of_the_policy_acting_otherwise():
    assessor = make_assessor(make_env(make_ensemble()))
    starts = torch.randn(12, 14, generator=torch.Generator().manual_seed(1)) * 0.1
    report = assessor.assess(starts, policy=stochastic_actor(), seed=0)
    success = torch.rand(12, 2, generator=torch.Generator().manual_seed(2)) < 0.5
    first = torch.where(success, 2, 6)
    mean = RealOutcomes(success, first, first + 1, acting="deterministic")
    refused = r"^{}: the real episodes' policy acted 'deterministic' .* imagined one 'random'"
    with pytest.raises(ValueError, match=refused.format("outcomes")):
        score_forecast(report, mean)
    with pytest.raises(ValueError, match=refused.format("real_success")):
        OutcomeCheck.from_outcomes(report, mean)
    check = OutcomeCheck.from_outcomes(report.competency["p_success"], mean.success)
    assert check.acting is None  # bare outcomes: not known
    known = OutcomeCheck.from_outcomes(
        report.competency["p_success"], mean, task=report.task, start_states=starts
    )
    assert known.acting == "deterministic"
    with pytest.raises(ValueError, match=refused.format("check")):
        report.with_forecast_check(known)
    sampled = RealOutcomes(success, first, first + 1, acting="random")
    assert set(score_forecast(report, sampled)) and OutcomeCheck.from_outcomes(report, sampled)
    assert report.with_forecast_check(OutcomeCheck.from_outcomes(report, sampled)).forecast_check

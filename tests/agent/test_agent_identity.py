"""A forecast is judged against real episodes of its own agent, judged by its own boundary.

A report, real outcomes and a forecast check each keep which agent acted (the digest of its
policy's weights) and, where a boundary judged them, its predicates; scoring or checking a
forecast against another agent's episodes, or against episodes judged by another radius, is
refused by name.
"""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import AdditiveGaussianModule

from rcvae_torchrl.agent import RealOutcomes, real_outcomes, score_forecast
from rcvae_torchrl.competency import SuccessBoundary
from rcvae_torchrl.data import acting_record, exploration_mode
from rcvae_torchrl.fingerprint import SETTINGS, agent_digest, weights_digest
from rcvae_torchrl.io import load_torch, save_torch
from rcvae_torchrl.training import OutcomeCheck
from tests.agent.test_exploration import point_mass, stochastic_actor
from tests.agent.worker_envs import plain_reset
from tests.competency.test_assessor import (
    DT,
    T,
    boundary,
    make_assessor,
    make_ensemble,
    make_env,
    obs_indices,
)

RANDOM, DETERMINISTIC = exploration_mode("random"), exploration_mode("deterministic")


def linear_policy(obs_dim: int, seed: int) -> TensorDictModule:
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(obs_dim, 2), nn.Tanh())
    return TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def test_the_weights_digest_names_the_weights_whatever_wraps_them():
    policy = linear_policy(4, seed=0)
    digest = weights_digest(policy)
    assert digest is not None and len(digest) == 64
    assert weights_digest(policy.module) == digest  # the bare network
    assert weights_digest(nn.Sequential(policy)) == digest  # under another name
    assert weights_digest(linear_policy(4, seed=0)) == digest  # a copy: the same values
    assert weights_digest(linear_policy(4, seed=1)) != digest
    with torch.no_grad():
        policy.module[0].bias[0] += 1e-6
    assert weights_digest(policy) != digest  # one weight changed
    assert weights_digest(nn.Tanh()) is None  # no weights: not known
    assert weights_digest(lambda td: td) is None


class Gains(nn.Module):
    """A scripted controller: no weights, its gains as settings."""

    def __init__(self, kp: float, target=(0.0, 0.0)) -> None:
        super().__init__()
        self.kp, self.target = kp, list(target)

    def forward(self, observation):
        return (-self.kp * (observation[..., :2] - torch.tensor(self.target))).clamp(-1, 1)


def test_a_controller_without_weights_is_known_by_its_class_and_settings():
    digest = agent_digest(Gains(2.0))
    assert digest.startswith(SETTINGS) and len(digest) == len(SETTINGS) + 64
    wrapped = TensorDictModule(Gains(2.0), in_keys=["observation"], out_keys=["action"])
    assert agent_digest(wrapped) == digest  # whatever wraps it
    assert agent_digest(nn.Sequential(Gains(2.0), nn.Tanh())) == digest
    assert agent_digest(Gains(2.0).train(False)) == digest  # not its training flag
    assert agent_digest(Gains(0.5)) != digest  # other gains
    assert agent_digest(Gains(2.0, target=(0.1, 0.0))) != digest  # another target
    assert agent_digest(nn.Sequential(Gains(2.0), Gains(2.0))) != digest  # two controllers
    policy = linear_policy(4, seed=0)  # with weights: the weights' digest, as before
    assert agent_digest(policy) == weights_digest(policy)
    assert agent_digest(nn.Tanh()) is None and agent_digest(lambda td: td) is None


_GAINS_SOURCE = """
import torch
from torch import nn

class Gains(nn.Module):
    def __init__(self, kp, target=(0.0, 0.0)):
        super().__init__()
        self.kp, self.target = kp, list(target)

    def forward(self, observation):
        return {body}
"""
_SAME = "(-self.kp * (observation[..., :2] - torch.tensor(self.target))).clamp(-1, 1)"


def _gains_class(body: str = _SAME, module: str = "__main__") -> type:
    """``Gains`` defined anew (another file, ``__main__``), with ``body`` as its action."""
    namespace = {"__name__": module}
    exec(_GAINS_SOURCE.format(body=body), namespace)
    return namespace["Gains"]


def test_a_controller_is_known_by_its_code_wherever_defined_and_by_all_its_gains():
    """A trial's team: a ``PD`` of the same name and gains but another ``forward`` (no
    damping) got the same digest, and so did gains kept private, in a dict or in an array."""
    assert agent_digest(_gains_class()(2.0)) == agent_digest(Gains(2.0))  # the same code
    assert agent_digest(_gains_class(module="agents")(2.0)) == agent_digest(Gains(2.0))
    other = _gains_class("(-self.kp * observation[..., :2]).clamp(-1, 1)")
    assert agent_digest(other(2.0)) != agent_digest(Gains(2.0))  # the same name, other code

    class Kept(nn.Module):
        def __init__(self, gains) -> None:
            super().__init__()
            self._kp, self.table, self.array = gains, {"kp": gains}, np.array([gains, 1.0])

        def forward(self, observation):
            return (-self._kp * observation[..., :2]).clamp(-1, 1)

    assert agent_digest(Kept(3.0)) == agent_digest(Kept(3.0))
    assert agent_digest(Kept(3.0)) != agent_digest(Kept(5.0))
    kept = Kept(3.0)
    kept.table["kp"] = 5.0  # in the dict alone
    assert agent_digest(kept) != agent_digest(Kept(3.0))
    kept = Kept(3.0)
    kept.array[1] = 2.0  # in the array alone
    assert agent_digest(kept) != agent_digest(Kept(3.0))


def test_another_controllers_episodes_are_warned_of_where_only_settings_tell_agents_apart():
    report, _ = _report_and_outcomes(Gains(0.5))
    assert report.agent == agent_digest(Gains(0.5))
    success = torch.rand(12, 2, generator=torch.Generator().manual_seed(2)) < 0.5
    first = torch.where(success, 2, 6)
    theirs = RealOutcomes(success, first, first + 1, agent=agent_digest(Gains(2.0)))
    said = r"^outcomes: the real episodes may be of another agent than the forecast's: settings"
    with pytest.warns(UserWarning, match=said):
        assert set(score_forecast(report, theirs))
    with pytest.warns(UserWarning, match=said.replace("outcomes", "real_success")):
        OutcomeCheck.from_outcomes(report, theirs)
    own = RealOutcomes(success, first, first + 1, agent=agent_digest(Gains(0.5)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert set(score_forecast(report, own))
    mixed = r"weights \(digest f{12}\) against the forecast's settings \(digest \w{12}\)"
    with pytest.warns(UserWarning, match=mixed):
        score_forecast(report, RealOutcomes(success, first, first + 1, agent="f" * 64))
    # a check of the other controller's episodes, though it passes, vouches for none of these
    real = torch.rand(12, 20, generator=torch.Generator().manual_seed(3)) < 0.5
    first = torch.where(real, 2, 6)
    passing = RealOutcomes(real, first, first + 1, agent=agent_digest(Gains(2.0)))
    halves = torch.full((12,), 0.5, dtype=torch.float64)
    check = OutcomeCheck.from_outcomes(halves, passing, task=report.task)
    assert check.passed and check.agent == agent_digest(Gains(2.0))
    with pytest.warns(UserWarning, match=said.replace("outcomes", "check")):
        attached = report.with_forecast_check(check)
    assert not attached.trustworthy
    assert "the forecast check attached may be of another agent" in attached.warning


def test_a_policy_that_acts_alike_in_every_mode_records_no_mode():
    assert acting_record(linear_policy(4, 0), RANDOM) is None
    assert acting_record(stochastic_actor(), RANDOM) == "random"
    assert acting_record(stochastic_actor(), DETERMINISTIC) == "deterministic"
    spec = Bounded(-1.0, 1.0, shape=(2,))
    noisy = TensorDictSequential(linear_policy(4, 0), AdditiveGaussianModule(spec))
    assert acting_record(noisy, DETERMINISTIC) == "deterministic"  # noise only when random
    assert acting_record(lambda td: td, RANDOM) == "random"  # not a module: may hold one


def _distance(observation: torch.Tensor) -> torch.Tensor:
    return observation[..., :2].norm(dim=-1)


def _real(policy, success, **kwargs) -> RealOutcomes:
    env = point_mass()
    starts = env.reset()["observation"].expand(3, -1).clone()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # copies: a deterministic policy
        return real_outcomes(
            env,
            policy,
            starts,
            runs_per_start=2,
            reset_to_state=plain_reset,
            max_steps=8,
            success=success,
            progress=False,
            **kwargs,
        )


def test_real_outcomes_keep_the_agent_and_the_boundary_and_read_them_back(tmp_path):
    policy = linear_policy(4, seed=0)
    near = SuccessBoundary.within_distance(_distance, 0.25, time_limit=8)
    outcomes = _real(policy, near.success_over_time, exploration_type="deterministic")
    assert outcomes.agent == weights_digest(policy)
    assert outcomes.acting is None  # a deterministic network: the mode does not matter
    assert outcomes.predicates == near.predicates
    flagged = _real(policy, lambda obs: obs[..., :2].norm(dim=-1) < 0.25)
    assert flagged.predicates is None  # a function of one's own: not a boundary's
    again = RealOutcomes.from_dict(outcomes.as_dict())
    assert (again.agent, again.acting, again.predicates) == (
        outcomes.agent,
        None,
        near.predicates,
    )
    save_torch(tmp_path / "real.pt", outcomes.as_dict())
    stored = RealOutcomes.from_dict(load_torch(tmp_path / "real.pt"))
    assert stored.agent == outcomes.agent and stored.predicates == near.predicates
    assert outcomes[1:].agent == outcomes.agent and outcomes[1:].predicates == near.predicates
    with pytest.raises(TypeError, match=r"^values\['agent'\]: expected a str"):
        RealOutcomes.from_dict({**outcomes.as_dict(), "agent": 3})
    other = SuccessBoundary.within_distance(_distance, 0.3, time_limit=8)
    assert other.predicates != near.predicates  # another radius, another digest


def _report_and_outcomes(policy, **known):
    assessor = make_assessor(make_env(make_ensemble()))
    starts = torch.randn(12, 14, generator=torch.Generator().manual_seed(1)) * 0.1
    report = assessor.assess(starts, policy=policy, seed=0)
    success = torch.rand(12, 2, generator=torch.Generator().manual_seed(2)) < 0.5
    first = torch.where(success, 2, 6)
    return report, RealOutcomes(success, first, first + 1, **known)


def test_a_forecast_is_not_judged_by_another_agent_s_episodes():
    agent, other = linear_policy(14, seed=0), linear_policy(14, seed=1)
    report, own = _report_and_outcomes(agent, agent=weights_digest(agent))
    assert report.agent == weights_digest(agent) and report.acting is None
    assert set(score_forecast(report, own))
    theirs = RealOutcomes(own.success, own.first_step, own.steps, agent=weights_digest(other))
    refused = r"^{}: the real episodes are of another agent than the forecast's: .*\(digest {}\)"
    mine = weights_digest(agent)[:12]
    with pytest.raises(ValueError, match=refused.format("outcomes", mine)):
        score_forecast(report, theirs)
    with pytest.raises(ValueError, match=refused.format("real_success", mine)):
        OutcomeCheck.from_outcomes(report, theirs)
    # a check made of bare forecasts and the other agent's outcomes keeps that agent
    check = OutcomeCheck.from_outcomes(
        report.competency["p_success"],
        theirs,
        task=report.task,
        start_states=report.data["observation"],
    )
    assert check.agent == weights_digest(other)
    with pytest.raises(ValueError, match=refused.format("check", mine)):
        report.with_forecast_check(check)
    kept = OutcomeCheck.from_dict(json.loads(json.dumps(check.as_dict())))
    assert kept.agent == check.agent
    with pytest.raises(ValueError, match=refused.format("check", mine)):
        report.with_forecast_check(kept)
    # outcomes that do not know their agent are not compared
    bare = RealOutcomes(own.success, own.first_step, own.steps)
    assert set(score_forecast(report, bare))
    assert report.with_forecast_check(OutcomeCheck.from_outcomes(report, own)).forecast_check


def test_a_deterministic_network_s_episodes_in_any_mode_judge_its_forecast():
    agent = linear_policy(14, seed=0)
    report, own = _report_and_outcomes(agent, agent=weights_digest(agent))
    assert report.acting is None  # sampled by default, but it draws nothing
    # its real episodes run by its mean, as a caller may well ask: the same agent
    by_mean = RealOutcomes(
        own.success, own.first_step, own.steps, acting=None, agent=weights_digest(agent)
    )
    assert set(score_forecast(report, by_mean))


def test_a_forecast_is_not_scored_against_episodes_judged_by_another_boundary():
    agent = linear_policy(14, seed=0)
    report, own = _report_and_outcomes(agent, predicates=boundary().predicates)
    assert report.predicates == boundary().predicates
    assert set(score_forecast(report, own))
    wider = SuccessBoundary.ball(
        obs_indices("ball"), 0.05, target=obs_indices("target"), time_limit=T, dt=DT
    )
    judged = RealOutcomes(own.success, own.first_step, own.steps, predicates=wider.predicates)
    refused = r"^{}: the real episodes were judged by another boundary than the forecast's"
    with pytest.raises(ValueError, match=refused.format("outcomes")):
        score_forecast(report, judged)
    with pytest.raises(ValueError, match=refused.format("real_success")):
        OutcomeCheck.from_outcomes(report, judged)


def test_a_forecast_is_not_scored_against_episodes_from_other_starts_or_order():
    agent = linear_policy(14, seed=0)
    report, own = _report_and_outcomes(agent)
    starts = report.data["observation"]
    kept = RealOutcomes(own.success, own.first_step, own.steps, starts=starts.double())
    assert set(score_forecast(report, kept)) and OutcomeCheck.from_outcomes(report, kept)
    assert torch.equal(kept[2:5].starts, starts[2:5].double())  # indexing keeps them
    assert torch.equal(RealOutcomes.from_dict(kept.as_dict()).starts, kept.starts)
    order = torch.arange(11, -1, -1)
    shuffled = RealOutcomes(own.success, own.first_step, own.steps, starts=starts[order])
    other = r"^{}: expected real episodes from the forecast's start states, in its order, got "
    with pytest.raises(ValueError, match=other.format("outcomes") + r"12 of 12 other ones"):
        score_forecast(report, shuffled)
    with pytest.raises(ValueError, match=other.format("real_success") + r"12 of 12 other"):
        OutcomeCheck.from_outcomes(report, shuffled)
    moved = starts.clone()
    moved[3] += 0.5
    one_off = RealOutcomes(own.success, own.first_step, own.steps, starts=moved)
    with pytest.raises(ValueError, match=r"1 of 12 other ones \(the first: start 3\)"):
        score_forecast(report, one_off)
    with pytest.raises(
        ValueError,
        match=r"^outcomes: expected the real outcomes of the forecast's 12 start "
        r"states, got 3$",
    ):
        score_forecast(report, own[:3])
    with pytest.raises(ValueError, match=r"^outcomes: expected the real outcomes of the forecast"):
        score_forecast(report.competency["p_success"], own[:3])


def test_real_outcomes_keep_their_start_states():
    policy = linear_policy(4, seed=0)
    near = SuccessBoundary.within_distance(_distance, 0.25, time_limit=8)
    outcomes = _real(policy, near.success_over_time)
    env = point_mass()
    assert torch.equal(outcomes.starts, env.reset()["observation"].expand(3, -1))


def test_a_comparison_of_two_agents_is_scored_against_their_real_episodes():
    from rcvae_torchrl.agent import score_comparison
    from rcvae_torchrl.competency import compare_agents

    first, second = linear_policy(14, seed=0), linear_policy(14, seed=1)
    a, _ = _report_and_outcomes(first)
    b, _ = _report_and_outcomes(second)
    starts = a.data["observation"]
    success_a = torch.zeros(12, 4, dtype=torch.bool)
    success_a[:6] = True  # agent a always succeeds from the first 6 starts, never after
    success_b = torch.zeros(12, 4, dtype=torch.bool)

    def outcomes(success, policy):
        first_step = torch.where(success, 2, 6)
        return RealOutcomes(
            success, first_step, first_step + 1, agent=weights_digest(policy), starts=starts
        )

    real_a, real_b = outcomes(success_a, first), outcomes(success_b, second)
    scored = score_comparison(a, b, real_a, real_b)
    compared = compare_agents(a, b)
    # per-start differences 1 or 0: Student's t with 11 degrees of freedom
    half = 2.200985 * math.sqrt(12 / 11 * 0.25) / math.sqrt(12)
    assert scored["real"] == pytest.approx(0.5)
    assert (scored["real_low"], scored["real_high"]) == pytest.approx((0.5 - half, 0.5 + half))
    assert scored["forecast"] == pytest.approx(compared.mean)
    assert scored["gap"] == pytest.approx(compared.mean - 0.5)
    per_start = compared.difference - torch.tensor([1.0] * 6 + [0.0] * 6, dtype=torch.float64)
    assert scored["per_start_mae"] == pytest.approx(float(per_start.abs().mean()))
    assert scored["same_sign"] == float(compared.mean > 0)
    with pytest.raises(ValueError, match=r"^real_b: the real episodes are of another agent"):
        score_comparison(a, b, real_a, outcomes(success_b, first))  # a's episodes as b's
    with pytest.raises(ValueError, match=r"^real_a: expected the real outcomes of the reports' 12"):
        score_comparison(a, b, real_a[:3], real_b)
    with pytest.raises(TypeError, match=r"^real_b: expected the RealOutcomes of real_outcomes"):
        score_comparison(a, b, real_a, success_b)

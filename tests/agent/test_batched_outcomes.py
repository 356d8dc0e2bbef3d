"""Real outcomes run N at a time in a batched env equal the one-env run, episode by episode."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import pytest
import torch

from rcvae_torchrl.agent import real_outcomes
from rcvae_torchrl.competency import SuccessBoundary
from rcvae_torchrl.envs import (
    ball_to_target,
    make_batched_pusher_env,
    make_pusher_env,
    pusher_success,
    reset_to_state,
)
from rcvae_torchrl.envs.scripted import make_scripted_policy
from tests.pusher_fixtures import pusher_starts


@pytest.mark.parametrize("terminate", [True, False])
def test_batched_outcomes_equal_the_one_env_run(terminate):
    starts, kwargs = pusher_starts(2), dict(time_limit=3.0, terminate_on_success=terminate)
    args = dict(
        runs_per_start=3,  # 6 episodes over 4 sub-envs: a padded second chunk
        reset_to_state=reset_to_state,
        max_steps=45,  # shorter than the 60-step episode: some runs neither end nor succeed
        trace=ball_to_target,
        seed=2,
        progress=False,
        policy_rows=64,  # the scripted pusher's float32 actions then do not depend on the batch
        keep_observations=True,
    )
    policy = make_scripted_policy()
    serial = real_outcomes(
        make_pusher_env("stochastic", action_noise_std=1.0, **kwargs), policy, starts, **args
    )
    batched = real_outcomes(
        make_batched_pusher_env(4, "stochastic", action_noise_std=1.0, **kwargs),
        policy,
        starts,
        **args,
    )
    assert batched.success.shape == (2, 3) and batched.trace.shape == (2, 3, 45)
    for name in ("success", "first_step", "steps"):
        assert torch.equal(getattr(batched, name), getattr(serial, name)), name
    torch.testing.assert_close(batched.trace, serial.trace, equal_nan=True)
    assert not torch.equal(batched.trace[:, 0], batched.trace[:, 1])  # each run its own noise
    # the kept observations: the same in both, NaN after each episode, and the trace's states
    assert batched.observation.shape == (2, 3, 45, 14)
    torch.testing.assert_close(batched.observation, serial.observation, equal_nan=True)
    ran = ~batched.observation.isnan().any(-1)
    assert torch.equal(ran, ~batched.trace.isnan())
    torch.testing.assert_close(ball_to_target(batched.observation)[ran], batched.trace[ran])


def test_batched_outcomes_by_a_success_function():
    starts = pusher_starts(1)
    out = real_outcomes(
        make_batched_pusher_env(3, "deterministic", time_limit=3.0, terminate_on_success=False),
        make_scripted_policy(),
        starts,
        runs_per_start=3,
        reset_to_state=reset_to_state,
        max_steps=60,
        success=lambda o: pusher_success(o, radius=0.1),
        trace=ball_to_target,
        progress=False,
    )
    hit = out.trace <= 0.1
    first = torch.where(hit.any(-1), hit.float().argmax(-1), torch.tensor(60))
    assert torch.equal(out.first_step, first) and torch.equal(out.success, hit.any(-1))
    with pytest.raises(ValueError, match="env: expected an env with batch_size"):
        real_outcomes(
            SimpleNamespace(batch_size=torch.Size([1, 2])),
            make_scripted_policy(),
            starts,
            runs_per_start=1,
            reset_to_state=reset_to_state,
            max_steps=2,
        )


def test_a_success_that_depends_on_time_counts_from_each_episodes_start():
    """A function of an episode's observations ``[T, S]`` sees one episode at a time, in a
    batched env and in one env alike: a survival boundary decides at its own step in every
    episode, and a trace is every episode's own."""
    from rcvae_torchrl.competency import SuccessBoundary

    starts = pusher_starts(2)
    lasted = SuccessBoundary.survival(lambda o: o[..., 0] > 2.0, time_limit=5)  # never fails
    args = dict(
        runs_per_start=2,
        reset_to_state=reset_to_state,
        max_steps=8,
        success=lasted.success_over_time,
        trace=lambda o: torch.arange(o.shape[-2], dtype=torch.float32).expand(o.shape[:-1]),
        progress=False,
    )
    kwargs = dict(time_limit=3.0, terminate_on_success=False)
    for env in (make_pusher_env("deterministic", **kwargs), make_batched_pusher_env(3, **kwargs)):
        out = real_outcomes(env, make_scripted_policy(), starts, **args)
        assert out.success.all() and (out.first_step == 4).all(), type(env).__name__
        assert torch.equal(out.trace, torch.arange(8.0).expand(2, 2, 8))


@pytest.mark.parametrize("batched", [False, True])
def test_kept_episodes_judged_by_another_boundary_equal_a_run_judged_by_it(batched):
    starts, env_kwargs = pusher_starts(2), dict(time_limit=3.0, terminate_on_success=False)
    near, far = (
        SuccessBoundary.within_distance(ball_to_target, radius, time_limit=60, dt=0.05)
        for radius in (0.03, 0.12)
    )

    def run(boundary, keep=False):
        env = (
            make_batched_pusher_env(3, "stochastic", action_noise_std=1.0, **env_kwargs)
            if batched
            else make_pusher_env("stochastic", action_noise_std=1.0, **env_kwargs)
        )
        return real_outcomes(
            env,
            make_scripted_policy(),
            starts,
            runs_per_start=3,
            reset_to_state=reset_to_state,
            max_steps=60,
            success=boundary.success_over_time,
            seed=4,
            progress=False,
            policy_rows=64,
            keep_observations=keep,
        )

    kept = run(near, keep=True)
    assert kept.predicates == near.predicates
    direct = run(far)
    judged = kept.judged_by(far)
    assert judged.predicates == far.predicates != near.predicates
    assert float(judged.success.float().mean()) > float(kept.success.float().mean())
    for name in ("success", "first_step", "steps"):
        assert torch.equal(getattr(judged, name), getattr(direct, name)), name
    again = judged.judged_by(near)  # judged back: the first outcomes
    for name in ("success", "first_step", "steps"):
        assert torch.equal(getattr(again, name), getattr(kept, name)), name
    with pytest.raises(ValueError, match=r"^observation: these outcomes kept no observations"):
        direct.judged_by(near)
    with pytest.raises(TypeError, match=r"^boundary: expected a SuccessBoundary, got function"):
        kept.judged_by(ball_to_target)
    # a boundary of other steps (a dt other than the env's 0.05 s): named with its time limit
    finer = SuccessBoundary.within_distance(ball_to_target, 0.12, time_limit_s=3.0, dt=0.01)
    with pytest.raises(
        ValueError,
        match=r"^boundary: expected a time limit within the kept episodes' 60 steps, got 300 "
        r"steps \(300 · dt 0.01 s\); a dt other than the env's step",
    ):
        kept.judged_by(finer)


class _Spread(torch.nn.Module):
    """A stochastic arm: loc and scale of its two actions from the observation."""

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = -observation[..., 4:6].clamp(-1, 1)
        return loc, torch.full_like(loc, 0.5)


def sampling_arm():
    """A ProbabilisticActor for the Pusher's arm (sampled by default)."""
    from tensordict.nn import TensorDictModule
    from torchrl.modules import ProbabilisticActor, TanhNormal

    return ProbabilisticActor(
        TensorDictModule(_Spread(), in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        out_keys=["action"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0},
    )


def test_a_sampling_policy_run_side_by_side_is_said_to_draw_otherwise():
    actor = sampling_arm()
    args = dict(
        runs_per_start=2, reset_to_state=reset_to_state, max_steps=5, progress=False, seed=1
    )
    side_by_side = r"^policy: it samples its actions .* with a batched env of 2 its episodes"
    with pytest.warns(UserWarning, match=side_by_side):
        real_outcomes(make_batched_pusher_env(2), actor, pusher_starts(1), **args)
    with warnings.catch_warnings(record=True) as caught:  # by its mean: the one-env episodes
        warnings.simplefilter("always")
        real_outcomes(
            make_batched_pusher_env(2),
            actor,
            pusher_starts(1),
            exploration_type="deterministic",
            **args,
        )
    assert not [w for w in caught if "samples its actions" in str(w.message)]


def test_a_longer_survival_is_not_taken_for_a_shorter_deadlines_outcome():
    """A trial's case: real episodes judged by a survival boundary of 8 steps, scored against a
    forecast of 5 (the same failure predicate, so the same predicates): ``within(5)`` counted
    every episode that lasted 8 steps a failure (its success came at step 7, past 5)."""
    from rcvae_torchrl.agent import RealOutcomes

    never = lambda o: o[..., 0] > 2.0  # noqa: E731 (the pusher's arm angle never gets there)
    longer, shorter = (SuccessBoundary.survival(never, time_limit=n) for n in (8, 5))
    assert longer.predicates == shorter.predicates
    env = make_pusher_env("deterministic", time_limit=3.0, terminate_on_success=False)

    def run(starts: int, success, keep: bool = False):
        return real_outcomes(
            env,
            make_scripted_policy(),
            pusher_starts(starts),
            runs_per_start=1,
            reset_to_state=reset_to_state,
            max_steps=8,
            success=success,
            progress=False,
            keep_observations=keep,
        )

    out = run(2, longer.success_over_time, keep=True)
    assert out.survival_limit == 8 and bool(out.success.all())
    said = r"^steps: these outcomes were judged by a survival boundary of 8 steps \(a success: "
    with pytest.raises(ValueError, match=said):
        out.within(5)
    assert bool(out.within(8).success.all())
    # judged again by the forecast's boundary, they answer its deadline
    judged = out.judged_by(shorter)
    assert judged.survival_limit == 5 and bool(judged.within(5).success.all())
    # kept by a record and by a subset; a reach boundary's outcomes have none
    assert RealOutcomes.from_dict(out.as_dict()).survival_limit == 8
    assert out[:1].survival_limit == 8
    reach = SuccessBoundary.within_distance(ball_to_target, 0.03, time_limit=8)
    assert out.judged_by(reach).survival_limit is None
    # a record written before survival_limit: said when read, and refused by a survival
    # forecast of the same predicates (its outcomes were read as 0 for 1 before)
    older = {k: v for k, v in out.as_dict().items() if k != "survival_limit"}
    with pytest.warns(UserWarning, match=r"^values: a record written before RealOutcomes kept"):
        unknown = RealOutcomes.from_dict(older)
    report = SimpleNamespace(predicates=shorter.predicates, survival=True)
    from rcvae_torchrl.competency import check_same_predicates

    with pytest.raises(ValueError, match=r"^outcomes: the real episodes were judged by the fo"):
        check_same_predicates(report, unknown)
    check_same_predicates(report, out)  # its limit known: within() decides
    # a limit is a whole number of steps >= 1; another method of a boundary labels nothing
    for bad in (0, -3, True, "5"):
        with pytest.raises(ValueError, match=r"^survival_limit: expected None or a survival"):
            RealOutcomes(out.success, out.first_step, out.steps, survival_limit=bad)
    with pytest.raises(ValueError, match=r"^values\['survival_limit'\]: expected a whole"):
        RealOutcomes.from_dict({**out.as_dict(), "survival_limit": 5.9})
    ended = run(1, longer.ended_over_time)
    assert ended.predicates is None and ended.survival_limit is None

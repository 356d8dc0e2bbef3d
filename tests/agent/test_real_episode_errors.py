"""Real episodes whose outcome the library cannot know, and policies it cannot call, are refused
with errors that say what to do."""

from __future__ import annotations

import re
import warnings

import pytest
import torch

from rcvae_torchrl.agent import real_outcomes, run_episodes
from rcvae_torchrl.competency import SuccessBoundary, time_to_success_scores
from rcvae_torchrl.envs import make_batched_pusher_env, make_pusher_env, reset_to_state
from tests.agent.worker_envs import plain_reset, terminating_point_mass
from tests.pusher_fixtures import pusher_starts

CUT = r"cut short by the env itself .* max_steps=45 .* after 20 steps.*DMControlEnv"


def _still(td):  # the arm does not move: the ball is never pushed onto the target
    return td.set("action", torch.zeros(*td.batch_size, 2))


def _never(observation):
    return torch.zeros(observation.shape[:-1], dtype=torch.bool)


def _at_once(observation):
    return torch.ones(observation.shape[:-1], dtype=torch.bool)


@pytest.mark.parametrize("batched", [False, True])
def test_an_env_time_limit_shorter_than_max_steps_is_refused(batched):
    env = make_batched_pusher_env(2, time_limit=1.0) if batched else make_pusher_env(time_limit=1.0)
    # checked as they run: the first episode alone, or the two run together
    which = "2 of the 2 episodes run together were" if batched else "an episode was"
    with pytest.raises(ValueError, match=f"^env: {which} {CUT}"):
        run_episodes(env, _still, seeds=[0, 1], max_steps=45, success=_never, progress=False)
    # run to the env's own limit: a failure, known
    stats = run_episodes(env, _still, seeds=[0, 1], max_steps=20, success=_never, progress=False)
    assert not stats.success.any() and stats.steps.tolist() == [20, 20]
    # a success before the cut is known too
    stats = run_episodes(env, _still, seeds=[0, 1], max_steps=45, success=_at_once, progress=False)
    assert stats.success.all() and stats.steps.tolist() == [1, 1]


@pytest.mark.parametrize("batched", [False, True])
def test_real_outcomes_refuse_episodes_the_env_cut_short(batched):
    env = make_batched_pusher_env(3, time_limit=1.0) if batched else make_pusher_env(time_limit=1.0)
    args = dict(runs_per_start=2, reset_to_state=reset_to_state, success=_never, progress=False)
    with pytest.raises(ValueError, match=CUT):
        real_outcomes(env, _still, pusher_starts(2), max_steps=45, **args)
    out = real_outcomes(env, _still, pusher_starts(2), max_steps=20, **args)
    assert not out.success.any() and (out.steps == 20).all()


@pytest.mark.parametrize("batched", [False, True])
def test_an_episode_cut_after_the_boundary_decided_it_is_known(batched):
    """A pendulum trial: ``StepCounter(50)``, ``max_steps=60`` and a 40-step deadline were
    refused, though every outcome was known at step 40. With the boundary's
    ``success_over_time`` as ``success``, an episode the env cuts after the boundary's time
    limit is not refused."""
    env = make_batched_pusher_env(3, time_limit=1.0) if batched else make_pusher_env(time_limit=1.0)
    args = dict(runs_per_start=2, reset_to_state=reset_to_state, progress=False)
    decided = SuccessBoundary(_never, time_limit=15)  # the env cuts at 20, max_steps is 45
    out = real_outcomes(
        env, _still, pusher_starts(2), max_steps=45, success=decided.success_over_time, **args
    )
    assert not out.success.any() and (out.steps == 20).all()
    late = SuccessBoundary(_never, time_limit=30)  # decided after the cut: unknown
    with pytest.raises(ValueError, match=r"cut short by the env itself .* max_steps=30 "):
        real_outcomes(
            env, _still, pusher_starts(2), max_steps=45, success=late.success_over_time, **args
        )


class _TensorPolicy(torch.nn.Module):
    """A tensor policy ``observation -> action``, not wired to TensorDict keys."""

    def forward(self, observation):
        return torch.zeros(*observation.shape[:-1], 2)


@pytest.mark.parametrize("batched", [False, True])
def test_a_tensor_policy_in_a_real_env_is_named_with_how_to_wire_it(batched):
    from rcvae_torchrl.agent import make_policy_module

    env = make_batched_pusher_env(2) if batched else make_pusher_env()
    args = dict(seeds=[0, 1], max_steps=5, success=_never, progress=False)
    with pytest.raises(
        TypeError,
        match=r"policy: calling _TensorPolicy in the env failed.*"
        r"TensorDictModule\(policy, in_keys=\[\"observation\"\]",
    ):
        run_episodes(env, _TensorPolicy(), **args)
    assert run_episodes(env, make_policy_module(_TensorPolicy()), **args).steps.tolist() == [5, 5]


class _Acts(torch.nn.Module):
    """A tensor policy whose action is ``value`` of ``shape`` (after the batch), from step
    ``after`` on (zeros before)."""

    def __init__(self, shape, value=0.0, after=0):
        super().__init__()
        self.shape, self.value, self.after, self.calls = shape, value, after, 0

    def forward(self, observation):
        self.calls += 1
        fill = self.value if self.calls > self.after else 0.0
        return torch.full((*observation.shape[:-1], *self.shape), fill)


@pytest.mark.parametrize("batched", [False, True])
def test_a_policy_s_wrong_shape_or_nan_action_is_named_before_the_env_acts_on_it(batched):
    from rcvae_torchrl.agent import make_policy_module

    env = make_batched_pusher_env(2) if batched else make_pusher_env()
    batch = [2] if batched else []
    args = dict(seeds=[0, 1], max_steps=5, success=_never, progress=False)
    for shape in [(), (3,)]:  # the Pusher's action is [2]
        wanted = re.escape(
            f"policy: expected actions of shape {(*batch, 2)} (the env's batch {batch} and its "
            f"action_spec's [2]), got {(*batch, *shape)} at step 0"
        )
        with pytest.raises(ValueError, match=f"^{wanted}$"):
            run_episodes(env, make_policy_module(_Acts(shape)), **args)
    # a NaN at the third step: named with its step, before the simulator steps on it
    n = 2 if batched else 1
    with pytest.raises(
        ValueError,
        match=f"^policy: expected finite actions, got {2 * n} of {2 * n} NaN or inf at step 2; ",
    ):
        run_episodes(env, make_policy_module(_Acts((2,), float("nan"), after=2)), **args)
    # and real_outcomes, whose episodes run the same way
    with pytest.raises(ValueError, match=r"^policy: expected actions of shape"):
        real_outcomes(
            env,
            make_policy_module(_Acts((1,))),
            pusher_starts(2),
            runs_per_start=1,
            reset_to_state=reset_to_state,
            success=_never,
            max_steps=5,
            progress=False,
        )


def test_recorded_actions_of_another_shape_are_named_by_shape_not_by_bounds():
    from tensordict import TensorDict

    from rcvae_torchrl.data import check_actions

    data = TensorDict({"action": torch.zeros(4, 3)}, batch_size=[4])
    with pytest.raises(
        ValueError,
        match=r"^policy: expected actions \[\.\.\., 2\] \(the env's action_spec shape "
        r"\[2\]\), got shape \(4, 3\)$",
    ):
        check_actions(make_pusher_env(), data)


@pytest.mark.parametrize("batched", [False, True])
def test_bad_starts_and_a_reset_that_returns_nothing_are_named(batched):
    env = make_batched_pusher_env(2) if batched else make_pusher_env()
    args = dict(runs_per_start=1, success=_never, max_steps=5, progress=False)
    starts = pusher_starts(2)
    starts[1, 3] = float("nan")
    with pytest.raises(ValueError, match=r"^starts: expected finite values, got 1 NaN"):
        real_outcomes(env, _still, starts, reset_to_state=reset_to_state, **args)

    def forgets_to_return(env, start):
        reset_to_state(env, start)

    with pytest.raises(TypeError, match=r"^reset_to_state: expected the env's reset TensorDict"):
        real_outcomes(env, _still, pusher_starts(2), reset_to_state=forgets_to_return, **args)
    # an env's seed is a 32-bit integer: seeds past it are named before any episode runs
    too_far = r"^seed: expected episode seeds below 2\*\*32 .* got seed=42950, .* seed <= 42948"
    with pytest.raises(ValueError, match=too_far):
        real_outcomes(
            env, _still, pusher_starts(2), reset_to_state=reset_to_state, seed=42950, **args
        )


def test_a_score_of_plain_outcomes_names_the_function_for_them():
    from rcvae_torchrl.agent import score_forecast

    with pytest.raises(TypeError, match=r"outcomes: expected the RealOutcomes .*, got Tensor; .*"):
        score_forecast(torch.full((2,), 0.5), torch.ones(2, 3, dtype=torch.bool))


def test_episodes_shorter_than_the_boundary_s_time_limit_are_refused():
    from rcvae_torchrl.competency import SuccessBoundary

    stay = SuccessBoundary.survival(_never, time_limit=20)
    args = dict(runs_per_start=1, reset_to_state=reset_to_state, progress=False)
    with pytest.raises(
        ValueError, match=r"^max_steps: expected at least the boundary's time_limit"
    ):
        real_outcomes(
            make_pusher_env(),
            _still,
            pusher_starts(2),
            max_steps=10,
            success=stay.success_over_time,
            **args,
        )
    out = real_outcomes(
        make_pusher_env(),
        _still,
        pusher_starts(2),
        max_steps=20,
        success=stay.success_over_time,
        **args,
    )
    assert out.success.all()  # nothing fails: every episode survives its 20 steps


def test_episodes_judged_by_the_env_s_flag_and_cut_before_a_deadline_are_refused_there():
    """A trial judged a 25-step forecast by the env's own flag in 10-step episodes: scored
    0.559 against 0.008 real ("too optimistic") with nothing said, while a boundary's
    success_over_time is refused at once. With a flag, real_outcomes cannot tell the
    deadline: the outcomes keep their max_steps, and scoring them against a longer one is
    refused; the name of a flag given as ('next', name) is corrected."""
    from rcvae_torchrl.agent import RealOutcomes
    from rcvae_torchrl.training import OutcomeCheck

    args = dict(runs_per_start=1, reset_to_state=reset_to_state, progress=False)
    out = real_outcomes(make_pusher_env(), _still, pusher_starts(2), max_steps=10, **args)
    assert out.max_steps == 10 and out[0:1].max_steps == 10 and not out.success.any()
    assert RealOutcomes.from_dict(out.as_dict()).max_steps == 10
    assert out.within(10).success.shape == (2, 1) and out.within(6).max_steps == 10
    with pytest.raises(
        ValueError,
        match=r"^steps: expected real episodes run for at least the forecast's deadline of 25 "
        r"steps, got episodes of at most max_steps=10: the 2 of 2 without a success by then "
        r"have no known outcome within the deadline .*max_steps >= 25$",
    ):
        out.within(25)

    class Report:  # what OutcomeCheck reads of a report with a 25-step deadline
        time_limit, acting, competency = 25, None, {"p_success": torch.full((2,), 0.5)}

    with pytest.raises(ValueError, match=r"^steps: expected real episodes run for at least"):
        OutcomeCheck.from_outcomes(Report(), out)
    with pytest.raises(KeyError, match=r"read under 'next': pass success='succes'"):
        real_outcomes(
            make_pusher_env(),
            _still,
            pusher_starts(1),
            max_steps=3,
            success=("next", "succes"),
            **args,
        )


def test_a_trace_of_several_values_per_step_is_named():
    """A trial traced two distances per step: the outcomes failed with "The expanded size of
    the tensor (50) must match the existing size (100)", naming neither trace nor its shape."""
    args = dict(runs_per_start=1, reset_to_state=reset_to_state, progress=False, max_steps=4)
    with pytest.raises(
        ValueError,
        match=r"^trace: expected one value per step of the observations \(4, 14\) "
        r"\(\[\.\.\., T, S\] -> \[\.\.\., T\] = \(4,\)\), got \(4, 2\)",
    ):
        real_outcomes(
            make_pusher_env(), _still, pusher_starts(1), trace=lambda o: o[..., :2], **args
        )
    out = real_outcomes(
        make_pusher_env(), _still, pusher_starts(1), trace=lambda o: o[..., 0], **args
    )
    assert out.trace.shape == (1, 1, 4) and torch.isfinite(out.trace).all()


def test_outcomes_of_some_start_states():
    from rcvae_torchrl.agent import RealOutcomes

    g = torch.Generator().manual_seed(0)
    success = torch.rand(5, 3, generator=g) < 0.5
    steps = torch.randint(1, 40, (5, 3), generator=g)
    trace = torch.rand(5, 3, 40, generator=g)
    out = RealOutcomes(success, torch.where(success, steps - 1, 40), steps, trace)
    assert len(out) == 5
    mask = torch.tensor([True, False, True, False, True])
    for index in (slice(1, 4), [0, 4], mask):
        part = out[index]
        for name, value in out.as_dict().items():
            if value is None:  # a label not known (survival_limit): kept as it is
                assert part.as_dict()[name] is None, name
                continue
            assert torch.equal(part.as_dict()[name], value[index])
    from rcvae_torchrl.agent import score_forecast
    from rcvae_torchrl.competency import validate_forecasts

    forecast = torch.rand(5, generator=g)  # the scores of a subset: its starts' outcomes
    want = validate_forecasts(forecast[mask], success[mask])
    assert score_forecast(forecast[mask], out[mask]) == want
    with pytest.raises(IndexError, match=r"index: expected a slice, .* outcomes\[i : i \+ 1\]"):
        out[2]


def test_a_report_is_scored_against_successes_within_its_own_deadline():
    """Real episodes run past the forecast's deadline: a success after it is a failure of the
    task the forecast answers, when the report itself is scored."""
    from rcvae_torchrl.agent import RealOutcomes, score_forecast
    from rcvae_torchrl.competency import CompetencyAssessor, SuccessBoundary, validate_forecasts
    from rcvae_torchrl.model_env import make_rcvae_env
    from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble

    torch.manual_seed(0)
    model = RCVAEEnsemble(RCVAEConfig(2, 1, hidden_dim=8, mlp_dim=8), 2)
    boundary = SuccessBoundary(lambda observation: observation[..., 0] > 0, time_limit=5)
    model_env = make_rcvae_env(
        model, None, lambda observation, action: observation[..., :1], boundary.success
    )
    assessor = CompetencyAssessor(model_env, boundary, bin_width=0.1, samples_per_member=4)
    report = assessor.assess(torch.zeros(3, 2), actions=torch.zeros(5, 1), seed=0)
    first = torch.tensor([[2, 7], [4, 9], [9, 12]])  # 12: never, in 12-step episodes
    success = first < 12
    outcomes = RealOutcomes(success, first, torch.where(success, first + 1, 12))
    p = report.competency["p_success"]
    scored = score_forecast(report, outcomes)
    assert {k: v for k, v in scored.items() if not k.startswith("time_")} == validate_forecasts(
        p, first < 5
    )
    assert score_forecast(p, outcomes) == validate_forecasts(p, success)  # no deadline known
    assert score_forecast(p, outcomes) != score_forecast(report, outcomes)
    # the times to success too, both censored at the deadline: a real success at step 7 or
    # later is "not within 5", as the imagined times say it
    within = outcomes.within(5)
    assert within.first_step.tolist() == [[2, 5], [4, 5], [5, 5]]
    imagined = report.competency["time_to_success", "first_step"].flatten(1).clamp_max(5)
    times = time_to_success_scores(imagined.double(), within.first_step.double(), horizon=5)
    assert {k: scored[f"time_to_success_{k}"] for k in times} == times


def test_real_times_past_the_forecast_s_horizon_are_refused():
    """A cart-pole trial scored a 2-s forecast (50 steps) against real times of up to 8 s:
    CRPS skill -2.34, where the times censored at 50 steps gave +0.03, with nothing said."""
    forecast = torch.tensor([[10.0, 50.0], [20.0, 30.0]])
    real = torch.tensor([[12.0, 120.0], [50.0, 25.0]])
    with pytest.raises(
        ValueError, match=r"^real_steps: expected first-success steps of at most the horizon 50 "
    ):
        time_to_success_scores(forecast, real, horizon=50)
    censored = time_to_success_scores(forecast, real.clamp_max(50), horizon=50)
    assert censored == time_to_success_scores(forecast, real.clamp_max(50))
    with pytest.raises(ValueError, match=r"^forecast_steps: expected first-success steps"):
        time_to_success_scores(forecast + 45, real.clamp_max(50), horizon=50)


def test_runs_that_repeat_one_episode_are_said_to_be_copies():
    """reset_by_seed replays a start's seeded reset: an env without noise of its own beyond
    the reset (here a deterministic one) repeats one episode in every run, and the runs are
    said to be copies, not draws of the start's chance; with actuator noise in a transform,
    which each run's seed restarts, the runs differ and nothing is said."""
    import warnings

    from tensordict.nn import TensorDictModule
    from torchrl.envs import DMControlEnv

    from rcvae_torchrl.agent import draw_starts, reset_by_seed
    from rcvae_torchrl.data import ActionNoise, prepare_env

    def make(noise: float = 0.0):
        env, _ = prepare_env(DMControlEnv("point_mass", "easy"))
        return env.append_transform(ActionNoise(noise)) if noise else env

    agent = TensorDictModule(lambda o: -o[..., :2], in_keys=["observation"], out_keys=["action"])
    starts = draw_starts(make(), seeds=[3, 4])
    args = dict(runs_per_start=3, reset_to_state=reset_by_seed, max_steps=8, progress=False)
    near = lambda o: o[..., :2].norm(dim=-1) < 0.01  # noqa: E731
    with pytest.warns(
        UserWarning,
        match=r"^runs_per_start: each of the 2 starts' 3 runs repeated one episode, step for "
        r"step: .* \(as reset_by_seed does, replaying the start's seeded reset\)",
    ):
        real_outcomes(make(), agent, starts, success=near, **args)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        real_outcomes(make(0.5), agent, starts, success=near, **args)


def test_a_reset_that_ignores_a_start_given_as_its_observation_is_refused():
    """Starts given as a tensor of observations [B, S] are held against the reset's
    observation too: a reset that ignores them starts elsewhere."""
    from torchrl.envs import DMControlEnv

    from rcvae_torchrl.agent import draw_starts
    from rcvae_torchrl.data import prepare_env

    env, _ = prepare_env(DMControlEnv("point_mass", "easy"))
    starts = draw_starts(env, seeds=[3, 4])["observation"]
    agent = lambda td: td.set("action", torch.zeros(2))  # noqa: E731
    with pytest.raises(ValueError, match=r"^reset_to_state: the env's reset observation differs"):
        real_outcomes(
            env,
            agent,
            starts,
            runs_per_start=1,
            reset_to_state=lambda env, start: env.reset(),
            max_steps=3,
            success=lambda o: o[..., 0] > 9,
            progress=False,
        )


def _to_origin(td):  # reaches the origin, where the terminating point mass ends its episode
    o = td["observation"]
    return td.set("action", (-1.0 * o[..., :2] - 1.5 * o[..., 2:4]).clamp(-1, 1))


def _at_origin(observation):  # the env's own termination condition
    return observation[..., :2].norm(dim=-1) < 0.1


@pytest.mark.parametrize("workers", [1, 2])
def test_episodes_the_env_ends_where_the_boundary_decides_nothing_are_named(workers):
    env = terminating_point_mass
    starts = env().reset()["observation"][None].repeat(2, 1)
    args = dict(runs_per_start=1, reset_to_state=plain_reset, max_steps=35, workers=workers)

    def outcomes(boundary):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            success = boundary.success_over_time
            out = real_outcomes(env, _to_origin, starts, success=success, progress=False, **args)
        return out, [str(w.message) for w in caught if "ended by the env" in str(w.message)]

    # a reach the env's end cuts off (the episodes end at step 14), and a survival whose
    # failure is looser than the env's end: real failures the forecast cannot see coming
    far = SuccessBoundary(lambda o: o[..., 0] < -5.0, time_limit=30)
    loose = SuccessBoundary.survival(lambda o: o[..., 0].abs() > 5.0, time_limit=30)
    cases = ((far, "a failure region"), (loose, "its failure"))
    # worker processes start slowly: one case there (a failure region, read at each end)
    for boundary, region in cases if workers == 1 else cases[1:]:
        out, said = outcomes(boundary)
        assert not out.success.any() and out.steps.tolist() == [[14], [14]]
        assert len(said) == 1 and said[0].startswith(
            "success: 2 of the 2 real episodes ended by the env itself (terminated) before the "
            "boundary's time limit of 30 steps, neither in its success region nor in its "
            "failure region. They count as failures"
        )
        assert f"termination condition as {region} (SuccessBoundary(..., failure=...)" in said[0]
    # the env's end as the boundary's failure or its success: both judge the same event
    for boundary in (
        SuccessBoundary(lambda o: o[..., 0] < -5.0, failure=_at_origin, time_limit=30),
        SuccessBoundary(_at_origin, time_limit=30),
        SuccessBoundary(lambda o: o[..., 0] < -5.0, time_limit=10),  # ended after its limit
    )[: 3 if workers == 1 else 0]:
        out, said = outcomes(boundary)
        assert said == [] and out.steps.tolist() == [[14], [14]]


def test_a_boundary_without_a_time_limit_is_judged_over_the_episodes_steps():
    env = terminating_point_mass()
    starts = env.reset()["observation"][None]
    args = dict(runs_per_start=1, reset_to_state=plain_reset, progress=False)
    anytime = SuccessBoundary(_at_origin)  # was refused: "at least ... (inf steps)"
    for max_steps, won in ((35, True), (10, False)):
        out = real_outcomes(
            env, _to_origin, starts, max_steps=max_steps, success=anytime.success_over_time, **args
        )
        assert out.success.tolist() == [[won]] and out.first_step.tolist() == [[13 if won else 10]]


def test_a_success_flag_that_is_no_bool_is_refused():
    # the env's reward as the flag: tiny rewards (1e-40) counted as successes
    env = terminating_point_mass()
    starts = env.reset()["observation"][None]
    with pytest.raises(
        TypeError,
        match=r"^success: expected the env's 'reward' entry to be a bool flag, got dtype "
        r"torch.float32; pass success= a function",
    ):
        real_outcomes(
            env,
            _to_origin,
            starts,
            runs_per_start=1,
            reset_to_state=plain_reset,
            max_steps=5,
            success="reward",
            progress=False,
        )
    flagged = real_outcomes(
        env,
        _to_origin,
        starts,
        runs_per_start=1,
        reset_to_state=plain_reset,
        max_steps=20,
        success="success",
        progress=False,
    )
    assert flagged.success.tolist() == [[True]] and flagged.first_step.tolist() == [[13]]


def _point_mass_episodes(policy, **kwargs):
    env = terminating_point_mass()
    args = {"seeds": [0], "max_steps": 3, "success": _never, "progress": False, **kwargs}
    return run_episodes(env, policy, **args)


def _zero_action(td):
    return td.set("action", torch.zeros(2))


@pytest.mark.parametrize(
    ("kwargs", "error", "words"),
    [
        ({"seeds": 10}, TypeError, "seeds: expected a sequence of integer seeds"),
        ({"seeds": [1.2, 1.7]}, ValueError, "seeds: expected integer seeds, got 1.2"),
        ({"seeds": [0], "starts": [[0.0] * 4]}, TypeError, "starts: expected start states as a"),
    ],
)
def test_seeds_and_starts_of_another_kind_are_refused(kwargs, error, words):
    """10 is not ten seeds, and 1.2 and 1.7 would both be seed 1: one episode twice."""
    args = {"reset_to_state": plain_reset} if "starts" in kwargs else {}
    with pytest.raises(error) as info:
        _point_mass_episodes(_zero_action, **kwargs, **args)
    assert words in str(info.value)


def test_a_plain_function_policy_has_its_actions_checked_as_a_module_s_are():
    with pytest.raises(
        ValueError, match=r"^policy: expected actions of shape \(2,\) .* got \(3,\)"
    ):
        _point_mass_episodes(lambda td: td.set("action", torch.zeros(3)))
    with pytest.raises(KeyError, match="policy: expected it to write the env's action 'action'"):
        _point_mass_episodes(lambda td: td)
    stats = _point_mass_episodes(_zero_action)  # a right one runs
    assert stats.steps.tolist() == [3]


def test_real_outcomes_refuses_an_array_of_starts():
    import numpy as np

    with pytest.raises(TypeError, match="starts: expected start states as a tensor"):
        real_outcomes(
            terminating_point_mass(),
            _zero_action,
            np.full((2, 4), 0.8, np.float32),
            runs_per_start=1,
            reset_to_state=plain_reset,
            max_steps=3,
            success=_never,
            progress=False,
        )


@pytest.mark.parametrize(
    ("kwargs", "error", "words"),
    [
        ({"success": 3}, TypeError, "success: expected the name of the env's success flag"),
        ({"first_id": "a"}, ValueError, "first_id: expected an integer >= 0, got 'a'"),
    ],
)
def test_how_episodes_are_judged_and_numbered_is_checked(kwargs, error, words):
    with pytest.raises(error) as info:
        _point_mass_episodes(_zero_action, **kwargs)
    assert words in str(info.value)


def test_real_outcomes_needs_an_env_and_a_policy():
    args = {"runs_per_start": 1, "max_steps": 3, "success": _never, "progress": False}
    with pytest.raises(TypeError, match="env: expected a TorchRL env or a function"):
        real_outcomes(None, _zero_action, torch.zeros(2, 4), reset_to_state=plain_reset, **args)
    with pytest.raises(TypeError, match="policy: expected a TorchRL policy"):
        real_outcomes(
            terminating_point_mass(), None, torch.zeros(2, 4), reset_to_state=plain_reset, **args
        )


def test_seeds_may_come_as_an_array_or_a_tensor_of_integers():
    import numpy as np

    for seeds in (np.arange(2), torch.arange(2), range(2)):
        stats = _point_mass_episodes(_zero_action, seeds=seeds)
        assert stats.success.shape == (2,)

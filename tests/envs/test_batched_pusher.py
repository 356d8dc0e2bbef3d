"""The batched Pusher equals the dm_control Pusher env by env: same seeds, same steps, same bits."""

import pytest
import torch
from dm_control.rl.control import PhysicsError
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs

from rcvae_torchrl.envs import (
    BatchedPusherEnv,
    make_batched_pusher_env,
    make_pusher_env,
    obs_indices,
)
from rcvae_torchrl.envs.scripted import make_scripted_policy
from rcvae_torchrl.envs.state import reset_to_state

KEYS = [
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "success"),
    ("next", "done"),
    ("next", "terminated"),
    ("next", "truncated"),
]
BALL_VEL = obs_indices("ball_vel")


def _random_actions(steps, n, seed):
    """Actions ``[n, steps, 2]`` in [-1.5, 1.5]: clipping is part of what must match."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, steps, 2, generator=g) * 3.0 - 1.5


def _replay(actions):
    """A policy writing ``actions[..., t, :]`` at its ``t``-th call."""
    t = iter(range(actions.shape[-2]))

    def policy(td):
        return td.set("action", actions[..., next(t), :])

    return policy


def _batched_rollout(env, steps, kind, seed=0, **rollout_kwargs):
    """A rollout with the scripted pusher (one batched call per step) or random actions."""
    policy = make_scripted_policy()
    if kind == "random":
        policy = _replay(_random_actions(steps, env.num_envs, seed))
    with torch.no_grad():
        return env.rollout(steps, policy, **{"break_when_any_done": False, **rollout_kwargs})


def _dm_replay(variant, seed, actions, **kwargs):
    """The dm_control Pusher of ``seed`` fed ``actions [T, 2]``, reset when an episode ends.

    Replaying the batched env's actions equals running its (closed-loop) policy here as long as
    the observations are equal, which is what the tests assert step by step.
    """
    env = make_pusher_env(variant, seed=seed, **kwargs)
    return env.rollout(actions.shape[0], _replay(actions), break_when_any_done=False)


def _assert_equal(batched, reference, keys=KEYS):
    for key in keys:
        a, b = batched[key], reference[key]
        assert torch.equal(a, b), f"{key}: max |diff| {(a.float() - b.float()).abs().max()}"


@pytest.mark.parametrize(
    ("variant", "seed", "kind"),
    [
        ("deterministic", 0, "scripted"),
        ("deterministic", 40, "random"),
        ("stochastic", 7, "scripted"),
        ("stochastic", 123, "random"),
        ("ood", 3, "scripted"),
        ("ood", 55, "random"),
    ],
)
def test_every_env_equals_the_dm_control_env_of_its_seed(variant, seed, kind):
    # 5 s episodes (100 steps) over 125 steps: successes (scripted), truncations (random) and the
    # partial resets that `rollout(break_when_any_done=False)` makes after both.
    n, steps, kwargs = 3, 125, {"time_limit": 5.0}
    td = _batched_rollout(make_batched_pusher_env(n, variant, seed=seed, **kwargs), steps, kind)
    for i in range(n):
        _assert_equal(td[i], _dm_replay(variant, seed + i, td["action"][i], **kwargs))
    assert not torch.equal(td["observation"][0, 0], td["observation"][1, 0])
    if kind == "scripted" and variant != "ood":
        # Out-of-distribution targets lie across the hub: the scripted pusher needs more than 5 s.
        assert td["next", "terminated"].any(), "no success: the scripted pusher should succeed"
    if kind == "scripted":
        assert (td["next", "observation"][..., BALL_VEL] != 0).any(), "the ball never moved"
    else:
        assert td["next", "truncated"].any(), "no episode reached the time limit"


def test_terminate_on_success_false_runs_past_success():
    kwargs = {"time_limit": 6.0, "terminate_on_success": False}
    td = _batched_rollout(make_batched_pusher_env(2, "stochastic", seed=5, **kwargs), 130, "")
    for i in range(2):
        _assert_equal(td[i], _dm_replay("stochastic", 5 + i, td["action"][i], **kwargs))
    assert td["next", "success"].any() and not td["next", "terminated"].any()
    assert td["next", "truncated"][:, 119].all()


def test_time_limit_truncates_at_the_same_step_as_dm_control():
    env = make_batched_pusher_env(3, seed=1, time_limit=1.0)
    assert env.step_limit == pytest.approx(20.0)
    td = _batched_rollout(env, 30, "random", break_when_any_done=True)
    assert td.shape == (3, 20)
    assert td["next", "truncated"][:, -1].all() and not td["next", "truncated"][:, :-1].any()
    assert not td["next", "terminated"].any()
    for i in range(3):
        _assert_equal(td[i], _dm_replay("deterministic", 1 + i, td["action"][i], time_limit=1.0))


def test_done_envs_stay_done_until_reset():
    env = make_batched_pusher_env(2, seed=0, time_limit=0.25)  # 5 steps
    td = env.reset()
    for _ in range(5):
        td = env.step(td.set("action", torch.full((2, 2), 0.5)))["next"]
    assert td["truncated"].all() and td["done"].all()
    frozen = td["observation"].clone()
    nxt = env.step(td.set("action", torch.full((2, 2), -1.0)))
    after = nxt["next"]
    assert torch.equal(after["observation"], frozen)
    assert (after["reward"] == 0).all() and after["truncated"].all() and after["done"].all()
    restarted = env.reset(nxt["next"].set("_reset", torch.tensor([[True], [False]])))
    assert not restarted["done"][0] and restarted["done"][1]
    assert not torch.equal(restarted["observation"][0], frozen[0])


def test_partial_reset_leaves_the_other_envs_on_their_course():
    env = make_batched_pusher_env(2, "stochastic", seed=20, terminate_on_success=False)
    reference = make_pusher_env("stochastic", seed=21, terminate_on_success=False)
    actions = _random_actions(40, 1, 0)[0]
    td, ref = env.reset(), reference.reset()
    for t in range(40):
        if t == 15:  # restart env 0 mid-episode; env 1 must not notice
            td = env.reset(td.set("_reset", torch.tensor([[True], [False]])))
        td = env.step(td.set("action", actions[t].expand(2, 2)))["next"]
        ref = reference.step(ref.set("action", actions[t]))["next"]
        assert torch.equal(td["observation"][1], ref["observation"])
        assert torch.equal(td["reward"][1], ref["reward"])


def test_rollout_until_all_done_masks_finished_envs():
    n, kwargs = 3, {"time_limit": 3.0}
    env = make_batched_pusher_env(n, seed=9, **kwargs)
    td = _batched_rollout(env, 200, "scripted", break_when_all_done=True)
    done = td["next", "done"].squeeze(-1)
    assert done[:, -1].all() and td.shape[1] <= 60
    for i in range(n):
        end = int(done[i].nonzero()[0]) + 1
        reference = _dm_replay("deterministic", 9 + i, td["action"][i, :end], **kwargs)
        _assert_equal(td[i, :end], reference)
        last = td["next", "observation"][i, end - 1]
        assert (td["next", "observation"][i, end:] == last).all(), "a finished env moved"


def test_collector_frames_equal_a_rollout():
    kwargs = {"time_limit": 1.5}  # 30 steps: the collector restarts envs mid-batch
    env = make_batched_pusher_env(2, "stochastic", seed=3, **kwargs)
    collector = Collector(
        env,
        make_scripted_policy(),
        frames_per_batch=140,
        total_frames=140,
        auto_register_policy_transforms=False,
    )
    try:
        batch = next(iter(collector))
    finally:
        collector.shutdown()
    reference = make_batched_pusher_env(2, "stochastic", seed=3, **kwargs)
    _assert_equal(batch, _batched_rollout(reference, 70, "scripted"))
    assert batch["next", "done"].sum() >= 4


def test_explicit_per_env_seeds():
    seeds = [11, 5, 42]
    env = make_batched_pusher_env(3, "stochastic")
    env.set_seeds(seeds)
    td = _batched_rollout(env, 40, "scripted")
    for i, seed in enumerate(seeds):
        _assert_equal(td[i], _dm_replay("stochastic", seed, td["action"][i]))
    env.set_seeds(torch.tensor([99]), envs=[1])
    last = td[:, -1]["next"].clone()
    restarted = env.reset(last.set("_reset", torch.tensor([[False], [True], [False]])))
    expected = make_pusher_env("stochastic", seed=99).reset()["observation"]
    assert torch.equal(restarted["observation"][1], expected)


def test_reset_to_given_states_matches_reset_to_state():
    seeds = [4, 8, 15]
    moving = _batched_rollout(make_batched_pusher_env(3, "ood", seed=60), 30, "scripted")
    starts = moving["next", "observation"][:, -1]  # mid-episode: arm and ball moving
    assert (starts[:, BALL_VEL] != 0).any()
    env = make_batched_pusher_env(3, "stochastic")
    env.set_seeds(seeds)
    td = reset_to_state(env, starts)
    out = _batched_rollout(env, 50, "scripted", auto_reset=False, tensordict=td)
    for i, seed in enumerate(seeds):
        single = make_pusher_env("stochastic", seed=seed)
        ref_td = reset_to_state(single, starts[i])
        assert torch.equal(td["observation"][i], ref_td["observation"])
        ref = single.rollout(
            50,
            _replay(out["action"][i]),
            auto_reset=False,
            tensordict=ref_td,
            break_when_any_done=False,
        )
        _assert_equal(out[i], ref)


@pytest.mark.parametrize("noise", [0.0, 0.7])
def test_actuator_strength_equals_the_dm_control_env(noise):
    kwargs = {"time_limit": 5.0, "action_noise_std": noise, "actuator_strength": (0.2, 0.6)}
    env = make_batched_pusher_env(3, "stochastic", seed=21, **kwargs)
    td = _batched_rollout(env, 125, "scripted")
    for i in range(3):
        _assert_equal(td[i], _dm_replay("stochastic", 21 + i, td["action"][i], **kwargs))
    strengths = env.strengths
    assert ((strengths >= 0.2) & (strengths <= 0.6)).all() and len(set(strengths)) == 3
    assert (make_batched_pusher_env(2, "stochastic", seed=0).strengths == 1.0).all()


def test_partial_reset_to_given_states():
    env = make_batched_pusher_env(3, seed=2)
    before = env.reset()["observation"]
    given = before.flip(0)
    mask = torch.tensor([[True], [False], [True]])
    td = env.reset(TensorDict(observation=given, _reset=mask, batch_size=[3]), set_state=True)
    torch.testing.assert_close(td["observation"][[0, 2]], given[[0, 2]], atol=1e-6, rtol=0)
    assert torch.equal(td["observation"][1], before[1])


def test_thread_count_does_not_change_results():
    rollouts = [
        _batched_rollout(make_batched_pusher_env(4, "stochastic", seed=30, num_threads=t), 40, "")
        for t in (1, 2)
    ]
    _assert_equal(*rollouts)


def test_specs_are_those_of_make_pusher_env_per_env():
    env = make_batched_pusher_env(4, "stochastic", seed=0)
    check_env_specs(env)
    single = make_pusher_env("stochastic", seed=0)
    assert env.batch_size == (4,)
    for name in ("observation_spec", "action_spec", "reward_spec", "full_done_spec"):
        batched, one = getattr(env, name), getattr(single, name)
        assert batched.shape[:1] == (4,)
        assert batched[0] == one, name


def test_physics_warnings_raise_like_dm_control():
    # MuJoCo rejects this velocity; dm_control raises when stepping, the batched env may already
    # raise when loading the state (its forward pass checks velocities).
    env = make_batched_pusher_env(2, seed=0)
    states = env.reset()["observation"]
    states[1, obs_indices("shoulder_vel")] = 1e12
    with pytest.raises(PhysicsError, match=r"envs \[1\]"):
        td = reset_to_state(env, states)
        env.step(td.set("action", torch.zeros(2, 2)))
    single = make_pusher_env(seed=1)
    with pytest.raises(PhysicsError):
        td = reset_to_state(single, states[1])
        single.step(td.set("action", torch.zeros(2)))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_envs": 0}, "num_envs: expected an integer >= 1, got 0"),
        ({"num_envs": 2.5}, "num_envs: expected an integer >= 1, got 2.5"),
        ({"num_envs": 2, "num_threads": 0}, "num_threads: expected an integer >= 1"),
        ({"num_envs": 2, "variant": "windy"}, "variant: expected one of"),
        ({"num_envs": 2, "time_limit": 1.03}, "whole number of control steps"),
        ({"num_envs": 2, "action_noise_std": -1.0}, "action_noise_std: expected a non"),
        ({"num_envs": 2, "seed": -1}, r"seed: expected an integer in \[0, 2\*\*32"),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_batched_pusher_env(**kwargs)


@pytest.mark.parametrize(
    ("action", "match"),
    [
        (torch.zeros(2, 3), r"action: expected shape \(2, 2\), got \(2, 3\)"),
        (torch.zeros(2), r"action: expected shape \(2, 2\), got \(2,\)"),
        (torch.tensor([[0.0, 0.0], [float("nan"), 0.0]]), r"action: expected finite.*\[1\]"),
    ],
)
def test_bad_actions_raise_clear_errors(action, match):
    env = make_batched_pusher_env(2, seed=0)
    td = env.reset()
    with pytest.raises(ValueError, match=match):
        env.step(td.set("action", action))


def test_bad_seeds_and_states_raise_clear_errors():
    env = make_batched_pusher_env(2, seed=0)
    with pytest.raises(ValueError, match="seeds: expected 2 integers"):
        env.set_seeds([1, 2, 3])
    with pytest.raises(ValueError, match=r"seeds: expected integers in \[0, 2\*\*32\)"):
        env.set_seeds([1, -2])
    with pytest.raises(ValueError, match=r"envs: expected env indices in \[0, 2\)"):
        env.set_seeds([1], envs=[2])
    with pytest.raises(ValueError, match=r"seeds: expected 1 integers \(one per env\), got \[\]"):
        env.set_seeds([], envs=[1])
    with pytest.raises(ValueError, match=r"seeds: expected 0 integers \(one per env\), got \[5\]"):
        env.set_seeds([5], envs=[])
    untouched = make_batched_pusher_env(2, seed=0)
    env.set_seeds([], envs=[])  # no env chosen: nothing seeded or reset
    env.set_seeds(torch.zeros(0, dtype=torch.int64), envs=torch.zeros(2, dtype=torch.bool))
    assert torch.equal(env.reset()["observation"], untouched.reset()["observation"])
    with pytest.raises(ValueError, match="observation: expected finite values"):
        bad = torch.zeros(2, 14).index_fill_(0, torch.tensor([1]), float("nan"))
        env.reset(TensorDict(observation=bad, batch_size=[2]), set_state=True)
    with pytest.raises(ValueError, match=r"observation: reset\(\.\.\., set_state=True\) expects"):
        env.reset(TensorDict(batch_size=[2]), set_state=True)
    with pytest.raises(ValueError, match=r"observation: expected a finite tensor of shape \(2, 14"):
        reset_to_state(env, torch.zeros(14))
    assert isinstance(env, BatchedPusherEnv)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"success_radius": float("nan")}, ValueError, "success_radius: expected a positive"),
        ({"action_noise_std": -1.0}, ValueError, "action_noise_std: expected a non-negative"),
        ({"action_noise_std": None}, ValueError, "action_noise_std: expected a non-negative"),
        ({"time_limit": 0.0}, ValueError, "time_limit: expected a positive finite number"),
        ({"time_limit": 1.03}, ValueError, "whole number of control steps"),
        ({"actuator_strength": (5.0, 9.0)}, ValueError, "actuator_strength: expected .* <= 1"),
        ({"terminate_on_success": "no"}, TypeError, "terminate_on_success: expected True or"),
        ({"region": "x"}, TypeError, "region: expected an InitialStateRegion, got str"),
        ({"device": "foo"}, ValueError, r"device: expected a torch device .* got 'foo'"),
    ],
)
def test_the_class_checks_its_arguments_as_the_factory_does(kwargs, error, match):
    with pytest.raises(error, match=match):
        BatchedPusherEnv(2, **kwargs)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"terminate_on_success": "no"}, TypeError, "terminate_on_success: expected True or"),
        ({"seed": True}, ValueError, r"seed: expected an integer in \[0, 2\*\*32 - num_envs\]"),
        ({"region": "x"}, TypeError, "region: expected an InitialStateRegion or None, got str"),
        ({"device": "foo"}, ValueError, r"device: expected a torch device .* got 'foo'"),
    ],
)
def test_flags_seed_region_and_device_of_the_factory_are_checked(kwargs, error, match):
    with pytest.raises(error, match=match):
        make_batched_pusher_env(2, **kwargs)


@pytest.mark.parametrize(
    ("args", "match"),
    [
        ((30.0, 0.005, 0), "n_sub_steps: expected an integer >= 1, got 0"),
        ((30.0, 0.0, 10), "physics_timestep: expected a positive number, got 0.0"),
        ((float("nan"), 0.005, 10), "time_limit: expected a positive number, got nan"),
    ],
)
def test_episode_step_limit_names_a_bad_argument(args, match):
    from rcvae_torchrl.envs.batched import episode_step_limit

    assert episode_step_limit(30.0, 0.005, 10) == 600.0
    with pytest.raises(ValueError, match=match):
        episode_step_limit(*args)

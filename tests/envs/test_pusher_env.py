"""Contract tests of the Pusher env: specs, determinism, regions, reward/success, arguments."""

import dataclasses
import functools
import math

import numpy as np
import pytest
import torch
from torchrl.envs import ParallelEnv
from torchrl.envs.utils import check_env_specs

from rcvae_torchrl.envs import (
    IN_DISTRIBUTION,
    OUT_OF_DISTRIBUTION,
    VARIANTS,
    InitialStateRegion,
    make_pusher_env,
    obs_indices,
    pusher_reward,
    pusher_success,
)
from rcvae_torchrl.envs.scripted import make_scripted_policy

BALL, BALL_VEL, JOINT_VEL = obs_indices("ball"), obs_indices("ball_vel"), obs_indices("joint_vel")
TARGET = obs_indices("target")


def _rollout(env, steps=60, policy=None):
    with torch.no_grad():
        return env.rollout(steps, policy or make_scripted_policy(), break_when_any_done=False)


@pytest.mark.parametrize("variant", VARIANTS)
def test_specs(variant):
    env = make_pusher_env(variant, seed=0)
    check_env_specs(env)
    assert env.observation_spec["observation"].shape == (14,)
    assert env.observation_spec["observation"].dtype == torch.float32
    assert env.action_spec.shape == (2,)
    assert torch.equal(env.action_spec.space.low, -torch.ones(2))
    assert torch.equal(env.action_spec.space.high, torch.ones(2))


def test_same_seed_same_rollout_and_different_seeds_differ():
    a = _rollout(make_pusher_env("stochastic", seed=7))
    b = _rollout(make_pusher_env("stochastic", seed=7))
    c = _rollout(make_pusher_env("stochastic", seed=8))
    assert torch.equal(a["next", "observation"], b["next", "observation"])
    assert not torch.allclose(a["observation"][0], c["observation"][0])


def test_stochastic_differs_from_deterministic_under_same_seed():
    det = _rollout(make_pusher_env("deterministic", seed=3))
    sto = _rollout(make_pusher_env("stochastic", seed=3))
    # Same start state (the noise is drawn after the episode is initialised) ...
    assert torch.equal(det["observation"][0], sto["observation"][0])
    # ... but the noisy actuators take the arm elsewhere.
    assert (det["next", "observation"][-1] - sto["next", "observation"][-1]).abs().max() > 1e-3


def _starts(variant, n=40):
    env = make_pusher_env(variant, seed=11)
    return torch.stack([env.reset()["observation"] for _ in range(n)])


def _polar_angle_deg(xy):
    return torch.rad2deg(torch.atan2(xy[:, 1], xy[:, 0]))


def test_ood_starts_lie_outside_the_training_region():
    ind, ood = _starts("deterministic"), _starts("ood")
    for obs in (ind, ood):
        for group in (BALL, TARGET):
            r = obs[:, group].norm(dim=-1)
            lo, hi = IN_DISTRIBUTION.ball_radius
            assert ((r >= lo - 1e-4) & (r <= hi + 1e-4)).all()
        assert (obs[:, BALL_VEL].abs().max() == 0) and (obs[:, JOINT_VEL].abs().max() == 0)
    for group, (lo, hi) in ((BALL, (100.0, 130.0)), (TARGET, (-80.0, -50.0))):
        a_ind, a_ood = _polar_angle_deg(ind[:, group]), _polar_angle_deg(ood[:, group])
        assert (a_ind.abs() <= 90.0 + 1e-3).all()  # the half of the arena in front of the arm
        assert ((a_ood >= lo - 1e-3) & (a_ood <= hi + 1e-3)).all()  # the ball: a disjoint sector
        assert a_ind.max() - a_ind.min() > 120.0  # spread over the half, not a corner of it


def test_region_angle_must_be_an_interval_of_at_most_a_turn():
    with pytest.raises(ValueError, match="angle: expected"):
        dataclasses.replace(OUT_OF_DISTRIBUTION, angle=(1.0, 0.5))
    with pytest.raises(ValueError, match="angle: expected"):
        dataclasses.replace(OUT_OF_DISTRIBUTION, angle=(0.0, 7.0))
    with pytest.raises(ValueError, match="target_angle: expected"):
        dataclasses.replace(OUT_OF_DISTRIBUTION, target_angle=(1.0, 0.5))


@pytest.mark.parametrize("variant", ["deterministic", "stochastic"])
def test_pure_reward_and_success_match_the_env(variant):
    env = make_pusher_env(variant, seed=5)
    td = _rollout(env, steps=600)
    nxt = td["next", "observation"]
    torch.testing.assert_close(
        pusher_reward(nxt, td["action"]), td["next", "reward"], atol=1e-5, rtol=0
    )
    success = pusher_success(nxt)
    assert torch.equal(success, td["next", "success"].squeeze(-1))
    assert success.any(), "the scripted pusher should succeed in this episode"
    assert torch.equal(td["next", "terminated"].squeeze(-1), success)
    assert (td["next", "reward"] <= 0).all()


def test_random_actions_give_nonpositive_rewards_and_time_limit_truncates():
    env = make_pusher_env(seed=1, time_limit=1.0)
    td = env.rollout(100, break_when_any_done=True)
    assert td.shape == (20,)
    assert td["next", "truncated"][-1].item() and not td["next", "terminated"].any()
    assert (td["next", "reward"] <= 0).all()


def test_pure_functions_take_any_batch_shape():
    obs = torch.randn(3, 4, 5, 14) * 0.1
    act = torch.rand(3, 4, 5, 2) * 2 - 1
    assert pusher_reward(obs, act).shape == (3, 4, 5, 1)
    assert pusher_success(obs, 0.05).shape == (3, 4, 5)
    with pytest.raises(ValueError, match=r"observation: expected shape \[\.\.\., 14\]"):
        pusher_reward(torch.zeros(3, 13), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="action: expected shape"):
        pusher_reward(torch.zeros(3, 14), torch.zeros(3, 3))
    with pytest.raises(ValueError, match="radius"):
        pusher_success(obs, 0.0)


def test_parallel_env():
    env = ParallelEnv(2, functools.partial(make_pusher_env, "stochastic", seed=None))
    try:
        env.set_seed(0)
        td = env.rollout(5)
        assert td["next", "observation"].shape == (2, 5, 14)
        assert not torch.equal(td["observation"][0, 0], td["observation"][1, 0])
    finally:
        env.close()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"variant": "windy"}, "variant: expected one of"),
        ({"variant": "stochastic", "action_noise_std": -0.1}, "action_noise_std: expected a non"),
        ({"variant": "deterministic", "action_noise_std": 0.2}, "deterministic variant takes no"),
        ({"time_limit": 0.0}, "time_limit: expected a positive"),
        ({"time_limit": -5}, "time_limit: expected a positive"),
        ({"time_limit": 1.03}, "whole number of control steps"),
        ({"success_radius": 0}, "success_radius"),
        ({"success_radius": math.inf}, "success_radius: expected a positive finite number"),
        ({"time_limit": True}, "time_limit: expected a positive finite number of seconds"),
        ({"variant": "stochastic", "action_noise_std": math.inf}, "action_noise_std: expected"),
        ({"variant": "deterministic", "actuator_strength": (0.5, 1.0)}, "fixed strength"),
        ({"variant": "stochastic", "actuator_strength": (0.0, 0.4)}, "0 < low <= high"),
        ({"variant": "stochastic", "actuator_strength": (0.5, 0.4)}, "0 < low <= high"),
        ({"variant": "stochastic", "actuator_strength": (0.5, 1.5)}, "high <= 1"),
        ({"variant": "ood", "actuator_strength": (0.5, float("nan"))}, "high <= 1"),
        ({"variant": "stochastic", "actuator_strength": 0.5}, "expected \\(low, high\\)"),
        ({"variant": "stochastic", "actuator_strength": (0.1, 0.2, 0.3)}, "two numbers"),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_pusher_env(**kwargs)


def test_region_validation():
    with pytest.raises(ValueError, match="ball_radius: expected"):
        InitialStateRegion((0.01, 0.1), (0, 0), (0, 0), (0.1, 0.12))
    with pytest.raises(ValueError, match="ball_speed"):
        InitialStateRegion((0.1, 0.12), (0.2, 0.1), (0, 0), (0.1, 0.12))


def test_custom_region_and_noise_for_ood():
    region = InitialStateRegion((0.1, 0.1), (0, 0), (0, 0), (0.15, 0.15))
    obs = make_pusher_env(region=region, seed=0).reset()["observation"]
    np.testing.assert_allclose(obs[BALL].norm().item(), 0.1, atol=1e-6)
    env = make_pusher_env("ood", seed=0, action_noise_std=0.2)
    assert env.base_env._env.task.action_noise_std == 0.2


def test_episodes_can_run_past_success():
    env = make_pusher_env(seed=5, time_limit=10.0, terminate_on_success=False)
    with torch.no_grad():
        td = env.rollout(1000, make_scripted_policy(), break_when_any_done=True)
    assert td.shape == (200,) and td["next", "truncated"][-1].item()
    assert td["next", "success"].any() and not td["next", "terminated"].any()


def test_reset_to_state_reproduces_an_episode():
    from rcvae_torchrl.envs.state import reset_to_state

    env = make_pusher_env("deterministic", seed=3)
    start = env.reset()
    with torch.no_grad():
        a = env.rollout(40, make_scripted_policy(), auto_reset=False, tensordict=start)
    other = make_pusher_env("deterministic", seed=99)
    td = reset_to_state(other, start["observation"])
    torch.testing.assert_close(td["observation"], start["observation"], atol=1e-6, rtol=0)
    with torch.no_grad():
        b = other.rollout(40, make_scripted_policy(), auto_reset=False, tensordict=td)
    torch.testing.assert_close(
        a["next", "observation"], b["next", "observation"], atol=1e-4, rtol=0
    )
    with pytest.raises(ValueError, match="observation: expected a finite tensor of shape"):
        reset_to_state(other, torch.full((14,), float("nan")))


def test_pusher_state_constraint_holds_on_real_states_and_repairs_others():
    from rcvae_torchrl.envs import obs_indices, pusher_state_constraint

    td = _rollout(make_pusher_env(seed=4), steps=80)
    real = td["next", "observation"]
    torch.testing.assert_close(
        pusher_state_constraint(td["observation"], real), real, atol=2e-5, rtol=0
    )
    broken = real.clone()
    broken[:, obs_indices("finger")] += 0.05
    broken[:, obs_indices("shoulder_cos")] *= 1.3
    broken[:, obs_indices("ball")] *= 5.0
    fixed = pusher_state_constraint(td["observation"], broken)
    cos, sin = obs_indices("shoulder_cos", "wrist_cos"), obs_indices("shoulder_sin", "wrist_sin")
    torch.testing.assert_close(fixed[:, cos] ** 2 + fixed[:, sin] ** 2, torch.ones(80, 2))
    assert (fixed[:, obs_indices("ball")].norm(dim=-1) <= 0.199 + 1e-6).all()
    only_finger = real.clone()
    only_finger[:, obs_indices("finger")] += 0.05
    torch.testing.assert_close(
        pusher_state_constraint(td["observation"], only_finger), real, atol=2e-5, rtol=0
    )


def test_pusher_input_features_match_the_simulated_geometry():
    from rcvae_torchrl.envs import (
        CONTROL_TIMESTEP,
        PUSHER_FEATURE_NAMES,
        obs_indices,
        pusher_input_features,
    )

    td = _rollout(make_pusher_env(seed=5), steps=120)
    obs, nxt = td["observation"], td["next", "observation"]
    feats = pusher_input_features(obs)
    assert feats.shape == (120, len(PUSHER_FEATURE_NAMES))
    rel = obs[:, obs_indices("finger")] - obs[:, obs_indices("ball")]
    torch.testing.assert_close(feats[:, :2], rel)
    torch.testing.assert_close(feats[:, 2], rel.norm(dim=-1))
    # the Jacobian velocity, averaged over a control step, is the fingertip's displacement rate
    mean_vel = 0.5 * (feats[:, 3:5] + pusher_input_features(nxt)[:, 3:5])
    moved = (nxt[:, obs_indices("finger")] - obs[:, obs_indices("finger")]) / CONTROL_TIMESTEP
    for k in range(2):
        assert torch.corrcoef(torch.stack([mean_vel[:, k], moved[:, k]]))[0, 1] > 0.9


def _scripted_motors(env, steps):
    """The controls that reach the motors over ``steps`` scripted steps, ``[steps, 2]``, and
    the commanded (clipped) actions."""
    policy, physics = make_scripted_policy(), env.base_env._env.physics
    td, applied, commanded = env.reset(), [], []
    with torch.no_grad():
        for _ in range(steps):
            td = policy(td)
            td = env.step(td)
            applied.append(physics.data.ctrl.copy())
            commanded.append(td["action"].clamp(-1, 1).double().numpy())
            td = td["next"]
    return np.stack(applied), np.stack(commanded)


def test_actuator_strength_scales_the_command_for_a_whole_episode():
    env = make_pusher_env("stochastic", seed=3, action_noise_std=0.0, actuator_strength=(0.2, 0.4))
    task = env.base_env._env.task
    applied, commanded = _scripted_motors(env, 20)
    g = task.strength
    assert 0.2 <= g <= 0.4
    np.testing.assert_allclose(applied, g * commanded, rtol=0, atol=1e-7)
    strengths = []
    for seed in range(40):  # each episode draws its own strength from the task's stream
        env.set_seed(seed)
        strengths.append(task.strength)
    strengths = np.array(strengths)
    assert strengths.min() >= 0.2 and strengths.max() <= 0.4 and strengths.std() > 0.04
    env.set_seed(3)
    env.reset()  # the seed's second episode, as in _scripted_motors
    assert task.strength == g  # reproducible under the seed


def test_actuator_strength_comes_after_the_start_state_in_the_stream():
    # A seeded stream's first start state is that of the env without it (the draw comes after).
    plain = make_pusher_env("stochastic", seed=11).base_env._env.physics
    strong = make_pusher_env("stochastic", seed=11, actuator_strength=(1.0, 1.0)).base_env._env
    np.testing.assert_array_equal(plain.ball_xy(), strong.physics.ball_xy())
    np.testing.assert_array_equal(plain.arm_angles(), strong.physics.arm_angles())
    weak = make_pusher_env(
        "stochastic", seed=4, action_noise_std=0.0, actuator_strength=(0.25, 0.25)
    )
    full = make_pusher_env("stochastic", seed=4, action_noise_std=0.0, actuator_strength=(1.0, 1.0))
    a, _ = _scripted_motors(weak, 5)
    b, _ = _scripted_motors(full, 5)
    np.testing.assert_allclose(a[0], 0.25 * b[0], rtol=0, atol=1e-7)


@pytest.mark.parametrize("seed", [-1, 1.5, "0", 2**40, True])
def test_seeds_numpy_cannot_take_are_named(seed):
    with pytest.raises(ValueError, match=r"seed: expected an integer in \[0, 2\*\*32\)"):
        make_pusher_env("deterministic", seed=seed)


def test_a_nan_start_is_said_to_be_nan():
    from rcvae_torchrl.envs import reset_to_state

    env = make_pusher_env("deterministic", seed=0)
    start = env.reset()["observation"].clone()
    start[3] = math.nan
    with pytest.raises(ValueError, match=r"got shape \(14,\) with 1 NaN or inf entries"):
        reset_to_state(env, start)


def test_reset_to_state_warns_when_it_moves_an_impossible_observation(recwarn):
    from rcvae_torchrl.envs.batched import BatchedPusherEnv
    from rcvae_torchrl.envs.state import PROJECTION_TOLERANCE, reset_to_state

    env = make_pusher_env("deterministic", seed=3)
    real = env.rollout(30, make_scripted_policy())["next", "observation"][[5, 20]]
    for start in real:
        reset_to_state(env, start)  # a real observation comes back within float32 rounding
    reset_to_state(BatchedPusherEnv(2), real)
    assert not [w for w in recwarn if issubclass(w.category, UserWarning)]
    off = real.clone()
    off[1, 1] += 0.05  # shoulder sin off the unit circle
    pattern = r"not a state the Pusher can be in; .* shoulder_(cos|sin) \(entry [01]\) moved by "
    with pytest.warns(UserWarning, match=pattern):
        td = reset_to_state(env, off[1])
    assert (td["observation"] - off[1]).abs().max() > PROJECTION_TOLERANCE  # where it starts
    with pytest.warns(UserWarning, match=pattern):
        reset_to_state(BatchedPusherEnv(2), off)


@pytest.mark.parametrize(
    ("action", "match"),
    [
        (torch.tensor([0.7]), r"action: expected shape \[2\], got \[1\]"),
        (torch.zeros(3), r"action: expected shape \[2\], got \[3\]"),
        (torch.zeros(1, 2), r"action: expected shape \[2\], got \[1, 2\]"),
        (torch.tensor([math.inf, 0.0]), r"action: expected finite values, got \[inf, 0\.0\]"),
        (torch.tensor([0.0, math.nan]), r"action: expected finite values, got \[0\.0, nan\]"),
    ],
)
def test_single_env_refuses_actions_of_another_shape_or_not_finite(action, match):
    env = make_pusher_env(seed=0)
    td = env.reset()
    with pytest.raises(ValueError, match=match):
        env.step(td.set("action", action))
    env.step(td.set("action", torch.zeros(2)))  # the env is still usable


# ball and target 0.1 m from the base at most 0.2 rad apart: never 0.06 m apart
_CRAMPED = InitialStateRegion((0.1, 0.1), (0, 0), (0, 0), (0.1, 0.1), angle=(0.0, 0.2))


def test_a_region_without_valid_starts_is_refused_not_sampled_forever():
    from rcvae_torchrl.envs.pusher import sample_start

    pattern = r"region: no start state found in 10000 candidates: 10000 had the ball within"
    with pytest.raises(ValueError, match=pattern):
        make_pusher_env(region=_CRAMPED, seed=0)
    with pytest.raises(ValueError, match=r"\d+ the fingertip within 0\.04 m of the ball"):
        sample_start(np.random.RandomState(0), IN_DISTRIBUTION, lambda state: 0.0)
    with pytest.raises(ValueError, match="finger_to_ball: expected a fingertip-to-ball distance"):
        sample_start(np.random.RandomState(0), IN_DISTRIBUTION, lambda state: math.nan)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("ball_radius", 0.1),
        ("ball_radius", (0.1, 0.1, 0.1)),
        ("target_radius", ("a", "b")),
        ("target_radius", "ab"),
        ("angle", None),
        ("ball_speed", (0, math.inf)),
        ("joint_speed", (0, math.inf)),
        ("joint_speed", (math.nan, 1.0)),
        ("angle", (-math.inf, -math.inf)),
        ("target_angle", (0.0, math.inf)),
        ("target_angle", (True, 1.0)),
    ],
)
def test_region_fields_are_pairs_of_finite_numbers(field, value):
    pattern = rf"{field}: expected \(low, high\), two finite numbers, got "
    with pytest.raises(ValueError, match=pattern):
        dataclasses.replace(IN_DISTRIBUTION, **{field: value})


def test_region_must_be_an_initial_state_region():
    from rcvae_torchrl.envs.pusher import sample_start

    with pytest.raises(TypeError, match="region: expected an InitialStateRegion or None, got str"):
        make_pusher_env(region="foo")
    with pytest.raises(TypeError, match="region: expected an InitialStateRegion, got NoneType"):
        sample_start(np.random.RandomState(0), None, lambda state: 1.0)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"from_pixels": "no"}, TypeError, "from_pixels: expected True or False, got 'no'"),
        ({"terminate_on_success": 1}, TypeError, "terminate_on_success: expected True or False"),
        ({"device": "foo"}, ValueError, r"device: expected a torch device .* got 'foo'"),
        ({"device": 2.5}, TypeError, r"device: expected a torch device .* got 2\.5"),
    ],
)
def test_flags_and_device_are_checked(kwargs, error, match):
    with pytest.raises(error, match=match):
        make_pusher_env(**kwargs)


@pytest.mark.parametrize(
    ("entries", "values", "moved"),
    [
        ((8, 9), (0.6, 0.0), "ball_x"),  # outside the fence
        ((8, 9), (0.0, 0.03), "ball_y"),  # inside the hub
        ((12,), (5.0,), "target_x"),  # far out of the ball's reach
    ],
)
def test_reset_to_state_moves_a_ball_or_target_out_of_reach_with_a_warning(entries, values, moved):
    from rcvae_torchrl.envs.batched import BatchedPusherEnv
    from rcvae_torchrl.envs.constraints import _BALL_MAX, _BALL_MIN
    from rcvae_torchrl.envs.state import reset_to_state

    start = make_pusher_env(seed=3).reset()["observation"]
    off = start.clone()
    off[list(entries)] = torch.tensor(values)
    pattern = rf"not a state the Pusher can be in; .* {moved} \(entry \d+\) moved by "
    single = make_pusher_env(seed=1)
    with pytest.warns(UserWarning, match=pattern):
        td = reset_to_state(single, off)
    for group in (BALL, TARGET):
        radius = float(td["observation"][group].norm())
        assert _BALL_MIN - 1e-6 <= radius <= _BALL_MAX + 1e-6
    with pytest.warns(UserWarning, match=pattern):
        both = reset_to_state(BatchedPusherEnv(2), torch.stack([start, off]))
    torch.testing.assert_close(both["observation"][1], td["observation"], atol=1e-6, rtol=0)


def test_observation_functions_refuse_another_width():
    from rcvae_torchrl.envs import pusher_input_features, pusher_state_constraint

    for width in (13, 16):
        with pytest.raises(
            ValueError, match=rf"observation: expected shape \[\.\.\., 14\], got \({width},\)"
        ):
            pusher_input_features(torch.zeros(width))
        with pytest.raises(
            ValueError, match=rf"state: expected shape \[\.\.\., 14\], got \({width},\)"
        ):
            pusher_state_constraint(torch.zeros(width), torch.zeros(width))


def test_a_success_radius_that_is_not_a_number_is_named():
    """A string radius failed inside the comparison ('<=' not supported)."""
    from rcvae_torchrl.envs import pusher_success

    for radius in ("0.1", None, True, 0.0):
        with pytest.raises(ValueError, match="radius: expected a positive distance in metres"):
            pusher_success(torch.zeros(14), radius=radius)
    assert pusher_success(torch.zeros(14), radius=np.float32(0.05)).shape == ()

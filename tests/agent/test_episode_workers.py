"""Real episodes in ParallelEnv worker processes equal the one-env run, episode by episode."""

from __future__ import annotations

from functools import partial

import pytest
import torch

from rcvae_torchrl.agent import (
    MLPPolicy,
    draw_starts,
    episode_workers,
    make_policy_module,
    real_outcomes,
    reset_to_physics,
)
from rcvae_torchrl.envs import (
    ball_to_target,
    make_batched_pusher_env,
    make_pusher_env,
    reset_to_state,
)
from rcvae_torchrl.envs.scripted import make_scripted_policy
from tests.agent.worker_envs import noisy_point_mass
from tests.pusher_fixtures import pusher_starts


def _push_to_centre(td):
    return td.set("action", -5 * td["observation"][..., :2].clamp(-0.2, 0.2))


def _centre_distance(observation):
    return torch.linalg.vector_norm(observation[..., :2], dim=-1)


def _pusher_case(batched: bool):
    noisy = dict(action_noise_std=1.0, time_limit=3.0, terminate_on_success=not batched)
    make = partial(make_pusher_env, "stochastic", **noisy)
    workers = partial(make_batched_pusher_env, 2, "stochastic", **noisy) if batched else make
    # the scripted pusher on fixed blocks of rows: bare, its float32 actions can depend on the batch
    args = dict(reset_to_state=reset_to_state, trace=ball_to_target, policy_rows=64)
    return make(), workers, make_scripted_policy(), pusher_starts(3), args


def _learned_policy_case():
    """A learned (matrix-product) policy called on fixed blocks of rows, in batched workers."""
    env, workers, _, starts, args = _pusher_case(True)
    torch.manual_seed(0)
    mlp = MLPPolicy(14, 2, hidden=64)
    mlp.obs_std.fill_(0.3)
    return env, workers, make_policy_module(mlp.eval()), starts, args | dict(policy_rows=4)


def _point_mass_case():
    make = partial(noisy_point_mass, 1.0)
    starts = draw_starts(make(), [0, 1, 2], physics=True)  # the simulator state crosses over
    args = dict(
        reset_to_state=reset_to_physics,
        success=lambda o: _centre_distance(o) <= 0.1,
        trace=_centre_distance,
    )
    return make(), make, _push_to_centre, starts, args


@pytest.mark.parametrize("case", ["pusher", "batched pusher", "learned policy", "point_mass"])
def test_worker_outcomes_equal_the_one_env_run(case):
    cases = {
        "pusher": lambda: _pusher_case(False),
        "batched pusher": lambda: _pusher_case(True),
        "learned policy": _learned_policy_case,
        "point_mass": _point_mass_case,
    }
    env, make, policy, starts, args = cases[case]()
    # 9 episodes over 2 workers (x 2 envs each when batched): the last chunk is padded
    args |= dict(runs_per_start=3, max_steps=40, seed=3, progress=False)
    serial = real_outcomes(env, policy, starts, **args)
    threads = torch.get_num_threads()
    parallel = real_outcomes(make, policy, starts, workers=2, **args)
    assert torch.get_num_threads() == threads  # the ParallelEnv's start and close undone
    assert parallel.success.shape == (3, 3) and parallel.trace.shape == (3, 3, 40)
    for name in ("success", "first_step", "steps"):
        assert torch.equal(getattr(parallel, name), getattr(serial, name)), name
    torch.testing.assert_close(parallel.trace, serial.trace, rtol=0, atol=0, equal_nan=True)
    assert not torch.equal(parallel.trace[:, 0], parallel.trace[:, 1])  # each run its own noise


def test_workers_need_a_positive_count_and_an_env_factory():
    make = partial(make_pusher_env, "stochastic")
    args = dict(runs_per_start=1, reset_to_state=reset_to_state, max_steps=2, progress=False)
    policy, starts = make_scripted_policy(), pusher_starts(1)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match=rf"^workers: expected a positive integer, got {bad}"):
            real_outcomes(make, policy, starts, workers=bad, **args)
        with pytest.raises(ValueError, match=r"^workers: expected a positive integer"):
            episode_workers(make, bad, reset_to_state)
    with pytest.raises(ValueError, match=r"^env: with workers=2, expected a function that makes"):
        real_outcomes(make(), policy, starts, workers=2, **args)
    one = real_outcomes(make, policy, starts, workers=1, **args)  # a factory, in this process
    assert one.steps.tolist() == [[2]]


def test_a_sampling_policy_over_workers_is_said_to_draw_otherwise():
    from tests.agent.test_batched_outcomes import sampling_arm

    make = partial(make_pusher_env, "deterministic")
    args = dict(runs_per_start=2, reset_to_state=reset_to_state, max_steps=2, progress=False)
    with pytest.warns(UserWarning, match=r"^policy: it samples its actions .* with workers=2 "):
        real_outcomes(make, sampling_arm(), pusher_starts(1), workers=2, **args)

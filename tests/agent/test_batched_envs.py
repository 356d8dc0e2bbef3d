"""TorchRL's batched envs (SerialEnv, ParallelEnv, a batched env of its own) as a user runs
them: seeded without crashing, episodes counted as asked, starts that are starts."""

from __future__ import annotations

import functools
import warnings

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import ParallelEnv, PendulumEnv, SerialEnv, StepCounter, TransformedEnv

from rcvae_torchrl.agent import draw_starts, real_outcomes, seed_episodes
from rcvae_torchrl.data import (
    ActionNoise,
    UniformRandomPolicy,
    collect_episodes,
    make_policy_module,
    prepare_env,
    seed_env,
)
from rcvae_torchrl.envs import make_batched_pusher_env, make_pusher_env, reset_to_state
from tests.pusher_fixtures import pusher_starts


def _pendulum() -> TransformedEnv:
    env, _ = prepare_env(TransformedEnv(PendulumEnv(), StepCounter(10)), ["th", "thdot"])
    return env


def _still(td):
    return td.set("action", torch.zeros(*td.batch_size, 2))


def _never(observation):
    return torch.zeros(observation.shape[:-1], dtype=torch.bool)


def test_a_parallel_env_is_seeded_without_asking_its_workers_for_transforms():
    env = ParallelEnv(2, _pendulum)
    try:
        seed_env(env, 3)  # looked up "transform" in the workers, which died of it
        first = env.reset()["observation"]
        seed_env(env, 3)
        torch.testing.assert_close(env.reset()["observation"], first)
    finally:
        env.close()


def test_noise_on_a_serial_env_is_seeded_with_a_warning_that_episodes_are_not_one_env_s():
    env = TransformedEnv(SerialEnv(2, _pendulum), ActionNoise(0.5))
    with pytest.warns(UserWarning, match=r"^env: SerialEnv \[2\] has no set_seeds\(seeds\), so it"):
        seed_episodes(env, [0, 1])  # was a RecursionError inside TorchRL's SerialEnv
    env.close()


def test_a_batched_env_with_set_seeds_is_seeded_per_episode_without_a_warning():
    env = make_batched_pusher_env(2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seed_episodes(env, [0, 1])


def _outcomes(env, starts, reset=reset_to_state, max_steps: int = 5):
    """One run of the still arm from each start, never a success."""
    return real_outcomes(
        env,
        _still,
        starts,
        runs_per_start=1,
        reset_to_state=reset,
        max_steps=max_steps,
        success=_never,
        progress=False,
    )


def test_only_the_episodes_asked_for_count_as_cut_short():
    # 3 episodes in an env of 8: the 5 rows that pad the group are no episodes of the user's
    env = make_batched_pusher_env(8, time_limit=1.0)
    with pytest.raises(ValueError, match=r"^env: 3 of the 3 episodes run together were cut short"):
        _outcomes(env, pusher_starts(3), max_steps=45)


def test_a_reset_that_does_not_reach_the_start_is_refused():
    def ignores_the_start(env, start):
        return env.reset()

    starts = TensorDict({"observation": pusher_starts(2)}, batch_size=[2])
    with pytest.raises(
        ValueError, match=r"^reset_to_state: the env's reset observation differs from the start's"
    ):
        _outcomes(make_pusher_env(), starts, reset=ignores_the_start)


def test_starts_of_one_state_and_starts_drawn_from_a_batched_env_are_named():
    with pytest.raises(ValueError, match=r"^starts: expected start states \[B, S\] .* \(14,\)"):
        _outcomes(make_pusher_env(), pusher_starts(2)[0])
    with pytest.raises(ValueError, match=r"^env: expected one env \(batch_size \[\]\), got batch"):
        draw_starts(make_batched_pusher_env(2), [0, 1])


def test_a_batched_env_collects_whole_steps_without_torchrl_s_rounding_warning():
    make = functools.partial(make_batched_pusher_env, 4, time_limit=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # TorchRL warns when frames_per_batch does not divide
        data = collect_episodes(
            make,
            make_policy_module(UniformRandomPolicy(2, seed=0)),
            4,
            frames_per_batch=10,
            progress=False,
        )
    assert data.shape == (80,)  # 4 episodes of 20 steps

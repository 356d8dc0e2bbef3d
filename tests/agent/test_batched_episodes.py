"""run_episodes in a batched env: N episodes side by side equal the one-env run, episode by
episode (a policy acting on each state alone, called on fixed blocks of rows: FixedRowsPolicy)."""

from __future__ import annotations

import pytest
import torch

from rcvae_torchrl.agent import FixedRowsPolicy, PerturbedPolicy, run_episodes
from rcvae_torchrl.data import TRAJ_KEY
from rcvae_torchrl.envs import (
    make_batched_pusher_env,
    make_pusher_env,
    pusher_success,
    reset_to_state,
)
from rcvae_torchrl.envs.scripted import make_scripted_policy
from tests.pusher_fixtures import pusher_starts


def _scripted():
    """The scripted pusher on blocks of 64 rows: its float32 actions then do not depend on the
    batch (bare, a vectorised kernel can round an element otherwise than the scalar loop)."""
    return FixedRowsPolicy(make_scripted_policy(), rows=64)


KEYS = ("observation", "action", ("next", "observation"), ("next", "done"), TRAJ_KEY)


def _same(batched, serial) -> None:
    assert torch.equal(batched.success, serial.success)
    assert torch.equal(batched.steps, serial.steps)
    assert batched.data.shape == serial.data.shape
    for key in KEYS:
        assert torch.equal(batched.data[key], serial.data[key]), key


@pytest.mark.parametrize("variant", ["deterministic", "stochastic"])
def test_batched_episodes_equal_the_one_env_run(variant):
    env_args = dict(time_limit=3.0, success_radius=0.1)
    if variant == "stochastic":
        env_args["action_noise_std"] = 1.0
    args = dict(seeds=[11, 12, 13, 14, 15], max_steps=60, first_id=3, progress=False)
    policy = _scripted()
    serial = run_episodes(make_pusher_env(variant, **env_args), policy, **args)
    # 5 episodes in groups of 2: the last group padded
    batched = run_episodes(make_batched_pusher_env(2, variant, **env_args), policy, **args)
    _same(batched, serial)
    assert torch.equal(batched.data[TRAJ_KEY].unique(), torch.arange(3, 8))
    lengths = torch.bincount(batched.data[TRAJ_KEY] - 3)
    assert bool((lengths <= 60).all()) and bool((lengths < 60).any())  # some ended at success


def test_batched_episodes_from_given_starts_by_a_success_function():
    starts = pusher_starts(3)
    env_args = dict(time_limit=2.0, terminate_on_success=False)
    args = dict(
        seeds=[1, 2, 3],
        starts=starts,
        reset_to_state=reset_to_state,
        max_steps=30,
        success=lambda o: pusher_success(o, radius=0.2),
        progress=False,
    )
    policy = _scripted()
    serial = run_episodes(make_pusher_env("deterministic", **env_args), policy, **args)
    batched = run_episodes(make_batched_pusher_env(3, "deterministic", **env_args), policy, **args)
    _same(batched, serial)
    first = batched.data["observation"][batched.data[TRAJ_KEY] == 0][0]
    torch.testing.assert_close(first, starts[0], rtol=0, atol=1e-6)


def test_a_noisy_behaviour_policy_runs_side_by_side():
    """PerturbedPolicy around the scripted pusher: one noise draw per step for all envs."""
    behaviour = PerturbedPolicy(make_scripted_policy(), 0.3, seed=0)
    env = make_batched_pusher_env(4, "deterministic", time_limit=2.0)
    out = run_episodes(env, behaviour, seeds=range(4), max_steps=40, progress=False)
    again = run_episodes(
        env,
        PerturbedPolicy(make_scripted_policy(), 0.3, seed=0),
        seeds=range(4),
        max_steps=40,
        progress=False,
    )
    assert torch.equal(out.data["label"], again.data["label"])  # deterministic under a seed
    assert not torch.equal(out.data["label"], out.data["action"])
    with pytest.raises(ValueError, match=r"env: expected batch_size \[\] or \[N\], got \[2, 2\]"):
        run_episodes(_TwoDim(), make_scripted_policy(), seeds=[0], max_steps=2, progress=False)


class _TwoDim:
    """Stands in for an env of two batch dimensions."""

    batch_size = torch.Size([2, 2])

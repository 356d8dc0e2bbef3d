"""The scripted reference pusher: a TorchRL policy that solves every variant."""

import pytest
import torch

from rcvae_torchrl.envs import make_pusher_env
from rcvae_torchrl.envs.scripted import ScriptedPusher, make_scripted_policy

EPISODES = 15


@pytest.mark.parametrize("variant", ["deterministic", "stochastic", "ood"])
def test_scripted_pusher_success_rate(variant):
    env = make_pusher_env(variant, seed=0)
    policy = make_scripted_policy()
    wins = 0
    for seed in range(EPISODES):
        env.set_seed(500 + seed)
        with torch.no_grad():
            td = env.rollout(600, policy, break_when_any_done=True)
        wins += bool(td["next", "success"].any())
    assert wins / EPISODES >= 0.9, f"{variant}: {wins}/{EPISODES} successes"


def test_scripted_pusher_batched_and_bounded():
    obs = make_pusher_env(seed=0).reset()["observation"]
    batch = obs.expand(4, 3, 14)
    action = ScriptedPusher()(batch)
    assert action.shape == (4, 3, 2)
    assert (action.abs() <= 1).all()
    torch.testing.assert_close(action[2, 1], ScriptedPusher()(obs))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"kp": float("nan")}, "kp: expected a positive number, got nan"),
        ({"kp": 0.0}, "kp: expected a positive number, got 0.0"),
        ({"max_turn": -1}, "max_turn: expected a positive number, got -1"),
        ({"align_angle": float("inf")}, "align_angle: expected a positive number, got inf"),
        ({"standoff": -0.5}, "standoff: expected a finite number >= 0, got -0.5"),
        ({"kd": float("nan")}, "kd: expected a finite number >= 0, got nan"),
        ({"push_depth": "0.02"}, "push_depth: expected a finite number >= 0, got '0.02'"),
    ],
)
def test_controller_arguments_are_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ScriptedPusher(**kwargs)


def test_observations_of_another_width_or_dtype_are_refused():
    pusher = ScriptedPusher()
    with pytest.raises(
        ValueError, match=r"observation: expected shape \[\.\.\., 14\], got \(13,\)"
    ):
        pusher(torch.zeros(13))
    with pytest.raises(TypeError, match="observation: expected a floating-point tensor, got dtype"):
        pusher(torch.zeros(14, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"observation: expected shape \[\.\.\., 14\]"):
        pusher.desired_fingertip(torch.zeros(2, 13))

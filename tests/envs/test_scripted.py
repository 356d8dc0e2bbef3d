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

"""``replay_episodes``: held-out episodes' actions replayed open loop in the real Pusher, the
truth of the far coverage check."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from rcvae_torchrl.data import TRAJ_KEY, episode_spans
from rcvae_torchrl.envs import make_batched_pusher_env
from recipes.pusher_competency.data import replay_episodes


def _episodes(variant: str, lengths: list[int]) -> TensorDict:
    """Flat episodes of random actions in the Pusher, of the given lengths."""
    n, steps = len(lengths), max(lengths)
    env = make_batched_pusher_env(n, variant, seed=3, terminate_on_success=False)
    td = env.reset()
    g = torch.Generator().manual_seed(0)
    obs, act, nxt = [], [], []
    for _ in range(steps):
        td["action"] = torch.rand(n, 2, generator=g) * 2 - 1
        obs.append(td["observation"]), act.append(td["action"])
        td = env.step(td)["next"]
        nxt.append(td["observation"])
    parts = []
    for i, length in enumerate(lengths):
        parts.append(
            TensorDict(
                {
                    "observation": torch.stack(obs, 1)[i, :length],
                    "action": torch.stack(act, 1)[i, :length],
                    ("next", "observation"): torch.stack(nxt, 1)[i, :length],
                    TRAJ_KEY: torch.full((length,), i),
                },
                batch_size=[length],
            )
        )
    return torch.cat(parts)


def test_a_replay_repeats_a_deterministic_episode_from_its_first_state():
    episodes = _episodes("deterministic", [30, 12, 30])
    replayed = replay_episodes(episodes, 20, "deterministic")
    first, lengths = episode_spans(replayed)
    assert lengths.tolist() == [20, 20]  # the 12-step episode is too short
    for start, kept in zip(first.tolist(), (0, 2), strict=True):
        begin = [0, 30, 42][kept]
        recorded = episodes[begin : begin + 20]
        ours = replayed[start : start + 20]
        assert torch.equal(ours["action"], recorded["action"])
        torch.testing.assert_close(ours["next", "observation"], recorded["next", "observation"])


def test_a_stochastic_replay_draws_new_noise():
    episodes = _episodes("deterministic", [20, 20])
    replayed = replay_episodes(episodes, 20, "stochastic", seed=5, action_noise_std=1.0)
    torch.testing.assert_close(replayed["observation"][::20], episodes["observation"][::20])
    gap = (replayed["next", "observation"] - episodes["next", "observation"]).abs().amax()
    assert gap > 1e-2

"""Pusher demo: the scripted reference controller in each variant, with a GIF of one episode.

python recipes/pusher_demo.py [--episodes 5] [--out outputs/demo]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from tqdm import tqdm

from rcvae_torchrl.envs import CONTROL_TIMESTEP, VARIANTS, make_pusher_env
from rcvae_torchrl.envs.render import gl_unavailable_reason, record_episode
from rcvae_torchrl.envs.scripted import make_scripted_policy


def run_variant(variant: str, episodes: int, policy) -> list[float | None]:
    """Time to success (s) of each episode, None for a failure."""
    env = make_pusher_env(variant, seed=0)
    times: list[float | None] = []
    for seed in tqdm(range(episodes), desc=variant, leave=False):
        env.set_seed(seed)
        with torch.no_grad():
            td = env.rollout(10_000, policy, break_when_any_done=True)
        won = bool(td["next", "success"].any())
        times.append(td.shape[0] * CONTROL_TIMESTEP if won else None)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"))
    args = parser.parse_args()
    policy = make_scripted_policy()
    print(f"{'variant':<14}{'success':>10}{'mean time (s)':>16}")
    for variant in VARIANTS:
        times = run_variant(variant, args.episodes, policy)
        wins = [t for t in times if t is not None]
        mean = sum(wins) / len(wins) if wins else float("nan")
        print(f"{variant:<14}{len(wins):>5}/{len(times):<4}{mean:>16.2f}")
    reason = gl_unavailable_reason()
    if reason is not None:
        print(f"no GIF: {reason}")
        return
    path = args.out / "pusher_scripted.gif"
    record_episode(make_pusher_env("deterministic", seed=0), policy, path)
    print(f"saved {path}")


if __name__ == "__main__":
    main()

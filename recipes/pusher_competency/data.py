"""Pusher datasets for the world model: scripted pushing with exploration noise, random play."""

from __future__ import annotations

import functools

import torch
from tensordict import TensorDict

from rcvae_torchrl.data import (
    TRAJ_KEY,
    GaussianExploration,
    UniformRandomPolicy,
    collect_episodes,
    episode_spans,
    make_policy_module,
)
from rcvae_torchrl.envs import CONTROL_TIMESTEP, make_batched_pusher_env, make_pusher_env
from rcvae_torchrl.envs.scripted import ScriptedPusher

__all__ = ["collect_pusher_data", "replay_episodes"]


def collect_pusher_data(
    variant: str = "deterministic",
    *,
    scripted_episodes: int = 100,
    random_episodes: int = 20,
    exploration_std: float = 0.3,
    random_hold: int = 5,
    time_limit: float = 30.0,
    random_time_limit: float = 10.0,
    terminate_on_success: bool = False,
    seed: int = 0,
    num_envs: int = 4,
    progress: bool = True,
    **env_kwargs,
) -> TensorDict:
    """Episodes ``[frames]`` of the scripted pusher with Gaussian exploration noise, then of
    uniformly random actions (held for ``random_hold`` steps), in one Pusher variant.

    Episode ids (:data:`rcvae_torchrl.data.TRAJ_KEY`) are unique across both parts. By default
    episodes run past success (``terminate_on_success=False``), so the data also shows the ball
    at rest on the target and long-horizon behaviour. ``num_envs`` envs are stepped together
    (see :func:`~rcvae_torchrl.data.collect_episodes`).
    """
    make_env = functools.partial(
        make_pusher_env,
        variant,
        time_limit=time_limit,
        terminate_on_success=terminate_on_success,
        **env_kwargs,
    )
    parts = []
    if scripted_episodes:
        policy = make_policy_module(
            GaussianExploration(ScriptedPusher(), exploration_std, seed=seed)
        )
        parts.append(
            collect_episodes(
                make_env,
                policy,
                scripted_episodes,
                seed=seed,
                num_envs=num_envs,
                progress=progress,
                desc=f"{variant}: scripted",
            )
        )
    if random_episodes:
        make_random_env = functools.partial(make_env, time_limit=random_time_limit)
        policy = make_policy_module(UniformRandomPolicy(2, random_hold, seed=seed + 1))
        parts.append(
            collect_episodes(
                make_random_env,
                policy,
                random_episodes,
                seed=seed + 1,
                num_envs=num_envs,
                progress=progress,
                desc=f"{variant}: random",
            )
        )
    if not parts:
        raise ValueError("scripted_episodes, random_episodes: expected at least one episode")
    offset = 0
    for part in parts:
        part[TRAJ_KEY] = part[TRAJ_KEY] - part[TRAJ_KEY].min() + offset
        offset = int(part[TRAJ_KEY].max()) + 1
    return torch.cat(parts)


def replay_episodes(
    episodes: TensorDict, steps: int, variant: str, *, seed: int = 0, **env_kwargs
) -> TensorDict:
    """The episodes of at least ``steps`` steps, their first ``steps`` recorded actions replayed
    open loop in a real Pusher of ``variant`` from their first states: flat episodes ``[frames]``.

    A truth for checking a world model far ahead (``check_model(..., coverage_steps=)``): the
    recorded episodes of a closed-loop policy are not one in a stochastic env (the policy's
    later actions answer the noise the episode met), their replays are. The stochastic
    variant draws new noise (seeded by ``seed``: env ``i`` by ``seed + i``); a deterministic
    episode is repeated from the float32 observation of its first state, which contacts can
    amplify over seconds. ``env_kwargs`` go to :func:`make_batched_pusher_env` (the variant's
    randomness).
    """
    first, lengths = episode_spans(episodes)
    first = first[lengths >= steps]
    n = first.numel()
    frames = first[:, None] + torch.arange(steps)
    actions = episodes.get("action")[frames]
    env = make_batched_pusher_env(
        n,
        variant,
        seed=seed,
        time_limit=steps * CONTROL_TIMESTEP,
        terminate_on_success=False,
        **env_kwargs,
    )
    starts = episodes.get("observation")[first]
    td = env.reset(TensorDict(observation=starts, batch_size=[n]), set_state=True)
    states = [td["observation"]]
    for t in range(steps):
        td["action"] = actions[:, t]
        td = env.step(td)["next"]
        states.append(td["observation"])
    states = torch.stack(states, 1)
    return TensorDict(
        {
            "observation": states[:, :-1],
            "action": actions,
            ("next", "observation"): states[:, 1:],
            TRAJ_KEY: torch.arange(n)[:, None].expand(n, steps),
        },
        batch_size=[n, steps],
    ).reshape(-1)

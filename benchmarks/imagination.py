"""Imagination throughput of the model env: fast paths and TorchRL rollouts against a raw loop.

Pusher-sized ensemble (S = 14, A = 2, E = 5, ``RCVAEConfig`` defaults: H = 128, Z = 8,
MLP 128), TS-∞, horizon 15, open loop, rewards and success of the Pusher task computed at every
step by every variant. Throughput in model-steps/s (particle × step). Variants, same run:

- ``raw``: a hand-written loop on member-major tensors ``[E, M/E, ·]`` calling
  ``ensemble.step`` directly, with ``pusher_reward`` / ``pusher_success`` and the masked
  return sum: the floor any wrapper can reach.
- ``evaluate``: ``RCVAEEnsembleEnv.evaluate_action_sequences`` (the planner's fast path), one
  start state, C candidates × P particles.
- ``imagine``: ``RCVAEEnsembleEnv.imagine``, |B| start states × N samples per member (builds
  the ``[E, N, *B, T]`` TensorDict with loc/scale/latent and the task entries).
- ``env.rollout``: TorchRL's ``env.rollout`` over a ``[C, P]`` tensordict (the stock planners'
  path), actions replayed by a policy.

The overhead ratio is time / raw time at the same particle count (target for ``evaluate``:
≤ 1.25 at planning batch sizes). Timings are medians of repeats taken round-robin across the
variants, so load drift on a shared machine hits all alike.

On a shared machine OpenMP threads waiting for busy cores distort timings badly (a 2-thread
run under load took 50x longer than on an idle machine); compare ``--threads 1`` runs there.

    python benchmarks/imagination.py [--repeats 7] [--threads N] [--quick]
"""

from __future__ import annotations

import argparse
import os
import statistics
from collections.abc import Callable

import torch
from _report import median_time, print_table, write_json
from tensordict import TensorDict, TensorDictBase

from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.model_env import RCVAEEnsembleEnv
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble

CONFIG = RCVAEConfig(obs_dim=14, action_dim=2, passthrough_dims=(12, 13))
ENSEMBLE_SIZE = 5
HORIZON = 15
# (candidates C, particles P): C·P particles from one start state
PLANNING_SIZES = ((200, 5), (200, 20), (800, 20))


def make_env() -> RCVAEEnsembleEnv:
    torch.manual_seed(0)
    model = RCVAEEnsemble(CONFIG, ENSEMBLE_SIZE)
    obs = torch.randn(16, 50, 14) * 0.1
    model.fit_normalizer(obs, torch.rand(16, 50, 2) * 2 - 1)
    return RCVAEEnsembleEnv(
        model, pusher_reward, pusher_success, terminate_on_success=True, seed=0, validate=False
    )


def start_state(batch: tuple[int, ...] = ()) -> torch.Tensor:
    """A Pusher-like observation with the ball 0.1 m from the target (no early success)."""
    obs = torch.zeros(*batch, 14)
    obs[..., [0, 2]] = 1.0  # cos of both joints
    obs[..., 8:10] = torch.tensor([0.12, 0.0])  # ball
    obs[..., 12:14] = torch.tensor([0.12, 0.1])  # target
    return obs


def raw_loop(ensemble: RCVAEEnsemble, start: torch.Tensor, actions: torch.Tensor, particles: int):
    """Returns ``[E, P/E, C]`` of actions ``[C, H, A]`` from ``start [S]``, member-major."""
    e, (c, h, _) = ensemble.ensemble_size, actions.shape
    m = particles // e * c
    gen = torch.Generator().manual_seed(0)
    obs = start.expand(e, m, start.shape[-1]).contiguous()
    hidden = ensemble.initial_hidden((m,), obs)
    returns = obs.new_zeros(e, m)
    alive = torch.ones(e, m, dtype=torch.bool)
    per_step = actions.transpose(0, 1)
    for t in range(h):
        action = per_step[t].expand(e, particles // e, c, -1).reshape(e, m, -1)
        out = ensemble.step(hidden, obs, action, generator=gen)
        obs, hidden = out.observation, out.hidden
        reward = pusher_reward(obs, action).squeeze(-1)
        returns += reward.masked_fill(~alive, 0.0)
        alive &= ~pusher_success(obs)
    return returns.view(e, particles // e, c)


class _Replay:
    """A policy writing ``actions[..., t, :]`` at its t-th call (as TorchRL's planners do)."""

    def __init__(self, actions: torch.Tensor) -> None:
        self.actions, self.t = actions, 0

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td.set("action", self.actions[..., self.t, :])
        self.t += 1
        return td


def variants(env: RCVAEEnsembleEnv, c: int, p: int) -> dict[str, Callable[[], object]]:
    gen = torch.Generator().manual_seed(1)
    actions = torch.rand(c, HORIZON, 2, generator=gen) * 2 - 1
    start = start_state()
    td_start = TensorDict({"observation": start[None]}, batch_size=[1])
    n_starts = c * p // ENSEMBLE_SIZE // 4  # imagine: E · N=4 · |B| = C·P particles (≤ C)
    imagine_actions = actions[:n_starts]
    rollout_actions = actions[:, None].expand(c, p, HORIZON, 2)
    reset_td = TensorDict({"observation": start.expand(c, p, 14)}, batch_size=[c, p])

    def evaluate() -> object:
        return env.evaluate_action_sequences(td_start, actions[None], p)

    def imagine() -> object:
        return env.imagine(start_state((n_starts,)), imagine_actions, samples_per_member=4)

    def rollout() -> object:
        td = env.reset(reset_td)
        return env.rollout(
            HORIZON,
            _Replay(rollout_actions),
            tensordict=td,
            auto_reset=False,
            break_when_any_done=False,
        )

    def raw() -> object:
        with torch.no_grad():
            return raw_loop(env.ensemble, start, actions, p)

    return {"raw": raw, "evaluate": evaluate, "imagine": imagine, "env.rollout": rollout}


def interleaved(runs: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """Median seconds per run over ``repeats`` rounds, one ``median_time`` call each per round."""
    for run in runs.values():
        run()
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            times[name].append(median_time(run, repeats=1, warmup=0))
    return {name: statistics.median(t) for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--quick", action="store_true", help="smallest size, 2 repeats")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    sizes, repeats = (PLANNING_SIZES[:1], 2) if args.quick else (PLANNING_SIZES, args.repeats)
    env = make_env()
    rows, results = [], []
    for c, p in sizes:
        particles = c * p
        with torch.no_grad():
            medians = interleaved(variants(env, c, p), repeats)
        for name, seconds in medians.items():
            ratio = seconds / medians["raw"]
            steps_per_s = particles * HORIZON / seconds
            rows.append([particles, f"{c}x{p}", name, seconds * 1e3, steps_per_s, ratio])
            results.append(
                {
                    "particles": particles,
                    "candidates": c,
                    "particles_per_candidate": p,
                    "variant": name,
                    "median_s": seconds,
                    "model_steps_per_s": steps_per_s,
                    "overhead_vs_raw": ratio,
                }
            )
    header = ["particles", "C x P", "variant", "median ms", "model-steps/s", "x raw"]
    print_table(
        f"Imagination throughput, E={ENSEMBLE_SIZE}, H={HORIZON}, hidden={CONFIG.hidden_dim}, "
        f"threads={torch.get_num_threads()}",
        header,
        rows,
    )
    write_json(
        "imagination",
        {
            "config": {
                "ensemble_size": ENSEMBLE_SIZE,
                "horizon": HORIZON,
                "hidden_dim": CONFIG.hidden_dim,
                "latent_dim": CONFIG.latent_dim,
                "mlp_dim": CONFIG.mlp_dim,
                "repeats": repeats,
                "load_average": os.getloadavg(),
            },
            "results": results,
        },
    )


if __name__ == "__main__":
    main()

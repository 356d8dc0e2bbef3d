"""World-model quality on the Pusher: open-loop forecasts against what really happened.

Trains an ensemble on deterministic-variant data (scripted pusher with exploration noise, plus
random play), another on stochastic-variant data, and one with open-loop steps in the ELBO window;
then forecasts held-out episodes (30 s, the episode's own actions replayed open loop) and reports,
for the ball position at 1 s, 5 s and 30 s: the median forecast error over episodes, the error of
a constant-position baseline, and how often the 5-95 % band covers the real position; and the
forecast spread of each model on the same inputs.

    python benchmarks/world_model.py [--quick] [--steps 3000] [--episodes 150]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import torch
from _report import print_table, write_json

from rcvae_torchrl.data import split_episodes
from rcvae_torchrl.envs import CONTROL_TIMESTEP, obs_indices
from rcvae_torchrl.envs.datasets import collect_pusher_data
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.training import TrainConfig, train_ensemble
from rcvae_torchrl.training.forecast import (
    band_coverage,
    constant_baseline_error,
    forecast_error,
    forecast_spread,
)

HORIZONS_S = (1.0, 5.0, 30.0)
BALL = obs_indices("ball")


def held_out(variant: str, episodes: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Start states ``[B, S]``, actions ``[B, T, A]`` and states ``[B, T, S]`` of full episodes."""
    data = collect_pusher_data(
        variant,
        scripted_episodes=episodes,
        random_episodes=0,
        time_limit=30.0,
        seed=seed,
        progress=False,
    )
    steps = round(30.0 / CONTROL_TIMESTEP)
    data = data.reshape(episodes, steps)
    return data["observation"][:, 0], data["action"], data["next", "observation"]


def train(variant: str, args, open_loop_steps: int = 0) -> tuple[RCVAEEnsemble, dict]:
    data = collect_pusher_data(
        variant,
        scripted_episodes=args.episodes,
        random_episodes=args.episodes // 5,
        time_limit=args.time_limit,
        seed=1,
        progress=False,
        num_envs=4,
    )
    train_data, val_data = split_episodes(data, 0.1, seed=0)
    config = RCVAEConfig(
        14,
        2,
        hidden_dim=args.hidden,
        mlp_dim=args.hidden,
        passthrough_dims=tuple(obs_indices("target")),
    )
    torch.manual_seed(0)
    ensemble = RCVAEEnsemble(config, args.members)
    tc = TrainConfig(
        max_steps=args.steps,
        batch_windows=args.batch,
        window=args.window,
        open_loop_steps=open_loop_steps,
        val_every=max(args.steps // 20, 1),
        patience=6,
    )
    start = time.perf_counter()
    result = train_ensemble(ensemble, train_data, val_data, tc, progress=True)
    info = {
        "frames": int(data.shape[0]),
        "train_s": time.perf_counter() - start,
        "steps": result.steps,
        "best_val": result.best_val.mean().item(),
        "config": dataclasses.asdict(tc),
    }
    return result.ensemble, info


def evaluate(ensemble, starts, actions, states, samples: int) -> dict:
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        out = ensemble.generate(starts, actions, samples_per_member=samples, generator=g)
    pred, truth = out["observation"][..., BALL], states[..., BALL]
    err = forecast_error(pred, truth)
    base = constant_baseline_error(truth, starts[..., BALL])
    cover = band_coverage(pred, truth)
    spread = forecast_spread(pred)
    rows = {}
    for h in HORIZONS_S:
        t = round(h / CONTROL_TIMESTEP) - 1
        rows[f"{h:g}s"] = {
            "median_error_m": err[:, t].median().item(),
            "constant_baseline_m": base[:, t].median().item(),
            "band_coverage": cover[:, t].float().mean().item(),
            "spread_m": spread[:, t].mean().item(),
        }
    rows["all_steps"] = {
        "band_coverage": cover.float().mean().item(),
        "spread_m": spread.mean().item(),
        "median_error_m": err.median().item(),
    }
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--episodes", type=int, default=150)
    parser.add_argument("--time-limit", type=float, default=15.0)
    parser.add_argument("--members", type=int, default=5)
    parser.add_argument("--hidden", type=int, default=128)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--window", type=int, default=32)
    parser.add_argument("--test-episodes", type=int, default=20)
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--open-loop", type=int, default=8, help="K for the open-loop variant")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    if args.quick:
        args.steps, args.episodes, args.test_episodes, args.samples = 200, 20, 5, 8
    test = {v: held_out(v, args.test_episodes, seed=100) for v in ("deterministic", "stochastic")}
    models = {
        "deterministic": train("deterministic", args),
        "stochastic": train("stochastic", args),
        f"deterministic, open loop K={args.open_loop}": train(
            "deterministic", args, args.open_loop
        ),
    }
    results = {}
    for name, (ensemble, info) in models.items():
        variant = "stochastic" if name == "stochastic" else "deterministic"
        results[name] = {
            "train": info,
            "own_variant": evaluate(ensemble, *test[variant], args.samples),
            "deterministic_inputs": evaluate(ensemble, *test["deterministic"], args.samples),
        }
    rows = []
    for name, r in results.items():
        for h in (*(f"{h:g}s" for h in HORIZONS_S),):
            m = r["own_variant"][h]
            rows.append(
                [
                    name,
                    h,
                    m["median_error_m"],
                    m["constant_baseline_m"],
                    m["band_coverage"],
                    m["spread_m"],
                ]
            )
    print_table(
        "Open-loop ball-position forecasts on held-out episodes of the model's variant",
        ["model", "horizon", "median err (m)", "constant (m)", "5-95% cover", "spread"],
        rows,
    )
    spread = {n: r["deterministic_inputs"]["all_steps"]["spread_m"] for n, r in results.items()}
    print_table(
        "Forecast spread on the same deterministic held-out inputs (mean over 30 s)",
        ["model", "mean spread (m)"],
        [[n, s] for n, s in spread.items()],
    )
    write_json("world_model", {"args": vars(args), "results": results})


if __name__ == "__main__":
    main()

"""World-model quality on the Pusher: open-loop forecasts against what really happened.

Uses the study's default data and ensembles (trained here if ``--work-dir`` has none): one on
deterministic-variant data (scripted pusher with exploration noise, plus random play), one on
stochastic-variant data, and one trained with K open-loop steps in each ELBO window;
then forecasts held-out episodes (30 s, the episode's own actions replayed open loop) and reports,
for the ball position at 1 s, 5 s and 30 s: the median forecast error over episodes, the error of
a constant-position baseline, and how often the 5-95 % band covers the real position; and the
forecast spread of each model on the same inputs.

Forecasts start from two origins in each held-out episode (40 s long, so 30 s of future exist):

- ``start``: the episode's first state. The arm needs more than a second to reach the ball, so
  at 1 s the ball has not moved in any episode and the constant baseline is exact (error 0): no
  forecast can beat it there;
- ``push``: push onset, the first step with the fingertip within 5 cm of the ball. From here
  the ball moves within the first second, which is where a forecast has something to say.

    python benchmarks/world_model.py [--work-dir DIR] [--test-episodes 20] [--open-loop 8]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import torch
from _report import print_table, write_json

from rcvae_torchrl.competency import (
    band_coverage,
    constant_baseline_error,
    forecast_error,
    forecast_spread,
)
from rcvae_torchrl.data import load_episodes, split_episodes
from rcvae_torchrl.envs import CONTROL_TIMESTEP, obs_indices, pusher_input_features
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout import imagine
from rcvae_torchrl.training import load_ensemble, save_ensemble, train_ensemble
from recipes.pusher_competency.config import StudyConfig
from recipes.pusher_competency.data import collect_pusher_data
from recipes.pusher_competency.pipeline import Study
from recipes.pusher_competency.pusher import MODEL_FUNCTIONS, rcvae_config

HORIZONS_S = (1.0, 5.0, 30.0)
FORECAST_S, EPISODE_S = 30.0, 40.0
ORIGINS = ("start", "push")
PUSH_DISTANCE = 0.05  # m, fingertip to ball at push onset
BALL = obs_indices("ball")
SPREAD_GROUPS = ("finger", "joint_vel", "ball")


def push_onset(observations: torch.Tensor) -> torch.Tensor:
    """First step ``[B]`` of each episode ``[B, T, S]`` with the fingertip near the ball."""
    near = pusher_input_features(observations)[..., 2] < PUSH_DISTANCE
    return near.to(torch.int64).argmax(-1)


def held_out(
    variant: str, episodes: int, seed: int
) -> dict[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    """Per origin: start states ``[B, S]``, actions ``[B, T, A]`` and real states ``[B, T, S]``
    of the 30 s that follow (the scripted pusher with the study's exploration noise)."""
    data = collect_pusher_data(
        variant,
        scripted_episodes=episodes,
        random_episodes=0,
        time_limit=EPISODE_S,
        seed=seed,
        progress=False,
    )
    data = data.reshape(episodes, round(EPISODE_S / CONTROL_TIMESTEP))
    obs, act, nxt = data["observation"], data["action"], data["next", "observation"]
    steps, rows = round(FORECAST_S / CONTROL_TIMESTEP), torch.arange(episodes)[:, None]
    out = {}
    for origin in ORIGINS:
        t0 = torch.zeros(episodes, dtype=torch.int64) if origin == "start" else push_onset(obs)
        t0 = t0.clamp_max(obs.shape[1] - steps)
        ix = t0[:, None] + torch.arange(steps)
        out[origin] = (obs[rows[:, 0], t0], act[rows, ix], nxt[rows, ix])
    return out


def open_loop_model(study: Study, k: int) -> tuple[RCVAEEnsemble, dict]:
    """The deterministic model trained with K open-loop steps per window (cached)."""
    path = study.dir / "models" / f"deterministic_open_loop_{k}.pt"
    if path.is_file():
        return load_ensemble(path, functions=MODEL_FUNCTIONS), {}
    m = study.cfg.model
    torch.manual_seed(study.cfg.seed)
    ensemble = RCVAEEnsemble(rcvae_config(m), m.ensemble_size, functions=MODEL_FUNCTIONS)
    train_data, val_data = split_episodes(
        load_episodes(study.dir / "data" / "deterministic.pt"), 0.1, seed=study.cfg.seed
    )
    tc = dataclasses.replace(study.cfg.train, open_loop_steps=k)
    start = time.perf_counter()
    result = train_ensemble(
        ensemble,
        train_data,
        val_data,
        tc,
        progress=True,
        checkpoint_path=path.with_name(path.stem + "_train.pt"),
        resume=True,
    )
    save_ensemble(result.ensemble, path)
    return result.ensemble, {"train_s": time.perf_counter() - start, "steps": result.steps}


def evaluate(ensemble, starts, actions, states, samples: int) -> dict:
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        out = imagine(ensemble, starts, actions, samples_per_member=samples, generator=g)
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
    # Spread of the arm too: action noise moves the arm directly, the ball only through contacts.
    rows["spread_by_group"] = {
        group: forecast_spread(out["observation"][..., obs_indices(group)]).mean().item()
        for group in SPREAD_GROUPS
    }
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work-dir", type=Path, default=Path("outputs/benchmarks/study_default"))
    parser.add_argument("--test-episodes", type=int, default=20)
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--open-loop", type=int, default=8, help="K for the open-loop variant")
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    study = Study(StudyConfig(), args.work_dir, torch.device("cpu"), progress=True)
    study.data()
    study.models()
    test = {v: held_out(v, args.test_episodes, seed=100) for v in ("deterministic", "stochastic")}
    models = {
        "deterministic": (study.load_model("deterministic"), "deterministic"),
        "stochastic": (study.load_model("stochastic"), "stochastic"),
    }
    if args.open_loop:
        model, _ = open_loop_model(study, args.open_loop)
        models[f"deterministic, open loop K={args.open_loop}"] = (model, "deterministic")
    results = {}
    for name, (ensemble, variant) in models.items():
        results[name] = {
            **{
                f"own_variant_{o}": evaluate(ensemble, *test[variant][o], args.samples)
                for o in ORIGINS
            },
            "deterministic_inputs": evaluate(
                ensemble, *test["deterministic"]["start"], args.samples
            ),
        }
    rows = []
    for name, r in results.items():
        for origin in ORIGINS:
            for h in (f"{h:g}s" for h in HORIZONS_S):
                m = r[f"own_variant_{origin}"][h]
                rows.append(
                    [
                        name,
                        origin,
                        h,
                        m["median_error_m"],
                        m["constant_baseline_m"],
                        m["median_error_m"] < m["constant_baseline_m"],
                        m["band_coverage"],
                        m["spread_m"],
                    ]
                )
    print_table(
        "Open-loop ball-position forecasts on held-out episodes of the model's variant",
        [
            "model",
            "origin",
            "horizon",
            "median err (m)",
            "constant (m)",
            "beats constant",
            "5-95% cover",
            "spread",
        ],
        rows,
    )
    print_table(
        "Forecast spread on the same deterministic held-out inputs (mean over 30 s)",
        ["model", "fingertip (m)", "joint velocities (rad/s)", "ball (m)"],
        [
            [n, *(r["deterministic_inputs"]["spread_by_group"][g] for g in SPREAD_GROUPS)]
            for n, r in results.items()
        ],
    )
    write_json(
        "world_model",
        {
            "args": {k: str(v) for k, v in vars(args).items()},
            "study_config": dataclasses.asdict(study.cfg),
            "results": results,
        },
    )


if __name__ == "__main__":
    main()

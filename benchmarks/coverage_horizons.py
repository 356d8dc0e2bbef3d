"""How far ahead a study's world models stay calibrated: the self-check's coverage by horizon.

After training, every world model checks the coverage of its spread on held-out episodes
(:func:`~rcvae_torchrl.training.check_model`): from each episode's first state, driven by the
episode's own actions, how often the real state lies inside the model's 90 % interval, by
default 20 steps (1 s) ahead. A forecast runs 12 s. This script measures the same coverage at
several horizons, for both models of a study run.

Held-out episodes of a closed-loop controller are not a fair truth for a stochastic model far
ahead: the controller's later actions answer the noise the episode met, so conditioning on them
tells more than a model driven by the same actions can know. So the truth here is a *replay*:
each held-out episode's recorded actions sent open loop to the real env of its variant, from
its first state, with new noise (the deterministic variant replays its episode from the
float32 observation of its first state; contacts amplify that rounding over seconds). Printed and
written to ``benchmarks/results/<out>.json``: per model, truth (replayed, and as recorded) and
horizon, the episodes, the fewest episodes covered on any checked dimension, and the
dimensions the binomial test names as overconfident.

    python benchmarks/coverage_horizons.py RUN_DIR [--steps 20 60 120 240] [--samples 8]
                                           [--out coverage_horizons]

``RUN_DIR`` is a finished study run (its ``study_config.json``, ``data/`` and ``models/``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from _report import conditions, print_table, write_json
from tensordict import TensorDict

from rcvae_torchrl.data import load_episodes, split_episodes
from rcvae_torchrl.envs import CONTROL_TIMESTEP
from rcvae_torchrl.training import check_model, load_ensemble
from recipes.pusher_competency.config import DataConfig
from recipes.pusher_competency.data import replay_episodes
from recipes.pusher_competency.pusher import MODEL_FUNCTIONS, variant_randomness

VARIANTS = ("deterministic", "stochastic")
REPLAY_SEED = 4_321
INTERVAL = 0.9  # check_model's default


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--steps", type=int, nargs="+", default=[20, 60, 120, 240])
    parser.add_argument("--samples", type=int, default=8, help="imagined samples per member")
    parser.add_argument("--out", default="coverage_horizons")
    args = parser.parse_args()
    torch.set_num_threads(1)
    study = json.loads((args.run_dir / "study_config.json").read_text())
    data = DataConfig(**study["data"])
    rows, results = [], {}
    for variant in VARIANTS:
        model = load_ensemble(args.run_dir / "models" / f"{variant}.pt", functions=MODEL_FUNCTIONS)
        episodes = load_episodes(args.run_dir / "data" / f"{variant}.pt")
        _, held_out = split_episodes(episodes, 0.1, seed=study["seed"])  # the recipe's split
        truths = {
            "replayed": replay_episodes(
                held_out,
                max(args.steps) + 1,
                variant,
                seed=REPLAY_SEED,
                **variant_randomness(variant, data),
            ),
            "recorded": held_out,
        }
        for truth_name, truth in truths.items():
            results[f"{variant}, {truth_name}"] = _by_horizon(
                model, truth, args, rows, f"{variant}, {truth_name}"
            )
    print_table(
        f"Coverage of the {INTERVAL:.0%} interval by horizon: held-out episodes replayed, and "
        f"as recorded ({args.run_dir})",
        ["model, truth", "horizon s", "episodes", "fewest covered", "overconfident"],
        rows,
    )
    write_json(
        args.out,
        {
            "run_dir": str(args.run_dir),
            "seed": study["seed"],
            "settings": {"steps": args.steps, "samples_per_member": args.samples},
            "conditions": conditions(),
            "results": results,
        },
    )


def _by_horizon(model, truth: TensorDict, args, rows: list, label: str) -> dict:
    """The self-check's coverage at each horizon of ``args.steps``: the JSON entry; appends
    the table's rows."""
    out = {}
    for steps in args.steps:
        checks = check_model(
            model,
            truth,
            coverage_steps=steps,
            samples_per_member=args.samples,
            interval=INTERVAL,
            warn=False,
        )
        covered = checks.covered
        fewest = min(checks.checked, key=lambda d: float(covered[d]))
        flagged = [checks.names[d] for d in checks.overconfident]
        out[str(steps)] = {
            "seconds": steps * CONTROL_TIMESTEP,
            "episodes": checks.episodes,
            "interval": checks.interval,
            "covered": {checks.names[d]: int(covered[d]) for d in checks.checked},
            "overconfident": flagged,
        }
        rows.append(
            [
                label,
                steps * CONTROL_TIMESTEP,
                checks.episodes,
                f"{int(covered[fewest])} ({checks.names[fewest]})",
                ", ".join(flagged) or "-",
            ]
        )
    return out


if __name__ == "__main__":
    main()

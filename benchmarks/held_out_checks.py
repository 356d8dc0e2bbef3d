"""Which held-out check predicts a study's forecast bias: open-loop replays or the forecast itself?

Before a forecast is trusted on the tasks that matter, it can be checked on start states whose
real outcomes are cheap to get and that are not scored: the first states of the world models'
held-out episodes. Two ways, both judged by the study's success boundary, per world model in
the env its data came from (the deterministic and stochastic conditions):

- **open loop**: each held-out episode's recorded actions imagined from its first state (all
  members' samples pooled) against ``--replays`` replays of the same actions in the real env
  (new noise), :class:`~rcvae_torchrl.training.OutcomeCheck` on the per-episode rates;
- **closed loop**: the agent's forecast from the same first states against the agent's real
  episodes from them, exactly as the study's report checks it (``Study.forecast_check``).

Each beside the condition's scored gap (forecast minus real over the study's own start states,
from the run's ``summary.json``). Printed and written to ``benchmarks/results/<out>.json``.

    python benchmarks/held_out_checks.py RUN_DIR [--replays 10] [--samples 20]
                                         [--out held_out_checks]

``RUN_DIR`` is a finished study run.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from _report import conditions, print_table, write_json

from rcvae_torchrl.data import episode_spans
from rcvae_torchrl.io import read_json
from rcvae_torchrl.reporting import signed
from rcvae_torchrl.rollout import imagine
from rcvae_torchrl.training import OutcomeCheck
from recipes.pusher_competency.data import replay_episodes
from recipes.pusher_competency.pipeline import CHECKED_CONDITIONS, Study, study_of_run
from recipes.pusher_competency.pusher import CONDITIONS, success_boundary, variant_randomness

REPLAY_SEED = 6_173


def open_loop(study: Study, condition: str, replays: int, samples: int) -> OutcomeCheck:
    """The held-out episodes' own actions, imagined and replayed ``replays`` times."""
    name, variant = CONDITIONS[condition]
    s, steps = study.cfg.assess, study.max_steps
    _, held_out = study.episodes(name)
    first, lengths = episode_spans(held_out)
    first = first[lengths >= steps]
    frames = first[:, None] + torch.arange(steps)
    boundary = success_boundary(s.success_radius, s.horizon_s)
    real = []
    for r in range(replays):  # each replay its own noise: env i of replay r by seed + 1000 r + i
        truth = replay_episodes(
            held_out,
            steps,
            variant,
            seed=REPLAY_SEED + 1000 * r,
            **variant_randomness(variant, study.cfg.data),
        )
        states = truth.get(("next", "observation")).reshape(first.numel(), steps, -1)
        real.append(boundary.outcome(states)[1])
    model = study.load_model(name)
    rollouts = imagine(
        model,
        held_out.get("observation")[first],
        held_out.get("action")[frames],
        samples_per_member=samples,
        generator=torch.Generator().manual_seed(study.cfg.seed),
    )
    forecast = boundary.outcome(rollouts.get("observation"))[1].double().mean((0, 1))
    return OutcomeCheck.from_outcomes(
        forecast, torch.stack(real, 1), what=f"the open-loop replays ({condition})"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--replays", type=int, default=10)
    parser.add_argument("--samples", type=int, default=20, help="imagined samples per member")
    parser.add_argument("--out", default="held_out_checks")
    args = parser.parse_args()
    torch.set_num_threads(1)
    study = study_of_run(args.run_dir)
    config = study.cfg
    scored = read_json(args.run_dir / "summary.json", "study summary")["validation"]
    rows, results = [], {}
    for condition in CHECKED_CONDITIONS:
        started = time.perf_counter()
        checks = {
            "open loop": open_loop(study, condition, args.replays, args.samples),
            "closed loop": study.forecast_check(condition),
        }
        gap = scored[condition]["forecast"] - scored[condition]["real"]
        results[condition] = {
            "scored_gap": gap,
            **{k: c.as_dict() for k, c in checks.items()},
            "seconds": time.perf_counter() - started,
        }
        for kind, c in checks.items():
            low, high = c.interval()
            rows.append(
                [
                    condition,
                    kind,
                    c.starts,
                    f"{float(c.forecast.mean()):.3f}",
                    f"{float(c.real.mean()):.3f}",
                    f"{signed(c.gap)} ({signed(low)} to {signed(high)})",
                    f"{c.p_value:.2g}",
                    c.verdict,
                    signed(gap),
                ]
            )
    print_table(
        f"Held-out checks against the scored gap ({args.run_dir}, 1 thread)",
        ["condition", "check", "starts", "forecast", "real", "gap (test's level)", "p",
         "verdict", "scored gap"],
        rows,
    )  # fmt: skip
    write_json(
        args.out,
        {
            "run_dir": str(args.run_dir),
            "seed": config.seed,
            "settings": {"replays": args.replays, "samples_per_member": args.samples},
            "conditions": conditions(),
            "results": results,
        },
    )


if __name__ == "__main__":
    main()

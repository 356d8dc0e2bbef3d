"""How often the novelty check cautions a study's start states, and what it costs.

The world model's check of novelty (:class:`~rcvae_torchrl.training.StateNovelty`: a state's
distance to the training states against levels measured on states training never saw) is
fitted by training. For runs whose models were trained before it existed, it is fitted here as
training fits it (the same split of the same episodes, the training seed). Per condition of
each run: the start states unlike the training states, those the report cautions (the start,
or more of its imagined states than real episodes have: ``CompetencyReport.novel``), and the
per-start error |forecast - real rate| of the run's own forecasts among them and among the
others. The imagined states come from an assessment with ``--samples`` samples per member (the
check reads every member's first two samples at 20 steps of the horizon, so the count changes
nothing else).

Costs, 1 thread: fitting the check on each model's episodes, and the first run's
deterministic assessment with and without the check (interleaved medians).

    python benchmarks/novelty.py RUN_DIR [RUN_DIR ...] [--samples 2] [--out novelty]

Printed and written to ``benchmarks/results/<out>.json``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from _report import conditions, interleaved_median_times, print_table, write_json

from rcvae_torchrl.io import load_torch
from rcvae_torchrl.training import StateNovelty
from recipes.pusher_competency.pipeline import Study, study_of_run
from recipes.pusher_competency.pusher import CONDITIONS, WORLD_MODELS
from recipes.pusher_competency.report import novelty_rows


def novelty_of(study: Study, name: str) -> tuple[StateNovelty, float, bool]:
    """World model ``name``'s check: its own (training fitted it), or fitted as training fits
    it; the seconds that fit took (0 for its own) and whether it was its own."""
    own = study.load_model(name).novelty
    if own is not None:
        return own, 0.0, True
    train, val = study.episodes(name)
    started = time.perf_counter()
    fitted = StateNovelty.from_episodes(train, val, seed=study._train_config(name).seed)
    return fitted, time.perf_counter() - started, False


def condition_rows(study: Study, checks: dict[str, StateNovelty]) -> dict[str, dict]:
    """Per condition: the cautions and the per-start error among them and the others (the
    report's rows, ``novelty_rows``, of the run's own forecasts), and the mean share of
    imagined states beyond the states' level."""
    forecasts, truths, shares = {}, {}, {}
    for condition, (name, variant) in CONDITIONS.items():
        forecast = load_torch(study.dir / "forecast" / f"{condition}.pt", "forecast")
        truths[condition] = load_torch(study.dir / "truth" / f"{condition}.pt", "real outcomes")
        assessor = study.assessor(name, variant)
        assessor.model_env.ensemble.novelty = checks[name]
        report = assessor.assess(
            forecast["starts"], policy=study.load_policy(), seed=study.cfg.seed
        )
        forecasts[condition] = {
            "p_success": forecast["p_success"],
            "novelty_start": report.data["novelty", "start"],
            "novel": report.novel,
        }
        shares[condition] = float(report.data["novelty", "imagined"].mean())
    rows = novelty_rows(forecasts, truths)
    return {c: {**row, "imagined_share_mean": shares[c]} for c, row in rows.items()}


def assessment_cost(study: Study, check: StateNovelty) -> dict[str, dict[str, float]]:
    """The deterministic condition's assessment with and without the check."""
    name, variant = CONDITIONS["deterministic"]
    starts = load_torch(study.dir / "forecast" / "deterministic.pt", "forecast")["starts"]
    assessor, policy = study.assessor(name, variant), study.load_policy()

    def assess(with_check: bool):
        def run():
            assessor.model_env.ensemble.novelty = check if with_check else None
            return assessor.assess(starts, policy=policy, seed=study.cfg.seed)

        return run

    return interleaved_median_times({"with": assess(True), "without": assess(False)}, repeats=3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dirs", type=Path, nargs="+")
    parser.add_argument("--samples", type=int, default=2, help="imagined samples per member")
    parser.add_argument("--out", default="novelty")
    args = parser.parse_args()
    torch.set_num_threads(1)
    results, rows, fits = {}, [], []
    for run_dir in args.run_dirs:
        changes = {"assess": {"samples_per_member": args.samples, "bias_correction": "none"}}
        study = study_of_run(run_dir, changes=changes)
        fitted = {name: novelty_of(study, name) for name in WORLD_MODELS}
        checks = {name: found[0] for name, found in fitted.items()}
        by_condition = condition_rows(study, checks)
        results[str(run_dir)] = {
            "seed": study.cfg.seed,
            "models": {
                name: {
                    "own": own,
                    "fit_s": seconds,
                    "states": int(c.states.shape[0]),
                    "held_out": c.held_out,
                    "level": c.level,
                }
                for name, (c, seconds, own) in fitted.items()
            },
            "conditions": by_condition,
        }
        fits += [[run_dir.name, n, c.states.shape[0], s] for n, (c, s, _) in fitted.items()]
        for condition, row in by_condition.items():
            rows.append(
                [
                    run_dir.name,
                    condition,
                    row["starts"],
                    row["start_unlike"],
                    row["cautioned"],
                    f"{row['imagined_share_mean']:.4f}",
                    "–" if row["mae_cautioned"] is None else f"{row['mae_cautioned']:.3f}",
                    "–" if row["mae_rest"] is None else f"{row['mae_rest']:.3f}",
                ]
            )
    first = study_of_run(args.run_dirs[0], changes=changes)
    cost = assessment_cost(first, novelty_of(first, CONDITIONS["deterministic"][0])[0])
    print_table(
        "Start states the novelty check cautions (per-start error |forecast - real rate|)",
        ["run", "condition", "starts", "start unlike", "cautioned", "imagined share",
         "error, cautioned", "error, others"],
        rows,
    )  # fmt: skip
    print_table("Fitting the check (1 thread)", ["run", "model", "states kept", "fit s"], fits)
    print_table(
        f"The deterministic assessment of {args.run_dirs[0].name}, {args.samples} samples per "
        "member (1 thread, medians of 3 interleaved rounds)",
        ["check", "wall s", "cpu s", "load"],
        [[k, v["wall_s"], v["cpu_s"], v["load_1min"]] for k, v in cost.items()],
    )
    write_json(
        args.out,
        {
            "settings": {"samples_per_member": args.samples},
            "conditions": conditions(),
            "runs": results,
            "assessment_cost": cost,
            "overhead_ratio": cost["with"]["wall_s"] / cost["without"]["wall_s"],
        },
    )


if __name__ == "__main__":
    main()

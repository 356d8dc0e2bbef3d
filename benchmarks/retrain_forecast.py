"""Does a training or model setting move the forecast? Retrain a finished run's world model with
other settings, forecast again, score against the same real episodes.

A finished study run holds its data, world models, agent, forecasts and real episodes. This
script trains the world model of each ``--conditions`` condition anew, as the run's models stage
did (same data, same split, same seed) but with ``--set SECTION.KEY=VALUE`` settings changed
(e.g. ``train.batch_windows=64``), forecasts the condition's scored start states again with the
run's own agent, and compares both forecasts with the run's own real episodes (``truth/``):
gap (forecast minus real), Brier skill against the condition's own rate, per-start Spearman and
mean absolute error, AUROC. The agent is the run's (distilled from a planner over the run's own
deterministic model), so only the world model of the forecast changes: what a whole run with
the setting would give beside it also depends on the agent that setting would make.

    python benchmarks/retrain_forecast.py RUN_DIR [RUN_DIR ...] --set train.batch_windows=64
        [--set ...] [--conditions stochastic] [--work-dir /tmp/retrain_forecast]
        [--out retrain_forecast]

Nothing in ``RUN_DIR`` is changed: each model and forecast goes to ``--work-dir/<run>``, and a
model already trained there with the same settings is reused (so a stopped script resumes).
One torch thread.
"""

from __future__ import annotations

import argparse
import ast
import time
from pathlib import Path

import torch
from _report import atomic_json, conditions, print_table, write_json
from closed_loop_data import check_finished, open_run

from rcvae_torchrl.competency import validate_forecasts
from rcvae_torchrl.io import load_torch, read_json
from recipes.pusher_competency.pusher import CONDITIONS


def parse_setting(text: str) -> tuple[str, str, object]:
    """``SECTION.KEY=VALUE`` as ``(section, key, value)``; the value as a Python literal where it
    reads as one (``64``, ``3e-3``, ``[0.2, 0.4]``, ``None``), else as the string."""
    name, sep, raw = text.partition("=")
    section, dot, key = name.partition(".")
    if not (sep and dot and section and key):
        raise SystemExit(
            f"--set: expected SECTION.KEY=VALUE (e.g. train.batch_windows=64), got {text!r}"
        )
    try:
        value = ast.literal_eval(raw)
    except (ValueError, SyntaxError):
        value = raw
    return section, key, value


def score(forecast: dict, truth: dict) -> dict:
    """The forecast's scores against the real episodes ``truth``."""
    p, success = forecast["p_success"], truth["success"]
    scores = validate_forecasts(p, success)
    return {
        "forecast": float(p.mean()),
        "gap": float(p.mean() - success.float().mean()),
        "brier_skill": scores["brier_skill"],
        "auroc": scores["auroc"],
        "per_start_mae": scores["per_start_mae"],
        "spearman": scores["spearman"],
    }


def one_run(run_dir: Path, changes: dict, args) -> list[dict]:
    """Retrain ``run_dir``'s world models of ``args.conditions`` with ``changes``, forecast and
    score each condition before and after."""
    work = args.work_dir / "_".join(run_dir.resolve().parts[-2:])
    (work / "models").mkdir(parents=True, exist_ok=True)
    (work / "forecast").mkdir(exist_ok=True)
    for part in ("data", "agent"):
        if not (work / part).exists():
            (work / part).symlink_to((run_dir / part).resolve())
    settings = work / "settings.json"
    if settings.exists() and read_json(settings, "settings") != changes:
        raise SystemExit(
            f"--work-dir: {str(work)!r} holds models trained with other settings "
            f"({read_json(settings, 'settings')}); give another --work-dir"
        )
    atomic_json(settings, changes)
    study = open_run(run_dir, work, changes)
    rows, trained = [], {}
    for condition in args.conditions:
        model_name = CONDITIONS[condition][0]
        if model_name not in trained:
            start = time.perf_counter()
            if not (work / "models" / f"{model_name}.pt").exists():
                study.train_world_model(model_name)
            trained[model_name] = time.perf_counter() - start
        start = time.perf_counter()
        study.forecast_condition(condition)
        truth = load_torch(run_dir / "truth" / f"{condition}.pt", "real outcomes")
        rows.append(
            {
                "run": str(run_dir),
                "condition": condition,
                "real": float(truth["success"].float().mean()),
                "before": score(
                    load_torch(run_dir / "forecast" / f"{condition}.pt", "forecast"), truth
                ),
                "after": score(
                    load_torch(work / "forecast" / f"{condition}.pt", "forecast"), truth
                ),
                "best_val_loss": [_best_val_loss(d, model_name) for d in (run_dir, work)],
                "train_s": trained[model_name],
                "forecast_s": time.perf_counter() - start,
            }
        )
    return rows


def _best_val_loss(run_dir: Path, model_name: str) -> float:
    """The best held-out loss world model ``model_name`` of ``run_dir`` reached in training."""
    saved = load_torch(run_dir / "models" / f"{model_name}.pt", "model checkpoint")
    return float(saved["extra"]["training"]["best_val_loss"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", type=Path, nargs="+")
    parser.add_argument("--set", dest="settings", action="append", required=True, default=[])
    parser.add_argument("--conditions", nargs="+", default=["stochastic"], choices=CONDITIONS)
    parser.add_argument("--work-dir", type=Path, default=Path("/tmp/retrain_forecast"))
    parser.add_argument("--out", default="retrain_forecast")
    args = parser.parse_args()
    changes: dict[str, dict] = {}
    for text in args.settings:
        section, key, value = parse_setting(text)
        changes.setdefault(section, {})[key] = value
    check_finished(args.run_dirs)
    torch.set_num_threads(1)
    rows = [row for run_dir in args.run_dirs for row in one_run(run_dir, changes, args)]
    print_table(
        f"Forecast before / after retraining the world model with {', '.join(args.settings)}",
        [
            "run",
            "condition",
            "real",
            "forecast",
            "gap",
            "Brier skill",
            "Spearman",
            "AUROC",
            "best val loss",
        ],
        [
            [
                "/".join(Path(r["run"]).parts[-1:]),
                r["condition"],
                f"{r['real']:.3f}",
                *(
                    f"{r['before'][k]:{fmt}} / {r['after'][k]:{fmt}}"
                    for k, fmt in (
                        ("forecast", ".3f"),
                        ("gap", "+.3f"),
                        ("brier_skill", ".3f"),
                        ("spearman", ".3f"),
                        ("auroc", ".3f"),
                    )
                ),
                "{:.2f} / {:.2f}".format(*r["best_val_loss"]),
            ]
            for r in rows
        ],
    )
    settings = {
        "run_dirs": [str(p) for p in args.run_dirs],
        "changes": changes,
        "conditions": args.conditions,
    }
    write_json(args.out, {"settings": settings, "conditions": conditions(), "rows": rows})


if __name__ == "__main__":
    main()

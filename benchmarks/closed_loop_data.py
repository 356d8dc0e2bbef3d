"""Does world-model data from the agent's own closed-loop episodes move the forecast?

A study's world models learn from the scripted pusher's episodes (with exploration noise) and
random ones; the agent they forecast is another policy, so the states it visits are not the
ones the model saw most. This script adds ``--episodes`` episodes of the run's own agent (its
distilled policy with the data's exploration noise, in the real Pusher the model was trained
on, from the data's own start distribution, ``data.time_limit`` long) to a finished run's
world-model data (90 % to training, 10 % to the held-out episodes, as the data's own split),
fine-tunes the trained model on the union for ``--steps`` steps at ``--lr`` (or, with
``--from-scratch``, trains a new ensemble on it with the run's own training settings, as its
models stage did), and forecasts the run's scored start states again. The real outcomes are
the run's own (``truth/``), so the forecast before and after is compared with the same
episodes: gap (forecast minus real), per-start Spearman, epistemic bits.

    python benchmarks/closed_loop_data.py RUN_DIR [RUN_DIR ...]
        [--conditions stochastic out-of-distribution] [--episodes 100] [--steps 2500]
        [--lr 3e-4] [--from-scratch] [--work-dir /tmp/closed_loop_data] [--out closed_loop_data]

``RUN_DIR``: a finished study run (``forecast/``, ``truth/``, ``models/``, ``agent/``, ``data/``,
and ``study_config.json``, or a run whose ``agent/`` links to the run that made it: its
settings are read there, the start states counted in the forecast). Nothing in it is changed:
the fine-tuned models and new forecasts go to ``--work-dir``. One torch thread.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import time
from pathlib import Path

import torch
from _report import conditions, print_table, write_json
from scipy.stats import spearmanr

from rcvae_torchrl.data import (
    GaussianExploration,
    collect_episodes,
    make_policy_module,
    merge_episodes,
    split_episodes,
)
from rcvae_torchrl.envs import make_pusher_env
from rcvae_torchrl.io import load_torch
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.reporting import signed
from rcvae_torchrl.training import save_ensemble, train_ensemble
from recipes.pusher_competency.pipeline import Study, study_of_run
from recipes.pusher_competency.pusher import (
    CONDITIONS,
    MODEL_FUNCTIONS,
    rcvae_config,
    variant_randomness,
)

#: The agent's episodes are seeded apart from every seed the study itself draws.
AGENT_DATA_SEED = 77_000
#: What a finished run holds that this script reads.
FINISHED = ("data", "models", "agent/policy.pt", "forecast", "truth")


def check_finished(run_dirs: list[Path]) -> None:
    """Refuse, naming ``run_dirs``, a directory that lacks a part of a finished run."""
    for run_dir in run_dirs:
        missing = [p for p in FINISHED if not (run_dir / p).exists()]
        if missing:
            raise SystemExit(
                f"run_dirs: expected finished study runs, {str(run_dir)!r} lacks "
                f"{', '.join(missing)}"
            )


def open_run(run_dir: Path, work: Path | None = None, changes: dict | None = None) -> Study:
    """The study of ``run_dir`` (with the settings of the run its ``agent/`` was made in where it
    records none, and the start-state count of its forecasts), in ``work`` if given, with each
    section's keys in ``changes`` replaced."""
    origin = run_dir
    if not (run_dir / "study_config.json").is_file():
        origin = (run_dir / "agent").resolve().parent
    starts = load_torch(run_dir / "forecast" / "deterministic.pt", "forecast")["starts"]
    changed = {section: dict(values) for section, values in (changes or {}).items()}
    changed.setdefault("assess", {})["start_states"] = len(starts)
    return study_of_run(work or run_dir, changes=changed, settings_from=origin)


def agent_episodes(study: Study, model_name: str, episodes: int):
    """``episodes`` episodes of the run's agent (with the data's exploration noise) in the real
    Pusher that world model ``model_name`` learned from: training and held-out parts."""
    d, seed = study.cfg.data, study.cfg.seed
    make_env = functools.partial(
        make_pusher_env,
        model_name,
        time_limit=d.time_limit,
        terminate_on_success=False,
        **variant_randomness(model_name, d),
    )
    behaviour = GaussianExploration(study.load_policy(), d.exploration_std, seed=AGENT_DATA_SEED)
    data = collect_episodes(
        make_env,
        make_policy_module(behaviour),
        episodes,
        seed=AGENT_DATA_SEED + seed,
        num_envs=4,
        progress=False,
    )
    return split_episodes(data, 0.1, seed=seed)


def refit(run_dir: Path, work: Path, model_name: str, args) -> dict:
    """Fine-tune ``run_dir``'s world model ``model_name`` on its data plus the agent's episodes;
    saved in ``work/models``. Returns the seconds spent and the validation losses."""
    study = open_run(run_dir)
    start = time.perf_counter()
    extra_train, extra_val = agent_episodes(study, model_name, args.episodes)
    train, val = study.episodes(model_name)
    collected = time.perf_counter()
    config = study._train_config(model_name)
    if args.from_scratch:  # a new ensemble, as the study's models stage makes it
        torch.manual_seed(study.cfg.seed)
        m = study.cfg.model
        model = RCVAEEnsemble(rcvae_config(m), m.ensemble_size, functions=MODEL_FUNCTIONS)
    else:
        model = study.load_model(model_name)
        config = dataclasses.replace(config, max_steps=args.steps, lr=args.lr)
    result = train_ensemble(
        model,
        merge_episodes(train, extra_train),
        merge_episodes(val, extra_val),
        config,
        progress=False,
        checks=False,
    )
    save_ensemble(result.ensemble, work / "models" / f"{model_name}.pt", extra={"refit": True})
    return {
        "collect_s": collected - start,
        "train_s": time.perf_counter() - collected,
        "val_loss_first": result.history[0]["val_loss"],
        "val_loss_last": result.history[-1]["val_loss"],
    }


def score(forecast: dict, truth: dict) -> dict:
    real = truth["success"].float()
    p = forecast["p_success"]
    return {
        "forecast": p.mean().item(),
        "gap": (p.mean() - real.mean()).item(),
        "spearman": float(spearmanr(p, real.mean(1)).statistic),
        "epistemic_bits": forecast["epistemic"].sum(-1).mean().item(),
    }


def one_run(run_dir: Path, args) -> list[dict]:
    work = args.work_dir / "_".join(run_dir.resolve().parts[-2:])  # e.g. weak_arm_seed0
    (work / "models").mkdir(parents=True, exist_ok=True)
    (work / "forecast").mkdir(exist_ok=True)
    for part in ("data", "agent"):
        if not (work / part).exists():
            (work / part).symlink_to((run_dir / part).resolve())
    study = open_run(run_dir, work)
    fits, rows = {}, []
    for condition in args.conditions:
        model_name = CONDITIONS[condition][0]
        if model_name not in fits:
            fits[model_name] = refit(run_dir, work, model_name, args)
        start = time.perf_counter()
        study.forecast_condition(condition)
        truth = load_torch(run_dir / "truth" / f"{condition}.pt", "real outcomes")
        before = score(load_torch(run_dir / "forecast" / f"{condition}.pt", "forecast"), truth)
        after = score(load_torch(work / "forecast" / f"{condition}.pt", "forecast"), truth)
        rows.append(
            {
                "run": str(run_dir),
                "condition": condition,
                "real": truth["success"].float().mean().item(),
                "before": before,
                "after": after,
                "refit": fits[model_name],
                "forecast_s": time.perf_counter() - start,
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dirs", type=Path, nargs="+")
    parser.add_argument(
        "--conditions", nargs="+", default=["stochastic", "out-of-distribution"], choices=CONDITIONS
    )
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--steps", type=int, default=2500)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument(
        "--from-scratch",
        action="store_true",
        help="train a new ensemble on the union with the run's own settings (not fine-tune)",
    )
    parser.add_argument("--work-dir", type=Path, default=Path("/tmp/closed_loop_data"))
    parser.add_argument("--out", default="closed_loop_data")
    args = parser.parse_args()
    for name in ("episodes", "steps"):
        if getattr(args, name) < 1:
            raise SystemExit(f"--{name}: expected at least 1, got {getattr(args, name)}")
    if not args.lr > 0:
        raise SystemExit(f"--lr: expected a positive learning rate, got {args.lr}")
    check_finished(args.run_dirs)
    torch.set_num_threads(1)
    rows = [row for run_dir in args.run_dirs for row in one_run(run_dir, args)]
    how = (
        "training anew"
        if args.from_scratch
        else f"fine-tuning ({args.steps} steps, lr {args.lr:g})"
    )
    print_table(
        f"Forecast before / after {how} on the data and {args.episodes} agent episodes",
        ["run", "condition", "real", "forecast", "gap", "Spearman", "epistemic bits"],
        [
            [
                "/".join(Path(r["run"]).parts[-2:]),
                r["condition"],
                r["real"],
                f"{r['before']['forecast']:.3f} / {r['after']['forecast']:.3f}",
                f"{signed(r['before']['gap'])} / {signed(r['after']['gap'])}",
                f"{r['before']['spearman']:.3f} / {r['after']['spearman']:.3f}",
                f"{r['before']['epistemic_bits']:.3f} / {r['after']['epistemic_bits']:.3f}",
            ]
            for r in rows
        ],
    )
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    settings["run_dirs"] = [str(p) for p in args.run_dirs]
    write_json(args.out, {"settings": settings, "conditions": conditions(), "rows": rows})


if __name__ == "__main__":
    main()

"""Competency of a PD controller on dm_control's point_mass, checked against real episodes.

    python recipes/point_mass_competency/main.py                 # default profile
    python recipes/point_mass_competency/main.py profile=quick   # every stage, tiny budgets

The library used as a new user would, on an env this project did not write: dict float64
observations prepared with ``prepare_env``, a stochastic variant through a TorchRL transform,
start states replayed by seed. Re-running with the same ``run_dir`` reuses finished stages;
``reuse_from=<another run_dir>`` takes that run's data and models where their settings match.
The console's lines also go to ``<run_dir>/run.log``; training curves and stage summaries go to
the logger chosen with ``logger=csv|tensorboard|wandb|mlflow|none`` under ``<run_dir>/logs``.
"""

from __future__ import annotations

import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import hydra
import torch
from omegaconf import DictConfig
from torchrl.record.loggers import generate_exp_name

from rcvae_torchrl.loggers import make_logger
from rcvae_torchrl.run_log import run_log
from rcvae_torchrl.stages import check_run_directory
from recipes._settings import (
    RUN_MADE,
    check_override_keys,
    check_printed_config,
    run_dir_refusal,
    set_threads,
)
from recipes.point_mass_competency.config import (
    PROFILES,
    RecipeConfig,
    register_configs,
    study_config,
)
from recipes.point_mass_competency.pipeline import run_study, study_settings

register_configs()


@hydra.main(config_path="conf", config_name="point_mass_competency", version_base="1.3")
def main(cfg: DictConfig) -> None:
    try:
        config = study_config(cfg)
    except (TypeError, ValueError) as error:  # a setting out of range: its message, no trace
        raise SystemExit(f"error: {error}") from None
    set_threads(config.threads)
    run_dir = Path(config.run_dir)
    # a run directory of other settings, or of files of the user's own, is refused before
    # anything is made in it
    try:
        check_run_directory(run_dir, study_settings(config), made_before=RUN_MADE)
    except ValueError as error:
        raise run_dir_refusal(error, run_dir, config.profile) from None
    with run_log(run_dir / "run.log") as log:
        threads = torch.get_num_threads()
        log.info(f"profile={config.profile} threads={threads} run_dir={run_dir}")
        logger = make_logger(
            config.logger, run_dir / "logs", generate_exp_name("point_mass", config.profile)
        )
        try:
            summary = run_study(
                config,
                run_dir,
                progress=config.progress,
                log=log.info,
                logger=logger,
                reuse_from=config.reuse_from,
            )
        finally:
            if logger is not None:
                logger.close()
        for name, check in summary["report"]["checks"].items():
            log.info(f"{'ok ' if check['met'] else 'NO '} {name}: {check['value']}")
        log.info(f"report: {run_dir}/report.md")


if __name__ == "__main__":
    check_override_keys(RecipeConfig, sys.argv[1:])
    check_printed_config(
        RecipeConfig, sys.argv[1:], PROFILES.parent, "point_mass_competency", PROFILES
    )
    main()

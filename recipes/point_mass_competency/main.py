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
from recipes._settings import (
    check_command_line,
    claim_run_dir,
    say_checks,
    set_threads,
    typed_settings,
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
    config = typed_settings(study_config, cfg)
    set_threads(config.threads)
    run_dir = Path(config.run_dir)
    claim_run_dir(run_dir, study_settings(config), config.profile)
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
        say_checks(summary, run_dir, log.info)


if __name__ == "__main__":
    check_command_line(RecipeConfig, sys.argv[1:], PROFILES, "point_mass_competency")
    main()

"""Pusher competency study: reproduce the paper's table and figure, then check the forecasts.

    python recipes/pusher_competency/main.py                      # default profile
    python recipes/pusher_competency/main.py profile=quick        # every stage, tiny budgets
    python recipes/pusher_competency/main.py profile=full device=cuda
    python recipes/pusher_competency/main.py run_dir=outputs/my_run train.max_steps=3000

Re-running with the same ``run_dir`` reuses the finished stages. The console's lines also go
to ``<run_dir>/run.log`` (plain text); training curves and stage summaries go to the logger
chosen with ``logger=csv|tensorboard|wandb|mlflow|none`` under ``<run_dir>/logs``. Every
setting and its default
is in ``config.py``; the profiles in ``conf/profile/`` hold their differences. Unknown keys
and values of the wrong type or out of range are rejected before anything runs.
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
from recipes.pusher_competency.config import register_configs, study_config
from recipes.pusher_competency.pipeline import resolve_device, run_study, set_threads

register_configs()


@hydra.main(config_path="conf", config_name="pusher_competency", version_base="1.3")
def main(cfg: DictConfig) -> None:
    config = study_config(cfg)
    device = resolve_device(config.device)
    set_threads(config.threads)
    run_dir = Path(config.run_dir)
    with run_log(run_dir / "run.log") as log:
        threads = torch.get_num_threads()
        log.info(f"profile={config.profile} device={device} threads={threads} run_dir={run_dir}")
        name = generate_exp_name("pusher_competency", config.profile)
        logger = make_logger(config.logger, run_dir / "logs", name)
        try:
            summary = run_study(
                config,
                run_dir,
                device=device,
                progress=config.progress,
                log=log.info,
                logger=logger,
            )
        finally:
            if logger is not None:
                logger.close()
        for name, check in summary["report"]["checks"].items():
            log.info(f"{'ok ' if check['met'] else 'NO '} {name}: {check['value']:.3f}")
        log.info(f"report: {run_dir}/report.md")


if __name__ == "__main__":
    main()

"""Pusher competency study: reproduce the paper's table and figure, then check the forecasts.

    python recipes/pusher_competency/main.py                      # default profile
    python recipes/pusher_competency/main.py profile=quick        # every stage, tiny budgets
    python recipes/pusher_competency/main.py profile=full device=cuda
    python recipes/pusher_competency/main.py run_dir=outputs/my_run train.max_steps=3000
    torchrun --nproc_per_node=2 recipes/pusher_competency/main.py profile=quick  # 2 ranks
    python recipes/pusher_competency/main.py -m hydra/launcher=local seed=0,1 \
        'run_dir=outputs/pusher_competency/${profile}/seed${seed}'          # a local sweep

Under ``torchrun`` the training, forecast and real-episode stages share their work over the
ranks and give the results of one process; rank 0 alone writes files and prints (see
docs/scale_out.rst). Re-running with the same ``run_dir`` reuses the finished stages; a new
``run_dir`` with ``reuse_from=<another run_dir>`` takes that run's finished stages whose
settings are the same (e.g. its data, world models and agent when only ``assess.*`` differs). The
console's lines also go to ``<run_dir>/run.log`` (plain text); training curves and stage
summaries go to the logger chosen with ``logger=csv|tensorboard|wandb|mlflow|none`` under
``<run_dir>/logs``. Every
setting and its default is in ``config.py``; the profiles in ``conf/profile/`` hold their
differences. Unknown keys and values of the wrong type or out of range are rejected before
anything runs, and before ``--cfg job`` prints the config.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import hydra
import torch
from omegaconf import DictConfig
from torchrl.record.loggers import generate_exp_name

from rcvae_torchrl import distributed
from rcvae_torchrl.loggers import make_logger
from rcvae_torchrl.run_log import run_log
from recipes._settings import (
    check_command_line,
    claim_run_dir,
    resolve_device,
    say_checks,
    set_threads,
    typed_settings,
)
from recipes.pusher_competency.config import (
    PROFILES,
    RecipeConfig,
    register_configs,
    study_config,
)
from recipes.pusher_competency.pipeline import run_study, study_settings, training_op_flop

register_configs()


@hydra.main(config_path="conf", config_name="pusher_competency", version_base="1.3")
def main(cfg: DictConfig) -> None:
    config = typed_settings(study_config, cfg)
    device = resolve_device(config.device)
    set_threads(config.threads, training_op_flop(config))
    with distributed.session():  # a process group under torchrun, nothing otherwise
        if device == "cuda" and distributed.is_active():
            device = f"cuda:{torch.cuda.current_device()}"
        if distributed.is_main():  # rank 0 alone prints, logs and writes run.log
            claim_run_dir(config.run_dir, study_settings(config), config.profile)
            with run_log(Path(config.run_dir) / "run.log") as log:
                _run(config, device, log.info)
        else:
            _run(config, device, None)


def _run(config: RecipeConfig, device: str, say: Callable[[str], None] | None) -> None:
    run_dir = Path(config.run_dir)
    logger = None
    if say is not None:
        say(
            f"profile={config.profile} device={device} threads={torch.get_num_threads()} "
            f"ranks={distributed.world_size()} run_dir={run_dir}"
        )
        name = generate_exp_name("pusher_competency", config.profile)
        logger = make_logger(config.logger, run_dir / "logs", name)
    say = say or (lambda line: None)
    try:
        summary = run_study(
            config,
            run_dir,
            device=device,
            progress=config.progress,
            log=say,
            logger=logger,
            stage_workers=config.stage_workers,
            reuse_from=config.reuse_from,
        )
    finally:
        if logger is not None:
            logger.close()
    say_checks(summary, run_dir, say)


if __name__ == "__main__":
    check_command_line(RecipeConfig, sys.argv[1:], PROFILES, "pusher_competency")
    main()

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
docs/scale_out.rst). Re-running with the same ``run_dir`` reuses the finished stages. Every
setting and its default is in ``config.py``; the profiles in ``conf/profile/`` hold their
differences. Unknown keys and values of the wrong type or out of range are rejected before
anything runs.
"""

from __future__ import annotations

import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import hydra
import torch
from omegaconf import DictConfig

from rcvae_torchrl import distributed
from recipes._settings import resolve_device, set_threads
from recipes.pusher_competency.config import register_configs, study_config
from recipes.pusher_competency.pipeline import run_study

register_configs()


@hydra.main(config_path="conf", config_name="pusher_competency", version_base="1.3")
def main(cfg: DictConfig) -> None:
    config = study_config(cfg)
    device = resolve_device(config.device)
    set_threads(config.threads)
    with distributed.session():  # a process group under torchrun, nothing otherwise
        if device == "cuda" and distributed.is_active():
            device = f"cuda:{torch.cuda.current_device()}"
        say = print if distributed.is_main() else lambda *args: None
        say(
            f"profile={config.profile} device={device} run_dir={config.run_dir} "
            f"ranks={distributed.world_size()}"
        )
        summary = run_study(config, config.run_dir, device=device, progress=config.progress)
        for name, check in summary["report"]["checks"].items():
            say(f"{'ok ' if check['met'] else 'NO '} {name}: {check['value']:.3f}")
        say(f"report: {config.run_dir}/report.md")


if __name__ == "__main__":
    main()

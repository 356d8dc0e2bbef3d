"""Pusher competency study: reproduce the paper's table and figure, then check the forecasts.

    python recipes/pusher_competency/main.py                      # default profile
    python recipes/pusher_competency/main.py profile=quick        # every stage, tiny budgets
    python recipes/pusher_competency/main.py profile=full device=cuda
    python recipes/pusher_competency/main.py run_dir=outputs/my_run train.max_steps=3000

Re-running with the same ``run_dir`` reuses the finished stages. Every setting and its default
is in ``config.py``; the profiles in ``conf/profile/`` hold their differences. Unknown keys
and values of the wrong type or out of range are rejected before anything runs.
"""

from __future__ import annotations

import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import hydra
from omegaconf import DictConfig

from recipes._settings import resolve_device, set_threads
from recipes.pusher_competency.config import register_configs, study_config
from recipes.pusher_competency.pipeline import run_study

register_configs()


@hydra.main(config_path="conf", config_name="pusher_competency", version_base="1.3")
def main(cfg: DictConfig) -> None:
    config = study_config(cfg)
    device = resolve_device(config.device)
    set_threads(config.threads)
    print(f"profile={config.profile} device={device} run_dir={config.run_dir}")
    summary = run_study(config, config.run_dir, device=device, progress=config.progress)
    for name, check in summary["report"]["checks"].items():
        print(f"{'ok ' if check['met'] else 'NO '} {name}: {check['value']:.3f}")
    print(f"report: {config.run_dir}/report.md")


if __name__ == "__main__":
    main()

"""Competency of a PD controller on dm_control's point_mass, checked against real episodes.

    python recipes/point_mass_competency/main.py                 # default profile
    python recipes/point_mass_competency/main.py profile=quick   # every stage, tiny budgets

The library used as a new user would, on an env this project did not write: dict float64
observations prepared with ``prepare_env``, a stochastic variant through a TorchRL transform,
start states replayed by seed. Re-running with the same ``run_dir`` reuses finished stages.
"""

from __future__ import annotations

import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import hydra
from omegaconf import DictConfig

from recipes._settings import set_threads
from recipes.point_mass_competency.config import register_configs, study_config
from recipes.point_mass_competency.pipeline import run_study

register_configs()


@hydra.main(config_path="conf", config_name="point_mass_competency", version_base="1.3")
def main(cfg: DictConfig) -> None:
    config = study_config(cfg)
    set_threads(config.threads)
    print(f"profile={config.profile} run_dir={config.run_dir}")
    summary = run_study(config, config.run_dir, progress=config.progress)
    for name, check in summary["report"]["checks"].items():
        print(f"{'ok ' if check['met'] else 'NO '} {name}: {check['value']}")
    print(f"report: {config.run_dir}/report.md")


if __name__ == "__main__":
    main()

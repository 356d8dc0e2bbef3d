"""Pusher competency study: reproduce the paper's table and figure, then check the forecasts.

    python recipes/pusher_competency.py                      # default profile (CPU, ~20 min)
    python recipes/pusher_competency.py profile=quick        # smoke run (~3 min)
    python recipes/pusher_competency.py profile=full device=cuda
    python recipes/pusher_competency.py run_dir=outputs/my_run train.max_steps=3000

Re-running with the same ``run_dir`` reuses the finished stages. Every setting is in
``recipes/config/``; unknown keys are rejected.
"""

from __future__ import annotations

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from rcvae_torchrl.study import StudyConfig, from_mapping, run_study

_RECIPE_KEYS = ("run_dir", "device", "threads", "progress", "profile")


def _device(name: str) -> str:
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device: {name!r} asked for, but CUDA is not available here")
    return name


@hydra.main(config_path="config", config_name="pusher_competency", version_base="1.3")
def main(cfg: DictConfig) -> None:
    values = OmegaConf.to_container(cfg, resolve=True)
    settings = {k: values.pop(k) for k in _RECIPE_KEYS if k in values}
    if settings.get("threads"):
        torch.set_num_threads(int(settings["threads"]))
    study = from_mapping(StudyConfig, values)
    device = _device(settings.get("device", "auto"))
    print(f"profile={settings.get('profile')} device={device} run_dir={settings['run_dir']}")
    summary = run_study(
        study, settings["run_dir"], device=device, progress=bool(settings.get("progress", True))
    )
    report = summary["report"]
    for name, check in report["checks"].items():
        print(f"{'ok ' if check['met'] else 'NO '} {name}: {check['value']:.3f}")
    print(f"report: {settings['run_dir']}/report.md")


if __name__ == "__main__":
    main()

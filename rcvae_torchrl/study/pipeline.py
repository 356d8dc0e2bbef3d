"""The Pusher competency study, stage by stage (used by ``recipes/pusher_competency.py``).

1. ``data``: world-model data in the deterministic and the stochastic Pusher.
2. ``models``: an RCVAE ensemble trained on each.
3. ``agent``: MPC episodes with the deterministic model teach the agent's amortised policy.
4. ``forecast``: the paper's three conditions, forecast in imagination with the agent's policy.
5. ``truth``: the same agent in the real env from the same start states.
6. ``report``: the paper's table plus calibration, the figures, a GIF and ``report.md``.

Every stage writes its outputs atomically under the run directory and a marker when done;
running again with the same directory reuses finished stages (and training resumes from its
last checkpoint).
"""

from __future__ import annotations

import dataclasses
import functools
import json
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from torchrl.envs import EnvBase

from rcvae_torchrl.agent import MLPPolicy, ResidualPolicy, make_policy_module, run_episodes
from rcvae_torchrl.data import load_episodes, save_episodes, split_episodes
from rcvae_torchrl.envs import (
    CONTROL_TIMESTEP,
    make_pusher_env,
    pusher_reward,
    pusher_success,
)
from rcvae_torchrl.envs.datasets import collect_pusher_data
from rcvae_torchrl.envs.scripted import ScriptedPusher
from rcvae_torchrl.model_env import make_rcvae_env
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.training import TrainConfig, load_ensemble, save_ensemble, train_ensemble
from rcvae_torchrl.training.atomic import atomic_write

from .agent_stage import collect_mpc_demonstrations, dagger
from .config import StudyConfig
from .forecast import forecast_condition
from .report import write_report
from .stages import StageRunner
from .truth import real_outcomes

__all__ = ["CONDITIONS", "run_study"]

#: condition -> (world model, real env variant), as in the paper's Table 1.
CONDITIONS: dict[str, tuple[str, str]] = {
    "deterministic": ("deterministic", "deterministic"),
    "stochastic": ("stochastic", "stochastic"),
    "out-of-distribution": ("deterministic", "ood"),
}
VARIANTS = ("deterministic", "stochastic")


def _save(obj: Any, path: Path) -> Path:
    return atomic_write(path, lambda f: torch.save(obj, f))


def _load(path: Path) -> Any:
    return torch.load(path, weights_only=True)


class _Study:
    def __init__(
        self, config: StudyConfig, run_dir: Path, device: torch.device, progress: bool
    ) -> None:
        self.cfg, self.dir, self.device, self.progress = config, run_dir, device, progress

    # ------------------------------------------------------------------ helpers
    def env(self, variant: str, **kwargs: Any) -> EnvBase:
        noise = self.cfg.data.stochastic_noise_std if variant == "stochastic" else None
        return make_pusher_env(
            variant, action_noise_std=noise, success_radius=self.cfg.assess.success_radius, **kwargs
        )

    def model(self, variant: str) -> RCVAEEnsemble:
        return load_ensemble(self.dir / "models" / f"{variant}.pt", map_location=self.device)

    def policy(self) -> torch.nn.Module:
        """The agent: the distilled MLP, or the scripted prior plus the distilled correction."""
        saved = _load(self.dir / "agent" / "policy.pt")
        mlp = MLPPolicy(saved["obs_dim"], saved["action_dim"], saved["hidden"])
        mlp.load_state_dict(saved["state_dict"])
        if saved.get("residual_of_scripted", False):
            return ResidualPolicy(ScriptedPusher(), mlp).eval()
        return mlp.eval()

    # ------------------------------------------------------------------ stages
    def data(self) -> dict[str, Any]:
        d, summary = self.cfg.data, {}
        for variant in VARIANTS:
            path = self.dir / "data" / f"{variant}.pt"
            if not path.is_file():
                noise = (
                    {"action_noise_std": d.stochastic_noise_std} if variant == "stochastic" else {}
                )
                data = collect_pusher_data(
                    variant,
                    scripted_episodes=d.scripted_episodes,
                    random_episodes=d.random_episodes,
                    exploration_std=d.exploration_std,
                    time_limit=d.time_limit,
                    random_time_limit=d.random_time_limit,
                    seed=self.cfg.seed,
                    progress=self.progress,
                    **noise,
                )
                save_episodes(data, path)
            summary[f"{variant}_frames"] = int(load_episodes(path).shape[0])
        return summary

    def _train_config(self, variant: str) -> TrainConfig:
        steps = self.cfg.model.stochastic_open_loop_steps
        if variant != "stochastic" or steps is None:
            return self.cfg.train
        return dataclasses.replace(self.cfg.train, open_loop_steps=steps)

    def models(self) -> dict[str, Any]:
        m, summary = self.cfg.model, {}
        for variant in VARIANTS:
            path = self.dir / "models" / f"{variant}.pt"
            if path.is_file():
                continue
            torch.manual_seed(self.cfg.seed)
            ensemble = RCVAEEnsemble(m.rcvae_config(), m.ensemble_size).to(self.device)
            train, val = split_episodes(
                load_episodes(self.dir / "data" / f"{variant}.pt"), 0.1, seed=self.cfg.seed
            )
            result = train_ensemble(
                ensemble,
                train,
                val,
                self._train_config(variant),
                checkpoint_path=self.dir / "models" / f"{variant}_train.pt",
                resume=True,
                progress=self.progress,
            )
            info = {
                "steps": result.steps,
                "stopped_early": result.stopped_early,
                "best_val_loss": result.best_val.mean().item(),
            }
            save_ensemble(result.ensemble, path, extra={"variant": variant, "training": info})
        for variant in VARIANTS:
            saved = torch.load(self.dir / "models" / f"{variant}.pt", weights_only=True)
            summary[variant] = saved["extra"].get("training", {})
        return summary

    def agent(self) -> dict[str, Any]:
        a = self.cfg.agent
        env = self.env("deterministic", time_limit=self.cfg.assess.horizon_s)
        demos = self.dir / "agent" / "demonstrations.pt"
        if demos.is_file():
            saved = _load(demos)
            obs, labels, info = saved["observations"], saved["labels"], saved["info"]
        else:
            obs, labels, info = collect_mpc_demonstrations(
                self.model("deterministic").cpu(),
                env,
                self.cfg.planner,
                episodes=a.mpc_episodes,
                action_noise=a.action_noise,
                seed=self.cfg.seed,
                progress=self.progress,
            )
            _save({"observations": obs, "labels": labels, "info": info}, demos)
        model = self.model("deterministic").cpu()
        base = ScriptedPusher() if self.cfg.planner.policy_prior else None
        policy, obs, labels, rounds = dagger(
            model,
            env,
            self.cfg.planner,
            obs,
            labels,
            a.distill,
            rounds=a.dagger_rounds,
            episodes=a.dagger_episodes,
            seed=self.cfg.seed,
            progress=self.progress,
            base=base,
        )
        _save({"observations": obs, "labels": labels}, self.dir / "agent" / "dagger_data.pt")
        seeds = [70_000 + self.cfg.seed * 1000 + i for i in range(a.eval_episodes)]
        evaluation = run_episodes(
            env, make_policy_module(policy), seeds=seeds, progress=self.progress, desc="policy eval"
        )
        stats = {
            **{k: v for k, v in rounds[-1].items() if k != "round"},
            "dagger": rounds,
            "policy_success_rate": evaluation.success_rate,
            "policy_median_steps": evaluation.steps.float().median().item(),
        }
        mlp = policy.residual if isinstance(policy, ResidualPolicy) else policy
        _save(
            {
                "obs_dim": mlp.obs_dim,
                "action_dim": mlp.action_dim,
                "hidden": mlp.net[0].out_features,
                "state_dict": mlp.state_dict(),
                "residual_of_scripted": isinstance(policy, ResidualPolicy),
            },
            self.dir / "agent" / "policy.pt",
        )
        return {**info, **stats}

    def starts(self, condition: str) -> torch.Tensor:
        env = self.env(CONDITIONS[condition][1])
        starts = []
        for i in range(self.cfg.assess.start_states):
            env.set_seed(self.cfg.seed * 7919 + 1000 * list(CONDITIONS).index(condition) + i)
            starts.append(env.reset()["observation"])
        return torch.stack(starts)

    def forecast(self) -> dict[str, Any]:
        s, summary = self.cfg.assess, {}
        policy = self.policy().to(self.device)
        for condition, (model_name, variant) in CONDITIONS.items():
            path = self.dir / "forecast" / f"{condition}.pt"
            if not path.is_file():
                starts = self.starts(condition)
                success_fn = functools.partial(pusher_success, radius=s.success_radius)
                model_env = make_rcvae_env(
                    self.model(model_name),
                    self.env(variant),
                    pusher_reward,
                    success_fn,
                    seed=self.cfg.seed,
                )
                result = forecast_condition(
                    model_env,
                    policy,
                    starts.to(self.device),
                    samples_per_member=s.samples_per_member,
                    horizon_s=s.horizon_s,
                    dt=CONTROL_TIMESTEP,
                    radius=s.success_radius,
                    open_loop=s.open_loop,
                    episode_end=s.episode_end,
                    bias_correction=s.bias_correction,
                    seed=self.cfg.seed,
                )
                _save({"starts": starts, **result}, path)
            saved = _load(path)
            summary[condition] = {"p_success": saved["p_success"].mean().item()}
        return summary

    def truth(self) -> dict[str, Any]:
        s, summary = self.cfg.assess, {}
        policy = make_policy_module(self.policy())
        for condition, (_, variant) in CONDITIONS.items():
            path = self.dir / "truth" / f"{condition}.pt"
            if not path.is_file():
                seeds = (
                    s.stochastic_seeds_per_start if variant == "stochastic" else s.seeds_per_start
                )
                starts = _load(self.dir / "forecast" / f"{condition}.pt")["starts"]
                result = real_outcomes(
                    self.env(variant, time_limit=s.horizon_s),
                    policy,
                    starts,
                    seeds_per_start=seeds,
                    max_steps=round(s.horizon_s / CONTROL_TIMESTEP),
                    seed=self.cfg.seed + 1 + list(CONDITIONS).index(condition),
                    progress=self.progress,
                    desc=f"real: {condition}",
                )
                _save(result, path)
            saved = _load(path)
            summary[condition] = {"success_rate": saved["success"].float().mean().item()}
        return summary

    def report(self) -> dict[str, Any]:
        forecasts = {c: _load(self.dir / "forecast" / f"{c}.pt") for c in CONDITIONS}
        truths = {c: _load(self.dir / "truth" / f"{c}.pt") for c in CONDITIONS}
        episode_env = self.env("deterministic", time_limit=self.cfg.assess.horizon_s)
        return write_report(
            self.dir, forecasts, truths, self.cfg, make_policy_module(self.policy()), episode_env
        )


def _record_config(path: Path, config: dict[str, Any]) -> None:
    """Write the run's config; a run directory made with other settings is an error."""
    if path.is_file():
        saved = json.loads(path.read_text())
        if saved != json.loads(json.dumps(config)):
            changed = sorted(k for k in config if saved.get(k) != json.loads(json.dumps(config[k])))
            raise ValueError(
                f"run_dir: {str(path.parent)!r} holds a run made with other settings (sections "
                f"{changed} differ); finished stages would be reused: use a new run_dir"
            )
        return
    atomic_write(path, lambda f: f.write(json.dumps(config, indent=2).encode()))


def run_study(
    config: StudyConfig,
    run_dir: str | Path,
    *,
    device: str | torch.device = "cpu",
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run (or resume) the study in ``run_dir``; returns every stage's summary."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    _record_config(run_dir / "study_config.json", asdict(config))
    study = _Study(config, run_dir, torch.device(device), progress)
    runner = StageRunner(run_dir, log)
    for name in ("data", "models", "agent", "forecast", "truth", "report"):
        runner.run(name, getattr(study, name))
    return runner.summaries

"""A survival forecast on an env the project did not write, held against real episodes.

dm_control's cartpole ``balance`` (through TorchRL's ``DMControlWrapper``, one model step =
``--frame-skip`` control steps) with wider seeded starts than its own (pole up to 0.25 rad,
angular velocity up to 1 rad/s, cart within 0.5 m and 0.5 m/s), and a weak linear balance
controller as the agent, so that from some starts it keeps the pole up and from others it
does not. The task is a survival boundary
(:meth:`~rcvae_torchrl.competency.SuccessBoundary.survival`): no failure (pole beyond 30°, or
the cart beyond 1.5 m) for ``--seconds``. Per seed and variant (deterministic, and stochastic
with :class:`~rcvae_torchrl.data.ActionNoise`):

- world-model data: the agent with Gaussian exploration noise (std 0.2, 0.5 and 1.0), a quarter
  of the episodes held out; an ensemble of 5 trained for ``--steps`` steps and, beside it, for
  ``--short-steps`` (an undertrained model), with the library's self-checks;
- each model's closed-loop forecast from 30 scored start states against ``--runs`` real
  episodes of the agent from each (``real_outcomes(..., success=boundary.success_over_time)``):
  mean forecast and real rate, per-start MAE, Spearman, AUROC, Brier skill; and
  :class:`~rcvae_torchrl.training.OutcomeCheck` on 20 other starts;
- out-of-distribution starts (pole 0.3-0.45 rad, up to 2 rad/s): the epistemic bits against the
  scored starts', as time means and per live step, and the cause the report names.

    python benchmarks/survival_forecast.py [--seeds 0 1 2] [--steps 4000] [--out survival_forecast]

One torch thread; prints one row per seed, variant and model and writes
``benchmarks/results/<out>.json``. About a minute per seed and variant on one core.
"""

from __future__ import annotations

import argparse
import time

import torch
from _report import print_table, write_json
from dm_control.rl import control
from dm_control.suite import cartpole
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import DMControlWrapper, FrameSkipTransform, StepCounter

from rcvae_torchrl import (
    CompetencyAssessor,
    RCVAEConfig,
    RCVAEEnsemble,
    SuccessBoundary,
    TrainConfig,
    make_rcvae_env,
    train_ensemble,
)
from rcvae_torchrl.agent import draw_starts, real_outcomes, reset_by_seed, score_forecast
from rcvae_torchrl.data import (
    ActionNoise,
    GaussianExploration,
    action_bounds,
    collect_episodes,
    make_policy_module,
    merge_episodes,
    prepare_env,
    split_episodes,
)
from rcvae_torchrl.reporting import signed
from rcvae_torchrl.training import OutcomeCheck

CONTROL_DT = 0.01  # dm_control cartpole's control step (s)
#: the agent's gains on (x, sin θ, ẋ, θ̇): weak, so that some starts are lost
GAINS = {"deterministic": (0.2, 2.0, 0.4, 0.6), "stochastic": (0.3, 3.0, 0.6, 1.0)}
NOISE = {"deterministic": 0.0, "stochastic": 0.5}
WIDE = {"angle": (0.0, 0.25), "ang_vel": 1.0, "x": 0.5, "x_vel": 0.5}
OUT_OF_DISTRIBUTION = {"angle": (0.3, 0.45), "ang_vel": 2.0, "x": 0.5, "x_vel": 1.0}
#: histogram bins: cart x, cos θ, sin θ, ẋ, θ̇
BIN_WIDTH = torch.tensor([0.05, 0.01, 0.02, 0.05, 0.1])


class WideBalance(cartpole.Balance):
    """cartpole ``balance`` whose seeded reset draws wider starts."""

    def __init__(self, angle, ang_vel, x, x_vel, **kwargs) -> None:
        super().__init__(swing_up=False, sparse=False, **kwargs)
        self.angle, self.ang_vel, self.x, self.x_vel = angle, ang_vel, x, x_vel

    def initialize_episode(self, physics) -> None:
        super().initialize_episode(physics)
        r = self.random
        qpos, qvel = physics.named.data.qpos, physics.named.data.qvel
        qpos["slider"] = r.uniform(-self.x, self.x)
        qpos["hinge_1"] = r.uniform(*self.angle) * r.choice([-1, 1])
        qvel["slider"] = r.uniform(-self.x_vel, self.x_vel)
        qvel["hinge_1"] = r.uniform(-self.ang_vel, self.ang_vel)


def make_env(noise: float, skip: int, starts: dict, steps: int | None = None):
    physics = cartpole.Physics.from_xml_string(*cartpole.get_model_and_assets())
    task = control.Environment(physics, WideBalance(**starts), time_limit=float("inf"))
    env, layout = prepare_env(DMControlWrapper(task))
    env.append_transform(FrameSkipTransform(skip))
    if noise > 0:
        env.append_transform(ActionNoise(noise))
    if steps is not None:
        env.append_transform(StepCounter(steps))
    return env, layout


class Balance(nn.Module):
    """``clamp(k · (x, sin θ, ẋ, θ̇), -1, 1)`` on observations (x, cos θ, sin θ, ẋ, θ̇)."""

    def __init__(self, gains) -> None:
        super().__init__()
        self.register_buffer("gains", torch.tensor(gains))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        x, _, sin, x_dot, theta_dot = observation.unbind(-1)
        k = self.gains
        u = k[0] * x + k[1] * sin + k[2] * x_dot + k[3] * theta_dot
        return u.clamp(-1.0, 1.0).unsqueeze(-1)


def fallen(observation: torch.Tensor) -> torch.Tensor:
    """The pole more than 30° from upright, or the cart beyond 1.5 m."""
    return (observation[..., 1] < 0.866) | (observation[..., 0].abs() > 1.5)


def upright(observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """The model env's reward: cos θ (unused by the forecast)."""
    return observation[..., 1:2]


def never(observation: torch.Tensor) -> torch.Tensor:
    return torch.zeros(observation.shape[:-1], dtype=torch.bool)


def run(seed: int, variant: str, args) -> list[dict]:
    torch.manual_seed(seed)
    noise, skip = NOISE[variant], args.frame_skip
    env, layout = make_env(noise, skip, WIDE)
    low, high = action_bounds(env)
    boundary = SuccessBoundary.survival(fallen, time_limit_s=args.seconds, dt=CONTROL_DT * skip)
    agent_module = Balance(GAINS[variant])
    agent = TensorDictModule(agent_module, in_keys=["observation"], out_keys=["action"])
    parts = []
    for i, std in enumerate((0.2, 0.5, 1.0)):
        behaviour = GaussianExploration(
            Balance(GAINS[variant]), std, seed=seed * 10 + i, low=low, high=high
        )
        parts.append(
            collect_episodes(
                lambda: make_env(noise, skip, WIDE, steps=args.episode_steps)[0],
                make_policy_module(behaviour),
                args.episodes,
                seed=seed * 10_000 + 1000 * (i + 1),
                first_id=i * args.episodes,
                progress=False,
            )
        )
    train, val = split_episodes(merge_episodes(*parts), val_fraction=0.25, seed=seed)
    config = RCVAEConfig(
        layout.dim, 1, hidden_dim=48, mlp_dim=48, latent_dim=4, observation_names=layout.names
    )
    starts = draw_starts(env, seeds=[seed * 10_000 + 5000 + i for i in range(30)])
    held_out = draw_starts(env, seeds=[seed * 10_000 + 7000 + i for i in range(20)])
    ood_env, _ = make_env(noise, skip, OUT_OF_DISTRIBUTION)
    ood = draw_starts(ood_env, seeds=[seed * 10_000 + 9000 + i for i in range(20)])
    kwargs = dict(
        reset_to_state=reset_by_seed,
        max_steps=boundary.time_limit,
        success=boundary.success_over_time,
        progress=False,
    )
    real = real_outcomes(env, agent, starts, runs_per_start=args.runs, seed=seed, **kwargs)
    real_held = real_outcomes(env, agent, held_out, runs_per_start=args.runs, seed=seed, **kwargs)
    rows = []
    for steps in (args.short_steps, args.steps):
        began = time.perf_counter()
        budget = TrainConfig(
            max_steps=steps, batch_windows=16, window=24, val_every=250, val_windows=64, seed=seed
        )
        result = train_ensemble(RCVAEEnsemble(config, 5), train, val, budget, progress=False)
        # the boundary decides the outcome: the model env raises no success flag of its own
        model_env = make_rcvae_env(result.ensemble, env, upright, never, seed=seed)
        assessor = CompetencyAssessor(
            model_env,
            boundary,
            bin_width=BIN_WIDTH,
            samples_per_member=20,
            policy=agent_module,
            episode_end=True,
        )
        report = assessor.assess(starts["observation"], seed=seed)
        forecast = report.competency["p_success"]
        score = score_forecast(forecast, real)
        held_forecast = assessor.assess(held_out["observation"], seed=seed + 1)
        check = OutcomeCheck.from_outcomes(
            held_forecast.competency["p_success"], real_held.success, what="held-out starts"
        )
        unseen = assessor.assess(ood["observation"], seed=seed + 2)
        plain = unseen.mean_bits()[1] / max(report.mean_bits()[1], 1e-12)
        live = unseen.mean_bits(True)[1] / max(report.mean_bits(True)[1], 1e-12)
        rows.append(
            {
                "seed": seed,
                "variant": variant,
                "train_steps": steps,
                "checks_passed": result.checks.passed,
                "flagged": [layout.names[d] for d in result.checks.flagged],
                "forecast": float(forecast.mean()),
                "real": float(real.success.float().mean()),
                "per_start_mae": score["per_start_mae"],
                "spearman": score["spearman"],
                "auroc": score["auroc"],
                "brier_skill": score["brier_skill"],
                "held_out_check": check.verdict,
                "held_out_gap": check.gap,
                "held_out_p": check.p_value,
                "ood_epistemic_ratio_time_mean": plain,
                "ood_epistemic_ratio_per_live_step": live,
                "ood_cause": unseen.with_reference(report).cause(),  # per live step
                "seconds": time.perf_counter() - began,
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--short-steps", type=int, default=100)
    parser.add_argument("--episodes", type=int, default=40, help="per exploration noise level")
    parser.add_argument("--episode-steps", type=int, default=80)
    parser.add_argument("--frame-skip", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--runs", type=int, default=10, help="real episodes per start")
    parser.add_argument("--out", default="survival_forecast")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = [row for seed in args.seeds for v in GAINS for row in run(seed, v, args)]
    print_table(
        f"Survival forecasts on cartpole balance ({args.seconds:g} s, 1 thread)",
        ["seed", "variant", "steps", "checks", "forecast", "real", "MAE", "Spearman", "AUROC",
         "BSS", "held-out check", "OOD epi x (mean / live)", "OOD cause"],
        [
            [r["seed"], r["variant"], r["train_steps"],
             "passed" if r["checks_passed"] else "flagged " + ",".join(r["flagged"]),
             r["forecast"], r["real"], r["per_start_mae"], r["spearman"], r["auroc"],
             r["brier_skill"], f"{r['held_out_check']} ({signed(r['held_out_gap'])})",
             f"{r['ood_epistemic_ratio_time_mean']:.2f} / "
             f"{r['ood_epistemic_ratio_per_live_step']:.2f}", r["ood_cause"]]
            for r in rows
        ],
    )  # fmt: skip
    write_json(args.out, {"settings": vars(args), "threads": 1, "rows": rows})


if __name__ == "__main__":
    main()

"""What makes the paper's pattern show: the study's uncertainty settings and OOD region, ablated.

On a finished study run's models and agent, imagines the three conditions' forecasts once (the
run's own start states, ``--samples`` per member, 30 s, closed loop) and measures them with the
histogram estimator four ways: with and without ended episodes in a terminal bin
(``episode_end``), with and without the shuffle correction of the epistemic part
(``bias_correction``). A fourth condition starts the deterministic model from the region the
study used before as out of distribution: the ball near the fence (0.17-0.185 m) and moving, the
arm swinging, in the training half of the arena. Prints the bits and the pattern's three ratios
per setting and writes ``benchmarks/results/pattern_ablation.json`` (``--out`` names another
file). With the study's setting (ended episodes in a terminal bin, the shuffle correction) it also
gives the aleatoric out-of-distribution / deterministic ratio second by second, beside the share
of each condition's imagined episodes still running then: ended episodes add no entropy, so a
condition whose episodes last longer keeps its bits longer. With that setting it also gives the
bits per step of the episodes' life (``UncertaintyMetric``'s ``per_live_step``: the time sum over
the mean number of steps an episode runs), which the episodes' lengths do not change.

    python benchmarks/pattern_ablation.py --run-dir outputs/pusher_competency/default
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch
from _report import print_table, write_json
from tensordict import TensorDict

from rcvae_torchrl.competency import UncertaintyMetric
from rcvae_torchrl.envs import (
    CONTROL_TIMESTEP,
    make_pusher_env,
    pusher_reward,
    resolution_tensor,
)
from rcvae_torchrl.envs.pusher import IN_DISTRIBUTION, OUT_OF_DISTRIBUTION, InitialStateRegion
from rcvae_torchrl.io import load_torch
from rcvae_torchrl.model_env import make_rcvae_env
from recipes.pusher_competency.pipeline import study_of_run
from recipes.pusher_competency.pusher import CONDITIONS, success_boundary, success_fn

#: The study's earlier out-of-distribution region: disjoint from the training starts, not from
#: the states the training episodes visit.
EARLIER_OOD = InitialStateRegion(
    ball_radius=(0.17, 0.185),
    ball_speed=(0.05, 0.15),
    joint_speed=(0.5, 2.0),
    target_radius=(0.09, 0.16),
    angle=IN_DISTRIBUTION.angle,
)
EARLIER_OOD_NAME = "earlier out-of-distribution"
SETTINGS = [(end, bias) for end in (False, True) for bias in ("none", "shuffle")]


def _starts(condition: str, run_dir: Path, count: int) -> torch.Tensor:
    if condition != EARLIER_OOD_NAME:
        return load_torch(run_dir / "forecast" / f"{condition}.pt", "forecast")["starts"]
    env = make_pusher_env("deterministic", region=EARLIER_OOD)
    starts = []
    for i in range(count):
        env.set_seed(7000 + i)
        starts.append(env.reset()["observation"])
    return torch.stack(starts)


def _per_second(det: dict[str, torch.Tensor], ood: dict[str, torch.Tensor]) -> list[dict]:
    """The aleatoric OOD / deterministic ratio at each whole second (bits summed over dimensions,
    averaged over start states), with the share of each condition's episodes still running."""
    steps_per_s = round(1.0 / CONTROL_TIMESTEP)
    rows = []
    for t in range(0, det["aleatoric"].shape[-1], steps_per_s):
        rows.append(
            {
                "second": t // steps_per_s,
                "ratio": (ood["aleatoric"][t] / det["aleatoric"][t]).item(),
                "running_det": det["running"][t].item(),
                "running_ood": ood["running"][t].item(),
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run-dir", default="outputs/pusher_competency/default")
    parser.add_argument("--samples", type=int, default=50, help="samples per member")
    parser.add_argument("--out", default="pattern_ablation", help="results/<out>.json")
    args = parser.parse_args()
    run_dir = Path(args.run_dir)
    study = study_of_run(run_dir)
    config = study.cfg
    policy = study.load_policy()
    a = config.assess
    boundary = success_boundary(a.success_radius, a.horizon_s)
    conditions = {**CONDITIONS, EARLIER_OOD_NAME: ("deterministic", "deterministic")}
    bits: dict[str, dict[str, list[float]]] = {}
    over_time: dict[str, dict[str, torch.Tensor]] = {}  # the study's setting, per step
    for condition, (model_name, variant) in conditions.items():
        starts = _starts(condition, run_dir, a.start_states)
        env = make_rcvae_env(
            study.load_model(model_name),
            study.env(variant),
            pusher_reward,
            success_fn(a.success_radius),
            terminate_on_success=True,
            seed=config.seed,
        )
        with torch.no_grad():
            obs = env.imagine(
                starts,
                policy=policy,
                horizon=round(a.horizon_s / CONTROL_TIMESTEP),
                samples_per_member=args.samples,
                generator=torch.Generator().manual_seed(config.seed),
            )["observation"]
        ended = boundary.ended_over_time(obs)
        rollout = TensorDict({"observation": obs, "ended": ended}, batch_size=obs.shape[:-1])
        for end, bias in SETTINGS:
            u = UncertaintyMetric(
                resolution_tensor(),
                episode_end=end,
                bias_correction=bias,
                generator=torch.Generator().manual_seed(config.seed),
            )(rollout)["uncertainty"]
            key = f"episode_end={end}, bias_correction={bias}"
            if end and bias == "shuffle":
                over_time[condition] = {
                    "aleatoric": u["aleatoric"].sum(-1).mean(0),
                    "running": u["live"].mean(0),
                }
                per_live = u["per_live_step"]  # the same bits per step of the episodes' life
                bits.setdefault(f"{key}, per live step", {})[condition] = [
                    per_live["aleatoric"].mean().item(),
                    per_live["epistemic"].mean().item(),
                ]
            bits.setdefault(key, {})[condition] = [
                u["summary", "aleatoric"].mean().item(),
                u["summary", "epistemic"].mean().item(),
            ]
    det, sto, ood = "deterministic", "stochastic", "out-of-distribution"
    rows, ratios = [], {}
    for key, b in bits.items():
        r = {
            "aleatoric stochastic / deterministic": b[sto][0] / b[det][0],
            "epistemic out-of-distribution / deterministic": b[ood][1] / b[det][1],
            "aleatoric out-of-distribution / deterministic": b[ood][0] / b[det][0],
            "epistemic earlier OOD / deterministic": b[EARLIER_OOD_NAME][1] / b[det][1],
            "aleatoric earlier OOD / deterministic": b[EARLIER_OOD_NAME][0] / b[det][0],
        }
        ratios[key] = r
        rows.append([key, *(round(v, 2) for v in r.values())])
    print_table(
        f"pattern ratios, bits averaged over {a.horizon_s:g} s ({run_dir})",
        ["setting", "ale sto/det", "epi ood/det", "ale ood/det", "epi old/det", "ale old/det"],
        rows,
    )
    print_table(
        "bits (aleatoric, epistemic), summed over dimensions",
        ["setting", *conditions],
        [[k, *(f"{v[0]:.2f}, {v[1]:.2f}" for v in b.values())] for k, b in bits.items()],
    )
    per_second = _per_second(over_time[det], over_time[ood])
    print_table(
        "aleatoric out-of-distribution / deterministic second by second, study's setting",
        ["second", "ratio", "running det", "running ood"],
        [
            [r["second"], *(round(r[k], 2) for k in ("ratio", "running_det", "running_ood"))]
            for r in per_second
        ],
    )
    path = write_json(
        args.out,
        {
            "run_dir": str(run_dir),
            "samples_per_member": args.samples,
            "bits": bits,
            "ratios": ratios,
            "aleatoric_ood_over_det_by_second": per_second,
            "targets": {"aleatoric sto/det": ">= 1.5", "epistemic ood/det": ">= 1.3"},
            "ood_sector_deg": [math.degrees(v) for v in OUT_OF_DISTRIBUTION.angle],
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

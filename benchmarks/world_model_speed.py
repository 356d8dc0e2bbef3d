"""World-model speed: one vectorised training step for E members, and generation throughput.

Pusher-sized models (S = 14, A = 2, Z = 8): ``RCVAEConfig``'s defaults (H = MLP = 128), the
study's default world model (``rcvae_config(ModelConfig())``: H = MLP = 64, Pusher input
features) and a small one (H = MLP = 32). On a shared machine, OpenMP threads that wait for busy
cores distort timings badly; compare ``--threads 1`` runs there (the JSON records the load
average).

All timings are medians of repeats taken round-robin across the variants compared.

1. Training step (loss forward + backward + Adam) on 64 windows × L = 32 per member, E = 1 vs
   E = 5, median of repeats; target: E = 5 step ≤ 3 × E = 1 step. The ratio depends on whether
   an E = 1 step is overhead- or work-bound, so the same step of one member on 5 × 64 windows
   (the E = 5 step's rows, no ensemble) is timed as a reference: a ratio near its own means the
   member dimension costs no more than a larger batch.
2. Generation throughput in model-steps/s (member × sample × step) at N = 16, 256, 4096 samples
   per member: the vectorised ``imagine`` (default chunks of 1024 trajectories per member, and
   all in one chunk) against a Python loop over single members, same run.
3. One transition step for E·N particles: member-major ``ensemble.step`` against the indexed
   layout (``RCVAETransition``, TS-∞ with round-robin and random members, and TS-1).
4. The GRU recurrence of a training step: :func:`~rcvae_torchrl.models.gru_scan` (one
   autograd node with a written-out backward pass) against
   :func:`~rcvae_torchrl.models.gru_scan_stepwise` (autograd through every step's ops), the
   study's default model at E = 1, 2, 4 (32 windows x L = 32 per member, the distributed
   training benchmark's step), same run, interleaved.

``--device cuda`` (or ``cuda:N``) runs every model on a GPU, each call timed until its kernels
have run, and records the GPU's name.

    python benchmarks/world_model_speed.py [--repeats 7] [--horizon 20] [--threads N] [--quick]
                                           [--device cpu|cuda|cuda:N] [--scan-only]
                                           [--out world_model_speed_2threads]
"""

from __future__ import annotations

import argparse
import contextlib
import os
from collections.abc import Callable
from dataclasses import asdict
from unittest import mock

import torch
from _report import (
    benchmark_device,
    device_name,
    interleaved_median_times,
    print_table,
    write_json,
)
from tensordict import TensorDict

from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble, gru_scan_stepwise
from rcvae_torchrl.models import rcvae as rcvae_module
from rcvae_torchrl.objectives import RCVAELoss
from rcvae_torchrl.rollout import imagine, init_model_state, make_transition_module
from recipes.pusher_competency.config import ModelConfig
from recipes.pusher_competency.pusher import MODEL_FUNCTIONS, rcvae_config

CONFIG = RCVAEConfig(obs_dim=14, action_dim=2, passthrough_dims=(12, 13))
SMALL = RCVAEConfig(obs_dim=14, action_dim=2, hidden_dim=32, mlp_dim=32, passthrough_dims=(12, 13))
# The study's default world model (H = MLP = 64, Pusher input features and state constraint).
DEFAULT = rcvae_config(ModelConfig())


def interleaved_medians(
    runs: dict[str, Callable[[], object]],
    repeats: int,
    device: torch.device,
    warmup: int = 1,
) -> dict[str, float]:
    """Median wall seconds of each run (:func:`_report.interleaved_median_times`)."""
    times = interleaved_median_times(runs, repeats, warmup, device=device)
    return {name: t["wall_s"] for name, t in times.items()}


def make_model(
    ensemble_size: int, config: RCVAEConfig = CONFIG, device: torch.device | str = "cpu"
) -> RCVAEEnsemble:
    torch.manual_seed(0)
    model = RCVAEEnsemble(config, ensemble_size, functions=MODEL_FUNCTIONS)
    s, a = config.obs_dim, config.action_dim
    model.fit_normalizer(torch.randn(16, 50, s), torch.rand(16, 50, a) * 2 - 1)
    return model.to(device)


def train_step(
    config: RCVAEConfig,
    ensemble_size: int,
    device: torch.device,
    windows: int = 64,
    length: int = 32,
    compiled: bool = False,
    stepwise_scan: bool = False,
):
    """A closure running one loss + backward + Adam step on fixed windows ``[E, W, L]``; with
    ``compiled`` the loss (forward and backward) under ``torch.compile``, static shapes (one
    compile per window count: a second count recompiled with dynamic shapes failed on a GPU,
    in the noise draw ``randn`` of a symbolic size); with ``stepwise_scan`` the model's GRU
    recurrence through :func:`gru_scan_stepwise` (patched in for the step only)."""
    model = make_model(ensemble_size, config, device)
    loss_fn = torch.compile(RCVAELoss(model), dynamic=False) if compiled else RCVAELoss(model)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    batch = (ensemble_size, windows, length)
    td = TensorDict(
        observation=torch.randn(*batch, config.obs_dim),
        action=torch.rand(*batch, config.action_dim),
        batch_size=batch,
    ).to(device)

    def step() -> None:
        scan = (
            mock.patch.object(rcvae_module, "gru_scan", gru_scan_stepwise)
            if stepwise_scan
            else contextlib.nullcontext()
        )
        with scan:
            out = loss_fn(td)
            opt.zero_grad()
            (out["loss_reconstruction"] + out["loss_kl"]).backward()
            opt.step()

    return step


def train_step_times(config: RCVAEConfig, repeats: int, device: torch.device) -> dict[str, float]:
    """Median step seconds for E = 1 and E = 5 (64 windows per member), and for one member on
    5 × 64 windows (``"1x5w"``)."""
    runs = {str(e): train_step(config, e, device) for e in (1, 5)}
    runs["1x5w"] = train_step(config, 1, device, windows=5 * 64)
    return interleaved_medians(runs, repeats, device, warmup=2)


SCAN_MEMBERS = (1, 2, 4)
SCAN_STEPS = 10


def scan_times(repeats: int, device: torch.device) -> dict[str, float]:
    """Median step seconds of the study's default model at E = 1, 2, 4 (32 windows per member),
    its recurrence through ``gru_scan`` (``"E<e>"``) and ``gru_scan_stepwise``
    (``"E<e>_stepwise"``). Each timed call runs ``SCAN_STEPS`` steps one after the other, as
    training does (a single step timed right after another variant's starts with that
    variant's data in the caches, which hides about half of the difference)."""

    def steps(step: Callable[[], None]) -> Callable[[], None]:
        return lambda: [step() for _ in range(SCAN_STEPS)]

    runs = {}
    for e in SCAN_MEMBERS:
        runs[f"E{e}"] = steps(train_step(DEFAULT, e, device, windows=32))
        runs[f"E{e}_stepwise"] = steps(
            train_step(DEFAULT, e, device, windows=32, stepwise_scan=True)
        )
    times = interleaved_medians(runs, repeats, device, warmup=1)
    return {name: t / SCAN_STEPS for name, t in times.items()}


def generation_rates(model: RCVAEEnsemble, n: int, horizon: int, repeats: int) -> dict[str, float]:
    """Model-steps/s of vectorised imagine (default chunks, one chunk) and of a member loop."""
    device = model.device
    obs, actions = torch.zeros(14, device=device), torch.rand(horizon, 2, device=device) * 2 - 1
    singles = [model.select_members([m]) for m in range(model.ensemble_size)]
    work = model.ensemble_size * n * horizon
    runs = {
        "vectorised": lambda: imagine(model, obs, actions, samples_per_member=n),
        "vectorised_one_chunk": lambda: imagine(
            model, obs, actions, samples_per_member=n, chunk_size=None
        ),
        "member_loop": lambda: [imagine(s, obs, actions, samples_per_member=n) for s in singles],
    }
    return {name: work / t for name, t in interleaved_medians(runs, repeats, device).items()}


def transition_times(model: RCVAEEnsemble, n: int, repeats: int) -> dict[str, float]:
    """Seconds per step for E·n particles in each layout."""
    e, particles = model.ensemble_size, model.ensemble_size * n
    device = model.device
    obs = torch.randn(particles, 14, device=device)
    action = torch.rand(particles, 2, device=device)
    hidden = torch.zeros(e, n, CONFIG.hidden_dim, device=device)
    runs = {"member_major": lambda: model.step(hidden, obs.view(e, n, 14), action.view(e, n, 2))}
    g = torch.Generator(device).manual_seed(0)
    for name, ts, member in (
        ("ts_inf_round_robin", "ts_inf", "round_robin"),
        ("ts_inf_random", "ts_inf", "random"),
        ("ts1", "ts1", "round_robin"),
    ):
        td = init_model_state(model, obs, trajectory_sampling=ts, member=member, generator=g)
        td["action"] = action
        module = make_transition_module(model, trajectory_sampling=ts)
        runs[name] = lambda td=td, module=module: module(td)
    return interleaved_medians(runs, repeats, device)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--horizon", type=int, default=20)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--quick", action="store_true", help="fewer repeats, smallest N only")
    parser.add_argument(
        "--out", default="world_model_speed", help="results name (benchmarks/results/<out>.json)"
    )
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument("--scan-only", action="store_true", help="the GRU recurrence's table only")
    args = parser.parse_args()
    device = benchmark_device(args.device)
    torch.set_num_threads(args.threads)
    repeats = 3 if args.quick else args.repeats
    sizes = (16, 256) if args.quick else (16, 256, 4096)

    meta = {
        "load_average_1min": os.getloadavg()[0],
        "repeats": repeats,
        "threads": args.threads,
        "device": device_name(device),
    }
    scan = scan_times(repeats, device)
    scan_ratio = {e: scan[f"E{e}_stepwise"] / scan[f"E{e}"] for e in SCAN_MEMBERS}
    print_table(
        "Training step, study default model, 32 windows x L=32 per member (median ms): the GRU "
        "recurrence as one node (gru_scan) vs autograd through each step",
        ["members", "gru_scan_ms", "stepwise_ms", "stepwise_over_gru_scan"],
        [
            [e, 1e3 * scan[f"E{e}"], 1e3 * scan[f"E{e}_stepwise"], scan_ratio[e]]
            for e in SCAN_MEMBERS
        ],
    )

    scan_results = {
        "scan_train_step_s": scan,
        "scan_stepwise_over_gru_scan": {str(e): r for e, r in scan_ratio.items()},
    }
    if args.scan_only:
        write_json(args.out, {**scan_results, **meta})
        return

    configs = {"pusher_H128": CONFIG, "study_default_H64": DEFAULT, "small_H32": SMALL}
    train = {name: train_step_times(cfg, repeats, device) for name, cfg in configs.items()}
    ratio = {name: t["5"] / t["1"] for name, t in train.items()}
    batch_ratio = {name: t["1x5w"] / t["1"] for name, t in train.items()}
    print_table(
        "Training step, 64 windows x L=32 per member (median s)",
        ["model", "E1_step_s", "E5_step_s", "ratio_E5_E1", "E1_5x_windows_s", "ratio_5x_windows"],
        [[n, t["1"], t["5"], ratio[n], t["1x5w"], batch_ratio[n]] for n, t in train.items()],
    )

    model = make_model(5, device=device)
    with torch.no_grad():
        gen = {n: generation_rates(model, n, args.horizon, repeats) for n in sizes}
        trans = {n: transition_times(model, n, repeats) for n in sizes}
    print_table(
        f"Generation, E=5, T={args.horizon} (model-steps/s)",
        ["N_per_member", "vectorised", "one_chunk", "member_loop", "speedup_vs_loop"],
        [
            [
                n,
                r["vectorised"],
                r["vectorised_one_chunk"],
                r["member_loop"],
                r["vectorised"] / r["member_loop"],
            ]
            for n, r in gen.items()
        ],
    )
    layouts = list(next(iter(trans.values())))
    print_table(
        "One transition step for E*N particles (ms)",
        ["N_per_member", *layouts],
        [[n, *(1e3 * t[k] for k in layouts)] for n, t in trans.items()],
    )
    write_json(
        args.out,
        {
            "configs": {name: asdict(cfg) for name, cfg in configs.items()},
            "load_average_1min": os.getloadavg()[0],
            "train_step_s": train,
            "train_step_ratio_e5_over_e1": ratio,
            "train_step_ratio_one_member_5x_windows": batch_ratio,
            "train_ratio_target_le_3": {name: r <= 3.0 for name, r in ratio.items()},
            **scan_results,
            "generation_steps_per_s": {str(n): r for n, r in gen.items()},
            "transition_step_s": {str(n): t for n, t in trans.items()},
            "horizon": args.horizon,
            "repeats": repeats,
            "threads": args.threads,
            "device": device_name(device),
        },
    )


if __name__ == "__main__":
    main()

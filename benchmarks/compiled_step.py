"""Does ``torch.compile`` pay for the training step and the imagination step of the study's model?

The plan-scoring rollout has its compiled paths (``compile=True`` and ``compile="aot"``,
``benchmarks/model_step.py``). This script measures the two other hot paths the same way, on
the study's world model (E = 5, H = MLP = 64, Z = 8, the Pusher's input features and state
constraint; untrained, normaliser fitted on random data: speed does not depend on the weights),
one torch thread, each case timed once per round, in turn (medians of interleaved rounds):

- training: one loss forward and backward (``RCVAELoss``) on the study's batch, 32 windows of
  32 steps per member, eager against ``torch.compile`` of the loss (forward and backward);
- imagination: H = 20 model steps (``ensemble.step``) at N trajectories per member (20, the
  forecast's samples per member, 256 and 4096), eager against ``torch.compile`` of the step.

For each compiled case also the seconds of its first call (compiling, with inductor's on-disk
cache emptied: a temporary directory) and the calls it takes to earn them back. Writes
``benchmarks/results/compiled_step.json``.

    python benchmarks/compiled_step.py [--repeats 7] [--device cpu|cuda|cuda:N] [--quick]
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable

import torch
from _report import (
    benchmark_device,
    conditions,
    device_name,
    interleaved_median_times,
    print_table,
    synchronize,
    write_json,
)
from model_step import MEMBERS, study_ensemble
from tensordict import TensorDict

from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.objectives import RCVAELoss

WINDOWS, LENGTH, HORIZON = 32, 32, 20
SAMPLES = (20, 256, 4096)


def training_step(model: RCVAEEnsemble, compiled: bool) -> Callable[[], None]:
    """One loss forward and backward on fixed windows ``[E, W, L]`` (the gradients are not
    applied: the optimiser's step is the same in both)."""
    loss_fn = RCVAELoss(model)
    forward = torch.compile(loss_fn) if compiled else loss_fn
    batch = (MEMBERS, WINDOWS, LENGTH)
    generator = torch.Generator().manual_seed(0)
    td = TensorDict(
        observation=torch.randn(*batch, 14, generator=generator) * 0.1,
        action=torch.rand(*batch, 2, generator=generator) * 2 - 1,
        batch_size=batch,
    ).to(model.device)

    def step() -> None:
        out = forward(td)
        model.zero_grad(set_to_none=True)
        (out["loss_reconstruction"] + out["loss_kl"]).backward()

    return step


def imagination(
    model: RCVAEEnsemble, per_member: int, compiled: bool, step: Callable | None = None
) -> Callable[[], None]:
    """``HORIZON`` model steps of ``per_member`` trajectories per member, noise drawn up front
    (the same for both: the compiled step reads it, as the AOT scoring does). ``step`` replaces
    the step function (``model.step``, or with ``compiled`` its ``torch.compile``), e.g. one
    compiled function shared by several batch sizes."""
    if step is None:
        step = torch.compile(model.step, dynamic=False) if compiled else model.step
    device, cfg = model.device, model.config
    hidden0 = torch.zeros(MEMBERS, per_member, model.carry_dim, device=device)
    obs0 = torch.zeros(MEMBERS, per_member, 14, device=device)
    action = torch.zeros(MEMBERS, per_member, 2, device=device)
    noise = [
        (
            torch.randn(MEMBERS, per_member, cfg.latent_dim, device=device),
            torch.randn(MEMBERS, per_member, cfg.predicted_dim, device=device),
        )
        for _ in range(HORIZON)
    ]

    def run() -> None:
        hidden, obs = hidden0, obs0
        with torch.no_grad():
            for latent, state in noise:
                out = step(hidden, obs, action, noise_latent=latent, noise_obs=state)
                hidden, obs = out.hidden, out.observation

    return run


def first_call_s(call: Callable[[], None], device: torch.device) -> float:
    start = time.perf_counter()
    call()
    synchronize(device)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    parser.add_argument("--quick", action="store_true", help="the smallest imagination only")
    args = parser.parse_args()
    device = benchmark_device(args.device)
    torch.set_num_threads(1)
    model = study_ensemble(device)
    cases = {"training step (loss forward + backward)": (training_step, ())}
    for n in SAMPLES[:1] if args.quick else SAMPLES:
        cases[f"imagination, {HORIZON} steps, {n} per member"] = (imagination, (n,))
    rows, results = [], {}
    # Cold compiles: inductor reads its cache directory when it first compiles, so an empty
    # temporary one set here (not at import: scripts importing this one keep their cache) is
    # what every case below compiles into; it is removed afterwards.
    cache = tempfile.mkdtemp(prefix="compiled_step_inductor_")
    before = os.environ.get("TORCHINDUCTOR_CACHE_DIR")
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = cache
    try:
        for name, (make, extra) in cases.items():
            eager, compiled = make(model, *extra, False), make(model, *extra, True)
            first = first_call_s(compiled, device)
            times = interleaved_median_times(
                {"eager": eager, "compiled": compiled}, args.repeats, device=device
            )
            e, c = times["eager"]["wall_s"], times["compiled"]["wall_s"]
            gain = e - c
            payback = math.ceil((first - c) / gain) if gain > 0 else None
            results[name] = {
                "eager_s": e,
                "compiled_s": c,
                "eager_over_compiled": e / c,
                "first_compiled_call_s": first,
                "calls_to_earn_the_compile_back": payback,
                **times["eager"],
            }
            rows.append([name, e, c, e / c, first, "never" if payback is None else payback])
    finally:
        if before is None:
            os.environ.pop("TORCHINDUCTOR_CACHE_DIR", None)
        else:
            os.environ["TORCHINDUCTOR_CACHE_DIR"] = before
        shutil.rmtree(cache, ignore_errors=True)
    print_table(
        f"eager against torch.compile, the study's model (E = {MEMBERS}, H = MLP = 64), on "
        f"{device_name(device)}, {torch.get_num_threads()} thread(s), medians of "
        f"{args.repeats} interleaved rounds",
        ["case", "eager s", "compiled s", "eager / compiled", "first call s", "calls to repay"],
        rows,
    )
    write_json(
        "compiled_step" + ("_quick" if args.quick else ""),
        {"cases": results, "repeats": args.repeats, **conditions(device)},
    )


if __name__ == "__main__":
    main()

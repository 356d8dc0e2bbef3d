"""Which changes of the Pusher's physics does a study's dynamics check find?

The study's report checks each condition's env with :meth:`Study.dynamics_check`: the agent's
episodes there against its own episodes in the world model's env (:meth:`Study.dynamics_reference`),
their one-step errors' size and their lean (``check_dynamics(..., shift=True)``). Here the
same check, with the same reference, is given batches of the agent's episodes from fresh start
states in envs whose physics changed (the MuJoCo model's attribute scaled in the checked
episodes only): how many batches fail, with both tests and with the size test alone, and the
agent's real success in each. Printed and written to ``benchmarks/results/<out>.json``.

    python benchmarks/dynamics_check.py RUN_DIR [--batches 3] [--episodes 40]
        [--conditions deterministic stochastic out-of-distribution]
        [--changes ball_damping=1.5 ball_mass=1.5 gear=0.95 gear=0.9 arm_damping=2.0]
        [--out dynamics_check]

``RUN_DIR`` is a finished study run. The unchanged env runs ``--batches + 2`` batches.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import time
from collections.abc import Iterator
from pathlib import Path

import torch
from _report import conditions, print_table, write_json

from rcvae_torchrl.envs.batched import BatchedPusherEnv
from rcvae_torchrl.training import check_dynamics
from recipes.pusher_competency.pipeline import study_of_run
from recipes.pusher_competency.pusher import CONDITIONS

#: what each change scales in the Pusher's MJCF: (the attribute as written, its name, value)
CHANGES = {
    "ball_damping": ('damping="0.02"', "damping", 0.02),  # the floor's friction on the ball
    "ball_mass": ('mass=".015"', "mass", 0.015),
    "gear": ('gear=".05"', "gear", 0.05),  # the motors' strength
    "arm_damping": ('damping="0.01"', "damping", 0.01),  # the arm's joints
}
#: start states of batch b: seeds this much (+ 1000·b) above the scored ones'
START_OFFSET = 200_000
#: the seed block of batch b, change k (Study.agent_episodes): EPISODE_BLOCK + 100·b + k, below
#: the study's own blocks
EPISODE_BLOCK = 6_000


@contextlib.contextmanager
def changed_physics(what: str, factor: float) -> Iterator[None]:
    """Batched Pushers built inside are of a model whose ``what`` is ``factor`` times the
    stock one (``"none"``: the stock model)."""
    module = importlib.import_module(BatchedPusherEnv.__module__)
    stock = module.get_model_and_assets

    def changed() -> tuple[bytes, dict]:
        xml, assets = stock()
        if what == "none":
            return xml, assets
        written, attribute, value = CHANGES[what]
        if written.encode() not in xml:
            raise ValueError(f"changes: {what}'s {written} is not in the Pusher's model")
        return xml.replace(written.encode(), f'{attribute}="{value * factor:.6g}"'.encode()), assets

    module.get_model_and_assets = changed
    try:
        yield
    finally:
        module.get_model_and_assets = stock


def _change(text: str) -> tuple[str, float]:
    what, _, factor = text.partition("=")
    if what not in CHANGES or not factor:
        raise argparse.ArgumentTypeError(
            f"expected NAME=FACTOR with NAME one of {sorted(CHANGES)}, got {text!r}"
        )
    return what, float(factor)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--batches", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=40, help="episodes per batch")
    parser.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=CONDITIONS)
    parser.add_argument(
        "--changes",
        nargs="+",
        type=_change,
        default=[_change(c) for c in ("ball_damping=1.5", "ball_mass=1.5", "gear=0.95",
                                      "gear=0.9", "arm_damping=2.0")],
    )  # fmt: skip
    parser.add_argument("--out", default="dynamics_check")
    args = parser.parse_args()
    torch.set_num_threads(1)
    study = study_of_run(args.run_dir)
    rows, results = [], []
    for condition in args.conditions:
        model_name = CONDITIONS[condition][0]
        model = study.load_model(model_name)
        reference = study.dynamics_reference(model_name, model)
        for k, (what, factor) in enumerate([("none", 1.0), *args.changes]):
            started = time.perf_counter()
            found = []
            for b in range(args.batches + (2 if what == "none" else 0)):
                starts = study.starts(condition, args.episodes, offset=START_OFFSET + 1000 * b)
                with changed_physics(what, factor):  # the study's own episodes, in it
                    stats = study.agent_episodes(condition, starts, EPISODE_BLOCK + 100 * b + k)
                both = check_dynamics(model, stats.data, novelty=reference, shift=True)
                size = check_dynamics(model, stats.data, novelty=reference)
                found.append({"batch": b, "check": both.as_dict(), "size_only_passed": size.passed,
                              "passed": both.passed, "success": stats.success_rate})  # fmt: skip
            failed = sum(not f["passed"] for f in found)
            size_failed = sum(not f["size_only_passed"] for f in found)
            success = sum(f["success"] for f in found) / len(found)
            results.append(
                {
                    "condition": condition,
                    "change": what,
                    "factor": factor,
                    "batches": found,
                    "failed": failed,
                    "size_only_failed": size_failed,
                    "seconds": time.perf_counter() - started,
                }
            )
            rows.append(
                [condition, what, f"{factor:g}", f"{failed} of {len(found)}",
                 f"{size_failed} of {len(found)}", f"{success:.2f}"]
            )  # fmt: skip
    print_table(
        f"Batches of {args.episodes} episodes the dynamics check failed ({args.run_dir}, 1 thread)",
        ["condition", "change", "factor", "failed (size + shift)", "failed (size alone)",
         "real success"],
        rows,
    )  # fmt: skip
    write_json(
        args.out,
        {
            "run_dir": str(args.run_dir),
            "seed": study.cfg.seed,
            "settings": {"batches": args.batches, "episodes": args.episodes},
            "conditions": conditions(),
            "results": results,
        },
    )


if __name__ == "__main__":
    main()

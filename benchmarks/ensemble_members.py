"""Would a larger ensemble forecast better? The Brier skill of k of a run's members.

A study run's forecast of P(success) per start state is the mean of its members' forecasts
(each over its own imagined samples). Members differ by their initialisation, the order of
their data and their samples; what they get wrong alike, no number of them averages out. On the
finished runs given, this script scores the forecast made with every subset of k members
(k = 1 .. E, each subset's members averaged as the study averages all of them) against the same
real episodes, pooled as the study pools its three conditions (every episode once), and the
skill of infinitely many members of the same kind, each with as many samples as the run drew.

Averaged over the subsets of k of E members, the Brier score of their mean forecast falls as
1 / k, exactly (``rcvae_torchrl.competency.members_brier_skill`` gives the closed form); its
limit is the unbiased estimate of the Brier score of the members' expected forecast (members
taken as independent draws of their training). Its skill is ``k -> inf``.
Beside it, two ceilings set by the agent's own outcomes:

- the study's oracle (each start's real rate as the forecast, scored in-sample: a little
  optimistic, since the rate is fitted to the very runs it is scored on);
- the forecast of each start's true chance, in expectation
  (``rcvae_torchrl.competency.chance_brier_skill``: the oracle without its in-sample
  optimism; a start's rate q over R > 1 runs counts q (1 - q) R / (R - 1), a start run once is
  taken as fixed).

    python benchmarks/ensemble_members.py outputs/pusher_competency/seeds/seed* [--out NAME]

Prints one row per run and writes ``benchmarks/results/<out>.json`` (default
``ensemble_members``). Reads only the runs' saved forecasts and real outcomes: nothing is
imagined or run again, so it takes seconds.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import torch
from _report import print_table, write_json

from rcvae_torchrl.competency import (
    chance_brier_skill,
    members_brier_skill,
    per_start_rates,
    pool_outcomes,
    validate_forecasts,
)
from rcvae_torchrl.io import load_torch
from recipes.pusher_competency.pusher import CONDITIONS


def subset_skills(members: torch.Tensor, outcome: torch.Tensor, mask: torch.Tensor) -> list:
    """The pooled Brier skill (against the outcomes' overall rate) of the mean of every subset
    of k of the members' forecasts ``[B, E]``, averaged over the subsets of each size: one value
    per k = 1 .. E."""
    size = members.shape[1]
    skills = []
    for k in range(1, size + 1):
        values = [
            validate_forecasts(members[:, list(subset)].mean(1), outcome, mask)["brier_skill"]
            for subset in itertools.combinations(range(size), k)
        ]
        skills.append(sum(values) / len(values))
    return skills


def score_run(run_dir: Path) -> dict:
    """The member subsets' skills, their limit and the two ceilings of one finished run."""
    forecasts = [load_torch(run_dir / "forecast" / f"{c}.pt", "forecast") for c in CONDITIONS]
    truths = [load_torch(run_dir / "truth" / f"{c}.pt", "truth") for c in CONDITIONS]
    members = torch.cat([f["p_success_member"] for f in forecasts]).double()
    outcome, mask = pool_outcomes([t["success"] for t in truths])
    skills = subset_skills(members, outcome, mask)
    rates, _ = per_start_rates(outcome, mask)
    return {
        "members": members.shape[1],
        "skill_by_members": skills,
        "infinite_members": members_brier_skill(members, outcome, mask),
        "oracle_in_sample": validate_forecasts(rates, outcome, mask)["brier_skill"],
        "true_chance_expected": chance_brier_skill(outcome, mask),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dirs", type=Path, nargs="+", help="finished study runs")
    parser.add_argument("--out", default="ensemble_members", help="name of the JSON written")
    args = parser.parse_args()
    results = {str(d): score_run(d) for d in args.run_dirs}
    size = max(r["members"] for r in results.values())
    rows = [
        [
            d,
            *(f"{s:.3f}" for s in r["skill_by_members"]),
            *([""] * (size - r["members"])),
            f"{r['infinite_members']:.3f}",
            f"{r['oracle_in_sample']:.3f}",
            f"{r['true_chance_expected']:.3f}",
        ]
        for d, r in results.items()
    ]
    print_table(
        "Brier skill against the overall rate, pooled over the conditions",
        [
            "run",
            *(f"k={k}" for k in range(1, size + 1)),
            "k -> inf",
            "oracle (in-sample)",
            "true chance (expected)",
        ],
        rows,
    )
    write_json(args.out, {"benchmark": "ensemble_members", "runs": results})


if __name__ == "__main__":
    main()

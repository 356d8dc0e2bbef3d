"""The multi-seed study in one table: every column and check as mean ± sd over seeds, how many
seeds meet each check, and every seed's value of each check.

    python recipes/pusher_competency/main.py -m seed=0,1,2,3,4 \\
        'run_dir=outputs/pusher_competency/seeds/seed${seed}'
    python recipes/pusher_competency/aggregate.py outputs/pusher_competency/seeds

reads ``seed*/summary.json`` under the given directory and writes ``aggregate.md`` and
``aggregate.json`` there (``make run-seeds`` does both).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from recipes._aggregate import (
    by_condition,
    cell,
    command,
    forecast_check_lines,
    forecast_checks,
    section,
    stats,
    table,
    table_lines,
)
from recipes._aggregate import checks as seed_checks
from recipes.pusher_competency.trust import TARGETS, THROUGH_MAP

__all__ = ["aggregate", "main"]

#: Columns of the aggregate table: (summary section, key, label).
COLUMNS = (
    ("rows", "aleatoric_bits", "aleatoric bits"),
    ("rows", "epistemic_bits", "epistemic bits"),
    ("validation", "forecast", "forecast P"),
    ("validation", "real", "real P"),
    ("validation", "gap", "gap"),
    ("validation", "gap_se", "gap's standard error"),
    ("validation", "per_start_mae", "per-start MAE"),
    ("validation", "spearman", "Spearman"),
    ("validation", "auroc", "AUROC"),
    ("validation", "bss_overall", "BSS (overall rate)"),
    ("validation", "brier_skill", "BSS (own rate)"),
    ("validation", "brier_skill_members_limit", "BSS (own rate), infinite members"),
    ("validation", "oracle_auroc", "oracle AUROC"),
    ("validation", "oracle_brier_skill", "oracle BSS (own rate)"),
    ("validation", "chance_brier_skill", "true-chance BSS (expected)"),
    ("validation", "oracle_spearman", "oracle Spearman"),
    ("validation", "bss_tasks", "BSS (tasks alike)"),
    ("validation", "tts_skill", "TTS CRPS skill"),
    ("validation", "recalibrated.gap", "gap, cross-fitted map"),
    ("validation", "recalibrated.brier_skill", "BSS (own rate), cross-fitted map"),
    ("validation", "recalibrated_held_out.gap", "gap, held-out map"),
    ("validation", "recalibrated_held_out.brier_skill", "BSS (own rate), held-out map"),
    ("validation", "recalibrated_held_out.auroc", "AUROC, held-out map"),
)
#: Across seeds, the mean gap per condition must stay within this.
MEAN_GAP = 0.05


def aggregate(summaries: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """``summaries``: seed name -> that run's summary.json. Returns the aggregate."""
    first = next(iter(summaries.values()))
    conditions = list(first["validation"])
    result_table = table(summaries, COLUMNS, conditions)
    checks = seed_checks(summaries)
    for c in conditions:
        if c == "overall":
            continue
        gap = result_table[c]["forecast"]["mean"] - result_table[c]["real"]["mean"]
        mean_abs = stats([s["validation"][c]["gap"] for s in summaries.values()])["mean"]
        checks[f"mean |forecast - real| over seeds <= {MEAN_GAP} ({c})"] = {
            "mean": mean_abs,
            "signed_mean": gap,
            "met": int(mean_abs <= MEAN_GAP),
            "seeds": 1,
        }
        mapped = [s["validation"][c].get("recalibrated_held_out") for s in summaries.values()]
        if all(mapped):  # every seed's forecasts through its own held-out map
            mapped_abs = stats([m["gap"] for m in mapped])["mean"]
            signed = (
                stats([m["forecast"] for m in mapped])["mean"] - result_table[c]["real"]["mean"]
            )
            checks[f"mean |forecast - real| over seeds <= {MEAN_GAP} {THROUGH_MAP} ({c})"] = {
                "mean": mapped_abs,
                "signed_mean": signed,
                "met": int(mapped_abs <= MEAN_GAP),
                "seeds": 1,
            }
    return {
        "seeds": list(summaries),
        "table": result_table,
        "checks": checks,
        "targets": TARGETS,
        "forecast_checks": forecast_checks(summaries),
        "pattern_per_live_step": _pattern_per_live_step(summaries),
        "novelty": _novelty(summaries),
    }


def _novelty(summaries: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per condition, the start states the report cautioned as unlike the world model's
    training states, summed over the seeds whose run made the check (its models trained
    with it), and each seed's count (None: no check)."""
    out = {}
    for c, by_seed, made in by_condition(summaries, "novelty"):
        out[c] = {
            "cautioned": sum(row["cautioned"] for row in made),
            "starts": sum(row["starts"] for row in made),
            "seeds": len(made),
            "by_seed": [None if row is None else row["cautioned"] for row in by_seed],
        }
    return out


#: The pattern's ratios, as the report names them, with their labels.
PATTERN_RATIOS = {
    "aleatoric_stochastic_over_deterministic": "aleatoric stochastic / deterministic",
    "epistemic_ood_over_deterministic": "epistemic out-of-distribution / deterministic",
    "aleatoric_ood_over_deterministic": "aleatoric out-of-distribution / deterministic",
}


def _pattern_per_live_step(summaries: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The pattern's ratios per live step over seeds (each report's last pattern row; seeds
    whose forecasts kept no share of running episodes are left out, ``None``)."""
    by_seed = [s.get("pattern_by_window", {}).get("per live step") for s in summaries.values()]
    if not any(by_seed):
        return {}
    return {
        key: {
            **stats([r[key] for r in by_seed if r]),
            "by_seed": [r[key] if r else None for r in by_seed],
        }
        for key in PATTERN_RATIOS
    }


def markdown(result: dict[str, Any]) -> str:
    """aggregate.md: the table and the checks."""
    n = len(result["seeds"])
    lines = [
        f"# Pusher competency study over {n} seeds ({', '.join(result['seeds'])})",
        "",
        "Mean ± sd over seeds.",
        "",
        *table_lines(result, COLUMNS),
        *forecast_check_lines(result),
    ]
    novelty = result.get("novelty") or {}
    if novelty:
        lines += section(
            "Start states unlike the training states",
            "The start states each run's report cautioned as unlike the world model's training "
            "states, or as imagining more of their states unlike them than real episodes do "
            "(the report's section of that name); – marks a seed whose models have no such "
            "check.",
            ["condition", "cautioned, all seeds"],
            result["seeds"],
        )
        for c, row in novelty.items():
            cells = " | ".join("–" if x is None else str(x) for x in row["by_seed"])
            lines.append(f"| {c} | {row['cautioned']} of {row['starts']} | {cells} |")
    live = result.get("pattern_per_live_step") or {}
    if live:
        lines += section(
            "The pattern per live step",
            "The checks' ratios average the bits over the whole horizon, in which an ended "
            "episode counts as certain: they also measure how long the episodes last. Per live "
            "step (each start's bits over the steps its imagined episodes run; each report's "
            "last pattern row) that is taken out; – marks a seed whose forecasts kept no share "
            "of running episodes.",
            ["ratio", "mean ± sd"],
            result["seeds"],
        )
        for key, label in PATTERN_RATIOS.items():
            cells = " | ".join("–" if v is None else f"{v:.2f}" for v in live[key]["by_seed"])
            lines.append(f"| {label} | {cell(live[key])} | {cells} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    return command(argv, __doc__.splitlines()[0], {"rows", "validation"}, aggregate, markdown)


if __name__ == "__main__":
    main()

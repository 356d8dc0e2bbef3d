"""The point-mass study over several seeds in one table: every column and check as mean ± sd
over seeds, how many seeds meet each check, every seed's value of each, and each condition's
outcome check over the seeds.

    python recipes/point_mass_competency/main.py -m hydra/launcher=local seed=0,1,2 threads=1 \\
        'run_dir=outputs/point_mass_competency/seeds/seed${seed}'
    python recipes/point_mass_competency/aggregate.py outputs/point_mass_competency/seeds

reads ``seed*/summary.json`` under the given directory and writes ``aggregate.md`` and
``aggregate.json`` there.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from recipes._aggregate import (
    checks,
    command,
    forecast_check_lines,
    forecast_checks,
    table,
    table_lines,
)

__all__ = ["aggregate", "main", "markdown"]

#: Columns of the aggregate table: (summary section, key, label).
COLUMNS = (
    ("rows", "aleatoric_bits", "aleatoric bits"),
    ("rows", "epistemic_bits", "epistemic bits"),
    ("rows", "forecast_p_success", "forecast P"),
    ("rows", "real_p_success", "real P"),
    ("rows", "gap", "gap"),
    ("rows", "brier", "Brier"),
    ("rows", "per_start_mae", "per-start MAE"),
    ("rows", "spearman", "Spearman"),
    ("rows", "auroc", "AUROC"),
)


def aggregate(summaries: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """``summaries``: seed name -> that run's summary.json. Returns the aggregate."""
    conditions = list(next(iter(summaries.values()))["rows"])
    return {
        "seeds": list(summaries),
        "table": table(summaries, COLUMNS, conditions),
        "checks": checks(summaries),
        "forecast_checks": forecast_checks(summaries),
    }


def markdown(result: dict[str, Any]) -> str:
    """aggregate.md: the table, the checks and the outcome checks."""
    n = len(result["seeds"])
    lines = [
        f"# Point-mass competency study over {n} seeds ({', '.join(result['seeds'])})",
        "",
        "Mean ± sd over seeds.",
        "",
        *table_lines(result, COLUMNS),
        *forecast_check_lines(result),
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict[str, Any]:
    return command(argv, __doc__.splitlines()[0], {"rows", "checks"}, aggregate, markdown)


if __name__ == "__main__":
    main()

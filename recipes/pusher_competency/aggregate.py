"""The multi-seed study in one table: every column and check as mean ± sd over seeds, how many
seeds meet each check, and every seed's value of each check.

    python recipes/pusher_competency/main.py -m seed=0,1,2,3,4 \\
        'run_dir=outputs/pusher_competency/seeds/seed${seed}'
    python recipes/pusher_competency/aggregate.py outputs/pusher_competency/seeds

reads ``seed*/summary.json`` under the given directory and writes ``aggregate.md`` and
``aggregate.json`` there (``make run-seeds`` does both).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from rcvae_torchrl.io import atomic_write, read_json, write_json
from rcvae_torchrl.training import OutcomeCheck
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


def _stats(values: list[float]) -> dict[str, Any]:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    n = len(finite)
    mean = sum(finite) / n if n else math.nan
    sd = math.sqrt(sum((v - mean) ** 2 for v in finite) / (n - 1)) if n > 1 else math.nan
    return {"mean": mean, "sd": sd, "values": values, "of": n}


def _get(scores: dict[str, Any], key: str) -> Any:
    """``scores[key]``, where ``"a.b"`` reads ``scores["a"]["b"]`` (None when absent)."""
    for part in key.split("."):
        scores = scores.get(part) if isinstance(scores, dict) else None
    return scores


def aggregate(summaries: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """``summaries``: seed name -> that run's summary.json. Returns the aggregate."""
    first = next(iter(summaries.values()))
    conditions = list(first["validation"])
    table = {}
    for c in conditions:
        table[c] = {}
        for section, key, _ in COLUMNS:
            values = [_get(s[section].get(c, {}), key) for s in summaries.values()]
            if any(v is not None for v in values):
                table[c][key] = _stats(values)
    checks = {}
    # A check applies to a seed only where its run made it (e.g. no own-rate Brier skill where
    # every real episode of a condition agreed): count the seeds it applied to.
    names = dict.fromkeys(name for s in summaries.values() for name in s["checks"])
    for name in names:
        by_seed = [s["checks"].get(name) for s in summaries.values()]
        per_seed = [c for c in by_seed if c is not None]
        checks[name] = {
            **_stats([c["value"] for c in per_seed]),
            "met": sum(bool(c["met"]) for c in per_seed),
            "seeds": len(per_seed),
            # every seed's value and verdict, in the order of "seeds" (None: did not apply)
            "by_seed": [
                None if c is None else {"value": c["value"], "met": bool(c["met"])} for c in by_seed
            ],
        }
    for c in conditions:
        if c == "overall":
            continue
        gap = table[c]["forecast"]["mean"] - table[c]["real"]["mean"]
        mean_abs = _stats([s["validation"][c]["gap"] for s in summaries.values()])["mean"]
        checks[f"mean |forecast - real| over seeds <= {MEAN_GAP} ({c})"] = {
            "mean": mean_abs,
            "signed_mean": gap,
            "met": int(mean_abs <= MEAN_GAP),
            "seeds": 1,
        }
        mapped = [s["validation"][c].get("recalibrated_held_out") for s in summaries.values()]
        if all(mapped):  # every seed's forecasts through its own held-out map
            mapped_abs = _stats([m["gap"] for m in mapped])["mean"]
            signed = _stats([m["forecast"] for m in mapped])["mean"] - table[c]["real"]["mean"]
            checks[f"mean |forecast - real| over seeds <= {MEAN_GAP} {THROUGH_MAP} ({c})"] = {
                "mean": mapped_abs,
                "signed_mean": signed,
                "met": int(mapped_abs <= MEAN_GAP),
                "seeds": 1,
            }
    return {
        "seeds": list(summaries),
        "table": table,
        "checks": checks,
        "targets": TARGETS,
        "forecast_checks": _forecast_checks(summaries),
        "pattern_per_live_step": _pattern_per_live_step(summaries),
        "novelty": _novelty(summaries),
    }


def _by_condition(summaries: dict[str, dict[str, Any]], section: str) -> list[tuple]:
    """Per condition of a per-condition ``section`` of the summaries: the condition, each
    seed's entry (None where its run made none), and the entries made."""
    conditions = dict.fromkeys(c for s in summaries.values() for c in s.get(section, {}))
    out = []
    for c in conditions:
        by_seed = [s.get(section, {}).get(c) for s in summaries.values()]
        out.append((c, by_seed, [entry for entry in by_seed if entry is not None]))
    return out


def _novelty(summaries: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per condition, the start states the report cautioned as unlike the world model's
    training states, summed over the seeds whose run made the check (its models trained
    with it), and each seed's count (None: no check)."""
    out = {}
    for c, by_seed, made in _by_condition(summaries, "novelty"):
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
            **_stats([r[key] for r in by_seed if r]),
            "by_seed": [r[key] if r else None for r in by_seed],
        }
        for key in PATTERN_RATIOS
    }


def _forecast_checks(summaries: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per condition, the forecast check from start states not scored, over seeds: its
    gap, and in how many seeds it found the forecasts biased (seeds whose run made none, e.g.
    runs from before the check, are left out)."""
    out = {}
    for c, by_seed, made in _by_condition(summaries, "forecast_checks"):
        verdicts = [None if found is None else _verdict(found) for found in by_seed]
        # a check that measured nothing has no gap to show (its run's report leaves it blank)
        shown = [
            found["gap"]
            for found, verdict in zip(by_seed, verdicts, strict=True)
            if verdict not in (None, "not measured")
        ]
        out[c] = {
            **_stats(shown),
            "biased": sum(v in ("too optimistic", "too pessimistic") for v in verdicts),
            "not_passed": sum(v not in (None, "passed") for v in verdicts),
            "seeds": len(made),
            "by_seed": [
                None
                if found is None
                else {"gap": found["gap"], "passed": found["passed"], "verdict": verdict}
                for found, verdict in zip(by_seed, verdicts, strict=True)
            ],
        }
    return out


def _verdict(found: dict[str, Any]) -> str:
    """A forecast check's verdict, judged from its record by the current rules; a record
    without its forecasts (a gap and a pass alone) is biased where it did not pass."""
    if "forecast" not in found:
        if found["passed"]:
            return "passed"
        return "too optimistic" if found["gap"] > 0 else "too pessimistic"
    return OutcomeCheck.from_dict(found).verdict


def _check_cell(found: dict[str, Any] | None) -> str:
    """One seed's forecast check: its gap and mark, its verdict where it measured nothing."""
    if found is None:
        return "–"
    verdict = found.get("verdict")
    if verdict == "not measured":
        return "not measured ?"
    if verdict in ("too optimistic", "too pessimistic") or (
        verdict is None and not found["passed"]
    ):
        return f"{found['gap']:+.3f} ✗"
    return f"{found['gap']:+.3f}" + ("" if found["passed"] else f" ? ({verdict})")


def _cell(stats: dict[str, Any]) -> str:
    """Mean ± sd, and over how many seeds where some had no finite value (a trial's CRPS skill
    read as two seeds' mean was one seed's, the other's NaN left out unsaid)."""
    if not math.isfinite(stats["mean"]):
        values = stats["values"]  # a rise from nothing in every seed (e.g. over 0 bits): inf
        return "inf" if values and all(v == math.inf for v in values) else "n/a"
    of = stats.get("of", len(stats["values"]))
    some = f" (of {of} seed{'' if of == 1 else 's'})" if of < len(stats["values"]) else ""
    if not math.isfinite(stats["sd"]):
        return f"{stats['mean']:.3f}{some}"
    return f"{stats['mean']:.3f} ± {stats['sd']:.3f}{some}"


def markdown(result: dict[str, Any]) -> str:
    """aggregate.md: the table and the checks."""
    n = len(result["seeds"])
    head = "| condition | " + " | ".join(label for *_, label in COLUMNS) + " |"
    lines = [
        f"# Pusher competency study over {n} seeds ({', '.join(result['seeds'])})",
        "",
        "Mean ± sd over seeds.",
        "",
        head,
        "|:---|" + "---:|" * len(COLUMNS),
    ]
    for c, row in result["table"].items():
        cells = [_cell(row[key]) if key in row else "" for _, key, _ in COLUMNS]
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    lines += ["", "## Checks", "", "| check | mean ± sd | seeds met |", "|:---|---:|---:|"]
    for name, c in result["checks"].items():
        value = _cell(c) if "sd" in c else format(c["mean"], ".3f")
        lines.append(f"| {_escaped(name)} | {value} | {c['met']}/{c['seeds']} |")
    lines += _section(
        "Every seed",
        "Each check's value in each seed; ✗ marks a seed that misses it, – one where it did not "
        "apply.",
        ["check"],
        result["seeds"],
    )
    for name, c in result["checks"].items():
        if "by_seed" in c:
            cells = " | ".join(map(_seed_cell, c["by_seed"]))
            lines.append(f"| {_escaped(name)} | {cells} |")
    held_out = result.get("forecast_checks") or {}
    if held_out:
        lines += _section(
            "The forecasts from start states they are not scored on",
            "Each run's self-check of its forecasts on start states it is not scored on (the "
            "report's section of that name): the gap, forecast minus real; ✗ marks a seed "
            "where the check found the forecasts biased, ? one where it did not pass otherwise "
            "(too few start states in doubt to measure, too imprecise, no better than a "
            "constant), – one whose run made no such check.",
            ["condition", "gap, mean ± sd", "seeds biased", "seeds not passed"],
            result["seeds"],
        )
        for c, found in held_out.items():
            cells = " | ".join(map(_check_cell, found["by_seed"]))
            lines.append(
                f"| {c} | {_cell(found)} | {found['biased']}/{found['seeds']} | "
                f"{found.get('not_passed', found['biased'])}/{found['seeds']} | {cells} |"
            )
    novelty = result.get("novelty") or {}
    if novelty:
        lines += _section(
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
        lines += _section(
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
            lines.append(f"| {label} | {_cell(live[key])} | {cells} |")
    return "\n".join(lines) + "\n"


def _section(title: str, text: str, head: list[str], seeds: list[str]) -> list[str]:
    """The lines that open a section of one table: its title, its text, the table's head
    (``head`` then a column per seed; the first column left-aligned, the others right)."""
    columns = [*head, *seeds]
    return [
        "",
        f"## {title}",
        "",
        text,
        "",
        "| " + " | ".join(columns) + " |",
        "|:---|" + "---:|" * (len(columns) - 1),
    ]


def _escaped(name: str) -> str:
    """A check's name in a markdown table cell (its ``|`` would end the cell)."""
    return name.replace("|", "\\|")


def _seed_cell(check: dict[str, Any] | None) -> str:
    if check is None:
        return "–"
    text = format(check["value"], ".3f")  # every check's value is a float (trust.py, report.py)
    return text if check["met"] else f"{text} ✗"


def _summary(path: Path) -> dict[str, Any]:
    summary = read_json(path, "study summary")
    if not isinstance(summary, dict) or not {"validation", "rows"} <= summary.keys():
        raise SystemExit(
            f"{path}: expected a study summary (a mapping with 'rows' and 'validation'), got "
            f"{type(summary).__name__}"
            + (f" with keys {sorted(summary)}" if isinstance(summary, dict) else "")
        )
    return summary


def _check_same_settings(configs: dict[str, Path]) -> None:
    """Seeds of one study: the same settings but the seed (each run records its own)."""
    settings = {}
    for name, path in configs.items():
        if path.is_file():
            recorded = read_json(path, "study settings")
            settings[name] = {k: v for k, v in recorded.items() if k != "seed"}
    if len(settings) < 2:
        return
    (first, reference), *others = settings.items()
    for name, values in others:
        differ = sorted(
            k for k in reference.keys() | values.keys() if reference.get(k) != values.get(k)
        )
        if differ:
            raise SystemExit(
                f"{name}: made with other settings than {first} (sections {differ} differ): "
                "aggregate the seeds of one study only"
            )


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("directory", type=Path, help="the directory holding seed*/summary.json")
    args = parser.parse_args(argv)
    for old in ("aggregate.json", "aggregate.md"):  # never left to look current after a failure
        (args.directory / old).unlink(missing_ok=True)
    found = sorted(args.directory.glob("seed*/summary.json"))
    if not found:
        raise SystemExit(
            f"directory: expected seed*/summary.json under {args.directory}, found none"
        )
    unfinished = sorted(
        p.name
        for p in args.directory.glob("seed*")
        if p.is_dir() and not (p / "summary.json").is_file()
    )
    if unfinished:
        raise SystemExit(
            f"directory: {unfinished} under {args.directory} hold no summary.json (runs that "
            "did not finish): finish them, or move them away to aggregate the others"
        )
    summaries = {p.parent.name: _summary(p) for p in found}
    _check_same_settings({p.parent.name: p.parent / "study_config.json" for p in found})
    result = aggregate(summaries)
    write_json(args.directory / "aggregate.json", result)
    text = markdown(result)
    atomic_write(args.directory / "aggregate.md", lambda f: f.write(text.encode()))
    print(text)
    return result


if __name__ == "__main__":
    main()

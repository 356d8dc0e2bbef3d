"""A multi-seed study in one table, shared by the recipes' ``aggregate.py`` scripts: each
column of the runs' summaries and each check as mean ± sd over seeds, how many seeds meet each
check, every seed's value of it, and the outcome checks over the seeds that made them.

A run's ``summary.json`` holds ``checks`` (``{name: {"value", "met"}}``), its per-condition
sections (``rows``, ``validation``, ...) and, where the run checked its forecasts,
``forecast_checks`` (``{condition: {"gap", "passed", ...}}``, an
:class:`~rcvae_torchrl.training.OutcomeCheck`'s record or its verdict).
"""

from __future__ import annotations

import argparse
import math
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from rcvae_torchrl.competency.intervals import mean_p_value
from rcvae_torchrl.io import StoredFileError, atomic_write, read_json, write_json
from rcvae_torchrl.reporting import escape_cell, signed
from rcvae_torchrl.training import OutcomeCheck

__all__ = [
    "by_condition",
    "cell",
    "check_cell",
    "checks",
    "checks_lines",
    "command",
    "forecast_check_lines",
    "forecast_checks",
    "get",
    "read_summaries",
    "section",
    "seed_cell",
    "shared_bias",
    "shared_cell",
    "stats",
    "table",
    "table_lines",
    "write",
]

#: A column of the aggregate table: (summary section, key, label).
Column = tuple[str, str, str]


def stats(values: list[float]) -> dict[str, Any]:
    """Mean and sd (n - 1) of the finite numbers among ``values`` (not ``None``, not a word
    such as a verdict), the values, and over how many."""
    finite = [v for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
    n = len(finite)
    mean = sum(finite) / n if n else math.nan
    sd = math.sqrt(sum((v - mean) ** 2 for v in finite) / (n - 1)) if n > 1 else math.nan
    return {"mean": mean, "sd": sd, "values": values, "of": n}


def get(scores: dict[str, Any], key: str) -> Any:
    """``scores[key]``, where ``"a.b"`` reads ``scores["a"]["b"]`` (None when absent)."""
    for part in key.split("."):
        scores = scores.get(part) if isinstance(scores, dict) else None
    return scores


def table(
    summaries: dict[str, dict[str, Any]], columns: Sequence[Column], conditions: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """Per condition, each column's :func:`stats` over the seeds (columns no seed has are
    left out)."""
    out: dict[str, dict[str, Any]] = {}
    for c in conditions:
        out[c] = {}
        for section_name, key, _ in columns:
            values = [get(s[section_name].get(c, {}), key) for s in summaries.values()]
            if any(v is not None for v in values):
                out[c][key] = stats(values)
    return out


def checks(summaries: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Each check's :func:`stats` over the seeds it applied to, the seeds that met it, and
    every seed's value and verdict (``None`` where the run did not make it: e.g. no own-rate
    Brier skill where every real episode of a condition agreed)."""
    out = {}
    names = dict.fromkeys(name for s in summaries.values() for name in s["checks"])
    for name in names:
        by_seed = [s["checks"].get(name) for s in summaries.values()]
        per_seed = [c for c in by_seed if c is not None]
        out[name] = {
            **stats([c["value"] for c in per_seed]),
            "met": sum(bool(c["met"]) for c in per_seed),
            "seeds": len(per_seed),
            # every seed's value and verdict, in the order of "seeds" (None: did not apply)
            "by_seed": [
                None if c is None else {"value": c["value"], "met": bool(c["met"])} for c in by_seed
            ],
        }
    return out


def by_condition(summaries: dict[str, dict[str, Any]], section_name: str) -> list[tuple]:
    """Per condition of a per-condition section of the summaries: the condition, each seed's
    entry (None where its run made none), and the entries made."""
    conditions = dict.fromkeys(c for s in summaries.values() for c in s.get(section_name, {}))
    out = []
    for c in conditions:
        by_seed = [s.get(section_name, {}).get(c) for s in summaries.values()]
        out.append((c, by_seed, [entry for entry in by_seed if entry is not None]))
    return out


def forecast_checks(summaries: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Per condition, the outcome check from start states not scored, over seeds: its gap,
    and in how many seeds it found the forecasts biased or did not pass (seeds whose run made
    none, e.g. runs from before the check, are left out)."""
    out = {}
    for c, by_seed, made in by_condition(summaries, "forecast_checks"):
        verdicts = [None if found is None else _verdict(found) for found in by_seed]
        # a check that measured nothing has no gap to show (its run's report leaves it blank)
        shown = [
            found["gap"]
            for found, verdict in zip(by_seed, verdicts, strict=True)
            if verdict not in (None, "not measured")
        ]
        alphas = {found.get("alpha", OutcomeCheck.alpha) for found in made}
        out[c] = {
            **stats(shown),
            "shared": shared_bias(shown, alphas.pop() if len(alphas) == 1 else OutcomeCheck.alpha),
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


#: Seeds the test of a bias they share needs (:func:`shared_bias`).
SHARED_MIN_SEEDS = 3


def shared_bias(gaps: Sequence[float], alpha: float) -> dict[str, Any] | None:
    """Whether the seeds' outcome checks share a bias: a two-sided one-sample t-test of their
    gaps at level ``alpha``, each seed one draw. A run's own check tests its model, whose
    starts all share that model's error; over seeds, each run's model is one draw of what
    training gives, so a bias every seed's model leans to shows here though each run's check
    alone, at its level, passes it (the Pusher's out-of-distribution forecasts, too optimistic
    by 0.06-0.14 in each of six seeds, one of them named biased by its own check). ``None``
    with fewer than :data:`SHARED_MIN_SEEDS` gaps."""
    if len(gaps) < SHARED_MIN_SEEDS:
        return None
    mean = sum(gaps) / len(gaps)
    p_value = mean_p_value(torch.tensor(list(gaps), dtype=torch.float64))
    verdict = "none found"
    if p_value < alpha:
        verdict = "too optimistic" if mean > 0 else "too pessimistic"
    return {"gap": mean, "p_value": p_value, "alpha": alpha, "seeds": len(gaps), "verdict": verdict}


def shared_cell(shared: dict[str, Any] | None) -> str:
    """The across-seeds test's cell: its verdict and p-value, ✗ where it found a bias."""
    if shared is None:
        return f"– (fewer than {SHARED_MIN_SEEDS} seeds)"
    mark = " ✗" if shared["verdict"] != "none found" else ""
    return f"{shared['verdict']} (p = {shared['p_value']:.2g}){mark}"


def _verdict(found: dict[str, Any]) -> str:
    """An outcome check's verdict, judged from its record by the current rules, else the one
    the run wrote; a record of a gap and a pass alone is biased where it did not pass."""
    if "forecast" in found:
        return OutcomeCheck.from_dict(found).verdict
    if "verdict" in found:
        return found["verdict"]
    if found["passed"]:
        return "passed"
    return "too optimistic" if found["gap"] > 0 else "too pessimistic"


def check_cell(found: dict[str, Any] | None) -> str:
    """One seed's outcome check: its gap and mark, its verdict where it measured nothing."""
    if found is None:
        return "–"
    verdict = found.get("verdict")
    if verdict == "not measured":
        return "not measured ?"
    if verdict in ("too optimistic", "too pessimistic") or (
        verdict is None and not found["passed"]
    ):
        return f"{signed(found['gap'])} ✗"
    return signed(found["gap"]) + ("" if found["passed"] else f" ? ({verdict})")


def cell(values: dict[str, Any]) -> str:
    """Mean ± sd, and over how many seeds where some had no finite value (a trial's CRPS skill
    read as two seeds' mean was one seed's, the other's NaN left out unsaid)."""
    if not math.isfinite(values["mean"]):
        seen = values["values"]  # a rise from nothing in every seed (e.g. over 0 bits): inf
        return "inf" if seen and all(v == math.inf for v in seen) else "n/a"
    of = values.get("of", len(values["values"]))
    some = f" (of {of} seed{'' if of == 1 else 's'})" if of < len(values["values"]) else ""
    if not math.isfinite(values["sd"]):
        return f"{values['mean']:.3f}{some}"
    return f"{values['mean']:.3f} ± {values['sd']:.3f}{some}"


def section(title: str, text: str, head: list[str], seeds: list[str]) -> list[str]:
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


def seed_cell(check: dict[str, Any] | None) -> str:
    """One seed's value of a check, ✗ where it missed, – where it did not apply."""
    if check is None:
        return "–"
    text = format(check["value"], ".3f") if isinstance(check["value"], float) else check["value"]
    return str(text) if check["met"] else f"{text} ✗"


def table_lines(result: dict[str, Any], columns: Sequence[Column]) -> list[str]:
    """The table of the columns' mean ± sd per condition, then the checks' mean ± sd and the
    seeds that met each, then each check's value in every seed."""
    lines = [
        "| condition | " + " | ".join(label for *_, label in columns) + " |",
        "|:---|" + "---:|" * len(columns),
    ]
    for c, row in result["table"].items():
        cells = [cell(row[key]) if key in row else "" for _, key, _ in columns]
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return lines + checks_lines(result)


def checks_lines(result: dict[str, Any]) -> list[str]:
    """The checks' mean ± sd and the seeds that met each, then each one's value per seed."""
    lines = ["", "## Checks", "", "| check | mean ± sd | seeds met |", "|:---|---:|---:|"]
    for name, c in result["checks"].items():
        value = _check_value(c)
        lines.append(f"| {escape_cell(name)} | {value} | {c['met']}/{c['seeds']} |")
    lines += section(
        "Every seed",
        "Each check's value in each seed; ✗ marks a seed that misses it, – one where it did not "
        "apply.",
        ["check"],
        result["seeds"],
    )
    for name, c in result["checks"].items():
        if "by_seed" in c:
            cells = " | ".join(map(seed_cell, c["by_seed"]))
            lines.append(f"| {escape_cell(name)} | {cells} |")
    return lines


def _check_value(c: dict[str, Any]) -> str:
    """A check's value over the seeds: mean ± sd, its mean alone, or, for a check whose value
    is a word (a verdict), none."""
    if "sd" in c:
        numbers = any(isinstance(v, (int, float)) for v in c["values"])
        return cell(c) if numbers or not c["values"] else ""
    return format(c["mean"], ".3f")


def forecast_check_lines(result: dict[str, Any]) -> list[str]:
    """The outcome checks' section (none where no run made one)."""
    held_out = result.get("forecast_checks") or {}
    if not held_out:
        return []
    lines = section(
        "The forecasts from start states they are not scored on",
        "Each run's self-check of its forecasts on start states it is not scored on (its "
        "outcome check, in its report): the gap, forecast minus real; ✗ marks a seed where the "
        "check found the forecasts biased, ? one where it did not pass otherwise (too few start "
        "states in doubt to measure, too imprecise, no better than a constant), – one whose run "
        "made no such check. Shared by the seeds: a t-test of the seeds' gaps, each seed one "
        "draw of the model training gives (at the checks' level), which finds a bias every "
        "seed's model leans to though each run's own check, on its own episodes, may pass it.",
        ["condition", "gap, mean ± sd", "shared by the seeds", "seeds biased", "seeds not passed"],
        result["seeds"],
    )
    for c, found in held_out.items():
        cells = " | ".join(map(check_cell, found["by_seed"]))
        lines.append(
            f"| {c} | {cell(found)} | {shared_cell(found.get('shared'))} | "
            f"{found['biased']}/{found['seeds']} | "
            f"{found.get('not_passed', found['biased'])}/{found['seeds']} | {cells} |"
        )
    return lines


def read_summaries(
    directory: Path, required: set[str], check: Callable[[Path, dict], None] | None = None
) -> dict[str, dict[str, Any]]:
    """``seed*/summary.json`` under ``directory`` by seed name: each must hold the
    ``required`` sections, every ``seed*`` folder a summary (a run that did not finish is
    named), and the runs the same settings but the seed. An earlier aggregate there is
    removed first, so that it never looks current after a failure."""
    for old in ("aggregate.json", "aggregate.md"):
        (directory / old).unlink(missing_ok=True)
    found = sorted(directory.glob("seed*/summary.json"), key=lambda p: _in_order(p.parent.name))
    if not found:
        raise SystemExit(f"directory: expected seed*/summary.json under {directory}, found none")
    unfinished = sorted(
        p.name for p in directory.glob("seed*") if p.is_dir() and not (p / "summary.json").is_file()
    )
    if unfinished:
        raise SystemExit(
            f"directory: {unfinished} under {directory} hold no summary.json (runs that "
            "did not finish): finish them, or move them away to aggregate the others"
        )
    summaries = {p.parent.name: _summary(p, required) for p in found}
    _check_same_settings({p.parent.name: p.parent / "study_config.json" for p in found})
    return summaries


def _in_order(name: str) -> list[Any]:
    """A sort key that orders ``seed2`` before ``seed10`` (numbers by value, not by digits)."""
    return [(0, int(part)) if part.isdigit() else (1, part) for part in re.split(r"(\d+)", name)]


def _summary(path: Path, required: set[str]) -> dict[str, Any]:
    try:  # a run's summary is checksummed: one edited by hand is named, not aggregated
        summary = read_json(path, "study summary")
    except StoredFileError as err:
        raise SystemExit(str(err)) from err
    if not isinstance(summary, dict) or not required <= summary.keys():
        named = " and ".join(repr(k) for k in sorted(required))
        raise SystemExit(
            f"{path}: expected a study summary (a mapping with {named}), got "
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


def write(directory: Path, result: dict[str, Any], text: str) -> None:
    """``aggregate.json`` and ``aggregate.md`` in ``directory``; the text printed."""
    write_json(directory / "aggregate.json", result)
    atomic_write(directory / "aggregate.md", lambda f: f.write(text.encode()))
    print(text)


def command(
    argv: list[str] | None,
    description: str,
    required: set[str],
    aggregate: Callable[[dict[str, dict[str, Any]]], dict[str, Any]],
    markdown: Callable[[dict[str, Any]], str],
) -> dict[str, Any]:
    """A recipe's aggregate command: the directory holding ``seed*/summary.json`` from
    ``argv``, its runs' summaries (:func:`read_summaries`, each with the ``required``
    sections) through ``aggregate``, written with ``markdown``'s text (:func:`write`)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("directory", type=Path, help="the directory holding seed*/summary.json")
    args = parser.parse_args(argv)
    result = aggregate(read_summaries(args.directory, required))
    write(args.directory, result, markdown(result))
    return result

"""Tables of competency results: Markdown and CSV from a list of rows."""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch

from rcvae_torchrl._checks import check_non_negative_int
from rcvae_torchrl.io import atomic_write

__all__ = ["format_table", "write_table"]


def _cell(value: object, digits: int) -> str:
    if isinstance(value, torch.Tensor) and value.numel() == 1:  # a tensor's number, not its repr
        value = value.item()
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def format_table(
    rows: Sequence[Mapping[str, object]], columns: Sequence[str], digits: int = 3
) -> tuple[str, str]:
    """``(markdown, csv)`` renderings of ``rows`` restricted to ``columns``, in that order."""
    check_non_negative_int("digits", digits)
    missing = [c for c in columns if any(c not in r for r in rows)]
    if missing:
        raise KeyError(f"columns: {missing} missing from some rows")
    header = "| " + " | ".join(columns) + " |"
    rule = "|" + "|".join("---:" if i else ":---" for i in range(len(columns))) + "|"
    body = ["| " + " | ".join(_cell(r[c], digits) for c in columns) + " |" for r in rows]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    writer.writerows([[r[c] for c in columns] for r in rows])
    return "\n".join([header, rule, *body]) + "\n", buffer.getvalue()


def write_table(
    rows: Sequence[Mapping[str, object]],
    columns: Sequence[str],
    stem: str | Path,
    digits: int = 3,
) -> tuple[Path, Path]:
    """Write ``<stem>.md`` and ``<stem>.csv`` atomically; returns both paths."""
    markdown, text = format_table(rows, columns, digits)
    stem = Path(stem)
    md = atomic_write(stem.with_suffix(".md"), lambda f: f.write(markdown.encode()))
    cs = atomic_write(stem.with_suffix(".csv"), lambda f: f.write(text.encode()))
    return md, cs

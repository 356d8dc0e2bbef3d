"""Tables of competency results: Markdown and CSV from a list of rows."""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch

from rcvae_torchrl._checks import check_non_negative_int
from rcvae_torchrl.io import atomic_write

__all__ = ["escape_cell", "format_table", "write_table"]


def escape_cell(text: str) -> str:
    """``text`` for a Markdown table cell: each ``|`` escaped (a bare one ends the cell, so a
    name such as ``|forecast - real| <= 0.1`` would push its row's values one column on)."""
    return text.replace("|", "\\|")


def _cell(value: object, digits: int) -> str:
    if isinstance(value, torch.Tensor) and value.numel() == 1:  # a tensor's number, not its repr
        value = value.item()
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return escape_cell(str(value))


def format_table(
    rows: Sequence[Mapping[str, object]], columns: Sequence[str], digits: int = 3
) -> tuple[str, str]:
    """``(markdown, csv)`` renderings of ``rows`` restricted to ``columns``, in that order."""
    check_non_negative_int("digits", digits)
    if isinstance(columns, str) or not isinstance(columns, Sequence):
        raise TypeError(f"columns: expected a sequence of column names, got {columns!r}")
    if isinstance(rows, (str, Mapping)) or not isinstance(rows, Sequence):
        raise TypeError(
            f"rows: expected a sequence of rows (mappings of column to value), got "
            f"{type(rows).__name__}"
        )
    for i, row in enumerate(rows):
        if not isinstance(row, Mapping):
            raise TypeError(f"rows[{i}]: expected a mapping of column to value, got {row!r}")
    missing = [c for c in columns if any(c not in r for r in rows)]
    if missing:
        raise KeyError(f"columns: {missing} missing from some rows")
    header = "| " + " | ".join(escape_cell(str(c)) for c in columns) + " |"
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
    """Write ``<stem>.md`` and ``<stem>.csv`` atomically; returns both paths. The suffixes are
    added to the whole stem (``table_lr0.5`` gives ``table_lr0.5.md``)."""
    markdown, text = format_table(rows, columns, digits)
    if not isinstance(stem, (str, os.PathLike)):
        raise TypeError(f"stem: expected a str or a path, got {type(stem).__name__}")
    stem = Path(stem)
    if stem.is_dir() or not stem.name:
        raise ValueError(
            f"stem: expected a file name without its suffix (e.g. 'results/table'), got the "
            f"directory {str(stem)!r}"
        )
    md = atomic_write(stem.with_name(stem.name + ".md"), lambda f: f.write(markdown.encode()))
    cs = atomic_write(stem.with_name(stem.name + ".csv"), lambda f: f.write(text.encode()))
    return md, cs

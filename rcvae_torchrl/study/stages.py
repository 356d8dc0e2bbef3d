"""Resumable stages: each writes its outputs atomically, then a marker with its summary."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rcvae_torchrl.training.atomic import atomic_write

__all__ = ["StageRunner"]


class StageRunner:
    """Runs named stages once per run directory; re-running reuses finished stages.

    A stage's function returns a JSON-able summary; the marker ``stages/<name>.json`` is written
    only after the function returned, so a stage interrupted half-way runs again (and its own
    checkpoints, if any, let it continue).
    """

    def __init__(self, run_dir: str | Path, log: Callable[[str], None] = print) -> None:
        self.run_dir = Path(run_dir)
        self.log = log
        self.summaries: dict[str, Any] = {}

    def marker(self, name: str) -> Path:
        return self.run_dir / "stages" / f"{name}.json"

    def run(self, name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        path = self.marker(name)
        if path.is_file():
            self.log(f"[{name}] done earlier: reusing {path.parent.name}/{path.name}")
            summary = json.loads(path.read_text())
        else:
            self.log(f"[{name}] running")
            start = time.perf_counter()
            summary = {**fn(), "seconds": round(time.perf_counter() - start, 1)}
            atomic_write(path, lambda f: f.write(json.dumps(summary, indent=2).encode()))
            self.log(f"[{name}] finished in {summary['seconds']} s")
        self.summaries[name] = summary
        return summary

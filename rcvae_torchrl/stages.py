"""Resumable stages of a pipeline: each writes its outputs atomically, then a marker.

A study (e.g. a recipe's pipeline) is a sequence of named stages, each a function that writes
its files under the run directory and returns a JSON-able summary. The marker
``stages/<name>.json`` holding the summary is written only after the function returned, so a
stage interrupted half-way runs again (and its own checkpoints, if any, let it continue), and a
finished one is reused by the next run.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from rcvae_torchrl import distributed
from rcvae_torchrl.io import read_json, write_json

__all__ = ["StageRunner"]


class StageRunner:
    """Runs named stages once per run directory; re-running reuses finished stages.

    Args:
        run_dir: the run directory (markers go to ``run_dir/stages``).
        log: where progress lines go.

    Example:
        >>> import tempfile
        >>> runner = StageRunner(tempfile.mkdtemp(), log=lambda line: None)
        >>> runner.run("count", lambda: {"n": 3})["n"]
        3
    """

    def __init__(self, run_dir: str | Path, log: Callable[[str], None] = print) -> None:
        self.run_dir = Path(run_dir)
        self.log = log
        self.summaries: dict[str, Any] = {}

    def marker(self, name: str) -> Path:
        """The marker file of stage ``name``."""
        return self.run_dir / "stages" / f"{name}.json"

    def run(
        self, name: str, fn: Callable[[], dict[str, Any]], sharded: bool = False
    ) -> dict[str, Any]:
        """Run stage ``name`` (unless its marker exists); returns its summary.

        Under ``torch.distributed`` (:mod:`rcvae_torchrl.distributed`) a ``sharded`` stage runs
        on every rank (it shares its work out and writes its files on rank 0), any other stage
        on rank 0 alone; rank 0 writes the marker and logs, and every rank waits for the stage
        to end before the next one.
        """
        path = self.marker(name)
        if distributed.broadcast(path.is_file()):  # rank 0's view: every rank takes one branch
            self._log(f"[{name}] done earlier: reusing {path.parent.name}/{path.name}")
            summary = read_json(path, f"marker of stage {name!r}")
        elif distributed.is_main() or sharded:
            self._log(f"[{name}] running")
            start = time.perf_counter()
            summary = {**fn(), "seconds": round(time.perf_counter() - start, 1)}
            if distributed.is_main():
                write_json(path, summary)
            self._log(f"[{name}] finished in {summary['seconds']} s")
            distributed.barrier()
        else:
            distributed.barrier()
            summary = read_json(path, f"marker of stage {name!r}")
        self.summaries[name] = summary
        return summary

    def _log(self, line: str) -> None:
        if distributed.is_main():
            self.log(line)

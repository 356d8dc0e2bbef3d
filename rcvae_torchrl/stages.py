"""Resumable stages of a pipeline: each writes its outputs atomically, then a marker.

A study (e.g. a recipe's pipeline) is a sequence of named stages, each a function that writes
its files under the run directory and returns a JSON-able summary. The marker
``stages/<name>.json`` holding the summary is written only after the function returned, so a
stage interrupted half-way runs again (and its own checkpoints, if any, let it continue), and a
finished one is reused by the next run. With a TorchRL logger, every stage's numbers are
logged too (``stages/<name>/<key>``), whether the stage ran or was reused.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from torchrl.record.loggers import Logger

from rcvae_torchrl.io import read_json, write_json
from rcvae_torchrl.loggers import log_scalars

__all__ = ["StageRunner"]


class StageRunner:
    """Runs named stages once per run directory; re-running reuses finished stages.

    Args:
        run_dir: the run directory (markers go to ``run_dir/stages``).
        log: where progress lines go.
        logger: a TorchRL logger the stage summaries' numbers go to (step: the stage's
            position in the run).

    Example:
        >>> import tempfile
        >>> runner = StageRunner(tempfile.mkdtemp(), log=lambda line: None)
        >>> runner.run("count", lambda: {"n": 3})["n"]
        3
    """

    def __init__(
        self,
        run_dir: str | Path,
        log: Callable[[str], None] = print,
        logger: Logger | None = None,
    ) -> None:
        self.run_dir = Path(run_dir)
        self.log = log
        self.logger = logger
        self.summaries: dict[str, Any] = {}

    def marker(self, name: str) -> Path:
        """The marker file of stage ``name``."""
        return self.run_dir / "stages" / f"{name}.json"

    def run(self, name: str, fn: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        """Run stage ``name`` (unless its marker exists); returns its summary."""
        path = self.marker(name)
        if path.is_file():
            self.log(f"[{name}] done earlier: reusing {path.parent.name}/{path.name}")
            summary = read_json(path, f"marker of stage {name!r}")
        else:
            self.log(f"[{name}] running")
            start = time.perf_counter()
            summary = {**fn(), "seconds": round(time.perf_counter() - start, 1)}
            write_json(path, summary)
            self.log(f"[{name}] finished in {summary['seconds']} s")
        log_scalars(self.logger, summary, len(self.summaries), prefix=f"stages/{name}/")
        self.summaries[name] = summary
        return summary

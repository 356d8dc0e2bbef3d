"""Resumable stages of a pipeline: each writes its outputs atomically, then a verified marker.

A study (e.g. a recipe's pipeline) is a sequence of named stages, each a function that writes
its files under the run directory and returns a JSON-able summary. The marker
``stages/<name>.json`` is written only after the function returned, so a stage interrupted
half-way runs again (and its own checkpoints, if any, let it continue), and a finished one is
reused by the next run.

A marker holds the summary, the size and SHA-256 of every output file of the stage (the files
matching the patterns the stage declares) and a digest of its inputs (the run's settings and the
output records of the stages before it). A rerun re-verifies what it reuses:

- an output file deleted, truncated or changed: the file is removed and the stage runs again
  (a line in the log says which file and why); its other files are reused where the stage
  function skips existing ones;
- a marker that cannot be read: the stage runs again;
- inputs that differ from the recorded ones (an earlier stage's outputs came out different when
  it ran again): every output of the stage is removed and it runs again;
- a file the stage function cannot read (:class:`~rcvae_torchrl.io.StoredFileError`): the file
  is removed and the stage runs once more when it is one of the stage's own outputs; otherwise a
  :class:`StageError` names the stage, the file and what to do.

Under ``torch.distributed`` (:mod:`rcvae_torchrl.distributed`) rank 0 verifies, writes the
markers and logs; a ``sharded`` stage runs on every rank (it shares its work out and writes its
files on rank 0), any other stage on rank 0 alone, and every rank waits for a stage to end
before the next one.

With a TorchRL logger, every stage's numbers are logged too (``stages/<name>/<key>``, on rank 0),
whether the stage ran or was reused.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from torchrl.record.loggers import Logger

from rcvae_torchrl import distributed
from rcvae_torchrl.io import StoredFileError, read_json, record_run_config, write_json
from rcvae_torchrl.loggers import log_scalars

__all__ = ["StageError", "StageRunner", "file_record"]

_CHUNK = 1 << 20


class StageError(RuntimeError):
    """A stage cannot run: a file it reads is unusable and is not its own to recompute."""


def file_record(path: str | Path) -> dict[str, Any]:
    """``{"bytes": size, "sha256": hex digest}`` of a file."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
    return {"bytes": Path(path).stat().st_size, "sha256": digest.hexdigest()}


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


class StageRunner:
    """Runs named stages once per run directory; re-running verifies and reuses finished stages.

    Args:
        run_dir: the run directory (markers go to ``run_dir/stages``).
        log: where progress lines go.
        settings: the run's settings (JSON-able). They are recorded in ``run_dir/config_name``
            (:func:`~rcvae_torchrl.io.record_run_config`: other settings than those recorded
            are refused) and are the first input of every stage. A recorded file that cannot be
            read is written again from ``settings`` (the markers' input digests still tell
            which results were made with them).
        config_name: the file the settings are recorded in.
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
        *,
        settings: Mapping[str, Any] | None = None,
        config_name: str = "study_config.json",
        logger: Logger | None = None,
    ) -> None:
        self.run_dir = Path(run_dir)
        self.log = log
        self.logger = logger if distributed.is_main() else None
        self.summaries: dict[str, Any] = {}
        self._inputs = _digest(dict(settings) if settings is not None else None)
        self._unverified = False  # the settings record was missing or unreadable
        if settings is not None and distributed.is_main():
            self._record_settings(dict(settings), self.run_dir / config_name)

    def _record_settings(self, settings: dict[str, Any], path: Path) -> None:
        existed = path.is_file()
        try:
            record_run_config(path, settings)
        except StoredFileError as err:
            self._log(f"[settings] {err}: writing it again from the current settings")
            path.unlink(missing_ok=True)
            record_run_config(path, settings)
            existed = False
        # files of unfinished stages cannot be told from those of other settings any more
        self._unverified = not existed

    def marker(self, name: str) -> Path:
        """The marker file of stage ``name``."""
        return self.run_dir / "stages" / f"{name}.json"

    def run(
        self,
        name: str,
        fn: Callable[[], dict[str, Any]],
        outputs: Sequence[str] = (),
        sharded: bool = False,
    ) -> dict[str, Any]:
        """Run stage ``name`` unless a verified marker says it is done; returns its summary.

        ``outputs``: glob patterns, relative to the run directory, of the files the stage
        writes (e.g. ``("models/*.pt",)``); their sizes and hashes go into the marker.
        ``sharded``: under ``torch.distributed`` the stage runs on every rank (see the module
        docstring).
        """
        saved = self._reusable(name) if distributed.is_main() else None
        if saved is None and self._unverified and distributed.is_main():
            self._remove_unverified(name, outputs)
        if distributed.broadcast(saved is not None):  # rank 0's view: every rank takes one branch
            saved = saved or read_json(self.marker(name), f"marker of stage {name!r}")
        elif distributed.is_main() or sharded:
            saved = self._compute(name, fn, outputs)
            distributed.barrier()
        else:
            distributed.barrier()
        if not distributed.is_main():
            saved = read_json(self.marker(name), f"marker of stage {name!r}")
        summary = {k: v for k, v in saved.items() if k not in ("outputs", "inputs")}
        log_scalars(self.logger, summary, len(self.summaries), prefix=f"stages/{name}/")
        self.summaries[name] = summary
        self._inputs = _digest([self._inputs, name, saved["outputs"]])
        return self.summaries[name]

    # ------------------------------------------------------------------ verification
    def _reusable(self, name: str) -> dict[str, Any] | None:
        """The marker of a finished stage whose outputs and inputs check out, else None (the
        files that failed the check are removed)."""
        path = self.marker(name)
        if not path.is_file():
            return None
        try:
            saved = read_json(path, f"marker of stage {name!r}")
            if not isinstance(saved, dict) or not isinstance(saved.get("outputs"), dict):
                raise StoredFileError(f"marker of stage {name!r} {str(path)!r}: no file records")
        except StoredFileError as err:
            self.log(f"[{name}] {err}: removing it and running the stage again")
            path.unlink()
            return None
        if saved.get("inputs") != self._inputs:
            self.log(
                f"[{name}] its inputs changed (settings or an earlier stage's files): removing "
                f"its {len(saved['outputs'])} files and running the stage again"
            )
            self._remove(saved["outputs"])
            return None
        bad = self._failed(saved["outputs"])
        if bad:
            for rel, why in bad.items():
                self.log(f"[{name}] {rel}: {why}; removing it and running the stage again")
            self._remove(bad)
            return None
        self.log(f"[{name}] done earlier: reusing {path.parent.name}/{path.name} (files verified)")
        return saved

    def _failed(self, records: Mapping[str, Mapping[str, Any]]) -> dict[str, str]:
        """The recorded files that are missing or differ from their record, with the reason."""
        bad = {}
        for rel, record in records.items():
            file = self.run_dir / rel
            if not file.is_file():
                bad[rel] = "the file is missing"
                continue
            actual = file_record(file)
            if actual["bytes"] != record.get("bytes"):
                size, recorded = actual["bytes"], record.get("bytes")
                bad[rel] = f"its size changed ({size} bytes, {recorded} recorded)"
            elif actual["sha256"] != record.get("sha256"):
                bad[rel] = "its content changed since the stage wrote it (SHA-256 differs)"
        return bad

    def _remove_unverified(self, name: str, outputs: Sequence[str]) -> None:
        """Remove the files an unfinished stage left when the run's settings record was
        missing or unreadable: nothing says they were made with these settings, and a stage
        keeps the files it finds (it resumes where it stopped)."""
        files = self._matching(outputs)
        if files:
            self._log(
                f"[{name}] the run's settings record was missing or unreadable: removing the "
                f"{len(files)} files the unfinished stage left (their settings are unknown)"
            )
            for path in files:
                path.unlink(missing_ok=True)

    def _remove(self, rels: Iterable[str]) -> None:
        for rel in rels:
            (self.run_dir / rel).unlink(missing_ok=True)

    # ------------------------------------------------------------------ running
    def _log(self, line: str) -> None:
        if distributed.is_main():
            self.log(line)

    def _compute(
        self, name: str, fn: Callable[[], dict[str, Any]], outputs: Sequence[str]
    ) -> dict[str, Any]:
        self._log(f"[{name}] running")
        start = time.perf_counter()
        summary = self._call(name, fn, outputs)
        saved = {
            **summary,
            "seconds": round(time.perf_counter() - start, 1),
            "inputs": self._inputs,
            "outputs": self._records(outputs) if distributed.is_main() else {},
        }
        if distributed.is_main():
            write_json(self.marker(name), saved)
        self._log(f"[{name}] finished in {saved['seconds']} s")
        return saved

    def _call(
        self, name: str, fn: Callable[[], dict[str, Any]], outputs: Sequence[str]
    ) -> dict[str, Any]:
        """``fn()``; an unreadable file of the stage's own is removed and ``fn`` runs once more."""
        for attempt in range(2):
            try:
                return fn()
            except StoredFileError as err:
                path = err.path
                own = path is not None and self._is_output(path, outputs)
                if not own or attempt == 1:
                    raise StageError(
                        f"stage {name!r} cannot read {str(path) if path else 'a stored file'!r}: "
                        f"{err}. Delete that file (or its stage's marker under "
                        f"{str(self.run_dir / 'stages')!r}) to have it made again, or start "
                        "a new run directory"
                    ) from err
                self._log(f"[{name}] {err}: removing it and running the stage again")
                Path(path).unlink(missing_ok=True)
        raise AssertionError("unreachable")

    def _is_output(self, path: str | Path, outputs: Sequence[str]) -> bool:
        try:
            rel = Path(path).resolve().relative_to(self.run_dir.resolve())
        except ValueError:
            return False
        return any(rel.match(pattern) for pattern in outputs)

    def _matching(self, outputs: Sequence[str]) -> list[Path]:
        """The files under the run directory that match the glob patterns ``outputs``."""
        return sorted({p for pattern in outputs for p in self.run_dir.glob(pattern) if p.is_file()})

    def _records(self, outputs: Sequence[str]) -> dict[str, dict[str, Any]]:
        return {str(p.relative_to(self.run_dir)): file_record(p) for p in self._matching(outputs)}

"""Resumable stages of a pipeline: each writes its outputs atomically, then a verified marker.

A study (e.g. a recipe's pipeline) is a sequence of named stages, each a function that writes
its files under the run directory and returns a JSON-able summary. The marker
``stages/<name>.json`` is written only after the function returned, so a stage interrupted
half-way runs again (and its own checkpoints, if any, let it continue), and a finished one is
reused by the next run.

A marker holds the summary, the size and SHA-256 of every output file of the stage (the files
matching the patterns the stage declares) and a digest of its inputs (the run's settings, or
those the stage declares it reads, and the output records of the stages before it). A rerun
re-verifies what it reuses:

- an output file deleted, truncated or changed: the stage runs again (a line in the log says
  which file and why); a changed file is first moved to ``changed_files/<UTC time>/`` (it may
  hold the user's edits), and the stage's other files are reused where the stage function
  skips existing ones;
- a marker that cannot be read, or whose content changed since the stage wrote it (its
  checksum differs: a number edited by hand would otherwise be reported as the stage's): it is
  set aside as a changed file is, and the stage runs again;
- a marker deleted (to run its stage again): the stage's files changed since its last finished
  run wrote them are set aside before it runs (``stages/<name>.records`` keeps that run's file
  records), the others reused where the stage function skips existing ones;
- inputs that differ from the recorded ones (an earlier stage's outputs came out different when
  it ran again): every output of the stage is removed (those changed since it wrote them are
  moved aside as above) and it runs again;
- a file that matches a stage's patterns but that the stage's records do not name (one the user
  put in ``models/`` after the stage ran, say): when the stage runs again, its journal
  ``stages/<name>.started`` lists the file at its first attempt, and the file is never taken
  for an output, so never recorded, set aside or removed with the stage's files (unless the
  stage writes over it). Where no record of the stage is left (``stages/`` deleted), nothing
  tells its files from others, and all are taken for its own. The journal also counts the
  attempts: a stage that resumed after an interrupted one says so in its log lines and its
  marker (``attempts``; its ``seconds`` are the last attempt's);
- a file the stage function cannot read (:class:`~rcvae_torchrl.io.StoredFileError`): the file
  is removed and the stage runs once more when it is one of the stage's own outputs; otherwise a
  :class:`StageError` names the stage, the file and what to do.

A stage may also declare the code it runs whose change its settings do not show
(``stage_code``: e.g. :func:`code_digest` of the real environment's sources, which every real
outcome and every world model trained on its data depends on). Its marker records that digest;
a finished stage whose marker records another one runs again, as after changed inputs. A
marker written before its stage declared code (none recorded) is reused, with a log line
saying that it was not verified against the code. Code whose every change need not mean a rerun
(``library_code``: e.g. :func:`library_digest`, the library's own sources) is recorded too; a
finished stage made with other such code is reused, with a log line saying so.

Another run directory's finished stages can be reused (``reuse_from``): a stage that is not
done in this run takes the other run's files when that run's marker records the same inputs
(the settings the stage reads, ``stage_settings``, and the same files from every stage before
it) and its files check out. The files are hard links where the file system allows (no copy;
stages only ever replace a file, never write into it, so neither run changes the other's), else
copies. A run whose settings differ only in what later stages read (e.g. how a forecast is
scored) thus reuses the other's data and trained models. The marker of a reused stage records
the seconds this run spent on it (placing the files) and, under ``reused_from``, the other run
and the seconds the stage took where it ran.

Under ``torch.distributed`` (:mod:`rcvae_torchrl.distributed`) rank 0 verifies, writes the
markers and logs; a ``sharded`` stage runs on every rank (it shares its work out and writes its
files on rank 0), any other stage on rank 0 alone (inside
:func:`~rcvae_torchrl.distributed.alone`: a library call in it that would share its work over
the ranks does it all there), and every rank waits for a stage to end before the next one.

With a TorchRL logger, every stage's numbers are logged too (``stages/<name>/<key>``, on rank 0),
whether the stage ran or was reused.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import json
import os
import shutil
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from torchrl.record.loggers import Logger

from rcvae_torchrl import distributed
from rcvae_torchrl._checks import check_bool
from rcvae_torchrl.io import (  # settings as they read back from JSON, as recorded
    StoredFileError,
    _as_json,
    _differences,
    _read_back,
    _same,
    atomic_write,
    check_run_config,
    read_json,
    record_run_config,
    write_json,
)
from rcvae_torchrl.loggers import log_scalars

__all__ = [
    "MARKERS",
    "SET_ASIDE",
    "StageError",
    "StageRunner",
    "check_run_directory",
    "code_digest",
    "library_digest",
    "file_record",
]

_CHUNK = 1 << 20
_MARKER_ONLY = ("outputs", "inputs", "code", "library_code")  # the marker's, not the summary's
#: what a marker adds to a stage's summary: a summary may not hold these keys
_RESERVED = ("outputs", "inputs", "code", "library_code", "seconds", "attempts", "reused_from")


#: The folder of a run directory that holds the stages' markers.
MARKERS = "stages"
#: The folder of a run directory where outputs changed since their stage wrote them (damaged,
#: or edited by hand) are moved, under the UTC time of the run that found them, before the
#: stage makes them again: nothing a user changed is deleted.
SET_ASIDE = "changed_files"

_MISSING = "the file is missing"
#: the suffix of a stage's file records beside its marker (not ``.json``: no marker)
_RECORDS = ".records"
#: the suffix of an unfinished stage's journal beside its marker: its attempts so far and the
#: files that matched its patterns before its first attempt (not the stage's: never recorded or
#: removed as its outputs)
_STARTED = ".started"


def check_run_directory(
    run_dir: str | Path,
    settings: Mapping[str, Any],
    *,
    config_name: str = "study_config.json",
    made_before: Iterable[str] = (),
) -> None:
    """Refuse, before a run creates anything in ``run_dir``, a directory it must not write in:
    one whose settings record (``config_name``) holds other settings
    (:func:`~rcvae_torchrl.io.check_run_config`), or one that holds files but neither a
    settings record nor stage markers (:data:`MARKERS`): a folder of the user's own (or files
    some other program left), whose files a stage would take for its unfinished outputs and
    remove or overwrite. ``made_before``: names of what a run itself creates in the directory
    before its runner records the settings (its log file, its logger's folder), which do not
    count. A missing or empty directory, and a run's directory whose record alone was lost (its
    markers name its files), pass."""
    run_dir = Path(run_dir)
    check_run_config(run_dir / config_name, settings)
    if not run_dir.is_dir() or (run_dir / config_name).exists() or (run_dir / MARKERS).is_dir():
        return
    allowed = set(made_before)
    foreign = sorted(p.name for p in run_dir.iterdir() if p.name not in allowed)
    if foreign:
        shown = ", ".join(repr(name) for name in foreign[:5])
        more = f" and {len(foreign) - 5} more" if len(foreign) > 5 else ""
        raise ValueError(
            f"run_dir: expected a new or empty directory, or one a run made, got "
            f"{str(run_dir)!r}, which holds {shown}{more} but no run's settings record "
            f"({config_name!r}) and no stage markers ({MARKERS + '/'!r}): a run would take "
            "those files for its own unfinished outputs and remove or overwrite them; give "
            "another run_dir"
        )


class StageError(RuntimeError):
    """A stage cannot run: a file it reads is unusable and is not its own to recompute."""


def file_record(path: str | Path) -> dict[str, Any]:
    """``{"bytes": size, "sha256": hex digest}`` of a file."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            digest.update(chunk)
    return {"bytes": Path(path).stat().st_size, "sha256": digest.hexdigest()}


def code_digest(paths: Iterable[str | Path], packages: Iterable[str] = ()) -> str:
    """SHA-256 hex digest of code a stage runs: the files at ``paths`` (a directory: every
    file under it, by relative name, compiled caches left out) and the installed versions of
    ``packages`` (distribution names, e.g. ``"mujoco"``; one not installed counts as such).
    For :class:`StageRunner`'s ``stage_code``.

    Example:
        >>> import pathlib, tempfile
        >>> folder = pathlib.Path(tempfile.mkdtemp())
        >>> _ = (folder / "env.py").write_text("GRAVITY = 9.81")
        >>> before = code_digest([folder])
        >>> _ = (folder / "env.py").write_text("GRAVITY = 9.80")
        >>> code_digest([folder]) == before
        False
    """
    h = hashlib.sha256()
    for path in map(Path, paths):
        if not path.exists():
            raise FileNotFoundError(f"paths: no file or directory {str(path)!r}")
        files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
        for file in files:
            if "__pycache__" in file.parts or file.suffix in (".pyc", ".pyo"):
                continue
            name = file.name if file == path else file.relative_to(path).as_posix()
            h.update(f"{name}\0{file.stat().st_size}\0".encode())
            h.update(file.read_bytes())
    for package in packages:
        try:
            version = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            version = "not installed"
        h.update(f"{package}=={version}\0".encode())
    return h.hexdigest()


def library_digest() -> str:
    """:func:`code_digest` of this library's own sources (every file of the installed
    ``rcvae_torchrl`` package): for :class:`StageRunner`'s ``library_code``."""
    return code_digest([Path(__file__).parent])


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
        stage_settings: per stage name, the settings it reads: top-level keys of
            ``settings``, or ``"section.key"`` for one key of a section (a mapping). A stage's
            inputs are then those settings and the files of the stages before it, so that
            changing a setting only later stages read keeps the earlier stages' results
            reusable from another run directory (``reuse_from``). A stage not named reads all
            settings. None (the default): every stage reads all settings. A setting a stage
            reads but does not declare would let it be reused with a stale result: declare
            generously.
        reuse_from: another run directory whose finished stages this run takes (checked,
            then hard-linked or copied) where their inputs are the same as this run's.
        stage_code: per stage name, a digest of the code it runs whose change its settings
            do not show (:func:`code_digest`, e.g. of the real environment's sources),
            recorded in its marker: a finished stage (here or in ``reuse_from``) made with
            another is not reused. A stage not named declares none.
        library_code: a digest of code whose change is worth a word but not a rerun (e.g.
            :func:`code_digest` of the library's own sources, which a docstring edit changes
            as much as a fix): recorded in every marker; a finished stage made with another
            is reused, with a log line naming the stage and how to run it again.

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
        stage_settings: Mapping[str, Sequence[str]] | None = None,
        reuse_from: str | Path | None = None,
        stage_code: Mapping[str, str] | None = None,
        library_code: str | None = None,
    ) -> None:
        if not isinstance(run_dir, (str, os.PathLike)):
            raise TypeError(f"run_dir: expected a str or a path, got {type(run_dir).__name__}")
        if not callable(log):
            raise TypeError(f"log: expected a callable taking a line, got {log!r}")
        if settings is not None and not isinstance(settings, Mapping):
            raise TypeError(
                f"settings: expected a mapping of the run's settings or None, got "
                f"{type(settings).__name__}"
            )
        self.run_dir = Path(run_dir)
        if stage_code is not None and not (
            isinstance(stage_code, Mapping)
            and all(isinstance(k, str) and isinstance(v, str) for k, v in stage_code.items())
        ):
            raise TypeError(
                "stage_code: expected a mapping of stage names to code digests (str), got "
                f"{stage_code!r}"
            )
        self._stage_code = dict(stage_code or {})
        if library_code is not None and not isinstance(library_code, str):
            raise TypeError(
                f"library_code: expected a code digest (str) or None, got {library_code!r}"
            )
        self._library_code = library_code
        self.log = log
        self.logger = logger if distributed.is_main() else None
        self.summaries: dict[str, Any] = {}
        self._settings = _as_json(dict(settings)) if settings is not None else None
        # the digest of every setting and the files of every stage so far: the inputs of a
        # stage that reads all settings (and what markers recorded before stage_settings)
        self._inputs = _digest(dict(settings) if settings is not None else None)
        self._stage_settings = _checked_stage_settings(stage_settings, self._settings)
        self._before: list[list[Any]] = []  # [name, output records] of the stages so far
        self._reuse_from = _checked_reuse_from(reuse_from, self.run_dir)
        self._config_name = config_name
        self._recorded_there: Any = None  # the reuse_from run's settings, once read
        self._unverified = False  # the settings record was missing or unreadable
        self._aside: Path | None = None  # where this run sets changed outputs aside
        if settings is not None and distributed.is_main():
            self._record_settings(dict(settings), self.run_dir / config_name)

    def _record_settings(self, settings: dict[str, Any], path: Path) -> None:
        existed = path.is_file()
        try:
            record_run_config(path, settings)
        except StoredFileError as err:
            aside = self._set_aside(self._rel(path))
            self._log(
                f"[settings] {err}: set aside as {aside}; writing it again from the current "
                "settings (every stage whose recorded inputs they change runs again)"
            )
            record_run_config(path, settings)
            existed = False
        # files of unfinished stages cannot be told from those of other settings any more
        self._unverified = not existed

    def marker(self, name: str) -> Path:
        """The marker file of stage ``name``."""
        return self.run_dir / MARKERS / f"{name}.json"

    def _records_path(self, name: str) -> Path:
        """Beside the marker, the file records of the stage's last finished run: they outlive
        a marker deleted to run the stage again (:meth:`_set_aside_edited`)."""
        return self.run_dir / MARKERS / f"{name}{_RECORDS}"

    def _journal_path(self, name: str) -> Path:
        """Beside the marker, the journal of stage ``name`` while it is unfinished
        (:meth:`_begin`)."""
        return self.run_dir / MARKERS / f"{name}{_STARTED}"

    def _journal(self, name: str) -> dict[str, Any] | None:
        """The journal of unfinished stage ``name``, None when there is none or it cannot be
        read (then the stage's next attempt starts a new one)."""
        path = self._journal_path(name)
        if not path.is_file():
            return None
        try:
            journal = read_json(path, f"journal of stage {name!r}", checksum=True)
        except StoredFileError:
            return None
        ok = isinstance(journal, dict) and isinstance(journal.get("foreign"), dict)
        return journal if ok and isinstance(journal.get("attempts"), int) else None

    def _foreign(self, name: str) -> dict[str, Any]:
        """The files of other origin that matched stage ``name``'s patterns before its first
        attempt (its journal's), with their records."""
        return (self._journal(name) or {}).get("foreign", {})

    def _last_outputs(self, name: str) -> set[str] | None:
        """The files stage ``name``'s marker or its last records name as its outputs (before a
        rerun removes or sets aside what failed their check): the stage's own, which it may
        reuse. ``None`` when neither can be read: no record tells its files from others."""
        own: set[str] | None = None
        for path, what in ((self.marker(name), "marker"), (self._records_path(name), "records")):
            if path.is_file():
                try:
                    saved = read_json(path, f"{what} of stage {name!r}", checksum=True)
                except StoredFileError:
                    continue
                if isinstance(saved, dict):
                    own = own or set()
                    own.update(saved.get("outputs", {}) if what == "marker" else saved)
        return own

    def _begin(self, name: str, outputs: Sequence[str], own: set[str] | None) -> dict[str, Any]:
        """Start an attempt at stage ``name``: its journal, kept until the marker is written,
        counts the attempts and records the files that match the stage's patterns before the
        first one and are not its own (``own``, its last records): a file the user put beside
        the stage's (in ``models/``, say) is never taken for an output, recorded, or removed
        with them. Where no record of the stage is left (``own`` None: a stage that never
        finished, or ``stages/`` deleted), nothing tells its files from others, and all are
        taken for its own."""
        journal = self._journal(name)
        if journal is None:
            foreign = {
                self._rel(p): file_record(p)
                for p in self._matching(outputs)
                if own is not None and self._rel(p) not in own
            }
            journal = {"attempts": 0, "foreign": foreign}
        journal = {**journal, "attempts": journal["attempts"] + 1}
        write_json(self._journal_path(name), journal, checksum=True)
        return journal

    def _write_marker(self, name: str, saved: Mapping[str, Any]) -> None:
        write_json(self._records_path(name), saved["outputs"], checksum=True)
        write_json(self.marker(name), saved, checksum=True)

    def _set_aside_edited(self, name: str) -> None:
        """Before stage ``name`` runs without a marker (one deleted to run it again, or one
        set aside): its files changed since its last finished run wrote them (a note added to
        ``report.md``) are set aside, not overwritten. The records are then removed: the
        files the stage writes from here on are its own, which a run interrupted now resumes
        from."""
        path = self._records_path(name)
        if self.marker(name).exists() or not path.is_file():
            return
        try:
            records = read_json(path, f"file records of stage {name!r}", checksum=True)
        except StoredFileError:
            records = {}
        if isinstance(records, dict):
            for rel, why in self._failed(records).items():
                if why != _MISSING:
                    self.log(
                        f"[{name}] {rel}: changed since the stage last wrote it ({why}); set "
                        f"aside as {self._set_aside(rel)}"
                    )
        path.unlink()

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
        outputs = _checked_stage(name, fn, outputs, sharded)
        if name in self.summaries:
            raise ValueError(
                f"name: stage {name!r} already ran in this runner (its marker would be written "
                "over, and the stages after it read its first files); give each stage its own "
                "name"
            )
        saved = self._reusable(name) if distributed.is_main() else None
        own = self._last_outputs(name) if saved is None and distributed.is_main() else None
        if saved is None and distributed.is_main():
            self._set_aside_edited(name)
        if saved is None and self._unverified and distributed.is_main():
            self._remove_unverified(name, outputs, own)
        if saved is None and self._reuse_from is not None and distributed.is_main():
            saved = self._borrowed(name, outputs)
        if distributed.broadcast(saved is not None):  # rank 0's view: every rank takes one branch
            saved = saved or _read_marker(self.marker(name), name)
        elif distributed.is_main() or sharded:
            # a stage on rank 0 alone acts as one process: a sharing call in it must not wait
            with contextlib.nullcontext() if sharded else distributed.alone():
                saved = self._compute(name, fn, outputs, own)
            distributed.barrier()
        else:
            distributed.barrier()
        if not distributed.is_main():
            saved = _read_marker(self.marker(name), name)
        summary = {k: v for k, v in saved.items() if k not in _MARKER_ONLY}
        log_scalars(self.logger, summary, len(self.summaries), prefix=f"stages/{name}/")
        self.summaries[name] = summary
        self._inputs = _digest([self._inputs, name, saved["outputs"]])
        self._before.append([name, saved["outputs"]])
        return self.summaries[name]

    def _stage_inputs(self, name: str) -> str:
        """The digest of stage ``name``'s inputs if it ran next: the settings it reads
        (``stage_settings``) and the output records of the stages run so far."""
        if self._stage_settings is None:
            return self._inputs
        keys = self._stage_settings.get(name)
        read = self._settings if keys is None else {k: _setting(self._settings, k) for k in keys}
        return _digest({"settings": read, "stages": self._before})

    # ------------------------------------------------------------------ verification
    def _reusable(self, name: str) -> dict[str, Any] | None:
        """The marker of a finished stage whose outputs and inputs check out, else None (the
        files that failed the check are removed)."""
        path = self.marker(name)
        if not path.is_file():
            return None
        try:
            saved = _read_marker(path, name)
        except StoredFileError as err:
            aside = self._set_aside(self._rel(path))
            self.log(f"[{name}] {err}: set aside as {aside}; running the stage again")
            return None
        inputs = self._stage_inputs(name)
        # a marker of all settings (written before the stage declared what it reads) still
        # holds: every setting is the same
        if saved.get("inputs") not in (inputs, self._inputs):
            return self._discard(
                name, saved, "its inputs changed (settings or an earlier stage's files)"
            )
        code = self._code_check(name, saved)
        if code is not None:
            return self._discard(name, saved, code)
        bad = self._failed(saved["outputs"])
        if bad:
            for rel, why in bad.items():
                kept = "" if why == _MISSING else f"; set aside as {self._set_aside(rel)}"
                self.log(f"[{name}] {rel}: {why}{kept}; running the stage again")
            self._remove(bad)
            return None
        if saved["inputs"] != inputs:  # recorded as the stage's own inputs from now on
            saved["inputs"] = inputs
            self._write_marker(name, saved)
        self.log(f"[{name}] done earlier: reusing {path.parent.name}/{path.name} (files verified)")
        return saved

    def _discard(self, name: str, saved: Mapping[str, Any], why: str) -> None:
        """Remove the files of finished stage ``name`` (those changed since it wrote them are
        set aside), which must run again because of ``why``."""
        self.log(
            f"[{name}] {why}: removing its {len(saved['outputs'])} files and running the stage "
            "again"
        )
        changed = self._failed(saved["outputs"])
        for rel, why_changed in changed.items():
            if why_changed != _MISSING:  # changed since the stage wrote it: perhaps by hand
                self.log(f"[{name}] {rel}: {why_changed}; set aside as {self._set_aside(rel)}")
        self._remove(saved["outputs"])

    def _code_check(self, name: str, saved: Mapping[str, Any], where: str = "") -> str | None:
        """Why the marker ``saved`` of stage ``name`` does not hold for this run's declared
        code (``stage_code``), else None; a marker that records no code holds, with a log line
        (``where``: the run it is from, for that line)."""
        library = saved.get("library_code")
        if self._library_code is not None and library not in (None, self._library_code):
            self.log(
                f"[{name}] made{where} by other library code (digest {library[:12]} recorded, "
                f"{self._library_code[:12]} now): reused as it is (a new run directory makes "
                "every stage with this code)"
            )
        code = self._stage_code.get(name)
        if code is None:
            return None
        recorded = saved.get("code")
        if recorded is None:
            self.log(
                f"[{name}] its marker{where} records no code digest (written before the stage "
                "declared the code it runs): not verified against the current code"
            )
            return None
        if recorded != code:
            return f"its code changed (digest {recorded[:12]} recorded, {code[:12]} now)"
        return None

    def _borrowed(self, name: str, outputs: Sequence[str]) -> dict[str, Any] | None:
        """The finished stage ``name`` of the ``reuse_from`` run, its files placed in this run
        and its marker written here, when its inputs are this stage's and its files check out;
        else None (a log line says why, when that run finished the stage)."""
        other = self._reuse_from
        path = other / MARKERS / f"{name}.json"
        if not path.is_file():
            return None
        try:
            saved = _read_marker(path, name)
        except StoredFileError as err:
            self.log(f"[{name}] not reused from {str(other)!r}: {err}")
            return None
        inputs = self._stage_inputs(name)
        if saved.get("inputs") != inputs and not self._same_inputs_recorded(name, saved):
            self.log(f"[{name}] not reused from {str(other)!r}: {self._why_different(name)}")
            return None
        code = self._code_check(name, saved, f" in {str(other)!r}")
        if code is not None:
            self.log(f"[{name}] not reused from {str(other)!r}: {code}")
            return None
        bad = self._failed(saved["outputs"], other)
        if bad:
            rel, why = next(iter(bad.items()))
            self.log(f"[{name}] not reused from {str(other)!r}: {rel}: {why}")
            return None
        foreign = self._foreign(name)
        own = [p for p in self._matching(outputs) if self._rel(p) not in foreign]
        if own:
            self.log(
                f"[{name}] not reused from {str(other)!r}: this run has {len(own)} files of "
                "the stage's own (an unfinished run of it, which it resumes)"
            )
            return None
        start = time.perf_counter()
        linked = sum(_place(other / rel, self.run_dir / rel) for rel in saved["outputs"])
        # this run's seconds are the placing's; the stage's own, where it ran, are kept apart
        ran = saved.get("reused_from", {}).get("seconds", saved.get("seconds"))
        saved = {
            **saved,
            "inputs": inputs,
            "seconds": round(time.perf_counter() - start, 1),
            "reused_from": {"run_dir": str(other), "seconds": ran},
        }
        self._write_marker(name, saved)
        count = len(saved["outputs"])
        self.log(
            f"[{name}] reusing the finished stage of {str(other)!r} (files verified; {linked} of "
            f"{count} hard-linked, {count - linked} copied)"
        )
        return saved

    def _why_different(self, name: str) -> str:
        """Which settings stage ``name`` reads differ in the ``reuse_from`` run (by the
        settings it recorded), else that an earlier stage's files differ."""
        recorded = self._settings_there()
        if recorded is None:
            return "its inputs differ (its settings record cannot be read to say which)"
        keys = (self._stage_settings or {}).get(name) or sorted(recorded.keys() | self._settings)
        changed = []
        for key in keys:
            there, here = (_setting_or_none(s, key) for s in (recorded, self._settings))
            if not _same(there, here):
                changed += _differences(key, there, here)
        if not changed:
            return "its inputs differ (an earlier stage's files)"
        shown = "; ".join(f"{k}: {a!r} there, {b!r} here" for k, a, b in changed[:5])
        more = f" and {len(changed) - 5} more" if len(changed) > 5 else ""
        return f"settings it reads differ ({shown}{more})"

    def _same_inputs_recorded(self, name: str, saved: Mapping[str, Any]) -> bool:
        """Whether the other run's marker of stage ``name``, written with the digest of all
        its settings (before its stages declared what they read), was made from the same
        files of the earlier stages as this run's and from the same settings the stage reads:
        its recorded inputs must be the digest of the settings that run recorded and of this
        run's earlier files."""
        recorded = self._settings_there()
        if recorded is None:
            return False
        chain = _digest(recorded)
        for before, outputs in self._before:
            chain = _digest([chain, before, outputs])
        if saved.get("inputs") != chain:
            return False
        keys = (self._stage_settings or {}).get(name)
        if keys is None:
            return _same(recorded, self._settings)
        try:
            return all(_same(_setting(recorded, k), _setting(self._settings, k)) for k in keys)
        except (KeyError, TypeError):
            return False

    def _settings_there(self) -> dict[str, Any] | None:
        """The settings the ``reuse_from`` run recorded (read once), None if unreadable."""
        if self._recorded_there is None:
            try:
                recorded = read_json(self._reuse_from / self._config_name, "run config")
            except StoredFileError:
                recorded = None
            self._recorded_there = recorded if isinstance(recorded, dict) else False
        return None if self._recorded_there is False else self._recorded_there

    def _failed(
        self, records: Mapping[str, Mapping[str, Any]], root: Path | None = None
    ) -> dict[str, str]:
        """The recorded files (under ``root``, default the run directory) that are missing or
        differ from their record, with the reason."""
        bad = {}
        for rel, record in records.items():
            file = (root or self.run_dir) / rel
            if not file.is_file():
                bad[rel] = _MISSING
                continue
            actual = file_record(file)
            if actual["bytes"] != record.get("bytes"):
                size, recorded = actual["bytes"], record.get("bytes")
                bad[rel] = f"its size changed ({size} bytes, {recorded} recorded)"
            elif actual["sha256"] != record.get("sha256"):
                bad[rel] = "its content changed since the stage wrote it (SHA-256 differs)"
        return bad

    def _remove_unverified(self, name: str, outputs: Sequence[str], own: set[str] | None) -> None:
        """Remove the files an unfinished stage left when the run's settings record was
        missing or unreadable: nothing says they were made with these settings, and a stage
        keeps the files it finds (it resumes where it stopped). The stage's files are those its
        records name (``own``) or, once an attempt began, all but those its journal found
        before it; a file neither names (put there by hand) is set aside, not removed."""
        journal = self._journal(name)
        foreign = (journal or {}).get("foreign", {})
        left, unknown = [], []
        for path in self._matching(outputs):
            rel = self._rel(path)
            if rel not in foreign:
                (left if journal is not None or rel in (own or ()) else unknown).append(rel)
        if left:
            self._log(
                f"[{name}] the run's settings record was missing or unreadable: removing the "
                f"{len(left)} files the unfinished stage left (their settings are unknown)"
            )
            self._remove(left)
        for rel in unknown:
            self._log(
                f"[{name}] {rel}: no record says the stage wrote it, and the run's settings "
                f"record was missing or unreadable; set aside as {self._set_aside(rel)}"
            )

    def _remove(self, rels: Iterable[str]) -> None:
        for rel in rels:
            (self.run_dir / rel).unlink(missing_ok=True)

    def _set_aside(self, rel: str) -> str:
        """Move the output ``rel`` (changed since its stage wrote it: damaged, or edited by
        hand) under :data:`SET_ASIDE` instead of deleting it; its new path, relative to the
        run directory."""
        if self._aside is None:  # one folder per run of the runner
            stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime())
            self._aside = Path(SET_ASIDE) / stamp
            suffix = 1
            while (self.run_dir / self._aside).exists():
                suffix += 1
                self._aside = Path(SET_ASIDE) / f"{stamp}_{suffix}"
        target = self.run_dir / self._aside / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(self.run_dir / rel, target)
        return str(self._aside / rel)

    # ------------------------------------------------------------------ running
    def _log(self, line: str) -> None:
        if distributed.is_main():
            self.log(line)

    def _compute(
        self,
        name: str,
        fn: Callable[[], dict[str, Any]],
        outputs: Sequence[str],
        own: set[str] | None,
    ) -> dict[str, Any]:
        """Run stage ``name`` (an attempt: :meth:`_begin`) and write its marker. The marker's
        ``seconds`` are this attempt's; a stage that resumed after an interrupted attempt
        (whose time no file recorded) says so under ``attempts``."""
        journal = self._begin(name, outputs, own) if distributed.is_main() else None
        attempts = journal["attempts"] if journal is not None else 1
        again = f" (attempt {attempts}: resuming from what the earlier ones wrote)"
        self._log(f"[{name}] running" + (again if attempts > 1 else ""))
        start = time.perf_counter()
        summary = self._call(name, fn, outputs)
        saved = {
            **summary,
            "seconds": round(time.perf_counter() - start, 1),
            **({"attempts": attempts} if attempts > 1 else {}),
            "inputs": self._stage_inputs(name),
            **({"code": self._stage_code[name]} if name in self._stage_code else {}),
            **({"library_code": self._library_code} if self._library_code is not None else {}),
            "outputs": self._records(outputs, journal["foreign"]) if journal is not None else {},
        }
        if distributed.is_main():
            self._write_marker(name, saved)
            self._journal_path(name).unlink(missing_ok=True)
        earlier = f" (attempt {attempts}; the earlier attempts' time is not counted)"
        self._log(f"[{name}] finished in {saved['seconds']} s" + (earlier if attempts > 1 else ""))
        return saved

    def _call(
        self, name: str, fn: Callable[[], dict[str, Any]], outputs: Sequence[str]
    ) -> dict[str, Any]:
        """``fn()``; an unreadable file of the stage's own is removed and ``fn`` runs once more."""
        for attempt in range(2):
            try:
                return _checked_summary(name, fn())
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

    def _rel(self, path: Path) -> str:
        """``path`` relative to the run directory, as records name it."""
        return str(path.relative_to(self.run_dir))

    def _matching(self, outputs: Sequence[str]) -> list[Path]:
        """The files under the run directory that match the glob patterns ``outputs``."""
        return sorted({p for pattern in outputs for p in self.run_dir.glob(pattern) if p.is_file()})

    def _records(
        self, outputs: Sequence[str], foreign: Mapping[str, Any] | None = None
    ) -> dict[str, dict[str, Any]]:
        """The records of the files matching ``outputs``, less the ``foreign`` ones the stage
        left as they were (one it wrote over is its own)."""
        records = {}
        for path in self._matching(outputs):
            rel, record = self._rel(path), file_record(path)
            if (foreign or {}).get(rel) != record:
                records[rel] = record
        return records


def _checked_stage(name: object, fn: object, outputs: object, sharded: object) -> tuple[str, ...]:
    """Refuse a stage a runner cannot run or record: ``name`` must be a marker's file name,
    ``fn`` callable, ``outputs`` a sequence of glob patterns inside the run directory (a bare
    string would be read letter by letter, and a pattern leaving the run directory would have
    the runner remove files elsewhere); the patterns as a tuple."""
    if not isinstance(name, str) or name in ("", ".", "..") or any(c in name for c in "/\\"):
        raise ValueError(
            f"name: expected a stage name usable as a file name (no path separators), got {name!r}"
        )
    if not callable(fn):
        raise TypeError(f"fn: expected a callable that runs stage {name!r}, got {fn!r}")
    check_bool("sharded", sharded)
    if isinstance(outputs, (str, bytes)) or not isinstance(outputs, Sequence):
        raise TypeError(
            f"outputs: expected a sequence of glob patterns (e.g. ('models/*.pt',)), got "
            f"{outputs!r}"
        )
    for pattern in outputs:
        if not isinstance(pattern, str) or not pattern:
            raise TypeError(f"outputs: expected glob patterns (str), got {pattern!r}")
        if Path(pattern).is_absolute() or ".." in Path(pattern).parts:
            raise ValueError(
                f"outputs: expected patterns relative to the run directory and inside it, got "
                f"{pattern!r} (the runner removes and sets aside the files its patterns match)"
            )
    return tuple(outputs)


def _checked_summary(name: str, summary: object) -> dict[str, Any]:
    """Stage ``name``'s summary as its marker will read back (so that a stage reused gives the
    same summary as one run): a mapping of JSON values, without the marker's own keys."""
    if not isinstance(summary, Mapping):
        raise TypeError(
            f"stage {name!r}: expected its function to return a dict summary (JSON values), "
            f"got {type(summary).__name__}"
        )
    reserved = sorted(set(map(str, summary)) & set(_RESERVED))
    if reserved:
        raise ValueError(
            f"stage {name!r}: its summary holds {reserved}, which the marker records itself "
            f"(reserved: {list(_RESERVED)}); rename them"
        )
    return _read_back(dict(summary), f"the summary of stage {name!r}")


def _read_marker(path: Path, name: str) -> dict[str, Any]:
    """The marker of stage ``name`` at ``path``; :class:`StoredFileError` when it cannot be
    read or records no files."""
    saved = read_json(path, f"marker of stage {name!r}", checksum=True)
    if not isinstance(saved, dict) or not isinstance(saved.get("outputs"), dict):
        raise StoredFileError(f"marker of stage {name!r} {str(path)!r}: no file records")
    return saved


def _setting(settings: Mapping[str, Any], key: str) -> Any:
    """``settings[key]``, or ``settings[section][name]`` for ``key = "section.name"``."""
    section, _, name = key.partition(".")
    value = settings[section]
    return value[name] if name else value


def _setting_or_none(settings: Mapping[str, Any], key: str) -> Any:
    try:
        return _setting(settings, key)
    except (KeyError, TypeError):
        return None


def _checked_stage_settings(
    stage_settings: Mapping[str, Sequence[str]] | None, settings: Mapping[str, Any] | None
) -> dict[str, list[str]] | None:
    """``stage_settings`` as lists, each key checked to name a setting."""
    if stage_settings is None:
        return None
    if settings is None:
        raise ValueError("stage_settings: expected the run's settings beside it, got settings=None")
    checked = {}
    for stage, keys in stage_settings.items():
        if isinstance(keys, str):
            raise TypeError(
                f"stage_settings[{stage!r}]: expected a sequence of setting names, got the "
                f"string {keys!r}"
            )
        for key in keys:
            try:
                _setting(settings, key)
            except (KeyError, TypeError):
                raise ValueError(
                    f"stage_settings[{stage!r}]: {key!r} is not a setting; expected a key of "
                    f"{sorted(settings)} or 'section.key' of a section's mapping"
                ) from None
        checked[stage] = list(keys)
    return checked


def _checked_reuse_from(reuse_from: str | Path | None, run_dir: Path) -> Path | None:
    if reuse_from is None:
        return None
    other = Path(reuse_from).expanduser()
    if not other.is_dir():
        raise ValueError(f"reuse_from: expected a run directory, got {str(other)!r} (not one)")
    if other.resolve() == run_dir.resolve():
        raise ValueError(
            f"reuse_from: expected another run directory than run_dir, got {str(other)!r} for both"
        )
    return other


def _place(source: Path, target: Path) -> bool:
    """Put ``source`` at ``target`` atomically: a hard link (True) or, where the file system
    cannot link them, a copy (False)."""
    target.parent.mkdir(parents=True, exist_ok=True)
    link = target.with_name(f".{target.name}.{os.getpid()}.link")
    try:
        link.unlink(missing_ok=True)
        os.link(source, link)
    except OSError:
        with open(source, "rb") as src:
            atomic_write(target, lambda f: shutil.copyfileobj(src, f))
        return False
    os.replace(link, target)
    return True

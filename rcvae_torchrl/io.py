"""Files the library writes and reads: atomic writes, JSON, torch payloads, run configs.

- :func:`atomic_write`: a crash (even ``kill -9``) leaves either the old file or the new one,
  never half of one; the new file gets the permissions the user's umask gives a new file.
- :func:`write_json` / :func:`read_json`, :func:`save_torch` / :func:`load_torch`: the one way
  to store and read back small records and tensors; a missing, truncated or corrupt file is a
  :class:`StoredFileError` that names the file and what it should hold. A dict saved by
  :func:`save_torch` carries the SHA-256 of its content (``fingerprint.digest``), checked on
  load: a file damaged on disk or in a copy is refused, not read as other numbers.
- :func:`record_run_config`: the settings a run directory was made with, so that a rerun with
  other settings cannot silently reuse its results.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import io
import json
import math
import os
import re
import socket
import tempfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch
from tensordict import TensorDictBase

from rcvae_torchrl import fingerprint

__all__ = [
    "StoredFileError",
    "atomic_write",
    "check_run_config",
    "load_torch",
    "read_json",
    "record_run_config",
    "save_torch",
    "write_json",
]


class StoredFileError(ValueError):
    """A stored file cannot be used: missing, truncated, corrupt or of another kind.

    ``path``: the file (None when not known), so that a caller can remove or remake it.
    """

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        super().__init__(message)
        self.path = None if path is None else Path(path)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | Path, write: Callable[[IO[bytes]], None]) -> Path:
    """Call ``write(f)`` on a temp file beside ``path``, fsync it, then rename it over ``path``.

    The file gets mode ``0o666 & ~umask`` (what ``open`` would give it), not the private mode
    of a temporary file. A temp file is named by this machine and process
    (``.<name>.<host>.<pid namespace>-<pid>.<random>.tmp``); one left beside ``path`` by a
    process of this machine and pid namespace that no longer runs (killed while writing) is
    removed by the next write of ``path``, where it can be. Other machines' and containers'
    temp files are left alone (their writers may still run)."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a file path (a str or a Path), got {type(path).__name__}")
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(
            f"{str(path)!r} is a directory; expected the path of a file (e.g. "
            f"{str(path / 'name')!r})"
        )
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):  # a folder of the path is a file
        blocking = next((p for p in path.parents if p.exists() and not p.is_dir()), None)
        if blocking is None:
            raise
        raise NotADirectoryError(
            f"path: expected a file path whose folders are folders, got {str(path)!r}, where "
            f"{str(blocking)!r} is a file"
        ) from None
    _remove_dead_writers_temps(path)
    fd, tmp = tempfile.mkstemp(
        prefix=f"{_temp_start(path)}{os.getpid()}.", suffix=".tmp", dir=path.parent
    )
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return path


def _temp_start(path: Path) -> str:
    """How the temp files of ``path`` written on this machine begin (the pid follows): its
    name (its first 100 characters: a long name's temp must still fit the file system's 255),
    the host and the pid namespace (a container's pids are not the host's)."""
    return f".{path.name[:100]}.{socket.gethostname()[:40]}.{_PID_NAMESPACE}-"


def _pid_namespace() -> str:
    """This process's pid namespace, as Linux names it (``pid:[4026531836]``: its inode); ''
    where it cannot be read."""
    try:
        return re.sub(r"\D", "", os.readlink("/proc/self/ns/pid"))
    except OSError:
        return ""


_PID_NAMESPACE = _pid_namespace()


def _remove_dead_writers_temps(path: Path) -> None:
    """Remove the temp files of ``path`` that processes of this machine left when they were
    killed while writing it (their process no longer runs)."""
    start = _temp_start(path)
    for temp in path.parent.glob(f"{glob.escape(start)}*.tmp"):
        found = re.fullmatch(r"(\d+)\.[^.]*\.tmp", temp.name[len(start) :])
        if found is None or _running(int(found.group(1))):
            continue
        # best effort: another writer may have removed it first, or it is another user's in
        # a shared folder; the write goes ahead either way
        with contextlib.suppress(OSError):
            temp.unlink()


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


#: How :func:`write_json` writes the floats JSON has no number for (as protobuf's JSON does),
#: and :func:`read_json` reads them back.
_NON_FINITE = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}


def _strict(obj: Any, where: str = "obj") -> Any:
    """``obj`` with every non-finite float as its string (``"NaN"``, ``"Infinity"``,
    ``"-Infinity"``): the bare ``NaN`` Python writes is not JSON, and strict parsers (jq,
    browsers, most languages' libraries) refuse the whole file for it. A tensor, or a record
    with an ``as_dict`` method (a check, real outcomes), is refused (``where`` names it): as a
    string it would not read back, and a long tensor's is elided."""
    obj = _python_scalar(obj)  # a NumPy number or bool as Python's (not its printed string)
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else ("NaN" if math.isnan(obj) else json.dumps(obj))
    if isinstance(obj, Mapping):
        for key in obj:
            if not isinstance(key, (str, int, float, bool)) and key is not None:
                raise TypeError(
                    f"{where}: expected str keys (JSON's), got the key {key!r} of type "
                    f"{type(key).__name__}"
                )
        return {key: _strict(value, f"{where}[{key!r}]") for key, value in obj.items()}
    if isinstance(obj, (set, frozenset)):
        raise TypeError(
            f"{where}: expected JSON values (numbers, strings, lists and dicts), got a set, "
            "which would be written as its printed string: write sorted(...) as a list"
        )
    if isinstance(obj, (list, tuple)):
        return [_strict(value, f"{where}[{i}]") for i, value in enumerate(obj)]
    _refuse_record(obj, where, "write_json")
    if isinstance(obj, (torch.Tensor, np.ndarray)):
        kind = "a tensor" if isinstance(obj, torch.Tensor) else "a NumPy array"
        raise TypeError(
            f"{where}: expected JSON values (numbers, strings, lists and dicts), got {kind} "
            f"of shape {tuple(obj.shape)}, whose printed form would not read back (a long "
            "one's is elided): write .tolist(), or save tensors with save_torch"
        )
    return obj


def _same(a: Any, b: Any) -> bool:
    """Whether two JSON-able values are equal as JSON records them: a NaN equals a NaN (a
    setting recorded as NaN is the same setting when the run resumes)."""
    return _strict(a) == _strict(b)


def _refuse_record(obj: Any, where: str, call: str) -> None:
    """Refuse a record that has its own plain form (``as_dict``): written whole, it would
    not read back."""
    if callable(getattr(obj, "as_dict", None)) and not isinstance(obj, type):
        name = type(obj).__name__
        raise TypeError(
            f"{where}: expected plain values, got a {name}; {call} its .as_dict() (and read it "
            f"back with {name}.from_dict)"
        )


def _numbers(obj: Any) -> Any:
    """:func:`_strict` undone: the strings of non-finite floats read back as floats."""
    if isinstance(obj, str):
        return _NON_FINITE.get(obj, obj)
    if isinstance(obj, dict):
        return {key: _numbers(value) for key, value in obj.items()}
    if isinstance(obj, list):
        return [_numbers(value) for value in obj]
    return obj


def _read_back(obj: Any, where: str = "obj") -> Any:
    """``obj`` as :func:`write_json` then :func:`read_json` give it back (tuples as lists,
    NumPy numbers as Python's, paths as strings); what would not read back is refused as
    :func:`write_json` refuses it (``where`` names it)."""
    return _numbers(json.loads(json.dumps(_strict(obj, where), default=str, allow_nan=False)))


def write_json(path: str | Path, obj: Any, *, checksum: bool = False) -> Path:
    """Write ``obj`` as indented, strict JSON, atomically: a non-finite float as the string
    ``"NaN"``, ``"Infinity"`` or ``"-Infinity"`` (which :func:`read_json` reads back as the
    float), other non-JSON values (a path, a dtype) as strings; a tensor, or a record with its
    own plain form (``as_dict``), is refused by name, since as a string it would not read
    back. ``checksum``: a dict gets one more entry,
    ``CHECKSUM_KEY``, the SHA-256 of the rest, which :func:`read_json` checks
    (so that a value edited by hand is not taken as the program's own)."""
    strict = _strict(obj)
    if checksum:  # the digest of the content as it reads back (tuples as lists, ...)
        if not isinstance(strict, Mapping):
            raise TypeError(f"obj: expected a dict to checksum, got {type(obj).__name__}")
        strict = json.loads(json.dumps(strict, default=str, allow_nan=False))
        strict = {**strict, CHECKSUM_KEY: _json_digest(strict)}
    text = json.dumps(strict, indent=2, default=str, allow_nan=False).encode()
    return atomic_write(path, lambda f: f.write(text))


def _json_digest(obj: Any) -> str:
    """The SHA-256 of JSON content (as :func:`json.loads` gives it), whatever its layout."""
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def _existing_file(path: object, what: str) -> Path:
    """``path`` as a ``Path`` of a file that exists: a ``TypeError`` for what is not a path, a
    :class:`StoredFileError` for a missing file."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a str or a path of {what}, got {type(path).__name__}")
    path = Path(path)
    if path.is_dir():
        raise StoredFileError(f"{what} {str(path)!r}: is a directory, expected a file", path)
    if not path.is_file():
        raise StoredFileError(f"{what} {str(path)!r}: the file is missing", path)
    return path


def read_json(path: str | Path, what: str = "a JSON file", *, checksum: bool = True) -> Any:
    """The JSON content of ``path`` (the strings :func:`write_json` writes for non-finite
    floats as those floats); :class:`StoredFileError` naming the file when it is missing or
    not valid JSON (e.g. truncated). ``checksum`` (the default): a dict's ``CHECKSUM_KEY``
    entry (written by ``write_json(..., checksum=True)``) is checked against the rest, a
    :class:`StoredFileError` when they differ, and left out of what is returned; a dict
    without one (written without) is taken as it is. ``checksum=False`` reads the content as
    it is, the entry unchecked and kept (to look at a damaged file)."""
    path = _existing_file(path, what)
    try:
        content = json.loads(path.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise StoredFileError(
            f"{what} {str(path)!r} is truncated or corrupt (not valid JSON: {err})", path
        ) from err
    if checksum and isinstance(content, dict) and CHECKSUM_KEY in content:
        recorded = content.pop(CHECKSUM_KEY)
        if recorded != _json_digest(content):
            raise StoredFileError(
                f"{what} {str(path)!r}: its content changed since it was written (its "
                f"{CHECKSUM_KEY!r} does not match the rest); a JSON file not written by this "
                f"library that holds a {CHECKSUM_KEY!r} entry of its own reads as it is with "
                "read_json(path, checksum=False)",
                path,
            )
    return _numbers(content)


#: the entry of a saved dict that holds the SHA-256 of the rest (in a torch file
#: ``fingerprint.digest``: every tensor's dtype, shape and bytes, every number and string, and
#: the layout holding them; in a JSON file, that of its content in a canonical layout)
CHECKSUM_KEY = "content_sha256"


def save_torch(path: str | Path, obj: Any) -> Path:
    """``torch.save(obj)`` to ``path``, atomically; a dict gets one more entry,
    ``CHECKSUM_KEY``, the digest of the rest, which :func:`load_torch` checks. A TensorDict
    is refused (it would be written whole, as objects :func:`load_torch` does not unpickle):
    save episodes with ``rcvae_torchrl.data.save_episodes``, or ``td.to_dict()``."""
    if isinstance(obj, TensorDictBase):
        raise TypeError(
            f"obj: expected plain tensors, numbers and strings in lists and dicts, got a "
            f"{type(obj).__name__}, which load_torch would refuse to unpickle; save episodes "
            "with rcvae_torchrl.data.save_episodes (load_episodes reads them back), or save "
            "td.to_dict()"
        )
    _refuse_record(obj, "obj", "save_torch")
    _refuse_module(obj, "obj")
    if isinstance(obj, dict):
        for key, value in obj.items():
            _refuse_record(value, f"obj[{key!r}]", "save_torch")
            _refuse_module(value, f"obj[{key!r}]")
        if CHECKSUM_KEY in obj:
            raise ValueError(f"obj: {CHECKSUM_KEY!r} is the entry save_torch writes; rename it")
        obj = {**obj, CHECKSUM_KEY: fingerprint.digest(obj)}
    return atomic_write(path, lambda f: torch.save(obj, f))


def _refuse_module(obj: Any, where: str) -> None:
    """A module is refused: pickled whole, :func:`load_torch` would not read it back."""
    if isinstance(obj, torch.nn.Module):
        raise TypeError(
            f"{where}: expected plain tensors, numbers and strings in lists and dicts, got a "
            f"{type(obj).__name__} module, which load_torch would refuse to unpickle; save its "
            ".state_dict() (or a world model with save_ensemble, a policy with save_policy)"
        )


def load_torch(path: str | Path, what: str = "a torch file", map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)``; :class:`StoredFileError` naming the file when it
    is missing, truncated or corrupt, or when a dict's content does not match the checksum
    :func:`save_torch` wrote with it (returned without that entry; a dict written before
    checksums, or by ``torch.save``, loads unchecked)."""
    if isinstance(map_location, (str, torch.device)):  # a device this machine lacks
        device = torch.device(map_location)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(
                f"map_location: expected a device of this machine, got {str(device)!r}, which "
                f"is not available here (load on 'cpu', then move what you need)"
            )
    path = _existing_file(path, what)
    data = path.read_bytes()
    try:
        obj = torch.load(io.BytesIO(data), map_location=map_location, weights_only=True)
    except Exception as err:  # torch raises several types for damaged archives
        other = re.search(r"GLOBAL (\S+) was not an allowed global", str(err))
        if other:  # a whole torch file, of objects no file of ours holds
            raise StoredFileError(
                f"{what} {str(path)!r} is another kind of file: a torch file holding "
                f"{other.group(1)} objects, which are not loaded (unpickling them could run "
                "code the file names); expected one saved by this library",
                path,
            ) from err
        if data and not data.startswith(_TORCH_STARTS):  # not even the start of one
            raise StoredFileError(
                f"{what} {str(path)!r} is not a torch file, or its start is damaged: it begins "
                f"{data[:12]!r}, where a torch file is a zip archive (b'PK\\x03\\x04...'); "
                "expected one saved by this library",
                path,
            ) from err
        why = (_load_failure(err) or "unreadable") if data else "the file is empty"
        raise StoredFileError(
            f"{what} {str(path)!r} is truncated or corrupt ({len(data)} bytes): {why}", path
        ) from err
    if isinstance(obj, dict) and CHECKSUM_KEY in obj:
        written = obj.pop(CHECKSUM_KEY)
        if written != fingerprint.digest(obj):
            raise StoredFileError(
                f"{what} {str(path)!r} is corrupt: its content does not match the checksum "
                "written with it (SHA-256), so some of its numbers changed after it was saved "
                "(a damaged disk or copy); remake it or restore a good copy",
                path,
            )
    return obj


#: How a torch file begins: a zip archive (torch.save's format), or a pickle (the legacy one).
_TORCH_STARTS = (b"PK\x03\x04", b"\x80")


def _load_failure(err: Exception) -> str:
    """What ``torch.load`` found wrong, without its advice to load with ``weights_only=False``
    (which runs whatever code the file holds)."""
    text = str(err)
    _, found, after = text.partition("WeightsUnpickler error:")
    if found:
        return next((line.strip() for line in after.splitlines() if line.strip()), "unreadable")
    return text


def _differences(key: str, old: Any, new: Any) -> list[tuple[str, Any, Any]]:
    """The leaves of two nested settings that differ, as (dotted key, old, new)."""
    if isinstance(old, dict) and isinstance(new, dict):
        return [
            d
            for k in sorted(old.keys() | new.keys())
            if not _same(old.get(k), new.get(k))
            for d in _differences(f"{key}.{k}", old.get(k), new.get(k))
        ]
    return [(key, old, new)]


def record_run_config(
    path: str | Path, config: Mapping[str, Any], *, may_change: Iterable[str] = ()
) -> None:
    """Write a run's settings to ``path``, or check them against the ones already there.

    A run directory holds results made with the settings recorded in it; reusing them under
    other settings would mix results silently, so that is a ``ValueError`` naming the settings
    that differ. Top-level keys in ``may_change`` may differ (e.g. a number of rounds a run can
    be extended by); the new values are recorded.
    """
    path = Path(path)
    current = _as_json(config)
    if path.is_file():
        saved = read_json(path, "run config")
        _compare_run_config(path, saved, current, may_change)
        if _same(saved, current):
            return
    write_json(path, current)


def check_run_config(
    path: str | Path, config: Mapping[str, Any], *, may_change: Iterable[str] = ()
) -> None:
    """The check of :func:`record_run_config` alone, writing nothing: a ``ValueError`` when
    ``path`` records other settings; nothing when it is missing or unreadable (the run then
    records them). For a run to refuse other settings before it creates anything."""
    path = Path(path)
    if not path.is_file():
        return
    try:
        saved = read_json(path, "run config")
    except StoredFileError:
        return
    current = _as_json(config)
    _compare_run_config(path, saved, current, may_change)


def _as_json(config: Mapping[str, Any]) -> Any:
    """Settings as they read back from JSON (tuples as lists, NumPy numbers as Python's,
    other values as strings)."""
    if not isinstance(config, Mapping):
        raise TypeError(
            f"config: expected a mapping of the run's settings, got {type(config).__name__}"
        )
    return json.loads(json.dumps(dict(config), default=_plain))


def _plain(value: Any) -> Any:
    """A value JSON has no form for: a NumPy number or bool as Python's, else its string."""
    scalar = _python_scalar(value)
    return str(value) if scalar is value else scalar


def _python_scalar(value: Any) -> Any:
    """A NumPy number or bool (``np.float32(0.5)``, ``np.bool_(True)``) as the Python one,
    which JSON writes as a number or bool; any other value as it is."""
    text = isinstance(value, (np.str_, np.bytes_, np.void))
    return value.item() if isinstance(value, np.generic) and not text else value


def _compare_run_config(
    path: Path, saved: Any, current: dict[str, Any], may_change: Iterable[str]
) -> None:
    if isinstance(saved, dict):
        skip = set(may_change)
        changed = sorted(
            k
            for k in set(saved) | set(current)
            if k not in skip and not _same(saved.get(k), current.get(k))
        )
        if changed:
            details = "; ".join(
                f"{key}: {old!r} recorded, {new!r} now"
                for k in changed
                for key, old, new in _differences(k, saved.get(k), current.get(k))
            )
            raise ValueError(
                f"run directory {str(path.parent)!r} holds a run made with other settings "
                f"({changed} differ: {details}); its results would be reused: use a new "
                "directory"
            )

"""A run's log: plain lines in a file, colour only on a terminal.

:func:`run_log` opens ``run.log`` (appending, so a resumed run adds to it) and returns a
:class:`logging.Logger` writing to it and to the console. The library's own lines (logger
``"rcvae_torchrl"`` and below: a training resumed from its checkpoint, an ahead-of-time package
built) go to both too; TorchRL's own logger (``"torchrl"``) and Python warnings to the file.
TorchRL colours its console lines with ANSI codes; in the file they are removed, and on a
console that is not a terminal (output redirected to a file or a pipe) too.
"""

from __future__ import annotations

import logging
import os
import re
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

__all__ = ["ANSI_CODE", "PlainFormatter", "forwarded_log", "log_targets", "run_log"]

#: An ANSI escape sequence (colours, cursor moves).
ANSI_CODE = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")

_FORMAT = "%(asctime)s [%(name)s][%(levelname)s] %(message)s"
_DATE = "%Y-%m-%d %H:%M:%S"
#: The library's loggers (``logging.getLogger(__name__)`` in its modules) are below this one.
_PACKAGE = "rcvae_torchrl"


class PlainFormatter(logging.Formatter):
    """A formatter whose lines hold no ANSI codes, whatever the message carries."""

    def format(self, record: logging.LogRecord) -> str:
        return ANSI_CODE.sub("", super().format(record))


def _is_terminal(stream: IO[str]) -> bool:
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty())


@contextmanager
def run_log(
    path: str | Path, name: str = "rcvae_torchrl.run", stream: IO[str] | None = None
) -> Iterator[logging.Logger]:
    """Log to ``path`` (plain text, appended) and to ``stream`` (default: stdout) inside the block.

    The library's loggers (INFO and above) go to both; TorchRL's logger and Python warnings
    also go to ``path`` for the block's duration; when ``stream`` is not a terminal, TorchRL's
    console lines are written without colour. Everything is put back as it was on exit.

    Example:
        >>> import io, tempfile
        >>> from pathlib import Path
        >>> path = Path(tempfile.mkdtemp()) / "run.log"
        >>> with run_log(path, stream=io.StringIO()) as log:
        ...     log.info("\\033[92mstage done\\033[0m")
        >>> path.read_text().endswith("stage done\\n")
        True
    """
    if stream is not None and not callable(getattr(stream, "write", None)):
        raise TypeError(
            "stream: expected a text stream (an object with write(), e.g. sys.stdout or "
            f"io.StringIO()) or None for stdout, got {type(stream).__name__} {stream!r}"
        )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stream = stream if stream is not None else sys.stdout
    to_file = logging.FileHandler(path, mode="a", encoding="utf-8")
    to_file.setFormatter(PlainFormatter(_FORMAT, _DATE))
    to_console = logging.StreamHandler(stream)
    to_console.setFormatter(
        logging.Formatter("%(message)s") if _is_terminal(stream) else PlainFormatter("%(message)s")
    )
    log, package = logging.getLogger(name), logging.getLogger(_PACKAGE)
    torchrl, warned = logging.getLogger("torchrl"), logging.getLogger("py.warnings")
    ours = list(dict.fromkeys((log, package)))  # the library's own lines (a resumed training)
    saved = {logger: (logger.level, logger.propagate) for logger in ours}
    for logger in ours:
        logger.setLevel(logging.INFO)
        logger.propagate = False
        logger.addHandler(to_file)
        logger.addHandler(to_console)
    recoloured = _plain_consoles(torchrl)
    # warnings still reach the console: through the root logger's handlers if it has any
    warned_console = None if warned.hasHandlers() else logging.StreamHandler(sys.stderr)
    torchrl.addHandler(to_file)
    warned.addHandler(to_file)
    if warned_console is not None:
        warned.addHandler(warned_console)
    logging.captureWarnings(True)
    try:
        yield log
    except BaseException as error:  # the file keeps why the run stopped (the console has it)
        if isinstance(error, (SystemExit, GeneratorExit)) and not getattr(error, "code", None):
            raise  # a clean exit
        interrupted = isinstance(error, KeyboardInterrupt)
        to_file.handle(
            log.makeRecord(
                log.name,
                logging.WARNING if interrupted else logging.ERROR,
                __file__,
                0,
                "interrupted (KeyboardInterrupt): the run stopped here"
                if interrupted
                else f"failed: {type(error).__name__}: {error}",
                None,
                None if interrupted else (type(error), error, error.__traceback__),
            )
        )
        raise
    finally:
        logging.captureWarnings(False)
        for logger, handler in (
            *((logger, handler) for logger in ours for handler in (to_file, to_console)),
            (torchrl, to_file),
            (warned, to_file),
            (warned, warned_console),
        ):
            if handler is not None:
                logger.removeHandler(handler)
        for handler, formatter in recoloured.items():
            handler.setFormatter(formatter)
        for logger, (level, propagate) in saved.items():
            logger.setLevel(level)
            logger.propagate = propagate
        to_file.close()


def _plain_consoles(logger: logging.Logger) -> dict[logging.Handler, logging.Formatter | None]:
    """Give ``logger``'s handlers that write to no terminal a colourless formatter; returns
    the old formatters."""
    old = {}
    for handler in logger.handlers:
        stream = getattr(handler, "stream", None)
        if stream is not None and not _is_terminal(stream):
            old[handler] = handler.formatter
            handler.setFormatter(PlainFormatter(_FORMAT, _DATE))
    return old


#: Where a handler of the library's logger writes, as a spawned process can open it again: a
#: file's path, or ``"stdout"`` / ``"stderr"``, with the handler's formatter.
LogTarget = tuple[str, str, logging.Formatter]


def log_targets() -> list[LogTarget]:
    """The files and console streams the library's logger writes to here (:func:`run_log`'s
    handlers), for a worker process to write its lines to the same places
    (:func:`forwarded_log`)."""
    targets: list[LogTarget] = []
    for handler in logging.getLogger(_PACKAGE).handlers:
        if isinstance(handler, logging.FileHandler):
            targets.append(("file", handler.baseFilename, handler.formatter))
        elif isinstance(handler, logging.StreamHandler):
            for name in ("stdout", "stderr"):
                if handler.stream is getattr(sys, name):
                    targets.append(("stream", name, handler.formatter))
    return targets


@contextmanager
def forwarded_log(targets: list[LogTarget]) -> Iterator[None]:
    """Inside the block, the library's INFO lines go to ``targets`` (from :func:`log_targets`
    in the parent process): a worker's resumed training is in the parent's ``run.log``.

    Each target is ``(kind, where, formatter)``: ``("file", <path>, formatter)`` or
    ``("stream", "stdout" | "stderr", formatter)``, the formatter a ``logging.Formatter`` or
    None; anything else is refused (``ValueError``) before any handler is made."""
    targets = _checked_targets(targets)
    package = logging.getLogger(_PACKAGE)
    handlers: list[logging.Handler] = []
    for kind, where, formatter in targets:
        handler = (
            logging.FileHandler(where, mode="a", encoding="utf-8")
            if kind == "file"
            else logging.StreamHandler(getattr(sys, where))
        )
        handler.setFormatter(formatter)
        handlers.append(handler)
    saved = package.level, package.propagate
    if handlers:
        package.setLevel(logging.INFO)
        package.propagate = False
    for handler in handlers:
        package.addHandler(handler)
    try:
        yield
    finally:
        for handler in handlers:
            package.removeHandler(handler)
            handler.close()
        package.setLevel(saved[0])
        package.propagate = saved[1]


def _checked_targets(targets: object) -> list[LogTarget]:
    """``targets`` as a list, each entry one :func:`log_targets` gives; a ValueError naming
    the entry and what is expected otherwise."""
    expected = (
        "(kind, where, formatter) entries from log_targets(): ('file', a path, formatter) or "
        "('stream', 'stdout' or 'stderr', formatter), the formatter a logging.Formatter or None"
    )
    if isinstance(targets, (str, bytes)) or not isinstance(targets, Iterable):
        raise TypeError(f"targets: expected a list of {expected}, got {targets!r}")
    targets = list(targets)
    for i, target in enumerate(targets):
        ok = isinstance(target, (tuple, list)) and len(target) == 3
        if ok:
            kind, where, formatter = target
            ok = formatter is None or isinstance(formatter, logging.Formatter)
            if kind == "file":
                ok = ok and isinstance(where, (str, os.PathLike))
            else:
                ok = ok and kind == "stream" and where in ("stdout", "stderr")
        if not ok:
            raise ValueError(f"targets[{i}]: expected {expected}, got {target!r}")
    return targets

"""Independent jobs in worker processes, as many as the machine's idle cores allow.

A study trains several world models that share nothing (one per env variant), each on one
torch thread: the world model's ops are too small for a second thread to pay
(:mod:`rcvae_torchrl.threads`), so on a machine with idle cores one process leaves them idle.
:func:`map_in_processes` runs such jobs side by side in spawned worker processes (each with
the caller's torch thread count), and :func:`choose_workers` picks how many: one per job, up
to the cores the machine's load leaves idle. A job's result does not depend on where it ran:
it is the same computation on the same thread count, in a fresh process.

Spawning a worker costs it the imports of torch and the rest (seconds of a core each): a run of
several calls (a study's stages) can keep its workers for all of them with :func:`worker_pool`.

A worker ends with the process that spawned it: killed mid-job (``kill -9``, an out-of-memory
kill), that process would otherwise leave its workers computing a job nobody waits for, on
cores the next run needs. A worker that dies mid-job (a crash in native code, a kill) fails
the call with :class:`~concurrent.futures.process.BrokenProcessPool`; a :func:`worker_pool`
block then starts fresh workers for its later calls.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import multiprocessing
import os
import pickle
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, TypeVar

import torch

from rcvae_torchrl._checks import check_positive, check_positive_int
from rcvae_torchrl.run_log import LogTarget, forwarded_log, log_targets
from rcvae_torchrl.threads import free_cores, set_threads

__all__ = [
    "ChildOutcome",
    "check_workers",
    "choose_workers",
    "map_in_processes",
    "try_in_a_child",
    "worker_pool",
]

T = TypeVar("T")


def check_workers(name: str, value: Any) -> None:
    """Require ``"auto"`` or an integer >= 1 (``name`` is the setting, for the error)."""
    if value == "auto":
        return
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}: expected a positive integer or 'auto', got {value!r}")


def choose_workers(
    jobs: int, setting: int | str = "auto", *, cpus: int | None = None, load: float | None = None
) -> int:
    """Worker processes for ``jobs`` independent jobs: ``setting`` (an int, capped at ``jobs``)
    or ``"auto"``: the cores the machine's 1-minute load average leaves idle, rounded (a core
    at least half idle counts), capped at ``jobs``; at least 1.

    Call it before the jobs' own work has loaded the machine (a recipe: once, when a run
    starts), so that the load is the other jobs'. Unlike torch threads
    (:func:`~rcvae_torchrl.threads.choose_threads`, which stall on a core they do not get), a
    process too many only shares a core: the rule need not be as strict.

    Example:
        >>> choose_workers(2, cpus=2, load=0.3), choose_workers(2, cpus=2, load=1.0)
        (2, 1)
        >>> choose_workers(3, 2)
        2
    """
    check_workers("workers", setting)
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 0:
        raise ValueError(f"jobs: expected a non-negative int, got {jobs!r}")
    if setting != "auto":
        return max(1, min(setting, jobs))
    return max(1, min(jobs, round(free_cores(cpus, load))))


def _call(threads: int, fn: Callable[..., T], args: tuple, logs: list[LogTarget]) -> T:
    set_threads(threads)
    with forwarded_log(logs):  # the library's lines where the caller's go (its run.log)
        return fn(*args)


def _end_with_parent() -> None:
    """A worker's first step: a thread that waits for the process that spawned this one to
    end (its sentinel, a pipe whose other end only that process holds, reads end-of-file then)
    and ends this one too, with the processes this one started (a batched env's workers)."""
    parent = multiprocessing.parent_process()
    if parent is None:  # not a spawned process: nothing to watch
        return

    def watch() -> None:
        parent.join()
        try:
            for child in multiprocessing.active_children():
                child.terminate()
        finally:  # whatever the children do, this process ends
            os._exit(1)

    threading.Thread(target=watch, name="end-with-parent", daemon=True).start()


def _executor(workers: int) -> concurrent.futures.ProcessPoolExecutor:
    context = multiprocessing.get_context("spawn")  # no fork of a process that holds torch
    return concurrent.futures.ProcessPoolExecutor(workers, context, initializer=_end_with_parent)


@dataclass
class _Kept:
    """The workers of a :func:`worker_pool` block: its executor (renewed when broken) and size."""

    pool: concurrent.futures.ProcessPoolExecutor
    workers: int


#: The kept workers of the open :func:`worker_pool` blocks, the innermost last.
_pools: list[_Kept] = []


@contextlib.contextmanager
def worker_pool(workers: int) -> Iterator[None]:
    """Inside the block, :func:`map_in_processes` runs its jobs on up to ``workers`` spawned
    processes kept for every call that asks for that many (or has no more jobs than it asks
    for), instead of spawning its own each time: each process pays its imports once. The
    processes start when a call first needs them and end with the block. ``workers=1`` keeps
    none (every call as without it). A call whose worker died mid-job fails; the block's
    later calls get fresh workers (as does a call after a worker died between calls).

    A job then may run in a process that ran other jobs before: one whose result depends
    only on its arguments (seeded, as :func:`map_in_processes` asks) is the same there.
    """
    check_positive_int("workers", workers)
    if workers == 1:
        yield
        return
    kept = _Kept(_executor(workers), workers)
    _pools.append(kept)
    try:
        yield
    finally:
        _pools.remove(kept)
        kept.pool.shutdown()


def map_in_processes(
    fn: Callable[..., T], jobs: Sequence[tuple], workers: int, *, threads: int | None = None
) -> list[T]:
    """``[fn(*args) for args in jobs]``, over ``workers`` spawned processes when > 1.

    Args:
        fn: a module-level function (it is pickled by name) whose arguments and result pickle.
        jobs: one argument tuple per job.
        workers: processes; 1 runs every job here, one after the other. Inside a
            :func:`worker_pool` block the block's processes run them where ``workers`` is
            its count or at least the jobs' (no more side by side than asked for).
        threads: torch intra-op threads in each worker (default: this process's count).

    The library's log lines in a worker go where this process's go (the file and console of
    :func:`~rcvae_torchrl.run_log.run_log`).

    Returns:
        the results in the order of ``jobs``; a job's exception is raised here.
    """
    check_positive_int("workers", workers)
    if not callable(fn):
        raise TypeError(f"fn: expected a module-level function, got {fn!r}")
    if isinstance(jobs, (str, bytes)) or not isinstance(jobs, Sequence):
        raise TypeError(
            f"jobs: expected a sequence of argument tuples (one per job), got {type(jobs).__name__}"
        )
    if threads is not None:
        check_positive_int("threads", threads)
    if workers == 1 or len(jobs) <= 1:
        return [fn(*args) for args in jobs]
    try:  # before any process starts: a worker finds the function by its module and name
        pickle.dumps(fn)
    except (pickle.PicklingError, AttributeError, TypeError) as err:
        raise TypeError(
            f"fn: expected a module-level function (worker processes import it by name), got "
            f"{fn!r}, which does not pickle: {err}"
        ) from err
    threads = torch.get_num_threads() if threads is None else threads
    logs = log_targets()
    kept = _pools[-1] if _pools else None

    def submit(pool: concurrent.futures.ProcessPoolExecutor) -> list[concurrent.futures.Future]:
        return [pool.submit(_call, threads, fn, tuple(args), logs) for args in jobs]

    if kept is not None and (workers == kept.workers or len(jobs) <= min(workers, kept.workers)):
        try:
            futures = submit(kept.pool)
        except BrokenProcessPool:  # a worker died between calls, before any of these jobs
            _renew(kept)
            futures = submit(kept.pool)
        try:
            return _results(futures, fn)
        except BrokenProcessPool:
            _renew(kept)  # the block's later calls: fresh workers
            raise
    with _executor(min(workers, len(jobs))) as pool:
        return _results(submit(pool), fn)


def _renew(kept: _Kept) -> None:
    """Replace a broken pool's processes with fresh ones."""
    kept.pool.shutdown(wait=False, cancel_futures=True)
    kept.pool = _executor(kept.workers)


def _results(futures: list[concurrent.futures.Future], fn: Callable) -> list:
    """The futures' results in order; at the first exception the jobs not started are
    cancelled (a kept pool's workers then take no more of them) and it is raised."""
    try:
        return [f.result() for f in futures]
    except BaseException as err:
        for future in futures:
            future.cancel()
        if isinstance(err, BrokenProcessPool):
            name = getattr(fn, "__qualname__", repr(fn))
            raise BrokenProcessPool(
                f"a worker process ended abruptly (killed, or a crash in native code) while "
                f"running the {len(futures)} jobs of {name}: none of their results is returned"
            ) from err
        raise


@dataclass(frozen=True)
class ChildOutcome:
    """How a try in a child process went (:func:`try_in_a_child`)."""

    problem: str | None  #: None when it exited with status 0, else what went wrong
    crashed: bool = False  #: a signal ended it (a segmentation fault, an abort), or it hung


def try_in_a_child(
    code: str, *args: str, timeout: float, env: dict[str, str] | None = None
) -> ChildOutcome:
    """Run ``code`` (as ``python -c code args...``) in a new interpreter with this one's import
    path and environment (plus ``env``), for what may end a process rather than raise (a
    native library's crash or abort) or leave it half set up (a failed import): the child
    ends, this process learns how. ``OSError`` when no child can be started."""
    check_positive("timeout", timeout)
    path = os.pathsep.join(p for p in sys.path if p)
    env = {**os.environ, "PYTHONPATH": path, **(env or {})}
    try:
        done = subprocess.run(
            [sys.executable, "-c", code, *args],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        return ChildOutcome(f"it did not finish in {timeout:g} s", crashed=True)
    if done.returncode == 0:
        return ChildOutcome(None)
    if done.returncode < 0:
        try:
            name = signal.Signals(-done.returncode).name
        except ValueError:
            name = f"signal {-done.returncode}"
        return ChildOutcome(f"its process was ended by {name}", crashed=True)
    lines = done.stderr.strip().splitlines()
    return ChildOutcome(lines[-1] if lines else f"exit status {done.returncode}")

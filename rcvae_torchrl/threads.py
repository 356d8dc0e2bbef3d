"""Torch intra-op threads chosen so that they never lose to one thread.

Torch's default is one thread per core. On a machine where other jobs hold the cores, every
parallel op then waits for a thread that is not scheduled: on 2 shared cores, 2 threads ran
3.8-17x slower than 1 (``benchmarks/threads.py`` measures it). And an op only gains from a
second thread when it is large: the world model's ops (a few hundred rows of 64-wide layers per
member) cost less than handing work to another thread.

:func:`choose_threads` therefore returns 1 unless both hold: the machine has idle cores (the
1-minute load average leaves at least one whole core free per extra thread) and the work per op
is large enough (:data:`MIN_FLOP_PER_THREAD` per thread). :func:`set_threads` applies it, and
:func:`threads_kept` keeps it across code that resets it: TorchRL's batched envs (``SerialEnv``,
``ParallelEnv``) change torch's thread count when they start and close workers (on close they
raise it by the number of workers, up to the count torch started with), so a process that set 1
thread trains on 2 after collecting data with a ``SerialEnv`` of 4 envs. A batched env left
unclosed is closed by Python's garbage collector, at whatever moment it runs: if that is while
``torch.compile`` traces, the trace fails ("Global num_threads state changed while dynamo
tracing"). :func:`collection_paused` calls a compiled function with the collector paused.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import math
import numbers
import os
from collections.abc import Callable, Iterator
from typing import ParamSpec, TypeVar

import torch

from rcvae_torchrl._checks import is_integer

__all__ = [
    "MIN_FLOP_PER_THREAD",
    "choose_threads",
    "collection_paused",
    "free_cores",
    "set_threads",
    "threads_kept",
]

_P = ParamSpec("_P")
_R = TypeVar("_R")

#: Floating-point operations per op below which a further thread is not given. A conservative
#: bound, not a measured break-even: on this project's shared 2-core machine (load 4-7) a second
#: thread lost at every size measured, from 378x slower for a 3.9 MFLOP matmul to 1.16x for a
#: 2 GFLOP one (``benchmarks/threads.py``); there the load rule alone already gives 1 thread.
MIN_FLOP_PER_THREAD = float(1 << 22)


def free_cores(cpus: int | None = None, load: float | None = None) -> float:
    """Cores this process may use minus the machine's 1-minute load average (at least 0).

    Args:
        cpus: cores available (default: this process's CPU affinity).
        load: runnable processes (default: ``os.getloadavg()[0]``; it counts this process too
            while it runs).
    """
    cpus = len(os.sched_getaffinity(0)) if cpus is None else cpus
    load = os.getloadavg()[0] if load is None else load
    if not is_integer(cpus) or cpus < 1:
        raise ValueError(f"cpus: expected a positive integer, got {cpus!r}")
    _check_load(load)
    return max(0.0, int(cpus) - load)


def _check_load(load: object) -> None:
    """Require a load average >= 0 (a Python or NumPy number, not a bool)."""
    if isinstance(load, bool) or not isinstance(load, numbers.Real) or not load >= 0:
        raise ValueError(f"load: expected a load average >= 0, got {load!r}")


def _check_op_flop(op_flop: object) -> None:
    """Require None or a finite FLOP count >= 0 (a Python or NumPy number, not a bool)."""
    if op_flop is not None and (
        isinstance(op_flop, bool)
        or not isinstance(op_flop, numbers.Real)
        or not math.isfinite(op_flop)
        or op_flop < 0
    ):
        raise ValueError(f"op_flop: expected a finite FLOP count >= 0 or None, got {op_flop!r}")


def choose_threads(
    op_flop: float | None = None, *, cpus: int | None = None, load: float | None = None
) -> int:
    """The intra-op thread count for work whose typical op costs ``op_flop`` FLOP.

    ``1 + min(whole idle cores beyond this process's own, op_flop // MIN_FLOP_PER_THREAD - 1)``,
    capped at the cores available; 1 when ``op_flop`` is None (unknown work is treated as small).

    Example:
        >>> choose_threads(1e9, cpus=8, load=0.0), choose_threads(1e9, cpus=8, load=7.5)
        (8, 1)
        >>> choose_threads(1e5, cpus=8, load=0.0)  # a small op: one thread
        1
    """
    _check_op_flop(op_flop)
    cpus = len(os.sched_getaffinity(0)) if cpus is None else cpus
    if not is_integer(cpus):
        raise ValueError(f"cpus: expected a positive integer (cores) or None, got {cpus!r}")
    if cpus < 1:
        raise ValueError(f"cpus: expected at least 1 core, got {cpus}")
    cpus = int(cpus)
    if load is not None:
        _check_load(load)
    if op_flop is None:
        return 1
    idle = math.floor(free_cores(cpus, load))
    by_work = int(op_flop // MIN_FLOP_PER_THREAD)
    return max(1, min(cpus, 1 + min(idle, by_work - 1)))


def set_threads(threads: int | str | None, op_flop: float | None = None) -> int:
    """Set torch's intra-op threads: a count, ``"auto"`` (:func:`choose_threads` for
    ``op_flop``) or None (leave torch's default). Returns the count in effect.

    ``op_flop`` (None or a finite FLOP count >= 0) is checked whatever ``threads`` is."""
    _check_op_flop(op_flop)
    if isinstance(threads, str) and threads == "auto":
        threads = choose_threads(op_flop)
    elif threads is not None and (not is_integer(threads) or threads < 1):
        raise ValueError(f"threads: expected a positive integer, 'auto' or None, got {threads!r}")
    if threads is not None:
        torch.set_num_threads(int(threads))
    return torch.get_num_threads()


@contextlib.contextmanager
def threads_kept() -> Iterator[int]:
    """Restore torch's intra-op thread count on exit (yields it), whatever the code inside
    set: wrap the start and the close of TorchRL batched envs, which change it."""
    count = torch.get_num_threads()
    try:
        yield count
    finally:
        if torch.get_num_threads() != count:
            torch.set_num_threads(count)


def collection_paused(fn: Callable[_P, _R]) -> Callable[_P, _R]:
    """``fn`` called with Python's cyclic garbage collector paused (as it was after the call).

    For ``torch.compile``-d functions, which trace at their first call and again at each new
    shape: a TorchRL batched env waiting in a reference cycle for the collector sets torch's
    thread count when it is collected, and a trace during which the count changes fails. With
    the collector paused nothing is collected during the call; what is left is collected at
    the collector's next run after it (its finalizers then change the count outside a trace).
    Pausing and resuming cost well under a microsecond a call.
    """

    @functools.wraps(fn)
    def paused(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        enabled = gc.isenabled()
        gc.disable()
        try:
            return fn(*args, **kwargs)
        finally:
            if enabled:
                gc.enable()

    return paused

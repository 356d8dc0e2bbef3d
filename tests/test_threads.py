"""The thread-count default: one thread unless the machine is idle and the ops are large."""

import contextlib
import functools
import gc
import math

import numpy as np
import pytest
import torch

from rcvae_torchrl.data import collect_episodes
from rcvae_torchrl.envs import make_pusher_env
from rcvae_torchrl.threads import (
    MIN_FLOP_PER_THREAD,
    choose_threads,
    collection_paused,
    free_cores,
    set_threads,
    threads_kept,
)


def test_busy_machine_or_small_ops_get_one_thread():
    big = 1000 * MIN_FLOP_PER_THREAD
    assert choose_threads(big, cpus=2, load=1.5) == 1  # less than a whole core free
    assert choose_threads(big, cpus=2, load=6.0) == 1
    assert choose_threads(MIN_FLOP_PER_THREAD * 1.9, cpus=16, load=0.0) == 1
    assert choose_threads(None, cpus=16, load=0.0) == 1  # unknown work counts as small


def test_idle_cores_and_large_ops_add_threads_up_to_both_limits():
    assert choose_threads(1000 * MIN_FLOP_PER_THREAD, cpus=16, load=12.2) == 4  # 3 idle cores
    assert choose_threads(3 * MIN_FLOP_PER_THREAD, cpus=16, load=0.0) == 3  # by the work
    assert choose_threads(1e12, cpus=4, load=0.0) == 4  # never more than the cores


def test_free_cores_is_cores_minus_load_at_least_zero():
    assert free_cores(cpus=8, load=2.5) == 5.5
    assert free_cores(cpus=2, load=7.0) == 0.0


def test_set_threads_applies_counts_and_auto_and_leaves_none_alone():
    before = torch.get_num_threads()
    try:
        assert set_threads(1) == 1 and torch.get_num_threads() == 1
        assert set_threads("auto") == 1  # no work size given: one thread
        assert set_threads(None) == 1  # left as it was
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: set_threads(0), r"^threads: expected a positive integer, 'auto' or None, got 0"),
        (lambda: set_threads("many"), r"^threads: expected .* got 'many'"),
        (lambda: set_threads(True), r"^threads: expected .* got True"),
        (lambda: choose_threads(-1.0), r"^op_flop: expected a finite FLOP count"),
        (lambda: choose_threads(1e9, cpus=0), r"^cpus: expected at least 1 core, got 0"),
    ],
)
def test_bad_arguments_name_themselves(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: choose_threads(None, load=-1), r"^load: expected a load average >= 0, got -1"),
        (lambda: choose_threads(None, cpus=True), r"^cpus: expected a positive integer .*True"),
        (lambda: choose_threads(None, cpus="2"), r"^cpus: expected a positive integer .*'2'"),
        (lambda: choose_threads(1e9, cpus=2.0), r"^cpus: expected a positive integer .*2\.0"),
        (lambda: choose_threads(True), r"^op_flop: expected a finite FLOP count .* got True"),
        (lambda: choose_threads("abc"), r"^op_flop: expected a finite FLOP count .* got 'abc'"),
        (lambda: set_threads(1, op_flop=math.nan), r"^op_flop: expected .* got nan"),
        (lambda: set_threads(None, op_flop=-1.0), r"^op_flop: expected .* got -1\.0"),
    ],
)
def test_bad_arguments_are_named_whatever_else_is_given(call, match):
    """A bad load or core count was taken where no work size was given, ``True`` as a FLOP
    count or a core count, and an ``op_flop`` that ``set_threads`` did not use was not
    looked at."""
    with pytest.raises(ValueError, match=match):
        call()


def test_numpy_integers_are_taken_where_ints_are():
    before = torch.get_num_threads()
    try:
        assert set_threads(np.int64(1)) == 1 and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    big = 1000 * MIN_FLOP_PER_THREAD
    assert choose_threads(np.float32(big), cpus=np.int64(16), load=np.float64(12.2)) == 4
    assert free_cores(cpus=np.int32(8), load=np.int64(2)) == 6.0


def test_threads_kept_restores_the_count_whatever_happens_inside():
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        with threads_kept() as count:
            assert count == 1
            torch.set_num_threads(2)
        assert torch.get_num_threads() == 1
        with pytest.raises(KeyError), threads_kept():
            torch.set_num_threads(2)
            raise KeyError("inside")
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_collecting_with_a_serial_env_keeps_the_thread_count():
    """TorchRL's SerialEnv raises torch's thread count when it closes (by its worker count, up
    to the count torch started with); a caller's choice must survive data collection."""
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)

        def policy(td):
            return td.set("action", torch.zeros(*td.batch_size, 2))

        make = functools.partial(make_pusher_env, time_limit=1.0)
        data = collect_episodes(make, policy, 2, num_envs=2, progress=False)
        assert data.numel() > 0
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


class _SetsThreadsWhenCollected:
    """What a TorchRL batched env left unclosed in a reference cycle does when the garbage
    collector frees it: it sets torch's thread count (here: records the call, then flips the
    count between 1 and 2)."""

    def __init__(self, calls: list[str], phase: list[str]) -> None:
        self.cycle, self.calls, self.phase = self, calls, phase

    def __del__(self) -> None:
        self.calls.append(self.phase[0])
        torch.set_num_threads(2 if torch.get_num_threads() == 1 else 1)


@contextlib.contextmanager
def _garbage_waiting_for_a_full_collection(calls: list[str], phase: list[str]):
    """One such object, unreachable, in the collector's oldest generation (every other object
    frozen out of its count), with thresholds at which a call that allocates a few thousand
    container objects runs a full collection."""
    threads = torch.get_num_threads()
    thresholds = gc.get_threshold()
    gc.collect()
    gc.freeze()
    try:
        garbage = _SetsThreadsWhenCollected(calls, phase)
        gc.collect()  # it survives into the oldest generation ...
        del garbage  # ... and is garbage there
        gc.set_threshold(100, 2, 2)
        yield
    finally:
        gc.set_threshold(*thresholds)
        gc.unfreeze()
        gc.collect()
        torch.set_num_threads(threads)


def _allocate() -> int:
    """Many container objects that live through the call, as a trace makes."""
    kept = [[i] for i in range(20_000)]
    return len(kept)


def test_collection_paused_runs_no_finalizer_during_the_call_and_restores_the_collector():
    calls: list[str] = []
    phase = ["before"]
    with _garbage_waiting_for_a_full_collection(calls, phase):
        phase[0] = "during"
        _allocate()  # unpaused, the finalizer runs inside the call: the setup bites
        phase[0] = "after"
    assert calls == ["during"]

    calls.clear()
    phase[0] = "before"
    with _garbage_waiting_for_a_full_collection(calls, phase):
        phase[0] = "during"
        collection_paused(_allocate)()
        phase[0] = "after"
        assert gc.isenabled()
        gc.collect()  # the next collection frees it, outside the call
    assert calls == ["after"]

    def fails() -> None:
        raise KeyError("inside")

    with pytest.raises(KeyError, match="inside"):
        collection_paused(fails)()
    assert gc.isenabled()
    gc.disable()
    try:
        assert collection_paused(gc.isenabled)() is False
        assert not gc.isenabled()  # a collector the caller paused stays paused
    finally:
        gc.enable()
    assert collection_paused(functools.partial(max, 1))(2) == 2  # arguments and result pass


def _sines(x: torch.Tensor) -> torch.Tensor:
    for _ in range(30):
        x = torch.sin(x) * 2 + x.cos()
    return x


def test_a_compiled_function_traces_with_the_collector_paused():
    """The failure the pause prevents: a trace during which the thread count changes fails."""
    x = torch.linspace(-1, 1, 8)
    calls: list[str] = []
    phase = ["during"]
    torch._dynamo.reset()
    compiled = torch.compile(_sines, dynamic=False)
    with _garbage_waiting_for_a_full_collection(calls, phase):
        with pytest.raises(AssertionError, match="num_threads"):
            compiled(x)
    assert calls == ["during"]
    calls.clear()
    torch._dynamo.reset()
    compiled = collection_paused(torch.compile(_sines, dynamic=False))
    with _garbage_waiting_for_a_full_collection(calls, phase):
        got = compiled(x)
        phase[0] = "after"
    torch.testing.assert_close(got, _sines(x))
    assert calls == ["after"]
    torch._dynamo.reset()

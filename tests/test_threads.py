"""The thread-count default: one thread unless the machine is idle and the ops are large."""

import functools
import math

import numpy as np
import pytest
import torch

from rcvae_torchrl.data import collect_episodes
from rcvae_torchrl.envs import make_pusher_env
from rcvae_torchrl.threads import (
    MIN_FLOP_PER_THREAD,
    choose_threads,
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

"""Independent jobs in worker processes: how many, in order, errors, threads, kept workers."""

from __future__ import annotations

import io
import logging
import math
import os
import signal
import subprocess
import sys
import time
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import pytest
import torch

from rcvae_torchrl.processes import (
    check_workers,
    choose_workers,
    map_in_processes,
    worker_pool,
)
from rcvae_torchrl.run_log import log_targets, run_log


@pytest.mark.parametrize(
    ("jobs", "setting", "load", "want"),
    [
        (2, "auto", 0.2, 2),  # an idle 2-core machine
        (2, "auto", 1.0, 1),  # another job holds a core
        (2, "auto", 1.4, 1),  # a core more than half idle counts, less does not
        (2, "auto", 0.6, 1),
        (2, "auto", 0.4, 2),
        (2, "auto", 3.0, 1),  # a loaded machine: at least one
        (3, "auto", 0.0, 2),  # no more than the idle cores
        (1, "auto", 0.0, 1),  # no more than the jobs
        (0, "auto", 0.0, 1),
        (3, 2, 7.0, 2),  # a count is taken as it is (capped at the jobs), whatever the load
        (1, 4, 0.0, 1),
    ],
)
def test_choose_workers(jobs, setting, load, want):
    assert choose_workers(jobs, setting, cpus=2, load=load) == want


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "two", None])
def test_bad_worker_settings_name_the_setting(bad):
    with pytest.raises(ValueError, match=r"train_workers: expected a positive integer or 'auto'"):
        check_workers("train_workers", bad)
    with pytest.raises(ValueError, match=r"workers: expected"):
        choose_workers(2, bad)


def test_jobs_run_in_workers_in_order_with_the_thread_count_given():
    assert map_in_processes(math.pow, [(2, 3), (3, 2), (2, 0.5)], 2) == [8.0, 9.0, 2**0.5]
    assert map_in_processes(torch.get_num_threads, [(), ()], 2, threads=1) == [1, 1]


def test_a_worker_pool_keeps_its_processes_for_every_call():
    """Inside ``worker_pool(2)`` the calls that ask for 2 workers, or for as many as their
    jobs, run on the block's two processes (their imports paid once), a job's error is raised
    and the processes go on; the calls' results are those without the block."""
    with worker_pool(2):
        pids = set()
        for _ in range(3):
            pids.update(map_in_processes(os.getpid, [(), (), ()], 2))
        pids.update(map_in_processes(os.getpid, [(), ()], 3))  # 2 jobs: no more than 2 at once
        with pytest.raises(ValueError, match="math domain error"):
            map_in_processes(math.sqrt, [(-1.0,), (4.0,)], 2)
        assert map_in_processes(math.pow, [(2, 3), (3, 2), (2, 0.5)], 2) == [8.0, 9.0, 2**0.5]
        pids.update(map_in_processes(os.getpid, [(), ()], 2, threads=1))
        assert map_in_processes(torch.get_num_threads, [(), ()], 2, threads=1) == [1, 1]
    assert 1 <= len(pids) <= 2 and os.getpid() not in pids
    with worker_pool(1):  # keeps none: one worker runs the jobs here
        assert map_in_processes(os.getpid, [(), ()], 1) == [os.getpid()] * 2
    with pytest.raises(ValueError, match="workers: expected a positive integer, got 0"):
        with worker_pool(0):
            pass


def test_a_worker_that_dies_mid_job_fails_its_call_and_the_block_gets_fresh_workers():
    """A worker killed mid-job (here it exits) fails the call with a message naming the jobs;
    a kept pool is then renewed: the block's later calls run on new, working processes."""
    with worker_pool(2):
        before = set(map_in_processes(os.getpid, [(), ()], 2))
        with pytest.raises(BrokenProcessPool, match=r"ended abruptly .* the 2 jobs of _exit"):
            map_in_processes(os._exit, [(3,), (3,)], 2)
        assert map_in_processes(math.pow, [(2, 3), (3, 2)], 2) == [8.0, 9.0]
        after = set(map_in_processes(os.getpid, [(), ()], 2))
    assert not before & after and os.getpid() not in after
    with worker_pool(2):  # a worker killed between calls: the next call runs on fresh ones
        before = set(map_in_processes(os.getpid, [(), ()] * 4, 2))
        for pid in before:
            os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 15
        while any(_running(p) for p in before) and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(1.0)  # the pool's manager sees it (it wakes on the dead worker's sentinel)
        assert map_in_processes(math.pow, [(2, 3), (3, 2)], 2) == [8.0, 9.0]
    with pytest.raises(BrokenProcessPool, match="ended abruptly"):  # without a kept pool too
        map_in_processes(os._exit, [(3,), (3,)], 2)


def _running(pid: int) -> bool:
    """Whether process ``pid`` exists and has not ended (a zombie has ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes in /proc")
@pytest.mark.parametrize("kept", [True, False])
def test_workers_end_when_the_process_that_spawned_them_is_killed(kept):
    """``kill -9`` of a process mid-call ends its workers within seconds, not when their job
    (here ten minutes of sleep) would have ended; kept workers or a call's own."""
    code = (
        "import contextlib, os, time\n"
        "from rcvae_torchrl.processes import map_in_processes, worker_pool\n"
        f"with (worker_pool(2) if {kept} else contextlib.nullcontext()):\n"
        "    map_in_processes(os.getpid, [(), ()], 2)\n"
        "    map_in_processes(time.sleep, [(600,), (600,)], 2)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", code])
    pids: list[int] = []
    try:
        deadline = time.monotonic() + 120
        while len(pids) < 2 and time.monotonic() < deadline:  # both sleeping (or the first
            time.sleep(0.5)  # call's workers, ended by now when not kept)
            pids = [p for p in _children(parent.pid) if _running(p)]
        time.sleep(2.0)
        pids = [p for p in _children(parent.pid) if _running(p)]
        assert len(pids) == 2, "expected the call's two workers"
        parent.send_signal(signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 15
        while any(_running(p) for p in pids) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_running(p) for p in pids), "a worker outlived its parent"
    finally:
        parent.kill()
        parent.wait()
        for pid in pids:
            if _running(pid):
                os.kill(pid, signal.SIGKILL)


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` that run Python's multiprocessing spawn."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmd = (stat.parent / "cmdline").read_bytes()
        except (FileNotFoundError, ProcessLookupError):
            continue
        if int(fields[1]) == pid and b"spawn_main" in cmd:
            found.append(int(stat.parent.name))
    return found


def test_a_worker_s_library_lines_reach_the_caller_s_run_log(tmp_path):
    say = logging.getLogger("rcvae_torchrl.some_module").info  # pickles by the logger's name
    console = io.StringIO()
    with run_log(tmp_path / "run.log", stream=console):
        map_in_processes(say, [("job %d resumed", 1), ("job %d resumed", 2)], 2)
    lines = (tmp_path / "run.log").read_text().splitlines()
    assert sorted(line.split("] ", 1)[1] for line in lines) == ["job 1 resumed", "job 2 resumed"]
    assert all("[rcvae_torchrl.some_module][INFO]" in line for line in lines)
    assert console.getvalue() == ""  # a StringIO is not a stream a worker can reach
    assert log_targets() == []  # nothing is left attached after the block


def test_one_worker_runs_the_jobs_here():
    calls = []
    assert map_in_processes(lambda x: calls.append(x) or -x, [(1,), (2,)], 1) == [-1, -2]
    assert calls == [1, 2]  # a lambda does not pickle: it ran in this process


def test_a_job_error_is_raised_in_the_caller():
    with pytest.raises(ValueError, match="math domain error"):
        map_in_processes(math.sqrt, [(4.0,), (-1.0,)], 2)
    with pytest.raises(ValueError, match="workers: expected a positive int"):
        map_in_processes(math.sqrt, [(4.0,)], 0)


@pytest.mark.parametrize(
    ("code", "problem", "crashed"),
    [
        ("pass", None, False),
        ("import os\nos.abort()", "its process was ended by SIGABRT", True),
        (
            "import os, signal\nos.kill(os.getpid(), signal.SIGSEGV)",
            "its process was ended by SIGSEGV",
            True,
        ),
        ("raise ValueError('bad state')", "ValueError: bad state", False),
        ("import sys\nsys.exit(3)", "exit status 3", False),
        ("import time\ntime.sleep(30)", "it did not finish in 1 s", True),
    ],
)
def test_a_try_in_a_child_says_how_it_ended(code, problem, crashed):
    """What would end a process (a native crash, an abort) ends only the child."""
    from rcvae_torchrl.processes import try_in_a_child

    outcome = try_in_a_child(code, timeout=1.0 if "sleep" in code else 60.0)
    assert outcome.problem == problem and outcome.crashed is crashed


def test_a_try_in_a_child_has_this_import_path_and_arguments(tmp_path, monkeypatch):
    from rcvae_torchrl.processes import try_in_a_child

    (tmp_path / "only_here.py").write_text("import sys\nif sys.argv[1] != 'x y': sys.exit(9)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert try_in_a_child("import only_here", "x y", timeout=60.0).problem is None


def test_a_function_workers_cannot_import_is_refused_before_any_starts():
    with pytest.raises(TypeError, match=r"fn: expected a module-level function .* does not pickle"):
        map_in_processes(lambda x: x, [(1,), (2,)], 2)
    with pytest.raises(TypeError, match="jobs: expected a sequence of argument tuples"):
        map_in_processes(abs, ((i,) for i in range(2)), 2)
    with pytest.raises(ValueError, match="threads: expected a positive integer, got 0"):
        map_in_processes(abs, [(1,), (2,)], 2, threads=0)
    assert map_in_processes(abs, [(-1,)], 2) == [1]  # one job runs here, pickled or not


def test_counts_and_limits_of_another_kind_are_named():
    from rcvae_torchrl.processes import try_in_a_child
    from rcvae_torchrl.threads import free_cores

    with pytest.raises(ValueError, match="load: expected a load average >= 0, got nan"):
        free_cores(2, math.nan)
    with pytest.raises(ValueError, match="load: expected a load average >= 0, got -5"):
        free_cores(2, -5)
    with pytest.raises(ValueError, match="cpus: expected a positive integer, got 0"):
        free_cores(0, 0.5)
    with pytest.raises(ValueError, match="timeout: expected a positive number, got -1"):
        try_in_a_child("pass", timeout=-1)

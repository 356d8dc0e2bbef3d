"""What a run leaves for its user: files a teammate can read, a log file without colour codes."""

from __future__ import annotations

import io
import logging
import os
import warnings

import pytest
import torch

from rcvae_torchrl.io import atomic_write, load_torch, read_json, save_torch, write_json
from rcvae_torchrl.run_log import ANSI_CODE, run_log


@pytest.fixture
def umask():
    """Set the process umask for a test, then put the old one back."""
    saved = os.umask(0o022)
    os.umask(saved)

    def set_mask(mask: int) -> None:
        os.umask(mask)

    yield set_mask
    os.umask(saved)


@pytest.mark.parametrize(("mask", "mode"), [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_atomic_writes_keep_the_umask(tmp_path, umask, mask, mode):
    umask(mask)
    written = [
        atomic_write(tmp_path / "raw.bin", lambda f: f.write(b"x")),
        write_json(tmp_path / "a.json", {"a": 1}),
        save_torch(tmp_path / "t.pt", torch.zeros(2)),
        atomic_write(tmp_path / "raw.bin", lambda f: f.write(b"y")),  # replacing a file too
    ]
    assert {p.name: p.stat().st_mode & 0o777 for p in written} == {
        "raw.bin": mode,
        "a.json": mode,
        "t.pt": mode,
    }


def test_saved_videos_keep_the_umask(tmp_path, umask):
    np = pytest.importorskip("numpy")
    from rcvae_torchrl.envs.render import save_video

    umask(0o022)
    frames = [np.full((8, 8, 3), 40 * i, dtype=np.uint8) for i in range(3)]
    path = save_video(frames, tmp_path / "e.gif", fps=10)
    assert path.stat().st_mode & 0o777 == 0o644
    assert path.read_bytes()[:6] == b"GIF89a"
    assert [p.name for p in tmp_path.iterdir()] == ["e.gif"]  # no temp file left


def test_run_log_is_plain_in_the_file_and_off_a_terminal(tmp_path):
    console = io.StringIO()  # not a terminal
    torchrl_logger = logging.getLogger("torchrl")
    torchrl_console = io.StringIO()
    extra = logging.StreamHandler(torchrl_console)
    extra.setFormatter(logging.Formatter("\033[92m%(name)s\033[0m %(message)s"))
    torchrl_logger.addHandler(extra)
    try:
        with run_log(tmp_path / "run.log", stream=console) as log:
            log.info("\033[92m[data]\033[0m running")
            torchrl_logger.info("a torchrl line")
            with warnings.catch_warnings():
                warnings.simplefilter("always")
                warnings.warn("model check failed for ball_x", UserWarning, stacklevel=1)
        with run_log(tmp_path / "run.log", stream=console) as log:
            log.info("second run")
        torchrl_logger.info("after the block")
    finally:
        torchrl_logger.removeHandler(extra)
    text = (tmp_path / "run.log").read_text()
    lines = text.splitlines()
    assert not ANSI_CODE.search(text)
    assert lines[0].endswith("[rcvae_torchrl.run][INFO] [data] running")
    assert lines[1].endswith("[torchrl][INFO] a torchrl line")
    assert "model check failed for ball_x" in lines[2]
    assert lines[-1].endswith("second run")  # appended, not overwritten
    assert "after the block" not in text  # the handlers are removed on exit
    assert console.getvalue().splitlines()[:1] == ["[data] running"]
    inside, after = torchrl_console.getvalue().splitlines()
    assert inside.endswith("[torchrl][INFO] a torchrl line")  # colourless off a terminal
    assert after == "\033[92mtorchrl\033[0m after the block"  # its own format restored
    assert (tmp_path / "run.log").stat().st_mode & 0o777 == 0o666 & ~_current_umask()


def test_the_library_s_lines_reach_the_run_log_and_levels_are_put_back(tmp_path):
    console = io.StringIO()
    package, module = logging.getLogger("rcvae_torchrl"), logging.getLogger("rcvae_torchrl.x.y")
    before = package.level, package.propagate
    with run_log(tmp_path / "run.log", stream=console):
        module.info("resuming from c.pt at step 30 of 40")
        module.debug("not at INFO")
    module.info("after the block")
    text = (tmp_path / "run.log").read_text()
    assert text.count("resuming") == 1  # once, not once per handler or logger
    assert text.splitlines()[0].endswith(
        "[rcvae_torchrl.x.y][INFO] resuming from c.pt at step 30 of 40"
    )
    assert "not at INFO" not in text and "after the block" not in text
    assert console.getvalue() == "resuming from c.pt at step 30 of 40\n"
    assert (package.level, package.propagate) == before
    with run_log(tmp_path / "own.log", name="rcvae_torchrl", stream=io.StringIO()) as log:
        log.info("one line")  # the package's own logger named: its handlers added once
    assert (tmp_path / "own.log").read_text().count("one line") == 1


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_terminal_keeps_its_colours(tmp_path):
    console = _Terminal()
    with run_log(tmp_path / "run.log", stream=console) as log:
        log.info("\033[92mgreen\033[0m")
    assert console.getvalue() == "\033[92mgreen\033[0m\n"
    assert (tmp_path / "run.log").read_text().endswith(" green\n")


def test_the_log_keeps_why_a_run_stopped(tmp_path):
    """A trial: after a crash and after Ctrl-C, run.log ended at '[forecast] running', with no
    traceback and no word of the interruption."""
    path = tmp_path / "run.log"
    with pytest.raises(ValueError, match="no bins"):
        with run_log(path, stream=io.StringIO()) as log:
            log.info("[forecast] running")
            raise ValueError("no bins")
    text = path.read_text()
    assert "[rcvae_torchrl.run][ERROR] failed: ValueError: no bins\nTraceback" in text
    assert text.rstrip().endswith("ValueError: no bins")
    with pytest.raises(KeyboardInterrupt):
        with run_log(path, stream=io.StringIO()):
            raise KeyboardInterrupt
    assert (
        path.read_text()
        .rstrip()
        .endswith("[WARNING] interrupted (KeyboardInterrupt): the run stopped here")
    )
    with pytest.raises(SystemExit):  # a clean exit is no failure
        with run_log(path, stream=io.StringIO()):
            raise SystemExit(0)
    assert path.read_text().rstrip().endswith("the run stopped here")


def test_a_folder_or_a_damaged_file_is_named_as_what_it_is(tmp_path):
    from rcvae_torchrl.io import StoredFileError, load_torch

    with pytest.raises(IsADirectoryError, match=r"is a directory; expected the path of a file"):
        save_torch(tmp_path, {"a": 1})
    assert list(tmp_path.iterdir()) == []  # no temp file left beside it
    with pytest.raises(StoredFileError, match=r"the model '.*': is a directory, expected a file"):
        load_torch(tmp_path, "the model")
    damaged = tmp_path / "damaged.pt"
    damaged.write_bytes(bytes(range(256)) * 2)
    with pytest.raises(StoredFileError, match=r"is not a torch file, or its start is damaged"):
        load_torch(damaged)
    zipped = tmp_path / "zipped.pt"
    zipped.write_bytes(b"PK\x03\x04" + bytes(range(256)) * 2)  # a zip's start, then damage
    with pytest.raises(StoredFileError, match=r"is truncated or corrupt \(516 bytes\)") as err:
        load_torch(zipped)
    assert "weights_only" not in str(err.value)  # torch's advice to load it unsafely is dropped


def test_a_torch_file_of_other_objects_is_named_another_kind_of_file(tmp_path):
    from tensordict import TensorDict

    from rcvae_torchrl.io import StoredFileError
    from rcvae_torchrl.training import CheckpointError, load_ensemble

    episodes = tmp_path / "episodes.pt"
    torch.save(TensorDict({"observation": torch.zeros(3, 2)}, batch_size=[3]), episodes)
    with pytest.raises(
        CheckpointError,
        match=r"^checkpoint '.*episodes\.pt' is another kind of file: a torch file holding "
        r"tensordict\._reductions\._make_td objects, which are not loaded .*; expected one "
        r"saved by this library$",
    ) as err:
        load_ensemble(episodes)
    assert isinstance(err.value, StoredFileError)
    assert "add_safe_globals" not in str(err.value)  # no advice to load it unsafely


def test_a_tensordict_given_to_save_torch_is_refused_naming_save_episodes(tmp_path):
    """A torchrun trial saved collected episodes with save_torch: written whole, then refused
    by load_torch as "another kind of file"."""
    from tensordict import TensorDict

    from rcvae_torchrl.data import load_episodes, save_episodes
    from rcvae_torchrl.io import StoredFileError

    episodes = TensorDict({"observation": torch.zeros(4, 2)}, batch_size=[4])
    with pytest.raises(
        TypeError,
        match=r"^obj: expected plain tensors, .* got a TensorDict, .*data\.save_episodes",
    ):
        save_torch(tmp_path / "episodes.pt", episodes)
    assert list(tmp_path.iterdir()) == []  # nothing written
    path = save_episodes(episodes, tmp_path / "episodes.pt")
    assert torch.equal(load_episodes(path)["observation"], episodes["observation"])
    # another file of this library, or a bare tensor, is named as what it is
    save_torch(tmp_path / "model.pt", {"kind": "rcvae_ensemble", "state_dict": {}})
    with pytest.raises(
        StoredFileError,
        match=r"expected what save_episodes writes, a dict of 'batch_size' and 'data', got a dict "
        r"of \['kind', 'state_dict'\] \(a 'rcvae_ensemble' file\)",
    ):
        load_episodes(tmp_path / "model.pt")
    save_torch(tmp_path / "tensor.pt", torch.zeros(3))
    with pytest.raises(StoredFileError, match=r"'batch_size' and 'data', got a Tensor$"):
        load_episodes(tmp_path / "tensor.pt")


def test_json_files_are_strict_and_read_back_their_non_finite_floats(tmp_path):
    """A NaN or an infinity is written as a string (Python's bare NaN is no JSON: strict
    parsers refuse the whole file) and read back as the float."""
    import json
    import math

    record = {"gap": math.nan, "ratios": [1.5, math.inf, -math.inf], "name": "x", "none": None}
    path = write_json(tmp_path / "summary.json", record)
    text = path.read_text()
    json.loads(text, parse_constant=lambda c: pytest.fail(f"bare {c} in the file"))
    assert json.loads(text)["ratios"] == [1.5, "Infinity", "-Infinity"]
    back = read_json(path)
    assert math.isnan(back["gap"]) and back["ratios"] == [1.5, math.inf, -math.inf]
    assert back["name"] == "x" and back["none"] is None
    (tmp_path / "old.json").write_text('{"gap": NaN}')  # files written before: read as they were
    assert math.isnan(read_json(tmp_path / "old.json")["gap"])


def test_a_temp_file_left_by_a_writer_killed_mid_save_is_removed_by_the_next_save(tmp_path):
    """A trial killed a process (kill -9) while save_torch wrote: the destination stayed whole,
    and a hidden temp file stayed beside it for good."""
    import signal
    import subprocess
    import sys
    import time

    from rcvae_torchrl.io import _temp_start, load_torch, save_torch

    path = tmp_path / "model.pt"
    save_torch(path, {"w": torch.zeros(3)})
    writer = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\n"
            "from rcvae_torchrl.io import atomic_write\n"
            "atomic_write(sys.argv[1], lambda f: (f.write(b'part'), f.flush(), time.sleep(60)))",
            str(path),
        ]
    )
    start = f"{_temp_start(path)}{writer.pid}."
    for _ in range(600):  # until its temp file is there
        left = [p for p in tmp_path.iterdir() if p.name.startswith(start)]
        if left:
            break
        time.sleep(0.05)
    assert left, "the writer made no temp file"
    # one of a process still running (this one's parent) is not touched
    alive = tmp_path / f"{_temp_start(path)}{os.getppid()}.abc.tmp"
    alive.write_bytes(b"x")
    other_host = tmp_path / ".model.pt.elsewhere-1.abc.tmp"  # another machine's: its own
    other_host.write_bytes(b"x")
    writer.send_signal(signal.SIGKILL)
    writer.wait()
    assert left[0].exists() and torch.equal(load_torch(path)["w"], torch.zeros(3))
    save_torch(path, {"w": torch.ones(3)})
    assert not left[0].exists() and alive.exists() and other_host.exists()
    assert torch.equal(load_torch(path)["w"], torch.ones(3))


def test_a_long_name_a_shared_folder_and_another_pid_namespace_do_not_stop_a_write(
    tmp_path, monkeypatch
):
    """A trial: a 238-character name (which the file system holds) no longer fitted its temp
    file's; another user's dead writer's temp in a sticky folder made every write fail; a
    container's writer (the same host name, another pid namespace) took the host's live
    writers for dead ones."""
    import socket
    from pathlib import Path

    from rcvae_torchrl import io as rio

    long = tmp_path / ("x" * 238 + ".pt")
    rio.save_torch(long, {"w": torch.ones(1)})
    assert torch.equal(rio.load_torch(long)["w"], torch.ones(1))
    path = tmp_path / "shared.json"
    start = rio._temp_start(path)
    assert rio._PID_NAMESPACE in start
    # another namespace's temp, whatever its pid, is not this one's to judge
    other = tmp_path / f".shared.json.{socket.gethostname()[:40]}.1-999999.abcd.tmp"
    other.write_bytes(b"x")
    dead = tmp_path / f"{start}999999.abcd.tmp"  # no such process here
    dead.write_bytes(b"x")
    real_unlink = Path.unlink

    def refused(self, *args, **kwargs):  # another user's file in a sticky folder
        if self == dead:
            raise PermissionError(1, "Operation not permitted", str(self))
        return real_unlink(self, *args, **kwargs)

    monkeypatch.setattr(Path, "unlink", refused)
    write_json(path, {"a": 1})  # the cleanup could not remove it: the write goes ahead
    assert dead.exists() and other.exists() and read_json(path) == {"a": 1}
    monkeypatch.setattr(Path, "unlink", real_unlink)
    write_json(path, {"a": 2})
    assert not dead.exists() and other.exists() and read_json(path) == {"a": 2}


def test_what_would_not_read_back_is_refused_by_name(tmp_path):
    with pytest.raises(TypeError, match=r"obj: expected str keys .* \(1, 2\)"):
        write_json(tmp_path / "a.json", {(1, 2): 3})
    with pytest.raises(TypeError, match=r"obj\['a'\]: .* got a set"):
        write_json(tmp_path / "a.json", {"a": {1, 2}})
    with pytest.raises(TypeError, match="got a Linear module, which load_torch would refuse"):
        save_torch(tmp_path / "m.pt", torch.nn.Linear(2, 2))
    with pytest.raises(TypeError, match=r"obj\['net'\]: .* Linear module"):
        save_torch(tmp_path / "m.pt", {"net": torch.nn.Linear(2, 2)})
    assert not (tmp_path / "m.pt").exists()
    save_torch(tmp_path / "ok.pt", {"a": torch.ones(2)})
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="map_location: expected a device of this machine"):
            load_torch(tmp_path / "ok.pt", map_location="cuda")


def test_an_empty_torch_file_and_settings_that_are_not_a_mapping_are_named(tmp_path):
    from rcvae_torchrl.io import StoredFileError, record_run_config

    (tmp_path / "empty.pt").write_bytes(b"")
    with pytest.raises(StoredFileError, match=r"\(0 bytes\): the file is empty"):
        load_torch(tmp_path / "empty.pt")
    with pytest.raises(
        TypeError, match="config: expected a mapping of the run's settings, got int"
    ):
        record_run_config(tmp_path / "c.json", 5)


def test_a_stream_without_write_is_refused_naming_stream(tmp_path):
    """``stream="stdout"`` was taken, then every line printed ``--- Logging error ---``."""
    with pytest.raises(TypeError, match=r"^stream: expected a text stream .* got str 'stdout'"):
        with run_log(tmp_path / "run.log", stream="stdout"):
            pass
    assert not (tmp_path / "run.log").exists()


@pytest.mark.parametrize(
    "targets",
    [
        [("bogus", "x", None)],
        [("stream", "x", None)],
        [("file", None, None)],
        [("stream", "stdout", "not a formatter")],
        [("stream", "stdout")],
    ],
)
def test_forwarded_log_names_a_target_it_cannot_write_to(targets):
    from rcvae_torchrl.run_log import forwarded_log

    before = list(logging.getLogger("rcvae_torchrl").handlers)
    with pytest.raises(ValueError, match=r"^targets\[0\]: expected \(kind, where, formatter\)"):
        with forwarded_log(targets):
            pass
    with pytest.raises(TypeError, match=r"^targets: expected a list of"):
        with forwarded_log(None):
            pass
    assert logging.getLogger("rcvae_torchrl").handlers == before  # no handler was made

"""Stage markers record and re-verify their files; one loader for every stored file."""

from __future__ import annotations

import json

import pytest
import torch

from rcvae_torchrl.io import StoredFileError, load_torch, read_json, save_torch, write_json
from rcvae_torchrl.stages import StageError, StageRunner, file_record


class Pipeline:
    """Two stages: ``make`` writes a/x.pt and a/y.pt (skipping existing ones), ``use`` sums them
    into b/z.pt. Counts how often each file is computed."""

    def __init__(self, run_dir, value: float = 1.0):
        self.dir, self.value, self.computed = run_dir, value, []

    def make(self):
        for name in ("x", "y"):
            path = self.dir / "a" / f"{name}.pt"
            if not path.is_file():
                self.computed.append(name)
                save_torch(path, torch.full((3,), self.value))
        return {"n": 2}

    def use(self):
        total = sum(load_torch(self.dir / "a" / f"{n}.pt", "input").sum() for n in ("x", "y"))
        self.computed.append("z")
        save_torch(self.dir / "b" / "z.pt", total)
        return {"total": float(total)}

    def run(self, settings=None):
        lines = []
        runner = StageRunner(self.dir, lines.append, settings=settings or {"seed": 0})
        runner.run("make", self.make, ("a/*.pt",))
        runner.run("use", self.use, ("b/*.pt",))
        return runner, lines


def test_markers_record_size_and_sha256_of_every_output(tmp_path):
    runner, _ = Pipeline(tmp_path).run()
    marker = json.loads((tmp_path / "stages" / "make.json").read_text())
    assert marker["n"] == 2 and set(marker["outputs"]) == {"a/x.pt", "a/y.pt"}
    assert marker["outputs"]["a/x.pt"] == file_record(tmp_path / "a" / "x.pt")
    assert marker["outputs"]["a/x.pt"]["bytes"] == (tmp_path / "a" / "x.pt").stat().st_size
    assert runner.summaries["use"]["total"] == 6.0
    assert "outputs" not in runner.summaries["use"]


def test_a_clean_rerun_reuses_every_stage(tmp_path):
    Pipeline(tmp_path).run()
    again = Pipeline(tmp_path)
    runner, lines = again.run()
    assert again.computed == [] and runner.summaries["use"]["total"] == 6.0
    assert all("files verified" in line for line in lines)


@pytest.mark.parametrize(
    ("damage", "why"),
    [
        (lambda p: p.write_bytes(b"garbage"), "size changed"),
        (lambda p: p.write_bytes(p.read_bytes()[:-10]), "size changed"),
        (lambda p: p.unlink(), "the file is missing"),
        (lambda p: p.write_bytes(bytes(b ^ 1 for b in p.read_bytes())), "SHA-256 differs"),
    ],
    ids=["garbage", "truncated", "deleted", "same-size-flip"],
)
def test_a_damaged_output_is_recomputed_with_a_log_line(tmp_path, damage, why):
    Pipeline(tmp_path).run()
    before = (tmp_path / "a" / "x.pt").read_bytes()
    damage(tmp_path / "a" / "x.pt")
    again = Pipeline(tmp_path)
    runner, lines = again.run()
    assert again.computed == ["x"]  # y is reused; z's inputs are unchanged, so it is too
    assert (tmp_path / "a" / "x.pt").read_bytes() == before
    assert any(line.startswith("[make] a/x.pt: ") and why in line for line in lines)
    assert runner.summaries["use"]["total"] == 6.0


def test_downstream_stages_rerun_when_a_recomputed_input_differs(tmp_path):
    Pipeline(tmp_path).run()
    (tmp_path / "a" / "x.pt").unlink()
    again = Pipeline(tmp_path, value=2.0)  # the recomputed file comes out different
    runner, lines = again.run()
    assert again.computed == ["x", "z"]
    assert runner.summaries["use"]["total"] == 9.0
    assert any("[use] its inputs changed" in line for line in lines)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "delete", "not-a-dict"])
def test_a_damaged_marker_reruns_its_stage(tmp_path, damage):
    Pipeline(tmp_path).run()
    marker = tmp_path / "stages" / "make.json"
    text = marker.read_text()
    if damage == "truncate":
        marker.write_text(text[: len(text) // 2])
    elif damage == "garbage":
        marker.write_bytes(b"\xff\x00garbage")
    elif damage == "not-a-dict":
        marker.write_text("[1, 2]")
    else:
        marker.unlink()
    again = Pipeline(tmp_path)
    runner, lines = again.run()
    assert again.computed == []  # its files are intact, so the stage function reuses them
    assert runner.summaries["use"]["total"] == 6.0
    assert json.loads(marker.read_text())["outputs"].keys() == {"a/x.pt", "a/y.pt"}
    if damage != "delete":
        assert any("[make] marker of stage 'make'" in line for line in lines)


def test_a_stage_that_reads_markers_is_not_stopped_by_its_own_damaged_one(tmp_path):
    """An unreadable marker is removed before its stage runs again (a report stage may read
    every marker present)."""
    runner = StageRunner(tmp_path, lambda line: None)
    runner.run("report", lambda: {"n": len(list((tmp_path / "stages").glob("*.json")))})
    runner.marker("report").write_text("{trunc")
    again = StageRunner(tmp_path, lambda line: None)
    reads = lambda: {"n": len([read_json(p) for p in (tmp_path / "stages").glob("*.json")])}  # noqa: E731
    assert again.run("report", reads)["n"] == 0


@pytest.mark.parametrize("damage", ["truncate", "delete"])
def test_a_damaged_run_config_is_written_again(tmp_path, damage):
    Pipeline(tmp_path).run()
    path = tmp_path / "study_config.json"
    if damage == "truncate":
        path.write_text(path.read_text()[:5])
    else:
        path.unlink()
    again = Pipeline(tmp_path)
    _, lines = again.run()
    assert again.computed == [] and read_json(path) == {"seed": 0}
    assert (damage == "truncate") == any("[settings] run config" in line for line in lines)


def test_other_settings_are_refused_and_a_lost_config_reruns_everything(tmp_path):
    Pipeline(tmp_path).run()
    with pytest.raises(
        ValueError, match=r"other settings \(\['seed'\] differ: seed: 0 recorded, 1 now\)"
    ):
        Pipeline(tmp_path).run({"seed": 1})
    with pytest.raises(
        ValueError,
        match=r"differ: seed: 0 recorded, None now; train: None recorded, \{'lr': 0.1\} now\)",
    ):
        Pipeline(tmp_path).run({"train": {"lr": 0.1}})
    (tmp_path / "study_config.json").unlink()  # the markers still know the old settings
    again = Pipeline(tmp_path)
    _, lines = again.run({"seed": 1})
    assert again.computed == ["x", "y", "z"]
    assert any("[make] its inputs changed" in line for line in lines)


def test_an_unreadable_file_of_the_stage_itself_is_remade(tmp_path):
    pipeline = Pipeline(tmp_path)
    (tmp_path / "b").mkdir()
    pipeline.make()
    (tmp_path / "stages").mkdir()
    (tmp_path / "a" / "x.pt").write_bytes(b"garbage")  # no marker yet: found while running
    runner = StageRunner(tmp_path, (lines := []).append)

    def use_own():  # a stage that resumes from a file of its own (a checkpoint)
        path = tmp_path / "a" / "x.pt"
        if not path.is_file():
            save_torch(path, torch.zeros(3))
        return {"sum": float(load_torch(path, "checkpoint").sum())}

    assert runner.run("own", use_own, ("a/*.pt",))["sum"] == 0.0
    assert any("removing it and running the stage again" in line for line in lines)
    assert load_torch(tmp_path / "a" / "x.pt").shape == (3,)


def test_an_unreadable_input_of_another_stage_is_a_named_refusal(tmp_path):
    Pipeline(tmp_path).make()
    (tmp_path / "a" / "x.pt").write_bytes(b"garbage")
    runner = StageRunner(tmp_path, lambda line: None)
    with pytest.raises(StageError) as info:
        runner.run("use", Pipeline(tmp_path).use, ("b/*.pt",))
    message = str(info.value)
    assert "stage 'use'" in message and str(tmp_path / "a" / "x.pt") in message
    assert "Delete that file" in message
    assert not (tmp_path / "stages" / "use.json").exists()


# --------------------------------------------------------------------------- one loader
@pytest.mark.parametrize("payload", [b"", b"{", b"\xff\xfe", b'{"a": 1'])
def test_read_json_names_the_file(tmp_path, payload):
    path = tmp_path / "m.json"
    path.write_bytes(payload)
    with pytest.raises(StoredFileError, match="truncated or corrupt") as info:
        read_json(path, "marker")
    assert info.value.path == path and str(path) in str(info.value)


@pytest.mark.parametrize("cut", [0, 10, 100, -1])
def test_load_torch_names_the_file(tmp_path, cut):
    path = tmp_path / "t.pt"
    save_torch(path, {"x": torch.arange(100)})
    path.write_bytes(path.read_bytes()[:cut])
    with pytest.raises(StoredFileError, match="truncated or corrupt") as info:
        load_torch(path, "tensor file")
    assert info.value.path == path and str(path) in str(info.value)


def test_missing_files_are_named(tmp_path):
    for load in (read_json, load_torch):
        with pytest.raises(StoredFileError, match="the file is missing") as info:
            load(tmp_path / "nope")
        assert info.value.path == tmp_path / "nope"
    write_json(tmp_path / "ok.json", {"a": 1})
    assert read_json(tmp_path / "ok.json") == {"a": 1}


@pytest.mark.parametrize("damage", ["truncate", "delete"])
def test_an_unfinished_stage_of_unknown_settings_leaves_nothing_to_reuse(tmp_path, damage):
    """A stage killed before its marker, then the settings record lost and the settings
    changed: the stage's files may come from the old settings, so none of them is kept."""
    Pipeline(tmp_path, value=1.0).run({"value": 1.0})
    (tmp_path / "stages" / "make.json").unlink()  # as if killed before the marker
    (tmp_path / "stages" / "use.json").unlink()
    path = tmp_path / "study_config.json"
    path.write_text("{trunc") if damage == "truncate" else path.unlink()
    again = Pipeline(tmp_path, value=2.0)
    runner, lines = again.run({"value": 2.0})
    assert again.computed == ["x", "y", "z"] and runner.summaries["use"]["total"] == 12.0
    assert any("removing the 2 files the unfinished stage left" in line for line in lines)
    # with the record intact the unfinished stage resumes from its files, as before
    (tmp_path / "stages" / "make.json").unlink()
    resumed = Pipeline(tmp_path, value=2.0)
    resumed.run({"value": 2.0})
    assert resumed.computed == []

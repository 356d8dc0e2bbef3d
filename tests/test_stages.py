"""Stage markers record and re-verify their files; one loader for every stored file."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from rcvae_torchrl.io import StoredFileError, load_torch, read_json, save_torch, write_json
from rcvae_torchrl.stages import (
    SET_ASIDE,
    StageError,
    StageRunner,
    check_run_directory,
    file_record,
)


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

    def run(self, settings=None, **kwargs):
        lines = []
        runner = StageRunner(self.dir, lines.append, settings=settings or {"seed": 0}, **kwargs)
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
    damaged = (tmp_path / "a" / "x.pt").read_bytes() if (tmp_path / "a" / "x.pt").exists() else None
    again = Pipeline(tmp_path)
    runner, lines = again.run()
    assert again.computed == ["x"]  # y is reused; z's inputs are unchanged, so it is too
    assert (tmp_path / "a" / "x.pt").read_bytes() == before
    assert any(line.startswith("[make] a/x.pt: ") and why in line for line in lines)
    assert runner.summaries["use"]["total"] == 6.0
    aside = list((tmp_path / SET_ASIDE).glob("*/a/x.pt"))
    if damaged is None:
        assert aside == []
    else:  # moved aside, not deleted: it may hold the user's own edits
        assert [p.read_bytes() for p in aside] == [damaged]
        line = next(line for line in lines if line.startswith("[make] a/x.pt: "))
        assert line.endswith(
            f"; set aside as {aside[0].relative_to(tmp_path)}; running the stage again"
        )


def test_outputs_edited_by_hand_are_set_aside_when_their_stage_reruns_for_new_inputs(tmp_path):
    Pipeline(tmp_path).run()
    (tmp_path / "b" / "z.pt").write_bytes(b"my own notes")
    (tmp_path / "a" / "x.pt").unlink()
    again = Pipeline(tmp_path, value=2.0)  # x comes out different: use's inputs change
    runner, lines = again.run()
    assert again.computed == ["x", "z"] and runner.summaries["use"]["total"] == 9.0
    (kept,) = (tmp_path / SET_ASIDE).glob("*/b/z.pt")
    assert kept.read_bytes() == b"my own notes"
    assert any(line.startswith("[use] b/z.pt: its size changed") for line in lines)
    Pipeline(tmp_path).run()  # a later run's changes go to a folder of their own
    (tmp_path / "b" / "z.pt").write_bytes(b"more notes")
    Pipeline(tmp_path).run()
    assert sorted(p.read_bytes() for p in (tmp_path / SET_ASIDE).glob("*/b/z.pt")) == [
        b"more notes",
        b"my own notes",
    ]


def test_a_file_of_the_users_beside_a_stages_outputs_is_never_taken_for_one(tmp_path):
    """A file put where a stage's patterns match (``b/*.pt``) is not recorded as the stage's
    when it runs again, so a later rerun, which removes the stage's files, leaves it."""
    Pipeline(tmp_path).run()
    (tmp_path / "b" / "mine.pt").write_bytes(b"my own model")
    for value in (2.0, 3.0):  # each time x comes out different: use's inputs change
        (tmp_path / "a" / "x.pt").unlink()
        again = Pipeline(tmp_path, value=value)
        _, lines = again.run()
        assert again.computed == ["x", "z"] and any("[use] its inputs changed" in x for x in lines)
        marker = json.loads((tmp_path / "stages" / "use.json").read_text())
        assert set(marker["outputs"]) == {"b/z.pt"}
        assert (tmp_path / "b" / "mine.pt").read_bytes() == b"my own model"
    assert not (tmp_path / SET_ASIDE).exists()
    assert not list((tmp_path / "stages").glob("*.started"))  # journals go with the markers


def test_a_stage_resumed_after_an_interrupted_attempt_says_so_and_keeps_the_users_files(tmp_path):
    """An attempt killed half-way leaves the stage's journal: the next attempt keeps its list of
    the files that were there before the first (never the stage's), and the marker and the log
    say which attempt finished (the time of the killed one is not known)."""
    Pipeline(tmp_path).run()  # a run's directory, its settings recorded
    for stage in ("make", "use"):  # run again: their markers deleted (their records kept)
        (tmp_path / "stages" / f"{stage}.json").unlink()
    for name in ("x", "y"):
        (tmp_path / "a" / f"{name}.pt").unlink()
    (tmp_path / "a" / "mine.pt").write_bytes(b"mine")
    pipeline = Pipeline(tmp_path)
    first = pipeline.make

    def killed():
        save_torch(tmp_path / "a" / "x.pt", torch.ones(3))  # then the process dies
        raise KeyboardInterrupt

    pipeline.make = killed
    with pytest.raises(KeyboardInterrupt):
        pipeline.run()
    journal = read_json(tmp_path / "stages" / "make.started", checksum=True)
    assert journal["attempts"] == 1 and set(journal["foreign"]) == {"a/mine.pt"}
    pipeline.make = first
    _, lines = pipeline.run()
    assert pipeline.computed == ["y", "z"]  # x was written by the killed attempt
    marker = json.loads((tmp_path / "stages" / "make.json").read_text())
    assert marker["attempts"] == 2 and set(marker["outputs"]) == {"a/x.pt", "a/y.pt"}
    assert "[make] running (attempt 2: resuming from what the earlier ones wrote)" in lines
    assert any(x.endswith("(attempt 2; the earlier attempts' time is not counted)") for x in lines)
    assert "attempts" not in json.loads((tmp_path / "stages" / "use.json").read_text())
    assert not (tmp_path / "stages" / "make.started").exists()
    assert (tmp_path / "a" / "mine.pt").read_bytes() == b"mine"
    # with no record of the stage left (stages/ deleted), nothing tells its files from others
    shutil.rmtree(tmp_path / "stages")
    Pipeline(tmp_path).run()
    marker = json.loads((tmp_path / "stages" / "make.json").read_text())
    assert set(marker["outputs"]) == {"a/mine.pt", "a/x.pt", "a/y.pt"}


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
        (aside,) = (tmp_path / SET_ASIDE).glob("*/stages/make.json")  # kept, not deleted
        assert any(
            line.endswith(f"set aside as {aside.relative_to(tmp_path)}; running the stage again")
            for line in lines
        )


def test_a_marker_edited_by_hand_reruns_its_stage_and_a_marker_from_before_checksums_holds(
    tmp_path,
):
    """A number changed in a marker would be reported as the stage's own: its checksum tells
    it, the stage runs again (its files are intact, so it reuses them) and the summary is the
    stage's."""
    Pipeline(tmp_path).run()
    marker = tmp_path / "stages" / "use.json"
    saved = json.loads(marker.read_text())
    assert len(saved["content_sha256"]) == 64  # the SHA-256 of the rest
    marker.write_text(json.dumps({**saved, "total": 60.0}, indent=2))
    again = Pipeline(tmp_path)
    runner, lines = again.run()
    assert again.computed == ["z"] and runner.summaries["use"]["total"] == 6.0
    assert any(
        line.startswith("[use] marker of stage 'use'")
        and "its content changed since it was written" in line
        for line in lines
    )
    assert "content_sha256" not in runner.summaries["use"]
    old = {k: v for k, v in json.loads(marker.read_text()).items() if k != "content_sha256"}
    marker.write_text(json.dumps(old))  # as markers were written before their checksums
    third = Pipeline(tmp_path)
    runner, lines = third.run()
    assert third.computed == [] and runner.summaries["use"]["total"] == 6.0


def test_json_checksums_hold_through_non_finite_floats_and_tuples_and_name_a_change(tmp_path):
    path = tmp_path / "f.json"
    write_json(path, {"a": float("nan"), "b": (1, 2.5), "c": {"d": float("inf")}}, checksum=True)
    back = read_json(path, "the file", checksum=True)
    assert back["b"] == [1, 2.5] and back["c"]["d"] == float("inf") and back["a"] != back["a"]
    assert "content_sha256" not in back
    path.write_text(path.read_text().replace("2.5", "2.75"))
    # checked by default (a trial's edit read back unchecked without checksum=True)
    with pytest.raises(StoredFileError, match=r"the file .*f\.json': its content changed"):
        read_json(path, "the file")
    with pytest.raises(StoredFileError, match=r"the file .*f\.json': its content changed"):
        read_json(path, "the file", checksum=True)
    unchecked = read_json(path, checksum=False)  # to look at it: as it is, the entry kept
    assert unchecked["b"] == [1, 2.75] and len(unchecked["content_sha256"]) == 64
    # a user's own JSON with an entry of that name: the refusal says how to read it
    own = tmp_path / "own.json"
    own.write_text('{"content_sha256": "my hash", "x": 1}')
    with pytest.raises(StoredFileError, match=r"not written by this library.*checksum=False"):
        read_json(own)
    assert read_json(own, checksum=False) == {"content_sha256": "my hash", "x": 1}
    with pytest.raises(TypeError, match="obj: expected a dict to checksum, got list"):
        write_json(path, [1, 2], checksum=True)


def test_tensors_and_records_are_refused_where_they_would_not_read_back(tmp_path):
    """A trial's team wrote a check and real outcomes with write_json: a check became its
    printed form, and long tensors were elided; save_torch of a check wrote a file load_torch
    then refused. Both are refused when written, by name, nothing written."""
    from rcvae_torchrl.training import OutcomeCheck

    check = OutcomeCheck.from_outcomes(torch.full((3,), 0.5), torch.ones(3, 2, dtype=torch.bool))
    said = r"^obj: expected plain values, got a OutcomeCheck; write_json its \.as_dict\(\)"
    with pytest.raises(TypeError, match=said):
        write_json(tmp_path / "check.json", check)
    with pytest.raises(TypeError, match=r"^obj\['success'\]: expected JSON values .*a tensor of"):
        write_json(tmp_path / "real.json", {"success": torch.ones(2000, dtype=torch.bool)})
    with pytest.raises(TypeError, match=r"^obj: expected plain values, got a OutcomeCheck; save"):
        save_torch(tmp_path / "check.pt", check)
    with pytest.raises(TypeError, match=r"^obj\['check'\]: expected plain values"):
        save_torch(tmp_path / "checks.pt", {"check": check})
    assert not list(tmp_path.iterdir())
    write_json(tmp_path / "check.json", check.as_dict())  # its plain form reads back
    again = OutcomeCheck.from_dict(read_json(tmp_path / "check.json"))
    assert again.verdict == check.verdict


def test_a_stage_run_again_by_deleting_its_marker_sets_aside_files_edited_since(tmp_path):
    """The way to run a stage again is to delete its marker: its files edited since it wrote
    them (a note added to a report) are set aside, not overwritten; the others are reused."""
    Pipeline(tmp_path).run()
    (tmp_path / "b" / "z.pt").write_bytes(b"my notes")
    (tmp_path / "stages" / "use.json").unlink()
    again = Pipeline(tmp_path)
    runner, lines = again.run()
    assert again.computed == ["z"] and runner.summaries["use"]["total"] == 6.0
    (kept,) = (tmp_path / SET_ASIDE).glob("*/b/z.pt")
    assert kept.read_bytes() == b"my notes"
    assert any(
        line.startswith("[use] b/z.pt: changed since the stage last wrote it (its size changed")
        for line in lines
    )
    (tmp_path / "stages" / "make.json").unlink()  # its files unchanged: reused, nothing set aside
    third = Pipeline(tmp_path)
    runner, lines = third.run()
    assert third.computed == [] and not list((tmp_path / SET_ASIDE).glob("*/a/*"))
    assert "[use] done earlier" in " ".join(lines)


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
    damaged = path.read_text() if path.exists() else None
    again = Pipeline(tmp_path)
    _, lines = again.run()
    assert again.computed == [] and read_json(path) == {"seed": 0}
    assert (damage == "truncate") == any("[settings] run config" in line for line in lines)
    kept = list((tmp_path / SET_ASIDE).glob("*/study_config.json"))  # the damaged one, kept
    assert [p.read_text() for p in kept] == ([] if damage == "delete" else [damaged])


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


def test_a_file_no_record_names_is_set_aside_not_removed_where_settings_are_unknown(tmp_path):
    """A runner in a folder without a settings record removes what an unfinished stage of
    unknown settings left; a file no record of the stage names (the user's) is set aside."""
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "mine.pt").write_bytes(b"mine")
    pipeline = Pipeline(tmp_path)
    _, lines = pipeline.run()
    assert pipeline.computed == ["x", "y", "z"]
    (kept,) = (tmp_path / SET_ASIDE).glob("*/a/mine.pt")
    assert kept.read_bytes() == b"mine" and not (tmp_path / "a" / "mine.pt").exists()
    said = "[make] a/mine.pt: no record says the stage wrote it"
    assert any(line.startswith(said) for line in lines)


# ---------------------------------------------------------------------- reuse across runs
# ``make`` reads the seed and ``data.n``; ``use`` reads every setting.
READS = {"make": ["seed", "data.n"]}


def _settings(n=2, scale=1.0):
    return {"seed": 0, "data": {"n": n}, "score": {"scale": scale}}


def test_a_run_reuses_another_runs_stages_whose_settings_are_the_same(tmp_path):
    first = Pipeline(tmp_path / "first")
    first.run(_settings(), stage_settings=READS)
    second = Pipeline(tmp_path / "second")  # only a setting of the later stage differs
    runner, lines = second.run(
        _settings(scale=2.0), stage_settings=READS, reuse_from=tmp_path / "first"
    )
    assert second.computed == ["z"]  # make's files came from the first run
    for rel in ("a/x.pt", "a/y.pt"):
        a, b = tmp_path / "first" / rel, tmp_path / "second" / rel
        assert a.read_bytes() == b.read_bytes() and a.stat().st_ino == b.stat().st_ino
    assert any(
        line.startswith("[make] reusing the finished stage of") and "2 of 2 hard-linked" in line
        for line in lines
    )
    assert any(
        "[use] not reused from" in line
        and line.endswith("settings it reads differ (score.scale: 1.0 there, 2.0 here)")
        for line in lines
    )
    # this run's seconds are the placing's; the stage's own stay with the other run's name
    ran = json.loads((tmp_path / "first" / "stages" / "make.json").read_text())["seconds"]
    summary = runner.summaries["make"]
    assert summary["n"] == 2 and summary["seconds"] < 1.0
    assert summary["reused_from"] == {"run_dir": str(tmp_path / "first"), "seconds": ran}
    third = Pipeline(tmp_path / "third")  # reused again from the reuse: where it ran is kept
    third_runner, _ = third.run(_settings(), stage_settings=READS, reuse_from=tmp_path / "second")
    assert third_runner.summaries["make"]["reused_from"]["seconds"] == ran
    # the reused stage is this run's own now: a rerun verifies and reuses it here
    again = Pipeline(tmp_path / "second")
    _, lines = again.run(_settings(scale=2.0), stage_settings=READS)
    assert again.computed == [] and all("files verified" in line for line in lines)


def test_a_setting_the_stage_reads_stops_the_reuse(tmp_path):
    Pipeline(tmp_path / "first").run(_settings(), stage_settings=READS)
    other = Pipeline(tmp_path / "other")  # a setting make reads differs
    _, lines = other.run(_settings(n=3), stage_settings=READS, reuse_from=tmp_path / "first")
    assert other.computed == ["x", "y", "z"]
    assert any(
        "[make] not reused from" in line
        and line.endswith("settings it reads differ (data.n: 2 there, 3 here)")
        for line in lines
    )
    same = Pipeline(tmp_path / "same")  # every setting the same: every stage reused
    same.run(_settings(), stage_settings=READS, reuse_from=tmp_path / "first")
    assert same.computed == []


def test_a_changed_earlier_file_is_not_reused_from_the_other_run(tmp_path):
    reads = {"make": ["seed"], "use": ["seed"]}
    Pipeline(tmp_path / "first").run(_settings(), stage_settings=reads)
    second = Pipeline(tmp_path / "second", value=2.0)
    # an unfinished run of make here: the settings recorded, its files written, no marker
    StageRunner(tmp_path / "second", settings=_settings(), stage_settings=reads)
    for name in ("x", "y"):
        save_torch(tmp_path / "second" / "a" / f"{name}.pt", torch.full((3,), 2.0))
    runner, lines = second.run(_settings(), stage_settings=reads, reuse_from=tmp_path / "first")
    assert any(
        "[make] not reused from" in line and "2 files of the stage's own" in line for line in lines
    )
    # its make records other files, so use's inputs differ from the first run's
    assert second.computed == ["z"] and runner.summaries["use"]["total"] == 12.0
    assert any(
        "[use] not reused from" in line
        and line.endswith("inputs differ (an earlier stage's files)")
        for line in lines
    )


def test_a_damaged_file_of_the_other_run_is_not_reused(tmp_path):
    Pipeline(tmp_path / "first").run(_settings(), stage_settings=READS)
    (tmp_path / "first" / "a" / "y.pt").write_bytes(b"garbage")
    second = Pipeline(tmp_path / "second")
    _, lines = second.run(_settings(), stage_settings=READS, reuse_from=tmp_path / "first")
    # make runs here; its files come out as the first run's were, so use is reused
    assert second.computed == ["x", "y"]
    assert any(
        "[make] not reused from" in line and "a/y.pt: its size changed" in line for line in lines
    )
    assert any(line.startswith("[use] reusing the finished stage of") for line in lines)
    assert (tmp_path / "first" / "a" / "y.pt").read_bytes() == b"garbage"  # not touched


def test_markers_of_all_settings_stay_reusable_when_stages_declare_what_they_read(tmp_path):
    """A run directory made before its stages declared their settings is reused as it is
    (every setting is the same), and its markers then record the stages' own inputs."""
    Pipeline(tmp_path).run(_settings())
    before = json.loads((tmp_path / "stages" / "make.json").read_text())["inputs"]
    again = Pipeline(tmp_path)
    _, lines = again.run(_settings(), stage_settings=READS)
    assert again.computed == [] and all("files verified" in line for line in lines)
    after = json.loads((tmp_path / "stages" / "make.json").read_text())["inputs"]
    assert after != before
    other = Pipeline(tmp_path / "other")  # and another run can now take them
    other.run(_settings(scale=3.0), stage_settings=READS, reuse_from=tmp_path)
    assert other.computed == ["z"]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"stage_settings": {"make": ["data.m"]}}, r"stage_settings\['make'\]: 'data.m' is not a"),
        ({"stage_settings": {"make": ["nope"]}}, r"'nope' is not a setting; expected a key of"),
        ({"stage_settings": {"make": "seed"}}, r"expected a sequence of setting names"),
        ({"reuse_from": "/no/such/run"}, r"reuse_from: expected a run directory, got"),
    ],
)
def test_bad_stage_settings_and_reuse_from_are_named(tmp_path, kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        StageRunner(tmp_path, settings=_settings(), **kwargs)


def test_reuse_from_the_run_itself_is_refused(tmp_path):
    with pytest.raises(ValueError, match="reuse_from: expected another run directory"):
        StageRunner(tmp_path, settings=_settings(), reuse_from=tmp_path / ".")
    with pytest.raises(ValueError, match="stage_settings: expected the run's settings"):
        StageRunner(tmp_path, stage_settings={"make": ["seed"]})


def test_a_run_of_markers_of_all_settings_lends_the_stages_whose_settings_match(tmp_path):
    """Another run made before its stages declared their settings: its recorded settings
    and its markers' digests say what each stage was made with."""
    Pipeline(tmp_path / "old").run(_settings())  # markers of all settings
    second = Pipeline(tmp_path / "second")
    _, lines = second.run(_settings(scale=2.0), stage_settings=READS, reuse_from=tmp_path / "old")
    assert second.computed == ["z"]
    assert any(line.startswith("[make] reusing the finished stage of") for line in lines)
    third = Pipeline(tmp_path / "third")  # a setting make reads differs
    third.run(_settings(n=3), stage_settings=READS, reuse_from=tmp_path / "old")
    assert third.computed == ["x", "y", "z"]
    # a marker whose digest does not follow from the recorded settings is not trusted
    (tmp_path / "old" / "study_config.json").write_text(json.dumps(_settings(scale=2.0)))
    fourth = Pipeline(tmp_path / "fourth")
    fourth.run(_settings(scale=2.0), stage_settings=READS, reuse_from=tmp_path / "old")
    assert fourth.computed == ["x", "y", "z"]


def test_a_run_directory_is_refused_where_a_run_would_remove_files_it_did_not_make(tmp_path):
    settings = {"seed": 0}
    check_run_directory(tmp_path / "new", settings)  # missing: a run makes it
    (tmp_path / "empty").mkdir()
    check_run_directory(tmp_path / "empty", settings)
    # what the run itself makes before its record (its log, its logger's folder) does not count
    made = tmp_path / "made"
    (made / "logs").mkdir(parents=True)
    (made / "run.log").write_text("started\n")
    check_run_directory(made, settings, made_before=("run.log", "logs"))
    with pytest.raises(ValueError, match=r"holds 'logs', 'run.log' but no run's settings record"):
        check_run_directory(made, settings)
    # a folder of the user's own: named, refused, untouched
    own = tmp_path / "own"
    (own / "a").mkdir(parents=True)
    (own / "a" / "x.pt").write_bytes(b"mine")
    for i in range(6):
        (own / f"note{i}.txt").write_text("mine")
    with pytest.raises(ValueError) as refused:
        check_run_directory(own, settings)
    assert str(refused.value).startswith(
        f"run_dir: expected a new or empty directory, or one a run made, got {str(own)!r}, which "
        "holds 'a', 'note0.txt', 'note1.txt', 'note2.txt', 'note3.txt' and 2 more but no run's "
        "settings record ('study_config.json') and no stage markers ('stages/')"
    )
    assert (own / "a" / "x.pt").read_bytes() == b"mine"
    # a run's directory: its own settings pass, others are refused
    Pipeline(tmp_path / "run").run()
    check_run_directory(tmp_path / "run", {"seed": 0})
    with pytest.raises(ValueError, match=r"other settings \(\['seed'\] differ"):
        check_run_directory(tmp_path / "run", {"seed": 1})
    # a run whose record alone was lost: its markers name its files, so it may run again
    (tmp_path / "run" / "study_config.json").unlink()
    check_run_directory(tmp_path / "run", {"seed": 1})


def test_a_stage_made_with_other_code_runs_again_and_later_stages_follow_its_files(tmp_path):
    first = Pipeline(tmp_path)
    first.run(stage_code={"make": "code-1"})
    assert json.loads((tmp_path / "stages" / "make.json").read_text())["code"] == "code-1"
    assert "code" not in json.loads((tmp_path / "stages" / "use.json").read_text())
    same = Pipeline(tmp_path)
    runner, _ = same.run(stage_code={"make": "code-1"})
    assert same.computed == [] and "code" not in runner.summaries["make"]
    # new code, the same files: the stage runs again, the next one (no code declared) is reused
    again = Pipeline(tmp_path)
    _, lines = again.run(stage_code={"make": "code-2"})
    assert again.computed == ["x", "y"]
    assert any(
        "[make] its code changed (digest code-1 recorded, code-2 now): removing its 2 files" in line
        for line in lines
    )
    # new code that makes other files: the next stage's inputs changed, so it runs too
    other = Pipeline(tmp_path, value=2.0)
    other.run(stage_code={"make": "code-3"})
    assert other.computed == ["x", "y", "z"]


def test_a_marker_from_before_code_was_declared_is_reused_and_says_it_is_unverified(tmp_path):
    Pipeline(tmp_path).run()
    later = Pipeline(tmp_path)
    runner, lines = later.run(stage_code={"make": "code-1"})
    assert later.computed == [] and runner.summaries["use"]["total"] == 6.0
    assert any("[make] its marker records no code digest" in line for line in lines)
    assert "code" not in json.loads((tmp_path / "stages" / "make.json").read_text())


def test_reuse_from_another_run_needs_the_same_code(tmp_path):
    Pipeline(tmp_path / "first").run(stage_code={"make": "code-1"})
    same = Pipeline(tmp_path / "same")
    same.run(stage_code={"make": "code-1"}, reuse_from=tmp_path / "first")
    assert same.computed == []
    other = Pipeline(tmp_path / "other")
    _, lines = other.run(stage_code={"make": "code-2"}, reuse_from=tmp_path / "first")
    assert other.computed == ["x", "y"]  # the same files: "use" (no code declared) is reused
    assert any(
        "[make] not reused from" in line and "its code changed (digest code-1" in line
        for line in lines
    )
    Pipeline(tmp_path / "old").run()  # no code recorded there: reused, and said so
    unverified = Pipeline(tmp_path / "unverified")
    _, lines = unverified.run(stage_code={"make": "code-1"}, reuse_from=tmp_path / "old")
    assert unverified.computed == []
    assert any("records no code digest" in line and "old" in line for line in lines)


def test_a_stage_made_with_other_library_code_is_reused_and_says_so(tmp_path):
    first = Pipeline(tmp_path / "run")
    runner, _ = first.run(library_code="lib-1")
    marker = json.loads((tmp_path / "run" / "stages" / "make.json").read_text())
    assert marker["library_code"] == "lib-1" and "library_code" not in runner.summaries["make"]
    same = Pipeline(tmp_path / "run")
    _, lines = same.run(library_code="lib-1")
    assert same.computed == [] and not any("library code" in line for line in lines)
    # other library code: every stage reused, each one named with what makes it anew
    later = Pipeline(tmp_path / "run")
    runner, lines = later.run(library_code="lib-2")
    assert later.computed == [] and runner.summaries["use"]["total"] == 6.0
    for name in ("make", "use"):
        assert any(
            line.startswith(f"[{name}] made by other library code (digest lib-1 recorded, lib-2")
            and "reused as it is (a new run directory makes every stage with this code)" in line
            for line in lines
        )
    borrowed = Pipeline(tmp_path / "borrowed")
    _, lines = borrowed.run(library_code="lib-3", reuse_from=tmp_path / "run")
    assert borrowed.computed == []
    assert any("[make] made in" in line and "by other library code" in line for line in lines)
    # markers that record none (written before, or by a runner not given any): nothing said
    Pipeline(tmp_path / "old").run()
    _, lines = Pipeline(tmp_path / "old").run(library_code="lib-1")
    assert not any("library code" in line for line in lines)
    with pytest.raises(TypeError, match=r"library_code: expected a code digest \(str\) or None"):
        StageRunner(tmp_path, library_code=3)
    with pytest.raises(ValueError, match="library_code"):  # reserved for the marker
        StageRunner(tmp_path / "x").run("s", lambda: {"library_code": 1})


def test_the_library_digest_is_the_digest_of_its_package(tmp_path):
    from pathlib import Path

    import rcvae_torchrl
    from rcvae_torchrl.stages import code_digest, library_digest

    assert library_digest() == code_digest([Path(rcvae_torchrl.__file__).parent])


@pytest.mark.parametrize("stage_code", [["make"], {"make": 3}, {1: "code"}])
def test_bad_stage_code_is_named(tmp_path, stage_code):
    with pytest.raises(TypeError, match="stage_code: expected a mapping of stage names"):
        StageRunner(tmp_path, stage_code=stage_code)


def test_code_digest_follows_the_files_their_names_and_the_package_versions(tmp_path):
    import importlib.metadata

    from rcvae_torchrl.stages import code_digest

    (tmp_path / "env").mkdir()
    (tmp_path / "env" / "dynamics.py").write_text("G = 9.81\n")
    (tmp_path / "env" / "model.xml").write_text("<mujoco/>\n")
    base = code_digest([tmp_path / "env"])
    assert base == code_digest([str(tmp_path / "env")])  # a str path or a Path
    (tmp_path / "env" / "__pycache__").mkdir()
    (tmp_path / "env" / "__pycache__" / "dynamics.cpython-311.pyc").write_bytes(b"\0")
    assert code_digest([tmp_path / "env"]) == base  # compiled caches do not count
    (tmp_path / "env" / "model.xml").rename(tmp_path / "env" / "arena.xml")
    assert code_digest([tmp_path / "env"]) != base  # a renamed file counts
    (tmp_path / "env" / "arena.xml").rename(tmp_path / "env" / "model.xml")
    assert code_digest([tmp_path / "env"]) == base
    (tmp_path / "env" / "dynamics.py").write_text("G = 9.80\n")
    assert code_digest([tmp_path / "env"]) != base
    with_torch = code_digest([tmp_path / "env"], packages=["torch"])
    assert with_torch != code_digest([tmp_path / "env"])
    assert importlib.metadata.version("torch") == torch.__version__
    assert code_digest([], packages=["no-such-package-here"]) != code_digest([])
    with pytest.raises(FileNotFoundError, match="paths: no file or directory"):
        code_digest([tmp_path / "missing"])


@pytest.mark.parametrize(
    ("call", "error", "words"),
    [
        (lambda r: r.run("s", lambda: None), TypeError, "stage 's': expected its function to "),
        (lambda r: r.run("s", lambda: 3), TypeError, "return a dict summary"),
        (lambda r: r.run("s", lambda: {"seconds": 1.0}), ValueError, "holds ['seconds']"),
        (lambda r: r.run("s", lambda: {"outputs": 3}), ValueError, "reserved"),
        (lambda r: r.run("s", {"x": 1}), TypeError, "fn: expected a callable"),
        (lambda r: r.run("s", dict, outputs="m/*.pt"), TypeError, "outputs: expected a sequence"),
        (lambda r: r.run("s", dict, outputs=[3]), TypeError, "outputs: expected glob patterns"),
        (lambda r: r.run("s", dict, outputs=["../x/*"]), ValueError, "inside it, got '../x/*'"),
        (lambda r: r.run("s", dict, outputs=["/tmp/*"]), ValueError, "relative to the run dir"),
        (lambda r: r.run("../evil", dict), ValueError, "name: expected a stage name"),
        (lambda r: r.run("", dict), ValueError, "name: expected a stage name"),
        (lambda r: r.run("s", dict, sharded="no"), TypeError, "sharded: expected True or False"),
        (lambda r: r.run("s", lambda: {"a": torch.ones(2)}), TypeError, "summary of stage 's'"),
    ],
)
def test_a_stage_the_runner_cannot_run_or_record_is_refused_by_name(tmp_path, call, error, words):
    runner = StageRunner(tmp_path / "run", lambda line: None)
    with pytest.raises(error) as info:
        call(runner)
    assert words in str(info.value)
    assert not (tmp_path / "run" / "stages" / "s.json").exists()  # no marker of a bad stage


def test_a_pattern_cannot_reach_files_outside_the_run_directory(tmp_path):
    precious = tmp_path / "victim" / "precious.txt"
    precious.parent.mkdir()
    precious.write_text("mine")
    runner = StageRunner(tmp_path / "run", lambda line: None)
    with pytest.raises(ValueError, match="outputs"):
        runner.run("s", dict, outputs=["../victim/*"])
    assert precious.read_text() == "mine"
    assert not (tmp_path / "evil.json").exists()


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"run_dir": 5}, "run_dir: expected a str or a path, got int"),
        ({"log": None}, "log: expected a callable"),
        ({"settings": [1, 2]}, "settings: expected a mapping"),
    ],
)
def test_a_runner_refuses_bad_arguments_by_name(tmp_path, kwargs, words):
    args = {"run_dir": tmp_path, "log": print, **kwargs}
    with pytest.raises(TypeError) as info:
        StageRunner(args.pop("run_dir"), **args)
    assert words in str(info.value)


def test_a_stage_name_runs_once_per_runner(tmp_path):
    runner = StageRunner(tmp_path, lambda line: None)
    runner.run("s", lambda: {"n": 1})
    with pytest.raises(ValueError, match="stage 's' already ran in this runner"):
        runner.run("s", lambda: {"n": 2})


def test_a_summary_reads_the_same_whether_the_stage_ran_or_was_reused(tmp_path):
    import numpy as np

    def fn():
        return {"p": np.float32(0.5), "n": np.int64(3), "ok": np.bool_(True), "pair": (1, 2)}

    first = StageRunner(tmp_path, lambda line: None).run("s", fn)
    again = StageRunner(tmp_path, lambda line: None).run("s", fn)
    assert first == again
    assert {k: type(first[k]) for k in ("p", "n", "ok", "pair")} == {
        "p": float,
        "n": int,
        "ok": bool,
        "pair": list,
    }
    assert (first["p"], first["n"], first["ok"], first["pair"]) == (0.5, 3, True, [1, 2])
    with pytest.raises(TypeError, match="a NumPy array of shape"):
        StageRunner(tmp_path, lambda line: None).run("t", lambda: {"a": np.zeros(2000)})


def test_a_run_with_a_nan_setting_resumes(tmp_path):
    settings = {"threshold": float("nan"), "seed": 0}
    StageRunner(tmp_path, lambda line: None, settings=settings).run("s", lambda: {"n": 1})
    lines = []
    StageRunner(tmp_path, lines.append, settings=settings).run("s", lambda: {"n": 2})
    assert any("done earlier" in line for line in lines)
    with pytest.raises(ValueError, match="threshold"):
        StageRunner(tmp_path, lines.append, settings={"threshold": 1.0, "seed": 0})

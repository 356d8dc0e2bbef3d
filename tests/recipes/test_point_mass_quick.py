"""The point-mass recipe (dm_control, public API only) end to end with micro budgets."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from micro import POINT_MASS_MICRO, broken_table_rows

from rcvae_torchrl.io import read_json, write_json
from recipes._settings import CHECKPOINTS
from recipes.point_mass_competency.report import COLUMNS
from recipes.point_mass_competency.task import CONDITIONS

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "point_mass_competency" / "main.py"
MICRO = POINT_MASS_MICRO


def _run(*overrides: str) -> subprocess.CompletedProcess:
    # The recipe renders nothing, so it must run where no offscreen OpenGL can: no backend is
    # forced, and PyOpenGL is pointed away from EGL (forcing MUJOCO_GL=egl where EGL cannot be
    # used, as on a GPU machine whose EGL library PyOpenGL could not load, fails dm_control's
    # import and with it the whole run)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYOPENGL_PLATFORM": "glx"}
    env.pop("MUJOCO_GL", None)
    return subprocess.run(
        [sys.executable, str(RECIPE), *overrides],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("point_mass") / "run"
    first = _run(*MICRO, f"run_dir={run_dir}")
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    second = _run(*MICRO, f"run_dir={run_dir}")
    assert second.returncode == 0, second.stderr[-3000:]
    assert "] running" not in second.stdout and "[report] done earlier" in second.stdout
    return run_dir


def test_every_output_and_a_row_per_condition(run_dir):
    for name in ("table.md", "table.csv", "report.md", "summary.json", "reliability.png"):
        assert (run_dir / name).is_file()
    report = (run_dir / "report.md").read_text()
    assert "\\|forecast - real\\| <= 0.10" in report  # a check's name, escaped
    assert broken_table_rows(report) == []
    with open(run_dir / "table.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["condition"] for r in rows] == list(CONDITIONS)
    assert all(tuple(r) == COLUMNS for r in rows)
    assert [int(r["real_episodes"]) for r in rows] == [2, 2 * 2, 2]  # repeated runs: noise only


def test_summary_checks_and_plain_words(run_dir):
    summary = read_json(run_dir / "summary.json")
    assert len(summary["checks"]) == 3 + 2 + 2 + 3  # gaps, ratios, causes, outcome checks
    for check in summary["checks"].values():
        assert isinstance(check["met"], bool)
    for condition in CONDITIONS:
        text = summary["overall"][condition]
        assert text.startswith("Warning: ") or text.startswith("Over 2 start states")
        if text.startswith("Warning: "):  # a model that failed its checks: bits, no cause
            assert "with the warning above this split does not say" in text
            assert "Against the" not in text and "the rise is" not in text
        else:
            assert "Against the in-distribution reference" in text
    report = (run_dir / "report.md").read_text()
    assert "## Summaries (against the deterministic condition)" in report


def test_each_condition_s_report_carries_its_outcome_check_from_other_starts(run_dir):
    """The check stage forecasts and runs the controller from start states of each condition's
    region that no score uses; the report attaches each check to its condition's report."""
    from rcvae_torchrl.io import load_torch
    from rcvae_torchrl.training import OutcomeCheck

    summary = read_json(run_dir / "summary.json")
    report = (run_dir / "report.md").read_text()
    assert "## Outcome checks" in report
    for condition in CONDITIONS:
        check = OutcomeCheck.from_dict(read_json(run_dir / "check" / f"{condition}.json"))
        assert check.starts == 3 and check.start_states is not None  # the quick profile's
        scored = load_torch(run_dir / "forecast" / f"{condition}.pt")["starts"]["observation"]
        assert not (check.start_states[:, None] == scored[None]).all(-1).any()  # none scored
        found = summary["forecast_checks"][condition]
        assert (found["verdict"], found["passed"]) == (check.verdict, check.passed)
        assert summary["checks"][f"outcome check passed ({condition})"] == {
            "value": check.verdict,
            "met": check.passed,
        }
        assert f"| {condition} | 3 | " in report and check.describe() in report
        if not check.passed:  # a report whose check did not pass opens with its warning
            assert summary["overall"][condition].startswith("Warning: ")
            assert not found["trustworthy"]


def test_the_model_config_names_the_dm_control_entries(run_dir):
    from rcvae_torchrl.training import load_ensemble

    model = load_ensemble(run_dir / "models" / "deterministic.pt")
    assert model.config.names == ("position[0]", "position[1]", "velocity[0]", "velocity[1]")
    assert model.checks is not None and model.checks.names == model.config.names


def test_run_log_and_the_logger(run_dir):
    log = (run_dir / "run.log").read_text()
    assert "\x1b[" not in log
    assert log.count("profile=quick threads=1") == 2  # both runs, appended
    assert "[models] running" in log and "[models] done earlier" in log
    experiments = sorted((run_dir / "logs" / "csv").glob("point_mass_quick_*"))
    assert len(experiments) == 2  # one per run
    curves = [e / "scalars" / "models" / "deterministic" / "val_loss.csv" for e in experiments]
    assert sum(c.is_file() for c in curves) == 1  # only the first run trained
    marker = json.loads((run_dir / "stages" / "data.json").read_text())
    frames = [k for k, v in marker.items() if k.endswith("_frames")]
    assert frames
    for experiment in experiments:  # both runs log every stage's numbers
        logged = (experiment / "scalars" / "stages" / "data" / f"{frames[0]}.csv").read_text()
        assert float(logged.split(",")[1]) == marker[frames[0]]


@pytest.mark.parametrize(
    "change", ["assess.samples_per_member=8", "task.deadline_s=0.8"], ids=["samples", "deadline"]
)
def test_a_new_run_reuses_the_data_and_models_of_the_same_settings(run_dir, tmp_path, change):
    """``reuse_from``: more imagined samples per member, or another deadline (which neither
    the data nor the models read), keep the data and the world models (the same files,
    hard-linked) and forecast anew."""
    new = tmp_path / "changed"
    proc = _run(*MICRO, f"run_dir={new}", f"reuse_from={run_dir}", change)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for stage in ("data", "models"):
        assert f"[{stage}] reusing the finished stage of {str(run_dir)!r}" in proc.stdout
        for rel in json.loads((new / "stages" / f"{stage}.json").read_text())["outputs"]:
            assert (new / rel).stat().st_ino == (run_dir / rel).stat().st_ino, rel
    for stage in ("forecast", "truth", "check", "report"):
        assert f"[{stage}] running" in proc.stdout


def test_a_lost_training_checkpoint_changes_nothing(run_dir, tmp_path):
    """The checkpoints are not outputs of the models stage (a finished stage needs none): a
    run whose checkpoints were deleted reuses every stage, remaking nothing."""
    copy = tmp_path / "run"
    shutil.copytree(run_dir, copy)
    checkpoints = sorted((copy / "models" / CHECKPOINTS).glob("*.pt"))
    assert [p.name for p in checkpoints] == ["deterministic.pt", "stochastic.pt"]
    recorded = json.loads((copy / "stages" / "models.json").read_text())["outputs"]
    assert sorted(recorded) == ["models/deterministic.pt", "models/stochastic.pt"]
    for path in checkpoints:
        path.unlink()
    proc = _run(*MICRO, f"run_dir={copy}")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "] running" not in proc.stdout and "[report] done earlier" in proc.stdout
    # run again by deleting its marker, the stage says what it keeps (it trains nothing)
    (copy / "stages" / "models.json").unlink()
    proc = _run(*MICRO, f"run_dir={copy}")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert (
        "[models] models/deterministic.pt, models/stochastic.pt written earlier: taken as they are"
    ) in proc.stdout
    assert "[forecast] done earlier" in proc.stdout  # the same files: nothing later reruns


def test_a_run_dir_of_another_profile_is_refused_naming_it(run_dir):
    """A forgotten ``profile=`` reads as a dozen settings that differ; its run.log names it."""
    proc = _run(f"run_dir={run_dir}")  # the default profile on the micro run's directory
    assert proc.returncode == 1
    error = proc.stderr.strip().splitlines()[-1]
    assert error.startswith(f"error: run directory {str(run_dir)!r} holds a run made with other")
    assert error.endswith(
        "; its run.log says it was made with profile=quick, and this run has profile=default: "
        "add profile=quick to go on with it"
    )


def test_each_condition_s_dynamics_check_is_recorded(run_dir):
    """The check stage also asks whether each condition's real env moves as its model learned;
    the micro profile's models hold 1 validation episode, too few to measure it: the report
    says so, and the run keeps an empty record (no check stage runs again for it)."""
    summary = read_json(run_dir / "summary.json")
    report = (run_dir / "report.md").read_text()
    assert "## Dynamics checks" in report
    for condition in CONDITIONS:
        assert read_json(run_dir / "check" / f"{condition}_dynamics.json") == {"check": None}
        assert summary["dynamics_checks"][condition] is None
        assert f"- **{condition}**: not checked: its model has no dynamics check" in report


def test_a_run_from_before_dynamics_checks_gets_them_when_its_report_is_made(run_dir, tmp_path):
    """A run directory whose check stage ran before dynamics checks were made has none: the
    report stage, run again, makes them (it does not say the model has none)."""
    old = tmp_path / "old"
    shutil.copytree(run_dir, old)
    made = [f"check/{condition}_dynamics.json" for condition in CONDITIONS]
    for name in made:  # as the check stage made and recorded its outputs before
        (old / name).unlink()
    stage = read_json(old / "stages" / "check.json")
    records = read_json(old / "stages" / "check.records")
    for name in made:
        del stage["outputs"][name], records[name]
    write_json(old / "stages" / "check.json", stage, checksum=True)
    write_json(old / "stages" / "check.records", records, checksum=True)
    (old / "stages" / "report.json").unlink()
    again = _run(*MICRO, f"run_dir={old}")
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert "[check] done earlier" in again.stdout and "[report] running" in again.stdout
    for condition in CONDITIONS:
        assert read_json(old / "check" / f"{condition}_dynamics.json") == {"check": None}
    third = _run(*MICRO, f"run_dir={old}")  # and the run directory stays usable
    assert third.returncode == 0 and "] running" not in third.stdout, third.stderr[-3000:]


def test_a_measured_dynamics_check_reaches_the_report(tmp_path):
    """With 110 episodes of 50 steps, a tenth held out, each model measures its one-step
    errors; each condition's controller episodes are checked against them, and a check that
    failed makes its report untrustworthy."""
    from rcvae_torchrl.training import DynamicsCheck

    run_dir = tmp_path / "run"
    more = [o for o in MICRO if not o.startswith("data.episodes")]
    done = _run(*more, "data.episodes=110", "assess.check_starts=12", f"run_dir={run_dir}")
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    summary = read_json(run_dir / "summary.json")
    report = (run_dir / "report.md").read_text()
    for condition in CONDITIONS:
        record = read_json(run_dir / "check" / f"{condition}_dynamics.json")["check"]
        check = DynamicsCheck.from_dict(record)
        assert check.episodes == 12 and check.short == 0
        row = summary["dynamics_checks"][condition]
        assert (row["passed"], row["episodes"]) == (check.passed, 12)
        assert f"- **{condition}**: {'passed' if check.passed else 'failed'}: " in report
        assert check.describe() in report
        if not check.passed:
            assert not summary["forecast_checks"][condition]["trustworthy"]

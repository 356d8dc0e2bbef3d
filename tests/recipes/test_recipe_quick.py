"""The competency recipe end to end, with micro budgets: every output, then a resumed run.

The recipe runs in a subprocess exactly as a user starts it (Hydra command line), with the quick
profile shrunk further so that both runs take well under a minute on two loaded cores.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from doc_blocks import rst_python_blocks, run_blocks
from micro import MICRO, START_STATES, broken_table_rows
from PIL import Image

from rcvae_torchrl.competency import AleatoricShare
from rcvae_torchrl.envs.batched import BatchedPusherEnv
from rcvae_torchrl.io import CHECKSUM_KEY, StoredFileError, read_json
from rcvae_torchrl.training import DynamicsCheck
from recipes._settings import CHECKPOINTS
from recipes.pusher_competency import pipeline
from recipes.pusher_competency.pusher import CONDITIONS
from recipes.pusher_competency.report import AFTER_SHARE, COLUMNS, DYNAMICS_CHECK

ROOT = Path(__file__).resolve().parents[2]
RECIPE = ROOT / "recipes" / "pusher_competency" / "main.py"
STAGES = ("data", "models", "agent", "forecast", "truth", "report")
FIGURES = (
    "uncertainty_over_time.png",
    "reliability.png",
    "forecast_vs_reality.png",
    "start_reliability.png",
    "surface.png",
)
STOCHASTIC_SEEDS = 2  # the quick profile's assess.stochastic_seeds_per_start


def run_recipe(*overrides: str, timeout: float = 300) -> tuple[subprocess.CompletedProcess, float]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, str(RECIPE), *overrides],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        preexec_fn=lambda: os.umask(0o022),  # a shared machine's usual umask
    )
    return proc, time.perf_counter() - start


def _snapshot(run_dir: Path) -> dict[str, tuple[int, int]]:
    """(mtime_ns, size) of every file the stages wrote (study_config.json is rewritten; each
    run appends to run.log and starts its own experiment under logs/)."""
    return {
        str(p.relative_to(run_dir)): (p.stat().st_mtime_ns, p.stat().st_size)
        for p in run_dir.rglob("*")
        if p.is_file()
        and p.name not in ("study_config.json", "run.log")
        and not {".hydra_run", "logs"} & set(p.relative_to(run_dir).parts)
    }


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The recipe run twice in the same run directory: (run_dir, first, second)."""
    run_dir = tmp_path_factory.mktemp("recipe") / "run"
    first, first_s = run_recipe(*MICRO, f"run_dir={run_dir}")
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    before = _snapshot(run_dir)
    second, second_s = run_recipe(*MICRO, f"run_dir={run_dir}")
    assert second.returncode == 0, second.stdout[-3000:] + second.stderr[-3000:]
    return {
        "dir": run_dir,
        "first": first.stdout,
        "second": second.stdout,
        "first_s": first_s,
        "second_s": second_s,
        "before": before,
        "after": _snapshot(run_dir),
    }


def _rows(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "table.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_every_stage_ran_and_left_its_outputs(runs):
    d = runs["dir"]
    for stage in STAGES:
        assert f"[{stage}] running" in runs["first"]
        marker = json.loads((d / "stages" / f"{stage}.json").read_text())
        assert marker["seconds"] >= 0
    for variant in ("deterministic", "stochastic"):
        assert (d / "data" / f"{variant}.pt").is_file()
        assert (d / "models" / f"{variant}.pt").is_file()
    assert (d / "agent" / "policy.pt").is_file()
    assert (d / "agent" / "demonstrations.pt").is_file()
    for condition in CONDITIONS:
        forecast = torch.load(d / "forecast" / f"{condition}.pt", weights_only=True)
        assert forecast["starts"].shape == (START_STATES, 14)
        assert forecast["epistemic"].shape[0] == START_STATES
        assert forecast["epistemic"].shape[-1] == 14
        truth = torch.load(d / "truth" / f"{condition}.pt", weights_only=True)
        assert truth["success"].shape[0] == START_STATES
        # the quick profile's 2 spread starts, 4 real runs each, in the forecast's bits
        spread = torch.load(d / "truth" / f"{condition}_spread.pt", weights_only=True)
        assert spread["index"].tolist() == [0, START_STATES - 1]
        assert spread["real_by_dim"].shape == spread["imagined_by_dim"].shape == (2, 14)
        assert bool((spread["imagined"] > 0).all())  # the models' own error, at least
        if condition != "stochastic":  # a deterministic Pusher and agent repeat an episode
            assert not bool(spread["real"].any())
    # the split calibrated on held-out starts of each world model's own env
    for condition, (model, variant) in CONDITIONS.items():
        if model != variant:
            assert not (d / "truth" / f"{condition}_share.pt").exists()
            continue
        share = AleatoricShare.from_dict(
            torch.load(d / "truth" / f"{condition}_share.pt", weights_only=True)
        )
        assert share.start_states == 2 and share.share.shape == (14,)
        if condition == "deterministic":  # real episodes repeat: nothing is the env's noise
            moving = share.imagined > 0
            assert bool(moving.any()) and not bool(share.share[moving].any())
    report = (d / "report.md").read_text()
    assert "### The aleatoric bits against the real episodes' spread" in report
    assert "### The split calibrated against real episodes" in report
    # out of sample: the scored starts' real spread against the aleatoric bits the share keeps
    assert re.search(r"\| deterministic \| 0\.00 \| 0\.00 \| 1 \|", report), report
    summary = json.loads((d / "summary.json").read_text())
    assert CHECKSUM_KEY in summary  # checksummed: a verdict edited by hand is refused
    edited = d.parent / "edited_summary.json"
    edited.write_text(json.dumps({**summary, "checks": {}}))
    with pytest.raises(StoredFileError, match="its content changed since it was written"):
        read_json(edited)
    edited.unlink()
    det = summary["calibrated_split"]["deterministic"]
    assert det["aleatoric_bits"] == 0.0  # a deterministic Pusher and agent: no chance left
    assert summary["calibrated_split"]["out-of-distribution"]["aleatoric_bits"] == 0.0
    name = "aleatoric out-of-distribution / deterministic within 0.7-1.3" + AFTER_SHARE
    assert summary["checks"][name] == {"value": 1.0, "met": True}  # nothing against nothing
    assert re.search(r"\| deterministic \| 2 \| [0-9.]+ \| 0\.00 \| inf \|", report), report
    assert json.loads((d / "study_config.json").read_text())["assess"]["horizon_s"] == 2.0


def test_table_has_the_three_conditions_and_the_columns(runs):
    d = runs["dir"]
    rows = _rows(d)
    assert [r["condition"] for r in rows] == list(CONDITIONS)
    assert all(tuple(r) == COLUMNS for r in rows)
    for r in rows:
        total, aleatoric, epistemic = (float(r[k]) for k in COLUMNS[1:4])
        assert aleatoric >= 0 and epistemic >= -1e-4
        assert total == pytest.approx(aleatoric + epistemic, rel=1e-4, abs=1e-4)
        for key in ("forecast_p_success", "empirical_p_success", "brier", "ece"):
            assert 0.0 <= float(r[key]) <= 1.0
        assert int(r["start_states"]) == START_STATES
        seeds = STOCHASTIC_SEEDS if r["condition"] == "stochastic" else 1
        assert int(r["real_episodes"]) == START_STATES * seeds
    header, rule, *body = (d / "table.md").read_text().strip().splitlines()
    assert [c.strip() for c in header.strip("|").split("|")] == list(COLUMNS)
    assert rule.count("|") == len(COLUMNS) + 1
    assert [line.split("|")[1].strip() for line in body] == list(CONDITIONS)


def test_figures_and_gif_are_valid_images(runs):
    d = runs["dir"]
    for name in FIGURES:
        with Image.open(d / name) as image:
            image.verify()
        with Image.open(d / name) as image:
            assert image.format == "PNG"
            assert min(image.size) >= 100
    with Image.open(d / "uncertainty_over_time.png") as image:
        width, height = image.size
        assert width > 2 * height  # three panels side by side
    summary = read_json(d / "summary.json")
    if summary["gif"] == "episode.gif":
        with Image.open(d / "episode.gif") as gif:
            assert gif.format == "GIF" and gif.n_frames > 1
    else:
        assert summary["gif"].startswith("no GIF: ")


def test_report_references_the_outputs(runs):
    d = runs["dir"]
    report = (d / "report.md").read_text()
    for name in FIGURES:
        assert f"]({name})" in report
    summary = read_json(d / "summary.json")
    gif = "![episode](episode.gif)" if summary["gif"] == "episode.gif" else summary["gif"]
    assert gif in report
    assert (d / "table.md").read_text() in report
    for stage in ("data", "models", "agent", "forecast", "truth"):
        assert f"- {stage}: " in report
    assert "\\|forecast - empirical\\| <= 0.10" in report  # a check's name, escaped
    assert broken_table_rows(report) == []


def test_summary_json(runs):
    summary = read_json(runs["dir"] / "summary.json")
    assert {"rows", "overall", "checks", "validation", "surfaces", "pattern_by_window"} <= set(
        summary
    )
    windows = summary["pattern_by_window"]
    # windows up to the horizon (2 s here), which closes them; then the bits per live step
    assert list(windows) == ["1s", "2s", "per live step"]
    assert all(len(r) == 3 and all(v > 0 for v in r.values()) for r in windows.values())
    assert list(summary["rows"]) == list(CONDITIONS)
    assert all(set(COLUMNS) <= set(row) for row in summary["rows"].values())
    for c in CONDITIONS:  # the gap with its interval over the start states
        v = summary["validation"][c]
        assert v["gap"] == pytest.approx(abs(v["gap_signed"]))
        assert v["gap_low"] <= v["gap_signed"] <= v["gap_high"] and v["gap_se"] >= 0
    assert set(summary["overall"]) == {"brier", "constant_brier", "success_rate"}
    names = set(summary["checks"])
    for condition in CONDITIONS:
        assert f"|forecast - empirical| <= 0.10 ({condition})" in names
        # where every real time agreed (no success in the quick profile's 2 s, say), a perfect
        # climatology leaves no skill to show: no check, as for the Brier skill
        crps = f"time-to-success CRPS skill > 0 ({condition})"
        assert (crps in names) == math.isfinite(summary["validation"][condition]["tts_skill"])
        assert f"competency surface: largest gap <= 0.1 ({condition})" in names
        surface = summary["surfaces"][condition]
        assert len(surface["forecast"]) == 4  # radii
        assert len(surface["forecast"][0]) == 2  # deadlines
    assert "AUROC >= 0.75 (all episodes)" in names
    assert set(summary["validation"]) == {*CONDITIONS, "overall"}
    for check in summary["checks"].values():
        assert isinstance(check["met"], bool) and isinstance(check["value"], float)
    # the forecasts from start states not scored: held-out episodes' first states in the
    # conditions of the data's own envs, fresh draws of the env's reset out of distribution
    held_out = summary["forecast_checks"]
    assert list(held_out) == list(CONDITIONS)
    for found in held_out.values():
        assert len(found["forecast"]) == len(found["real"]) == found["starts"] >= 1
        assert found["passed"] is False or found["starts"] >= found["min_starts"]
    report = (runs["dir"] / "report.md").read_text()
    assert "### The forecasts, from start states they are not scored on" in report
    # the Platt map fitted on those episodes, applied to the scored forecasts beside them
    for condition in CONDITIONS:
        after = summary["validation"][condition].get("recalibrated_held_out")
        assert (after is not None) == (condition in held_out)
        if after is not None:
            assert math.isfinite(after["slope"]) and 0 <= after["forecast"] <= 1
    assert "The held-out map (this table): the Platt map fitted on the real episodes" in report
    # every condition had its map: the pooled forecasts through them, scored over all episodes
    pooled = summary["validation"]["overall"]["recalibrated_held_out"]
    assert 0 <= pooled["forecast"] <= 1 and "slope" not in pooled
    assert "| overall | – | – |" in report
    rows = {r["condition"]: r for r in _rows(runs["dir"])}
    for condition, row in summary["rows"].items():
        assert float(rows[condition]["brier"]) == pytest.approx(row["brier"])


def test_start_states_unlike_the_training_states_are_counted_per_condition(runs):
    rows = read_json(runs["dir"] / "summary.json")["novelty"]
    assert list(rows) == list(CONDITIONS)  # training fitted the novelty check of each model
    for condition, row in rows.items():
        saved = torch.load(runs["dir"] / "forecast" / f"{condition}.pt", weights_only=True)
        assert row["starts"] == saved["p_success"].numel() == saved["novel"].numel()
        assert row["start_unlike"] == int((saved["novelty_start"] > 1).sum())
        assert row["cautioned"] == int(saved["novel"].sum()) >= row["start_unlike"]
        assert saved["novel"][saved["novelty_start"] > 1].all()
    report = (runs["dir"] / "report.md").read_text()
    assert "### Start states unlike the training states" in report
    for condition, row in rows.items():
        assert f"| {condition} | {row['starts']} | {row['start_unlike']} | " in report


def _study(run_dir: Path) -> pipeline.Study:
    from recipes.pusher_competency.config import study_config

    config = study_config({**read_json(run_dir / "study_config.json"), "run_dir": run_dir})
    return pipeline.Study(config, run_dir, torch.device("cpu"), progress=False)


def test_a_study_of_a_run_takes_only_a_device_this_machine_has(runs):
    """study_of_run refuses a device that is not here by name, before any work (an episode
    run on the CPU failed later, moving its frames to it)."""
    with pytest.raises(ValueError, match="device: 'cuda:99' asked for"):
        pipeline.study_of_run(runs["dir"], "cuda:99")
    assert pipeline.study_of_run(runs["dir"]).device == torch.device("cpu")


def test_each_condition_s_dynamics_check_is_reported(runs):
    """Each condition's env is checked to move as its world model learned: the agent's
    episodes from the forecast check's start states against its episodes in the model's own
    env, over the horizon; the report states the verdicts, and each is a check."""
    summary = read_json(runs["dir"] / "summary.json")
    report = (runs["dir"] / "report.md").read_text()
    assert "### Does each env move as its world model learned?" in report
    assert list(summary["dynamics_checks"]) == list(CONDITIONS)
    for condition, record in summary["dynamics_checks"].items():
        check = DynamicsCheck.from_dict(record)
        assert (check.episodes, check.short) == (pipeline.DYNAMICS_EPISODES, 0)
        verdict = "passed" if check.passed else "failed"
        assert f"| {condition} | {check.episodes} | {check.beyond} | " in report
        assert f"- **{condition}**: {verdict}: {check.describe()}." in report
        found = summary["checks"][DYNAMICS_CHECK.format(condition)]
        assert found == {"value": check.p_value, "met": check.passed}


def test_a_dynamics_check_finds_a_stronger_arm_and_repeats_itself(runs, monkeypatch):
    """The dynamics check of the micro run's deterministic condition, made again: the same
    verdict and p-values (its episodes are seeded); with the arm's motors at twice their gear
    in the checked episodes (not in the reference), it fails, naming arm dimensions. The
    reference starts are none of the scored or unscored start states."""
    study = _study(runs["dir"])
    saved = read_json(runs["dir"] / "summary.json")["dynamics_checks"]["deterministic"]
    again = study.dynamics_check("deterministic")
    torch.testing.assert_close(
        again.p_values, DynamicsCheck.from_dict(saved).p_values, rtol=0, atol=0, equal_nan=True
    )
    reference = study.dynamics_reference("deterministic", study.load_model("deterministic"))
    assert reference.held_out == pipeline.DYNAMICS_REFERENCE
    assert reference.steps == study.max_steps  # the horizon's transitions
    drawn = study.starts(
        "deterministic", pipeline.DYNAMICS_REFERENCE, offset=pipeline.DYNAMICS_START_SEEDS
    )
    for other in (study.starts("deterministic"), study.held_out_starts("deterministic")):
        assert not (drawn[:, None] == other[None]).all(-1).any()

    # fewer forecast-check starts than episodes: topped up with fresh draws, never repeated
    # (a deterministic env would repeat the episode, and the rank tests count it twice)
    few = study.held_out_starts("deterministic")[:7]
    seen = []
    made = study.agent_episodes

    def recorded(condition, starts, block):
        seen.append(starts)
        return made(condition, starts, block)

    monkeypatch.setattr(study, "held_out_starts", lambda condition: few)
    monkeypatch.setattr(study, "agent_episodes", recorded)
    topped = study.dynamics_check("deterministic")
    assert topped.episodes == pipeline.DYNAMICS_EPISODES and torch.equal(seen[0][:7], few)
    assert len(torch.unique(seen[0], dim=0)) == pipeline.DYNAMICS_EPISODES
    monkeypatch.undo()

    module = sys.modules[BatchedPusherEnv.__module__]
    stock = module.get_model_and_assets

    def stronger_arm():
        xml, assets = stock()
        assert b'gear=".05"' in xml
        return xml.replace(b'gear=".05"', b'gear=".1"'), assets

    monkeypatch.setattr(module, "get_model_and_assets", stronger_arm)
    stronger = study.dynamics_check("deterministic")  # the reference made above is kept
    assert not stronger.passed and stronger.p_value < 1e-6
    arm = {"shoulder_cos", "shoulder_sin", "wrist_cos", "wrist_sin", "shoulder_vel", "wrist_vel"}
    assert stronger.named() and {name.split(" ")[0] for name in stronger.named()} <= arm


def test_every_file_a_stage_wrote_is_in_its_marker_and_no_other(runs):
    """Every output of the run is in the marker of the stage that wrote it (so a damaged one
    is found and made again); a file of the user's beside them is in none, so no stage ever
    removes it."""
    d = runs["dir"]
    recorded = set()
    for stage in STAGES:
        recorded |= set(json.loads((d / "stages" / f"{stage}.json").read_text())["outputs"])
    # the training checkpoints are no output: a finished stage needs none of them
    checkpoints = f"models/{CHECKPOINTS}/"
    written = {rel for rel in runs["before"] if not rel.startswith(("stages/", checkpoints))}
    assert recorded == written
    assert {rel for rel in runs["before"] if rel.startswith(checkpoints)} == {
        f"{checkpoints}deterministic.pt",
        f"{checkpoints}stochastic.pt",
    }
    # top-level files are named one by one: no pattern that would take a user's notes
    assert not any(set("*?[") & set(pattern) for pattern in pipeline.STAGES["report"])


def test_second_run_reuses_every_stage(runs):
    log = runs["second"]
    for stage in STAGES:
        assert f"[{stage}] done earlier" in log
    assert "] running" not in log
    assert runs["after"] == runs["before"]  # nothing rewritten
    assert runs["second_s"] < 120  # imports and the report's printout only


def test_run_log_is_plain_text_and_files_keep_the_umask(runs):
    d = runs["dir"]
    log = (d / "run.log").read_text()
    assert "\x1b[" not in log, "no terminal colour codes in the log file"
    assert "\x1b[" not in runs["first"], "no colour codes on a console that is not a terminal"
    for stage in STAGES:
        assert f"[{stage}] running" in log and f"[{stage}] done earlier" in log  # both runs
    modes = {str(p.relative_to(d)): p.stat().st_mode & 0o777 for p in d.rglob("*") if p.is_file()}
    assert len(modes) > 20
    assert {name: m for name, m in modes.items() if m != 0o644} == {}  # umask 022: rw-r--r--


def test_stage_summaries_and_training_curves_reach_the_logger(runs):
    experiments = list((runs["dir"] / "logs" / "csv").glob("pusher_competency_quick_*"))
    assert len(experiments) == 2  # one per run; only the first trained
    (scalars,) = (e / "scalars" for e in experiments if (e / "scalars" / "models").is_dir())
    for variant in ("deterministic", "stochastic"):
        rows = (scalars / "models" / variant / "val_loss.csv").read_text().split()
        assert [int(r.split(",")[0]) for r in rows] == [10, 20]  # train.val_every=10, 20 steps
    marker = json.loads((runs["dir"] / "stages" / "truth.json").read_text())
    logged = (scalars / "stages" / "truth" / "stochastic" / "success_rate.csv").read_text()
    assert float(logged.split(",")[1]) == pytest.approx(marker["stochastic"]["success_rate"])


def test_tutorial_python_example_reads_the_run(runs):
    """The tutorial's "closer look" block, pointed at this run directory."""
    page = ROOT / "docs" / "tutorial.rst"
    blocks = [
        block.replace("outputs/pusher_competency/default", str(runs["dir"]))
        for block in rst_python_blocks(page)
    ]
    assert blocks
    namespace = run_blocks(blocks, "tutorial")
    assert namespace["forecast"]["epistemic"].shape[0] == START_STATES


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("train.max_step=3", "max_step"),  # not in TrainConfig's schema
        ("train.lr=-1", "train.lr: expected a positive number, got -1"),  # out of range
        ("device=tpu", "device: expected 'auto', 'cpu', 'cuda' or 'cuda:N'"),
        ("logger=tb", "logger: expected one of ['csv', 'mlflow', 'none', 'tensorboard', 'wandb']"),
    ],
)
def test_bad_settings_fail_clearly_before_anything_is_written(tmp_path, override, expected):
    proc, _ = run_recipe("profile=quick", f"run_dir={tmp_path / 'run'}", override, timeout=120)
    output = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert expected in output
    assert not (tmp_path / "run").exists()  # failed before the run directory was made


def test_a_folder_of_the_users_own_files_is_refused_and_left_as_it_was(tmp_path):
    """A stage would take files it finds under its output patterns for its unfinished outputs
    (and remove them): a directory that holds files but no run's record is refused."""
    own = tmp_path / "mine"
    (own / "data").mkdir(parents=True)
    (own / "data" / "mine.pt").write_bytes(b"mine")
    (own / "report.md").write_text("notes")
    before = _snapshot(own)
    proc, _ = run_recipe("profile=quick", f"run_dir={own}", timeout=120)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert (
        f"error: run_dir: expected a new or empty directory, or one a run made, got {str(own)!r}, "
        "which holds 'data', 'report.md' but no run's settings record ('study_config.json')"
    ) in proc.stderr
    assert _snapshot(own) == before


def test_a_run_of_other_settings_is_refused_before_it_makes_anything(runs):
    """The refusal comes before run.log and the logger's folder: the directory is as it was."""
    d = runs["dir"]
    log_before = (d / "run.log").read_bytes()
    experiments = sorted((d / "logs" / "csv").iterdir())
    proc, _ = run_recipe(*MICRO, f"run_dir={d}", "seed=1", timeout=120)
    assert proc.returncode != 0
    assert "holds a run made with other settings (['seed'] differ: seed: 0 recorded, 1 now)" in (
        proc.stderr
    )
    assert "error: run directory" in proc.stderr and "Traceback" not in proc.stderr
    assert (d / "run.log").read_bytes() == log_before
    assert sorted((d / "logs" / "csv").iterdir()) == experiments
    assert _snapshot(d) == runs["after"]


def test_held_out_checks_benchmark_judges_the_run_both_ways(runs):
    """``benchmarks/held_out_checks.py`` on a finished run: the open-loop replays of the
    held-out episodes' actions and the report's own closed-loop check."""
    from rcvae_torchrl.data import episode_spans
    from recipes.pusher_competency.config import study_config

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from held_out_checks import open_loop

    config = study_config({**read_json(runs["dir"] / "study_config.json"), "run_dir": runs["dir"]})
    study = pipeline.Study(config, runs["dir"], torch.device("cpu"), progress=False)
    _, held_out = study.episodes("stochastic")
    long_enough = int((episode_spans(held_out)[1] >= study.max_steps).sum())
    check = open_loop(study, "stochastic", replays=3, samples=2)
    assert check.runs == 3 and check.starts == long_enough >= 1
    assert bool(((check.forecast >= 0) & (check.forecast <= 1)).all())
    assert bool(torch.isin(check.real * 3, torch.arange(4.0, dtype=torch.float64)).all())
    closed = study.forecast_check("stochastic")
    saved = read_json(runs["dir"] / "summary.json")["forecast_checks"]["stochastic"]
    assert json.dumps(closed.as_dict()) == json.dumps(saved)  # the report's, made again (NaN too)


def test_dynamics_check_benchmark_counts_the_batches_a_change_fails(runs, tmp_path):
    """``benchmarks/dynamics_check.py`` on a finished run: the study's check, with its own
    reference, on batches from fresh starts in the stock env and in one whose motors are twice
    as strong (failed, as the check's own test finds); a change it does not know is refused."""
    script = ROOT / "benchmarks" / "dynamics_check.py"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = tmp_path / "dynamics"
    args = [
        sys.executable, str(script), str(runs["dir"]), "--batches", "1", "--episodes", "12",
        "--conditions", "deterministic", "--changes", "gear=2.0", "--out", str(out),
    ]  # fmt: skip
    proc = subprocess.run(args, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = read_json(out.with_suffix(".json"))["results"]
    assert [(r["change"], len(r["batches"])) for r in results] == [("none", 3), ("gear", 1)]
    assert results[1]["failed"] == 1 and results[1]["size_only_failed"] == 1
    for r in results:
        for batch in r["batches"]:
            assert DynamicsCheck.from_dict(batch["check"]).episodes == 12
            assert 0.0 <= batch["success"] <= 1.0
    bad = subprocess.run([*args[:-4], "--changes", "wind=2"], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert bad.returncode == 2 and "expected NAME=FACTOR with NAME one of" in bad.stderr


def test_novelty_benchmark_fits_the_check_as_training_does(runs, monkeypatch):
    """``benchmarks/novelty.py`` on a finished run: the models' own checks, or (for models
    trained before the check existed) the same check fitted again; the report's counts."""
    from recipes.pusher_competency.pusher import WORLD_MODELS

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from novelty import condition_rows, novelty_of

    changes = {"assess": {"samples_per_member": 2, "bias_correction": "none"}}
    study = pipeline.study_of_run(runs["dir"], changes=changes)
    own = {name: novelty_of(study, name) for name in WORLD_MODELS}
    assert all(found[2] and found[1] == 0.0 for found in own.values())  # training fitted them
    load = study.load_model

    def without_check(name):
        model = load(name)
        model.novelty = None
        return model

    monkeypatch.setattr(study, "load_model", without_check)
    for name in WORLD_MODELS:
        again, seconds, is_own = novelty_of(study, name)
        assert not is_own and seconds > 0
        assert torch.equal(again.states, own[name][0].states) and again.level == own[name][0].level
    monkeypatch.setattr(study, "load_model", load)
    rows = condition_rows(study, {name: found[0] for name, found in own.items()})
    saved = read_json(runs["dir"] / "summary.json")["novelty"]
    for condition in CONDITIONS:  # the starts' verdicts do not depend on the samples
        assert rows[condition]["start_unlike"] == saved[condition]["start_unlike"]
        assert rows[condition]["starts"] == saved[condition]["starts"]
        assert 0.0 <= rows[condition]["imagined_share_mean"] <= 1.0


def test_the_unscored_start_states_of_each_condition(runs):
    """The forecast check's start states: the held-out episodes' first states in the world
    models' own envs, then fresh draws of the condition's env's reset up to
    assess.check_episodes real episodes; none of them a scored start, the same in every call."""
    from rcvae_torchrl.data import episode_spans
    from recipes.pusher_competency.config import study_config

    config = study_config({**read_json(runs["dir"] / "study_config.json"), "run_dir": runs["dir"]})
    study = pipeline.Study(config, runs["dir"], torch.device("cpu"), progress=False)
    for condition, (model, variant) in CONDITIONS.items():
        unscored = study.held_out_starts(condition)
        episodes = -(-study.cfg.assess.check_episodes // study.runs_per_start(variant))
        first = torch.empty(0, 14)
        if model == variant:
            _, held_out = study.episodes(model)
            first = held_out["observation"][episode_spans(held_out)[0]]
        assert len(unscored) == max(len(first), episodes), condition
        assert torch.equal(unscored[: len(first)], first)
        assert torch.equal(unscored, study.held_out_starts(condition))
        scored = study.starts(condition)
        assert not (unscored[:, None] == scored[None]).all(-1).any()  # no scored start among them


def test_the_report_opens_with_what_each_forecast_can_be_trusted_for(runs):
    """Before its table, the report says per condition what a person would be told before any
    scored outcome: the mean forecast and its forecast check's verdict."""
    report = (runs["dir"] / "report.md").read_text()
    summary = read_json(runs["dir"] / "summary.json")
    told = report.index("## What the forecasts can be trusted for")
    assert told < report.index("## Table")
    section = report[told : report.index("## Table")]
    from rcvae_torchrl.training import OutcomeCheck

    for condition, row in summary["rows"].items():
        check = OutcomeCheck.from_dict(summary["forecast_checks"][condition])
        line = f"- **{condition}**: forecast {row['forecast_p_success']:.2f}"
        assert line in section, condition
        said = f"on {check.starts} start states" if check.measured else check.verdict
        assert said in section[section.index(line) :].split("\n")[0], condition


def test_the_forecast_check_imagines_fewer_samples_only_where_a_start_runs_once(runs, monkeypatch):
    """Where each of the forecast check's starts is run once (a deterministic env), only the
    forecasts' mean is judged: they are made with assess.check_samples_per_member samples per
    member, as many trajectories per chunk of starts; where a start runs several times (the
    stochastic env) each start's forecast is judged too, and made as the scored ones are."""
    study = pipeline.study_of_run(
        runs["dir"], changes={"assess": {"check_episodes": 12, "check_samples_per_member": 2}}
    )
    s = study.cfg.assess
    assert s.samples_per_member == 4  # the quick profile's: 2 per member is fewer
    asked = []
    assessor = pipeline.Study.assessor

    def spy(self, model_name, variant, samples_per_member=None):
        made = assessor(self, model_name, variant, samples_per_member)
        asked.append((variant, made.samples_per_member, made.start_chunk))
        return made

    monkeypatch.setattr(pipeline.Study, "assessor", spy)
    for condition in ("deterministic", "stochastic"):
        forecast, success = study.held_out_outcomes(condition)
        starts = study.held_out_starts(condition)
        assert forecast.shape == (len(starts),) and success.shape[0] == len(starts)
        assert ((forecast >= 0) & (forecast <= 1)).all()
    assert asked == [
        ("deterministic", 2, s.start_chunk * 2),  # 4 / 2 samples: twice the starts per chunk
        ("stochastic", s.samples_per_member, s.start_chunk),
    ]


def test_no_scored_start_begins_a_data_episode(runs):
    """At seed 0 the data's collection seeds the deterministic env with the seeds the scored
    starts begin at, so the first draw is a data episode's first state: the scored starts (and
    those drawn past them) pass over every such draw for the next seed, and stay as many."""
    from rcvae_torchrl.data import episode_spans, load_episodes, seed_env
    from recipes.pusher_competency.pusher import WORLD_MODELS

    study = _study(runs["dir"])
    assert study.cfg.seed == 0
    firsts = []
    for variant in WORLD_MODELS:
        data = load_episodes(runs["dir"] / "data" / f"{variant}.pt")
        firsts.append(data["observation"][episode_spans(data)[0]])
    firsts = torch.cat(firsts)
    env = study.env("deterministic")
    seed_env(env, 0)  # the deterministic condition's first seed at study seed 0
    assert (env.reset()["observation"] == firsts).all(-1).any()  # a data episode's first state
    for condition in CONDITIONS:
        for starts in (study.starts(condition), study.starts(condition, 12, offset=1)):
            assert not (starts[:, None] == firsts[None]).all(-1).any(), condition
            assert len(starts.unique(dim=0)) == len(starts) in (START_STATES, 12)
    for seed in range(1, 100):  # to the first seed no data episode began with
        seed_env(env, seed)
        first = env.reset()["observation"]
        if not (first == firsts).all(-1).any():
            break
    assert torch.equal(study.starts("deterministic")[0], first)


def test_demonstrations_side_by_side(runs):
    """agent.demo_envs: the MPC episodes in one batched env, one plan of all states per step;
    every episode recorded (a padded last group dropped), the same under the same seed."""
    from recipes.pusher_competency.config import study_config

    saved = read_json(runs["dir"] / "study_config.json")
    saved["agent"] |= {"mpc_episodes": 3, "demo_envs": 2}
    config = study_config({**saved, "run_dir": runs["dir"]})
    study = pipeline.Study(config, runs["dir"], torch.device("cpu"), progress=False)
    model = study.load_model("deterministic")
    env = study.env("deterministic", time_limit=config.assess.horizon_s)
    demos = [study._demonstrations(model, env) for _ in range(2)]
    info, pairs = demos[0]["info"], int(demos[0]["info"]["pairs"])
    assert demos[0]["observations"].shape == (pairs, 14) and demos[0]["labels"].shape == (pairs, 2)
    assert 3 <= pairs <= 3 * study.max_steps
    assert info["mpc_noisy_success_rate"] * 3 == pytest.approx(
        round(info["mpc_noisy_success_rate"] * 3)
    )
    for key in ("observations", "labels"):
        assert torch.equal(demos[0][key], demos[1][key]), key


def test_a_new_run_reuses_the_stages_whose_settings_are_the_same(runs, tmp_path):
    """``reuse_from``: a run that changes how forecasts are made takes the finished run's data,
    world models and agent (hard links of the same files) and runs the later stages; one that
    changes the horizon (which the agent acts within) also trains its own agent."""
    first = runs["dir"]
    chunked = tmp_path / "chunked"
    proc, _ = run_recipe(
        *MICRO, f"run_dir={chunked}", f"reuse_from={first}", "assess.start_chunk=1"
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for stage in ("data", "models", "agent"):
        assert f"[{stage}] reusing the finished stage of {str(first)!r}" in proc.stdout
        for rel in json.loads((chunked / "stages" / f"{stage}.json").read_text())["outputs"]:
            assert (chunked / rel).stat().st_ino == (first / rel).stat().st_ino, rel
    for stage in ("forecast", "truth", "report"):
        assert f"[{stage}] running" in proc.stdout
    report = (chunked / "report.md").read_text()
    ran = json.loads((first / "stages" / "models.json").read_text())["seconds"]
    where = re.escape(f"(reused from {str(first)!r}, where it took {ran} s)")
    assert re.search(rf"- models: [0-9.]+ s {where}", report), report[-600:]
    # the same agent from the same starts: the real episodes come out the same
    for condition in CONDITIONS:
        rel = f"truth/{condition}.pt"
        assert (chunked / rel).read_bytes() == (first / rel).read_bytes(), rel
    longer = tmp_path / "longer"
    proc, _ = run_recipe(*MICRO, f"run_dir={longer}", f"reuse_from={first}", "assess.horizon_s=3.0")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "[models] reusing the finished stage of" in proc.stdout
    assert "settings it reads differ (assess.horizon_s: 2.0 there, 3.0 here)" in proc.stdout
    assert "[agent] not reused from" in proc.stdout and "[agent] running" in proc.stdout


@pytest.mark.parametrize(
    ("where", "expected"),
    [
        ("missing", "reuse_from: expected a run directory (with its study_config.json), got"),
        ("itself", "reuse_from: expected another directory than run_dir"),
    ],
)
def test_a_bad_reuse_from_is_refused_before_anything_is_written(runs, tmp_path, where, expected):
    run_dir = runs["dir"] if where == "itself" else tmp_path / "run"
    other = run_dir if where == "itself" else tmp_path / "nothing"
    snapshot = _snapshot(run_dir) if where == "itself" else None
    proc, _ = run_recipe(*MICRO, f"run_dir={run_dir}", f"reuse_from={other}", timeout=120)
    assert proc.returncode != 0 and expected in proc.stdout + proc.stderr
    if where == "itself":
        assert _snapshot(run_dir) == snapshot
    else:
        assert not run_dir.exists()

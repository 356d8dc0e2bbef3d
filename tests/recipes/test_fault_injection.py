"""Fault injection into a finished run of the Pusher recipe: every stage file is damaged
(garbage, truncation, deletion) and the run is started again.

Every case must end in a correct rerun (afterwards every file recorded in every stage marker
matches its size and SHA-256, and the damage shows in the log; the damaged file is made again,
or, for a file the finished stage no longer needs such as a training checkpoint, dropped from
its marker) or in a refusal naming the file;
never in a "success" that keeps a bad file. The default suite damages a handful of files;
``test_every_file_and_every_damage`` (slow) goes through all of them.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from micro import MICRO  # the quick profile, smaller still (as the end-to-end recipe test)

from rcvae_torchrl.io import StoredFileError
from rcvae_torchrl.stages import StageError, file_record
from recipes.pusher_competency.config import register_configs, study_config
from recipes.pusher_competency.pipeline import STAGES, run_study

CONF = Path(__file__).resolve().parents[2] / "recipes" / "pusher_competency" / "conf"
register_configs()
DAMAGES = ("garbage", "truncate", "delete")


def _run(run_dir: Path) -> tuple[dict, list[str]]:
    lines: list[str] = []
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name="pusher_competency", overrides=[*MICRO, f"run_dir={run_dir}"])
    config = study_config(cfg)
    return run_study(config, run_dir, progress=False, log=lines.append), lines


def _outputs(run_dir: Path, stage: str) -> dict:
    return json.loads((run_dir / "stages" / f"{stage}.json").read_text())["outputs"]


def _stage_files(run_dir: Path) -> list[str]:
    """Every file a stage reads back: the outputs recorded in the markers, the markers and the
    run config."""
    files = ["study_config.json"]
    for name in STAGES:
        files += [f"stages/{name}.json", *_outputs(run_dir, name)]
    return files


def _damage(path: Path, how: str) -> None:
    if how == "delete":
        path.unlink()
    elif how == "edit":  # a number changed by hand: the file stays valid JSON
        content = json.loads(path.read_text())
        path.write_text(json.dumps({**content, "seconds": content["seconds"] + 1000}))
    elif how == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    else:
        path.write_bytes(b"\x00garbage\xff" * 7)


def _verified(run_dir: Path) -> None:
    """Every marker readable, every recorded file present with its recorded size and hash."""
    for name in STAGES:
        for rel, record in _outputs(run_dir, name).items():
            assert file_record(run_dir / rel) == record, f"{rel} does not match its marker"
    json.loads((run_dir / "study_config.json").read_text())


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("finished") / "run"
    summaries, _ = _run(run_dir)
    assert set(summaries) == set(STAGES)
    return run_dir


def _inject(finished: Path, tmp_path: Path, rel: str, how: str) -> str:
    """Damage ``rel`` in a copy of the finished run and run again: 'rerun' or 'refused'."""
    run_dir = tmp_path / "run"
    shutil.copytree(finished, run_dir)
    target = run_dir / rel
    _damage(target, how)
    try:
        summaries, lines = _run(run_dir)
    except (StageError, StoredFileError, ValueError) as err:
        assert rel in str(err) or target.name in str(err), f"refusal names no file: {err}"
        return "refused"
    assert set(summaries) == set(STAGES)
    _verified(run_dir)
    recorded = {r for name in STAGES for r in _outputs(run_dir, name)}
    if not target.is_file():  # a file the finished stage no longer needs (a checkpoint)
        assert rel not in recorded, f"{rel} is recorded but was not made again"
        return "rerun, dropped"
    if target.read_bytes() == (finished / rel).read_bytes():
        return "rerun, identical"
    stage = rel.split("/")[1].removesuffix(".json") if rel.startswith("stages/") else None
    noted = [
        line
        for line in lines
        if rel in line or (stage and line.startswith(f"[{stage}] ")) or "[settings]" in line
    ]
    assert any("again" in line or "running" in line for line in noted), lines
    return "rerun"


# A handful of files across the stages, one damage each (the default suite).
SAMPLE = [
    ("models/deterministic.pt", "garbage"),
    ("forecast/stochastic.pt", "truncate"),
    ("agent/policy.pt", "garbage"),
    ("truth/deterministic.pt", "truncate"),
    ("stages/agent.json", "truncate"),
    ("stages/report.json", "garbage"),
    ("stages/truth.json", "edit"),
    ("study_config.json", "truncate"),
    ("data/stochastic.pt", "delete"),
]


@pytest.mark.parametrize(("rel", "how"), SAMPLE, ids=[f"{r}-{h}" for r, h in SAMPLE])
def test_a_damaged_stage_file_is_remade_or_refused_by_name(finished, tmp_path, rel, how):
    outcome = _inject(finished, tmp_path, rel, how)
    assert outcome in ("rerun", "rerun, identical", "rerun, dropped", "refused")


@pytest.mark.slow
def test_every_file_and_every_damage(finished, tmp_path):
    outcomes = {}
    for rel in _stage_files(finished):
        for how in DAMAGES:
            case = tmp_path / f"{rel.replace('/', '_')}-{how}"
            outcomes[rel, how] = _inject(finished, case, rel, how)
    assert len(outcomes) == 3 * len(_stage_files(finished))
    counts = {kind: list(outcomes.values()).count(kind) for kind in set(outcomes.values())}
    print(f"fault injection: {len(outcomes)} cases: {counts}")
    for (rel, how), outcome in sorted(outcomes.items()):
        print(f"  {rel:40s} {how:9s} {outcome}")


def test_a_stage_run_again_says_which_of_its_files_it_keeps(finished, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(finished, run_dir)
    (run_dir / "data" / "stochastic.pt").unlink()
    _, lines = _run(run_dir)
    assert "[data] data/deterministic.pt written earlier: taken as they are" in lines
    assert "[models] done earlier" in " ".join(lines)  # the remade data is the same

"""The README and the docs quote durations from one source: benchmarks/results/durations.json."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import durations  # noqa: E402  (benchmarks/ is not a package)

QUOTING = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.rst"))]
QUOTING += sorted((ROOT / "recipes").glob("*/main.py"))
DURATION = re.compile(r"(\d+(?:\.\d+)?)\s*(?:minutes?|min)\b")
VAGUE = re.compile(r"(?:a few|several) (?:minutes|seconds)|about \d+ min|~\s*\d+ ?min", re.I)


def test_readme_table_is_the_json():
    readme = (ROOT / "README.md").read_text()
    assert durations.render_table(durations.load()) in readme


def test_the_readme_states_the_test_suite_duration():
    record = durations.load()
    assert "test_suite" in record["entries"], "run: python benchmarks/durations.py tests"
    entry = record["entries"]["test_suite"]
    assert entry["threads"] == 1 and entry["seconds"] > 0
    assert f"| {durations.minutes(entry['seconds'])} | 1 |" in (ROOT / "README.md").read_text()


def test_every_quoted_duration_is_a_recorded_one():
    recorded = {f"{e['seconds'] / 60:.1f}" for e in durations.load()["entries"].values()}
    for path in QUOTING:
        text = path.read_text()
        quoted = set(DURATION.findall(text))
        assert quoted <= recorded, f"{path.name} quotes {sorted(quoted - recorded)} min"
        assert not VAGUE.findall(text), f"{path.name}: {VAGUE.findall(text)}"


def test_a_run_directory_gives_its_profile_threads_and_stage_time(tmp_path):
    run = tmp_path / "run"
    (run / "stages").mkdir(parents=True)
    (run / "run.log").write_text("profile=quick device=cpu threads=1 run_dir=x\n[data] running\n")
    for name, seconds in [("data", 19.2), ("models", 3.2), ("report", 14.5)]:
        (run / "stages" / f"{name}.json").write_text(json.dumps({"seconds": seconds}))
    key, entry = durations.read_run(run)
    assert key == "quick_profile"
    assert entry["threads"] == 1 and entry["seconds"] == pytest.approx(36.9)
    assert entry["source"] == "the stage markers of a quick run"
    (run / "run.log").write_text("profile=full device=cuda:0 threads=1 run_dir=x\n")
    key, entry = durations.read_run(run)
    assert key == "full_profile" and entry["source"] == "the stage markers of a full run on cuda:0"
    for extra, why in [
        ({"attempts": 2}, r"stage 'models' finished at attempt 2 \(the earlier ones' time"),
        ({"reused_from": {"run_dir": "y"}}, "stage 'models' was reused from another run"),
    ]:
        (run / "stages" / "models.json").write_text(json.dumps({"seconds": 3.2, **extra}))
        with pytest.raises(ValueError, match=why):
            durations.read_run(run)
    (run / "stages" / "report.json").unlink()
    with pytest.raises(ValueError, match="has not finished"):
        durations.read_run(run)


def test_the_table_is_rewritten_between_its_markers(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{durations.BEGIN}\nold\n{durations.END}\nafter\n")
    record = {
        "entries": {
            "quick_profile": {
                "seconds": 90.0,
                "threads": 1,
                "machine": {"cpus": 2, "machine": "x86_64"},
                "loadavg_1min": 4.8,
                "source": "a test",
            }
        }
    }
    durations.write_readme(record, readme)
    text = readme.read_text()
    assert text.startswith("intro\n") and text.endswith("after\n") and "old" not in text
    assert "| `make run-quick` (the recipe's quick profile) | 1.5 min | 1 | 2 CPU cores" in text
    assert (
        "| `make test` (the default test suite) | not measured yet "
        "(`python benchmarks/durations.py tests`) |" in text
    )


def test_the_suite_is_timed_with_its_thread_count_and_summary(tmp_path):
    case = tmp_path / "test_tiny.py"
    case.write_text(
        "import os\n\ndef test_threads():\n    assert os.environ['OMP_NUM_THREADS'] == '1'\n"
    )
    entry = durations.time_tests(1, (str(case),))
    assert entry["threads"] == 1 and entry["seconds"] >= entry["cpu_seconds"] / 2 > 0
    assert entry["source"].startswith("measured: 1 passed")
    case.write_text("def test_fails():\n    assert False\n")
    with pytest.raises(SystemExit, match=r"the test suite failed \(.*1 failed"):
        durations.time_tests(1, (str(case),))

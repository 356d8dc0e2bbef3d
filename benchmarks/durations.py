"""How long things take: the one source of every duration the README and the docs quote.

Each subcommand measures (or records) one duration into ``benchmarks/results/durations.json``,
with the torch threads, the machine and the load, then rewrites the durations table in
``README.md`` (between the ``durations`` markers) from the JSON; a test checks that the README and
the docs quote nothing else.

    python benchmarks/durations.py tests [--threads 1]   # times the default suite as `make test`
    python benchmarks/durations.py run outputs/pusher_competency/quick   # a finished recipe run
    python benchmarks/durations.py record default_profile 684 --threads 2 --source "..."
    python benchmarks/durations.py readme                # only rewrite the README's table

``tests`` runs the suite as ``make test`` does (its files spread over the cores: pytest-xdist's
``-n auto --dist loadfile``) with ``OMP_NUM_THREADS`` set to ``--threads`` (1 by default; the
tests set torch to 1 thread themselves), leaving out the one test that checks this benchmark's own
test-suite entry (it cannot hold before the suite has been timed once). ``run`` reads a run
directory: the profile and threads from the first line of its ``run.log``, the time from its
stage markers (the stages' own seconds, summed: a run resumed in several goes counts its stages
once; the imports before the first stage are not counted).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the library, when run from a checkout without installing it

from rcvae_torchrl.io import atomic_write, read_json, write_json  # noqa: E402
from rcvae_torchrl.stages import MARKERS  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "durations.json"
README = ROOT / "README.md"
BEGIN = (
    "<!-- durations: written by benchmarks/durations.py from benchmarks/results/durations.json -->"
)
END = "<!-- /durations -->"

#: The test of this benchmark's own output, which cannot hold before the suite has been timed.
OWN_TEST = "tests/test_durations_quoted.py::test_the_readme_states_the_test_suite_duration"

#: What each entry is, as the README's table names it (in this order).
WHAT = {
    "test_suite": "`make test` (the default test suite)",
    "quick_profile": "`make run-quick` (the recipe's quick profile)",
    "default_profile": "`make run` (the recipe's default profile)",
    "default_profile_second_machine": "`make run`, on a second 2-core machine (an AMD EPYC)",
    "weak_arm_profile": "`make run PROFILE=weak_arm` (the default without per-step noise)",
    "action_noise_profile": "`make run PROFILE=action_noise` (the first stochastic design)",
    "full_profile": "`recipes/pusher_competency/main.py profile=full device=cuda` (on a GPU)",
}


def load(path: Path = RESULTS) -> dict[str, Any]:
    """The recorded durations (an empty record when there are none yet)."""
    if not path.is_file():
        return {"benchmark": "durations", "entries": {}}
    return json.loads(path.read_text())


def minutes(seconds: float) -> str:
    """A duration as the docs quote it: minutes with one decimal (``"11.4 min"``)."""
    return f"{seconds / 60:.1f} min"


def machine_text(machine: dict[str, Any]) -> str:
    return f"{machine['cpus']} CPU cores ({machine['machine']})"


def render_table(record: dict[str, Any]) -> str:
    """The README's durations table (Markdown) of ``record``."""
    lines = [
        BEGIN,
        "",
        "| what | took | torch threads | machine | 1-minute load | measured |",
        "|:---|---:|---:|:---|---:|:---|",
    ]
    for key, what in WHAT.items():
        entry = record["entries"].get(key)
        if entry is None:
            command = {"test_suite": "tests"}.get(key, "run <run_dir>")
            lines.append(
                f"| {what} | not measured yet (`python benchmarks/durations.py {command}`) "
                "| | | | |"
            )
            continue
        load = entry.get("loadavg_1min")
        lines.append(
            f"| {what} | {minutes(entry['seconds'])} | {entry['threads']} | "
            f"{machine_text(entry['machine'])} | {'' if load is None else f'{load:.1f}'} | "
            f"{entry['source']} |"
        )
    return "\n".join([*lines, "", END])


def write_readme(record: dict[str, Any], readme: Path = README) -> None:
    """Replace the table between the markers in ``readme`` by :func:`render_table`."""
    text = readme.read_text()
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise ValueError(f"{readme}: expected the markers {BEGIN!r} ... {END!r}")
    new = text[:start] + render_table(record) + text[end + len(END) :]
    atomic_write(readme, lambda f: f.write(new.encode()))


def _machine() -> dict[str, Any]:
    return {"cpus": os.cpu_count(), "machine": platform.machine(), "python": sys.version.split()[0]}


def _save(key: str, entry: dict[str, Any]) -> None:
    record = load()
    record["entries"][key] = {
        "machine": _machine(),
        "recorded_on": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
        **entry,
    }
    write_json(RESULTS, record)
    write_readme(record)
    print(f"{key}: {minutes(entry['seconds'])} ({entry['seconds']:.0f} s), wrote {RESULTS}")


def time_tests(threads: int, paths: tuple[str, ...] = ()) -> dict[str, Any]:
    """Wall and CPU seconds of the default suite (or ``paths``), run as ``make test`` runs it."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    load_before = os.getloadavg()[0]
    cpu_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-n",
            "auto",
            "--dist",
            "loadfile",
            "-p",
            "no:cacheprovider",
            "--deselect",
            OWN_TEST,
            *paths,
        ],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    seconds = time.perf_counter() - start
    cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = cpu.ru_utime + cpu.ru_stime - cpu_before.ru_utime - cpu_before.ru_stime
    summary = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    if proc.returncode != 0:
        print("\n".join(proc.stdout.splitlines()[-80:]), file=sys.stderr)  # what failed
        raise SystemExit(f"the test suite failed ({summary}); nothing recorded")
    return {
        "seconds": round(seconds, 1),
        "cpu_seconds": round(cpu_s, 1),  # what it would take on free cores, near enough
        "threads": threads,
        "loadavg_1min": round((load_before + os.getloadavg()[0]) / 2, 2),
        "source": f"measured: {summary}",
    }


def read_run(run_dir: Path) -> tuple[str, dict[str, Any]]:
    """``(entry key, entry)`` of a finished recipe run in ``run_dir``."""
    first = (run_dir / "run.log").read_text().splitlines()[0]
    found = dict(re.findall(r"(\w+)=(\S+)", first))
    if "profile" not in found or "threads" not in found:
        raise ValueError(f"{run_dir / 'run.log'}: expected 'profile=... threads=...' first")
    markers = sorted((run_dir / MARKERS).glob("*.json"))
    if not any(m.stem == "report" for m in markers):
        raise ValueError(f"{run_dir}: the run has not finished (no report stage marker)")
    saved = {m.stem: read_json(m, "stage marker", checksum=True) for m in markers}
    for stage, marker in saved.items():  # a stage's seconds must be all of its time
        if "attempts" in marker or "reused_from" in marker:
            why = (
                f"finished at attempt {marker['attempts']} (the earlier ones' time is not known)"
                if "attempts" in marker
                else "was reused from another run (its seconds are the placing of its files)"
            )
            raise ValueError(f"{run_dir}: stage {stage!r} {why}; record a run that ran through")
    seconds = sum(marker["seconds"] for marker in saved.values())
    where = f" on {found['device']}" if found.get("device", "cpu") != "cpu" else ""
    entry = {
        "seconds": round(seconds, 1),
        "threads": int(found["threads"]),
        "source": f"the stage markers of a {found['profile']} run{where}",
    }
    return f"{found['profile']}_profile", entry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    tests = sub.add_parser("tests", help="time the default test suite")
    tests.add_argument("--threads", type=int, default=1)
    run = sub.add_parser("run", help="record a finished recipe run from its run directory")
    run.add_argument("run_dir", type=Path)
    run.add_argument("--load", type=float, default=None, help="1-minute load average then")
    record = sub.add_parser("record", help="record a duration measured elsewhere")
    record.add_argument("key", choices=list(WHAT))
    record.add_argument("seconds", type=float)
    record.add_argument("--threads", type=int, required=True)
    record.add_argument("--source", required=True)
    record.add_argument("--load", type=float, default=None, help="1-minute load average then")
    sub.add_parser("readme", help="rewrite the README's table from the JSON")
    args = parser.parse_args()
    if args.command == "tests":
        _save("test_suite", time_tests(args.threads))
    elif args.command == "run":
        key, entry = read_run(args.run_dir)
        _save(key, entry if args.load is None else {**entry, "loadavg_1min": args.load})
    elif args.command == "record":
        entry = {"seconds": args.seconds, "threads": args.threads, "source": args.source}
        _save(args.key, entry if args.load is None else {**entry, "loadavg_1min": args.load})
    else:
        write_readme(load())


if __name__ == "__main__":
    main()

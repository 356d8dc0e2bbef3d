"""Fingerprints of code and values: equal for the same behaviour, different when it can change."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from rcvae_torchrl.fingerprint import describe, digest

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 0.5
_CACHE: dict[str, float] = {}  # state, not code: filling it must not change a digest


def _above(x: float):
    return lambda observation: observation[..., 0] > x


def _reads_a_constant(observation):
    return observation[..., 0] > LIMIT


def _helper(observation):
    return observation.abs()


def _calls_a_helper(observation):
    _CACHE.setdefault("calls", 0.0)
    return _helper(observation).sum(-1) > 1.0


def _with_a_set(name):
    return name in {"alpha", "beta", "gamma", "delta"}


def test_the_same_function_has_the_same_digest():
    assert digest(_above(0.1)) == digest(_above(0.1))
    assert digest(_reads_a_constant) == digest(_reads_a_constant)


def test_closure_values_and_bound_arguments_change_it():
    assert digest(_above(0.1)) != digest(_above(0.2))
    partial = functools.partial(lambda observation, x: observation > x, x=1.0)
    assert digest(partial) != digest(functools.partial(partial.func, x=2.0))
    assert digest(_above(torch.zeros(3))) != digest(_above(torch.ones(3)))


def test_module_constants_and_helpers_are_followed(monkeypatch):
    before = digest(_reads_a_constant)
    monkeypatch.setattr(sys.modules[__name__], "LIMIT", 0.7)
    assert digest(_reads_a_constant) != before
    helper = describe(_calls_a_helper)["globals"]["_helper"]
    assert helper["function"].endswith("._helper")


def test_mutable_module_state_is_not_part_of_it():
    before = digest(_calls_a_helper)
    _CACHE["filled"] = 1.0
    assert digest(_calls_a_helper) == before
    assert "_CACHE" not in describe(_calls_a_helper)["globals"]


def test_another_interpreter_gives_the_same_digest():
    """No addresses and no hash-seed-dependent order (set literals) in the description: an
    interpreter with another hash seed than this one's agrees."""
    code = (
        "import sys; sys.path[:0] = ['tests', '.']\n"
        "import test_fingerprint as t; from rcvae_torchrl.fingerprint import digest\n"
        "print(digest(t._with_a_set), digest(t._above(0.1)), digest(t._calls_a_helper))"
    )

    def run(seed: str) -> str:
        env = {**os.environ, "PYTHONHASHSEED": seed}
        command = [sys.executable, "-c", code]
        return subprocess.run(
            command, capture_output=True, text=True, check=True, cwd=ROOT, env=env
        ).stdout

    assert run("1").split() == [digest(_with_a_set), digest(_above(0.1)), digest(_calls_a_helper)]


def test_a_task_digest_names_the_parts_another_task_differs_in():
    """A refusal of another task names what differs (the trial's "task 3f2a… against 9c1e…"
    told the user nothing): boundary, deadline, step or world model, each on its own."""
    from rcvae_torchrl.fingerprint import task_difference, task_digest

    weights = {"w": torch.ones(3)}
    base = task_digest("predicates-a", 60, 0.05, weights)
    assert base == task_digest("predicates-a", 60, 0.05, {"w": torch.ones(3)})
    assert task_difference(base, base) == ""
    other_weights = task_digest("predicates-a", 60, 0.05, {"w": torch.zeros(3)})
    assert (
        task_difference(other_weights, base)
        == "another world model (its weights, config or functions)"
    )
    sooner = task_digest("predicates-a", 40, 0.05, weights)
    assert task_difference(sooner, base) == "another deadline (40 steps there, 60 steps here)"
    assert task_difference(task_digest("predicates-b", 60, 0.1, weights), base) == (
        "another boundary (its predicates' code or values) and another step (dt) "
        "(0.1 there, 0.05 here)"
    )
    assert task_difference(task_digest("predicates-a", 60, None, weights), base) == (
        "another step (dt) (None there, 0.05 here)"
    )
    # a boundary without a time limit (inf) has a deadline of none
    unlimited = task_digest("predicates-a", float("inf"), 0.05, weights)
    assert task_difference(unlimited, base) == "another deadline (none there, 60 steps here)"
    # an older record's plain digest is another task, with no part to name
    assert task_difference("3f2a" * 16, base) == "another task"


def test_values_kept_in_slots_count():
    """A trial's boundary held its radius in a ``dataclass(slots=True)``: objects without a
    ``__dict__`` were described by their class alone, and every radius had one digest."""
    import dataclasses

    from rcvae_torchrl.competency import SuccessBoundary

    @dataclasses.dataclass(frozen=True, slots=True)
    class Near:
        radius: float

        def __call__(self, observation):
            return observation[..., 0].abs() <= self.radius

    class Plain:
        __slots__ = ("limit",)

        def __init__(self, limit):
            self.limit = limit

    assert digest(Near(0.03)) != digest(Near(0.5)) and digest(Near(0.03)) == digest(Near(0.03))
    assert digest(Plain(1.0)) != digest(Plain(2.0))
    boundaries = [SuccessBoundary(Near(r), time_limit=5) for r in (0.03, 0.5)]
    assert boundaries[0].predicates != boundaries[1].predicates


def test_a_tasks_digest_ignores_an_unrelated_edit_of_the_file_defining_it(tmp_path, monkeypatch):
    """A trial changed ``NUMBER_OF_STARTS = 100`` to 200 in the script defining its model's
    constraint and boundary: its saved checks were then refused as of "another world model"."""
    import importlib

    from rcvae_torchrl.competency import SuccessBoundary

    source = (
        "NUMBER_OF_STARTS = {n}\nLIMIT = {limit}\n\ndef near(o):\n    return o[..., 0] < LIMIT\n"
    )
    module = tmp_path / "task_module_for_digest.py"
    module.write_text(source.format(n=100, limit=0.5))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)  # each reload reads the source
    mod = importlib.import_module("task_module_for_digest")

    def predicates():
        return SuccessBoundary(mod.near, time_limit=5).predicates, digest(mod.near, sources=False)

    before = predicates()
    module.write_text(source.format(n=200, limit=0.5))  # an unrelated line
    importlib.reload(mod)
    assert predicates() == before
    module.write_text(source.format(n=200, limit=0.6))  # the value the predicate reads
    importlib.reload(mod)
    assert predicates()[0] != before[0] and predicates()[1] != before[1]


def test_a_large_numpy_array_is_hashed_by_its_values():
    """NumPy abridges the repr of an array of more than 1000 elements (``[0., 0., ..., 0.]``):
    two arrays that differ in the middle had one digest, and so had functions closing over
    them."""
    import hashlib
    import json

    a = np.zeros(5000)
    b = a.copy()
    b[2500] = 1.0
    assert digest(a) != digest(b) and digest(a) == digest(a.copy())
    assert digest(_above(a)) != digest(_above(b))
    assert digest(a.reshape(50, 100)) != digest(a)  # the shape counts
    assert digest(a.astype(np.float32)) != digest(np.zeros(5000, np.float32) + 1)
    assert describe(a) == {
        "dtype": "float64",
        "shape": [5000],
        "sha256": hashlib.sha256(a.tobytes()).hexdigest(),
    }
    objects = np.array([0.5] * 2000, dtype=object)
    other = objects.copy()
    other[1000] = 0.25
    assert digest(objects) != digest(other)
    # an array whose repr shows every value keeps its description, and so its digest: the
    # digests kept in users' records still match
    for small in (np.arange(10.0), np.ones((10, 100)), np.array(["x", "y"])):
        assert describe(small) == repr(small)
        text = json.dumps(repr(small), sort_keys=True, default=str)
        assert digest(small) == hashlib.sha256(text.encode()).hexdigest()
        assert describe(_above(small))["closure"] == [repr(small)]
    # a small array whose repr rounds (to NumPy's 8 digits) is hashed: 1e-12 apart, two digests
    near, nearer = np.array([0.1, 0.123456789012]), np.array([0.1, 0.123456789013])
    assert repr(near) == repr(nearer) and digest(near) != digest(nearer)
    assert describe(near)["sha256"] == hashlib.sha256(near.tobytes()).hexdigest()
    assert digest(near) == digest(near.copy())


def test_a_task_s_bad_parts_are_named():
    """A NaN deadline read as none, 2.7 steps as 2, and a str given as the files to hash was
    read letter by letter."""
    import math

    from rcvae_torchrl.fingerprint import (
        source_digest,
        task_difference,
        task_labels,
        task_parts,
    )

    assert task_labels("p", 60, 0.05)["deadline"] == "60"
    assert task_labels("p", 60.0, 0.05) == task_labels("p", 60, 0.05)
    for unlimited in (None, math.inf):
        assert task_labels("p", unlimited, None)["deadline"] == "none"
    for bad in (math.nan, 2.7, -5, 0, -math.inf, True, "60"):
        with pytest.raises(ValueError, match=r"^time_limit: expected a whole number of steps"):
            task_labels("p", bad, 0.05)
    for bad in (math.nan, math.inf, 0.0, -0.05, "0.05"):
        with pytest.raises(ValueError, match=r"^dt: expected the seconds per step"):
            task_labels("p", 60, bad)
    for bad in ("file.py", Path("file.py"), 3):
        with pytest.raises(TypeError, match=r"^paths: expected an iterable of file paths"):
            source_digest(bad)
    with pytest.raises(TypeError, match=r"^theirs: expected a task_digest string"):
        task_difference(None, "x")
    with pytest.raises(TypeError, match=r"^mine: expected a task_digest string"):
        task_difference("x", 5)
    with pytest.raises(TypeError, match=r"^task: expected a task_digest string .* got int 5"):
        task_parts(5)
    assert task_parts("3f2a") is None  # a str of another form: not a task digest

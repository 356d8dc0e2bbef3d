"""Fingerprints of code and values: equal for the same behaviour, different when it can change."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

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
    # an older record's plain digest is another task, with no part to name
    assert task_difference("3f2a" * 16, base) == "another task"

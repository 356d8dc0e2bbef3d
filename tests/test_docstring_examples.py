"""Every runnable example in the library's docstrings gives the output it shows."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import rcvae_torchrl
import rcvae_torchrl.envs

# the envs live in a folder of their own (setup.cfg maps it to rcvae_torchrl.envs)
MODULES = sorted(
    m.name
    for package in (rcvae_torchrl, rcvae_torchrl.envs)
    for m in pkgutil.walk_packages(package.__path__, f"{package.__name__}.")
)


def _examples(name: str) -> int:
    finder = doctest.DocTestFinder()
    return sum(len(t.examples) for t in finder.find(importlib.import_module(name)))


@pytest.mark.parametrize("name", [m for m in MODULES if _examples(m)])
def test_docstring_examples(name):
    module = importlib.import_module(name)
    flags = doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS
    result = doctest.testmod(module, optionflags=flags, report=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples fail"


def test_the_modules_users_start_from_show_examples():
    """The walk finds the examples (a broken walk would pass the test above by finding none)."""
    for name in (
        "rcvae_torchrl.competency.assessor",
        "rcvae_torchrl.model_env.env",
        "rcvae_torchrl.planners.cem",
        "rcvae_torchrl.stages",
        "rcvae_torchrl.run_log",
    ):
        assert _examples(name) > 0, name

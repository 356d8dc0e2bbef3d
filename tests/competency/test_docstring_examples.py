"""The runnable examples in the competency docstrings give the outputs they show."""

import doctest
import importlib

import pytest

MODULES = [
    "boundary",
    "calibration",
    "decomposition",
    "entropy",
    "intervals",
    "metrics",
    "mixture",
    "outcome",
    "outcome_assessment",
    "validation",
]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(f"rcvae_torchrl.competency.{name}")
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0
    assert result.failed == 0

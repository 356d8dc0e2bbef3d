"""The runnable examples in the model-env docstrings give the outputs they show."""

import doctest
import importlib

import pytest


@pytest.mark.parametrize("name", ["env", "factory", "propagation", "task"])
def test_docstring_examples(name):
    module = importlib.import_module(f"rcvae_torchrl.model_env.{name}")
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0
    assert result.failed == 0

"""The runnable examples in the model-env and rollout docstrings give the outputs they show."""

import doctest
import importlib

import pytest


@pytest.mark.parametrize(
    "name",
    [
        "model_env.env",
        "model_env.factory",
        "rollout.task",
        "rollout.imagine",
        "rollout.transition",
        "rollout.layout",
    ],
)
def test_docstring_examples(name):
    module = importlib.import_module(f"rcvae_torchrl.{name}")
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0
    assert result.failed == 0

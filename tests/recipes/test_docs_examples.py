"""The code on the documentation pages runs as written (so it cannot drift from the library).

Each page's ``.. code-block:: python`` blocks (README: the fenced ``python`` blocks) are run in
order in one namespace, in a temporary working directory, as a reader would paste them.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from doc_blocks import markdown_python_blocks, rst_python_blocks, run_blocks

ROOT = Path(__file__).resolve().parents[2]


def test_blocks_are_found():
    blocks = rst_python_blocks(ROOT / "docs" / "world_model_in_your_recipe.rst")
    assert len(blocks) >= 6
    assert all(block.strip() for block in blocks)
    assert markdown_python_blocks(ROOT / "README.md")


def test_world_model_in_your_recipe(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    blocks = rst_python_blocks(ROOT / "docs" / "world_model_in_your_recipe.rst")
    ns = run_blocks(blocks, "world_model_in_your_recipe")
    assert (tmp_path / "point_mass_model.pt").is_file()
    # the pieces the page promises, on a dm_control env with float64 dict observations
    assert ns["result"].steps == 20 and ns["result"].checks is not None
    assert ns["layout"].names[0] == "position[0]"
    assert ns["report"].batch_size == (3,)
    p = ns["report"].competency["p_success"]
    assert bool(((p >= 0) & (p <= 1)).all())
    assert ns["outcomes"].success.shape == (3, 4)
    assert ns["lasted"].success.shape == (3, 4) and ns["lasting"].survival
    assert ns["reacher_config"].passthrough_dims == (4, 5)


@pytest.mark.parametrize("page", ["README.md"])
def test_readme_examples(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run_blocks(markdown_python_blocks(ROOT / page), page)

"""Code blocks of documentation pages, to run them as tests."""

from __future__ import annotations

import re
import textwrap
from pathlib import Path


def rst_python_blocks(path: Path) -> list[str]:
    """The bodies of the ``.. code-block:: python`` directives of an rST file, dedented."""
    blocks, lines, i = [], path.read_text().splitlines(), 0
    while i < len(lines):
        if lines[i].strip() == ".. code-block:: python":
            i += 1
            body = []
            while i < len(lines) and (not lines[i].strip() or lines[i].startswith((" ", "\t"))):
                body.append(lines[i])
                i += 1
            blocks.append(textwrap.dedent("\n".join(body)).strip() + "\n")
        else:
            i += 1
    return blocks


def markdown_python_blocks(path: Path) -> list[str]:
    """The bodies of the fenced ``python`` blocks of a Markdown file."""
    return re.findall(r"^```python\n(.*?)^```", path.read_text(), flags=re.M | re.S)


def run_blocks(blocks: list[str], name: str) -> dict:
    """Run ``blocks`` in order in one fresh namespace; return it."""
    namespace: dict = {"__name__": f"docs_example_{name}"}
    for i, block in enumerate(blocks):
        exec(compile(block, f"<{name} block {i + 1}>", "exec"), namespace)
    return namespace

"""The library's boundaries: no env, study or Hydra knowledge inside, and no import cycles."""

from __future__ import annotations

import ast
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ROOT / "rcvae_torchrl"
FORBIDDEN = ("rcvae_torchrl.envs", "hydra", "omegaconf")


def _modules() -> dict[str, Path]:
    """Library module name -> file (the Pusher domain, installed as .envs, is not the library)."""
    out = {}
    for path in sorted(LIBRARY.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _subpackages() -> list[str]:
    return sorted(n for n, p in _modules().items() if p.name == "__init__.py")


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The library modules ``name`` imports at module level or inside functions."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")
                parent = parent[: len(parent) - node.level + 1]
                base = ".".join([*parent, base] if base else parent)
            # "from package import submodule" depends on the submodule, not the package
            targets = [
                f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base
                for alias in node.names
            ]
        else:
            continue
        for target in targets:
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, set(modules)) for name, path in modules.items()}


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` (a list of nodes), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt) :], nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def _package(name: str) -> str:
    parts = name.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 else name


def test_no_subpackage_imports_an_env_a_study_or_hydra():
    code = (
        "import importlib, json, sys\n"
        "name = sys.argv[1]\nimportlib.import_module(name)\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('hydra', 'omegaconf') or m.startswith('rcvae_torchrl.envs'))))"
    )
    for name in _subpackages():
        out = subprocess.run(
            [sys.executable, "-c", code, name], capture_output=True, text=True, check=True
        )
        assert json.loads(out.stdout) == [], f"{name} imports {out.stdout}"


def test_no_import_cycles_between_modules():
    assert _cycle(_graph()) is None


def test_no_import_cycles_between_packages():
    graph: dict[str, set[str]] = {}
    for name, targets in _graph().items():
        edges = graph.setdefault(_package(name), set())
        edges.update(_package(t) for t in targets if _package(t) != _package(name))
    graph.pop("rcvae_torchrl", None)  # the top level re-exports; nothing imports it back
    for targets in graph.values():
        targets.discard("rcvae_torchrl")
    assert _cycle(graph) is None


@pytest.mark.parametrize("word", ["pusher", "fingertip", "scripted"])
def test_the_library_holds_no_pusher_knowledge(word):
    hits = [
        f"{path.relative_to(ROOT)}:{i}"
        for path in _modules().values()
        for i, line in enumerate(path.read_text().splitlines(), 1)
        if re.search(rf"\b{word}", line, flags=re.IGNORECASE)
    ]
    assert not hits, hits


def test_the_cycle_finder_finds_cycles():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None

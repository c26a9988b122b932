"""The package's layering: torchcage's import graph (module-level and function-level imports
alike) has no cycle, and the custom ops are registered at ``import torchcage``."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import torchcage

ROOT = Path(torchcage.__file__).parent


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def import_graph() -> dict[str, set[str]]:
    """``{module: modules of torchcage it imports}``; ``from pkg import name`` counts as importing
    ``pkg.name`` when that is a module, else ``pkg``."""
    modules = {_module_name(p): p for p in ROOT.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                deps.update(a.name for a in node.names if a.name in modules)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    if sub in modules:
                        deps.add(sub)
                    elif target in modules:
                        deps.add(target)
        deps.discard(name)
        graph[name] = deps
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(u: str) -> list[str] | None:
        state[u] = 1
        stack.append(u)
        for v in sorted(graph.get(u, ())):
            if state.get(v) == 1:
                return [*stack[stack.index(v) :], v]
            if v not in state and (found := visit(v)):
                return found
        stack.pop()
        state[u] = 2
        return None

    for u in sorted(graph):
        if u not in state and (found := visit(u)):
            return found
    return None


def test_the_import_graph_has_no_cycle() -> None:
    graph = import_graph()
    assert "torchcage.autograd.mean_value" in graph["torchcage.functional.mean_value"]  # the reader works
    # A package's __init__ re-exports its submodules; what must not happen is a submodule that
    # imports, directly or through others, a module that imports it back.
    inner = {u: {v for v in vs if not (graph.get(v) is not None and u.startswith(v + "."))} for u, vs in graph.items()}
    cycle = _cycle(inner)
    assert cycle is None, " -> ".join(cycle)


def test_custom_ops_are_registered_at_import() -> None:
    code = (
        "import torch, torchcage\n"
        "torch.ops.torchcage.mean_value_coordinates\n"
        "torch.ops.torchcage.mean_value_derivatives\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_docstring_examples_render_as_code():
    """Issue 22 item 17: Google-style ``Examples:`` sections (griffe renders their ``>>>`` lines as
    code); a singular ``Example:`` became a grey block quote in the API reference."""
    import re

    bad = []
    for path in sorted(ROOT.rglob("*.py")):
        for k, line in enumerate(path.read_text().splitlines(), 1):
            if re.fullmatch(r"\s*Example:\s*", line):
                bad.append(f"{path.relative_to(ROOT.parent)}:{k}")
    assert not bad, f"use 'Examples:' in docstrings: {bad}"

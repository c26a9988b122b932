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
    assert "torchcage.families.mean_value.ops" in graph["torchcage.families.mean_value.api"]  # the reader works
    # A package's __init__ re-exports its submodules; what must not happen is a submodule that
    # imports, directly or through others, a module that imports it back.
    inner = {u: {v for v in vs if not (graph.get(v) is not None and u.startswith(v + "."))} for u, vs in graph.items()}
    cycle = _cycle(inner)
    assert cycle is None, " -> ".join(cycle)


#: The layers, lowest first: a module may import its own layer and those below it, never above.
#: Facades re-export; families hold each family's code; _core and backends import no family.
LAYERS = (
    {"errors", "_timing", "_intersections", "_raster", "cage", "geometry", "data", "backends"},
    {"_core", "io", "testing"},
    {"families", "solvers"},
    {"functional", "nn", "autograd"},
)


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _layer(package: str) -> int | None:
    return next((k for k, names in enumerate(LAYERS) if package in names), None)


def test_packages_import_downwards_only() -> None:
    """No package-level cycle among the layered packages: ``_core`` and ``backends`` import no
    family and no facade, families import no facade (``functional``, ``nn``, ``autograd``)."""
    bad = []
    for u, vs in import_graph().items():
        lu = _layer(_package(u))
        for v in vs:
            lv = _layer(_package(v))
            if lu is not None and lv is not None and lv > lu:
                bad.append(f"{u} -> {v}")
    assert not bad, "imports against the layering:\n" + "\n".join(sorted(bad))


def test_a_family_imports_no_other_family_but_the_ones_it_builds_on() -> None:
    """A family's code lives in its folder; the only cross-family imports are the quad families'
    use of the triangle kernels (and quad Green's of quad mean value's argument checks), and the
    Triton kernel of Green coordinates' use of mean value's thin-face routine."""
    allowed = {
        ("quad_mean_value", "mean_value"),
        ("quad_green", "green"),
        ("quad_green", "quad_mean_value"),
        ("quad_green", "mean_value"),
        ("maximum_entropy", "mean_value"),
        ("maximum_entropy", "quad_mean_value"),
        ("local_barycentric", "harmonic"),
        ("biharmonic", "harmonic"),
        ("green", "mean_value"),
    }
    found = set()
    for u, vs in import_graph().items():
        pu = u.split(".")
        if len(pu) < 4 or pu[1] != "families":
            continue
        for v in vs:
            pv = v.split(".")
            if len(pv) >= 3 and pv[1] == "families" and len(pv) > 2 and pv[2] != pu[2] and len(pv) >= 4:
                found.add((pu[2], pv[2]))
    assert found <= allowed, sorted(found - allowed)


def test_custom_ops_are_registered_at_import() -> None:
    code = (
        "import torch, torchcage\n"
        "torch.ops.torchcage.mean_value_coordinates\n"
        "torch.ops.torchcage.mean_value_derivatives\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_docstring_examples_render_as_code():
    """Google-style ``Examples:`` sections (griffe renders their ``>>>`` lines as
    code); a singular ``Example:`` became a grey block quote in the API reference."""
    import re

    bad = []
    for path in sorted(ROOT.rglob("*.py")):
        for k, line in enumerate(path.read_text().splitlines(), 1):
            if re.fullmatch(r"\s*Example:\s*", line):
                bad.append(f"{path.relative_to(ROOT.parent)}:{k}")
    assert not bad, f"use 'Examples:' in docstrings: {bad}"

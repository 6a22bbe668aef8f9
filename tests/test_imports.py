"""No import cycles in the package, at module level or inside functions.

An import inside a function hides a cycle from Python's import machinery but
not from the design: the two modules still need each other.  The graph is
read from the source (every ``import`` statement anywhere in a module), so a
cycle through a function-level import fails here as one at the top would.
"""

import ast
import graphlib
from pathlib import Path

import pytest

import bayescal

ROOT = Path(bayescal.__file__).parent


def _modules() -> dict[str, Path]:
    out = {}
    for p in ROOT.rglob("*.py"):
        parts = list(p.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _targets(module: str, node: ast.AST, is_package: bool, known: set[str]) -> set[str]:
    """The package's modules an import statement loads (``from a import b``: ``a``, and ``a.b`` if a module)."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        if node.level:
            base = module.split(".") if is_package else module.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            mod = ".".join(base + ([node.module] if node.module else []))
        else:
            mod = node.module or ""
        names = [mod] + [f"{mod}.{a.name}" for a in node.names]
    return {n for n in names if n in known}


def _explicit_edges() -> dict[str, set[str]]:
    mods = _modules()
    known = set(mods)
    graph = {}
    for m, p in mods.items():
        deps = set()
        for node in ast.walk(ast.parse(p.read_text(), filename=str(p))):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                deps |= _targets(m, node, p.name == "__init__.py", known)
        deps.discard(m)
        graph[m] = deps
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        return exc.args[1]
    return None


def test_the_graph_is_read():
    graph = _explicit_edges()
    assert "bayescal.machines.base" in graph["bayescal.effects.stored"]  # top level
    assert "bayescal.diagnose.verb" in graph["bayescal.api"]  # inside a function


def test_no_cycle_among_the_imports_as_written():
    """Every import statement, the package ``__init__`` files' imports of their own modules included."""
    assert _cycle(_explicit_edges()) is None, f"import cycle: {' -> '.join(_cycle(_explicit_edges()))}"


def test_no_cycle_once_a_module_loads_its_packages():
    """Loading ``a.b.c`` runs ``a/b/__init__.py`` first: an import of ``a.b.c`` is one of ``a.b`` as well."""
    graph = _explicit_edges()
    implied = {}
    for m, deps in graph.items():
        own = {d for d in deps if d.startswith(m + ".")}  # a package's imports of its own modules run inside it
        parent = m.rsplit(".", 1)[0] if m.count(".") > 1 else None
        implied[m] = (deps - own) | ({parent} if parent in graph else set())
    cycle = _cycle(implied)
    assert cycle is None, f"import cycle: {' -> '.join(cycle)}"


@pytest.mark.parametrize("text, cyclic", [
    ("from .a import f\n", True),
    ("def g():\n    from .a import f\n", True),  # a function-level import counts
    ("import p.a\n", True),
    ("from . import c\n", False),
])
def test_a_planted_cycle_is_found(text, cyclic):
    known = {"p.a", "p.b", "p.c"}
    graph = {"p.a": {"p.b"}, "p.b": set(), "p.c": set()}
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            graph["p.b"] |= _targets("p.b", node, False, known)
    assert (_cycle(graph) is not None) is cyclic

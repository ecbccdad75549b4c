"""Module layout: the import circles that once tied the package's stages together stay broken.

Each pair below imported each other (often through an import inside a function, placed there only to
dodge the cycle at import time). The graph is read from the source with ``ast``: every ``import``
statement, at module level or inside a function, counts; importing ``a.b.c`` also runs the packages
``a.b`` (their ``__init__``), so those count too (the root ``simgap`` package aside). A pair is a circle
when each side reaches the other."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "simgap"

#: (one side, other side) that must not reach each other in both directions
CIRCLES = [
    ("simgap.collect", "simgap.dataset"),
    ("simgap.pipeline", "simgap.perrun.stage"),
    ("simgap.systems", "simgap.refine.refined"),
    ("simgap.simulators.base", "simgap.simulators.parallel"),
]


def _modules() -> dict:
    """{dotted name: (path, is_package)} of every module of the simgap package."""
    out = {}
    for p in sorted(PKG.rglob("*.py")):
        parts = list(p.relative_to(ROOT).with_suffix("").parts)
        pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if pkg else parts)] = (p, pkg)
    return out


def import_graph() -> dict:
    """{module: set of simgap modules it imports anywhere in its source (module or function level)}."""
    mods = _modules()
    graph = {}
    for name, (path, pkg) in mods.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".") if pkg else name.split(".")[:-1]
                    base = base[:len(base) - (node.level - 1)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                targets.add(mod)
                targets.update(f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in mods)
        edges = set()
        for t in targets:
            parts = t.split(".")
            # importing a.b.c runs a.b's __init__ too (the root package aside: every module has it)
            edges.update(".".join(parts[:i]) for i in range(2, len(parts) + 1))
        graph[name] = {t for t in edges if t in mods and t != name}
    return graph


def reaches(graph: dict, start: str, goal: str) -> list:
    """An import path from ``start`` to ``goal`` (empty if there is none)."""
    prev, todo = {start: None}, [start]
    while todo:
        m = todo.pop()
        for t in sorted(graph.get(m, ())):
            if t not in prev:
                prev[t] = m
                if t == goal:
                    path = [t]
                    while prev[path[-1]] is not None:
                        path.append(prev[path[-1]])
                    return path[::-1]
                todo.append(t)
    return []


def test_the_graph_sees_function_level_imports():
    """The checker itself: a lazy import inside a function is an edge (so a dodged circle is still found)."""
    g = import_graph()
    assert "simgap.systems" in g["simgap.dataset"]          # module level
    assert set(g) >= {a for pair in CIRCLES for a in pair}
    src = ast.parse("def f():\n    from .collect import x\n")
    assert any(isinstance(n, ast.ImportFrom) and n.module == "collect" for n in ast.walk(src))
    assert reaches({"a": {"b"}, "b": {"c"}, "c": {"a"}}, "a", "c") == ["a", "b", "c"]
    assert reaches({"a": {"b"}, "b": set()}, "b", "a") == []


@pytest.mark.parametrize("a,b", CIRCLES, ids=[f"{a}<->{b}" for a, b in CIRCLES])
def test_no_import_circle(a, b):
    g = import_graph()
    there, back = reaches(g, a, b), reaches(g, b, a)
    assert not (there and back), (f"import circle: {' -> '.join(there)} and {' -> '.join(back)}; move the "
                                  f"shared piece into a module both import")


def test_each_side_imports_alone_in_a_fresh_interpreter():
    """Each side imports first in a new interpreter (a circle dodged by import order fails here).
    The interpreters run side by side: each one is mostly start-up time."""
    mods = sorted({m for pair in CIRCLES for m in pair})
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    procs = {m: subprocess.Popen([sys.executable, "-c", f"import {m}"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True) for m in mods}
    failed = {m: p.communicate()[1] for m, p in procs.items() if p.wait() != 0}
    assert not failed, failed



def test_named_system_builders_resolve():
    """systems names the refined-system builders instead of importing them: each name must still resolve."""
    from simgap import system_ref
    for kind in system_ref.SYSTEM_BUILDERS:
        assert callable(system_ref.system_builder(kind)), kind

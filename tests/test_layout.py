"""Module layout: the import circles that once tied the package's stages together stay broken.

Each pair below imported each other (often through an import inside a function, placed there only to
dodge the cycle at import time). The graph is read from the source with ``ast``: every ``import``
statement, at module level or inside a function, counts; importing ``a.b.c`` also runs the packages
``a.b`` (their ``__init__``), so those count too (the root ``simgap`` package aside). A pair is a circle
when each side reaches the other.

The stages run System -> Dataset -> Certificate -> Abstraction/Controller -> Rollouts -> per-run
statement (:data:`STAGES`): a module of one stage never reaches (directly or through any other module)
a module of a later stage; what two stages share lives in the earlier one (the Runge-Kutta step a
system file integrates with is :mod:`simgap.runge_kutta`, not a synthesis module; the in-set rollouts
of a proved set get :func:`simgap.rollout.rollout` from their caller)."""

import ast
import functools
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
    ("simgap.certify.audit", "simgap.certify.pipeline"),
]

#: the stages in the order they run, each a list of modules or packages (a package: all its modules);
#: modules in no stage (cli, pipeline, config, errors, fileio, ...) are free to import any stage
STAGES = [
    ("system", ["simgap.systems", "simgap.system_file", "simgap.system_ref", "simgap.expr", "simgap.runge_kutta",
                "simgap.jit", "simgap.simulators"]),
    ("dataset", ["simgap.cover", "simgap.collect", "simgap.store", "simgap.dataset"]),
    ("certificate", ["simgap.certify"]),
    ("abstraction/controller", ["simgap.synthesis"]),
    ("rollouts", ["simgap.rollout"]),
    ("per-run statement", ["simgap.perrun"]),
]

#: upward arrows that once existed, named so that their return fails with its own message
#: (lower module or package, higher package)
GONE_ARROWS = [
    ("simgap.system_file", "simgap.synthesis"),
    ("simgap.synthesis", "simgap.rollout"),
]


def _modules() -> dict:
    """{dotted name: (path, is_package)} of every module of the simgap package."""
    out = {}
    for p in sorted(PKG.rglob("*.py")):
        parts = list(p.relative_to(ROOT).with_suffix("").parts)
        pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if pkg else parts)] = (p, pkg)
    return out


@functools.lru_cache(maxsize=1)
def import_graph() -> dict:
    """{module: set of simgap modules it imports anywhere in its source (module or function level)};
    read once per test session (callers do not change it)."""
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


def reachable(graph: dict, start: str) -> dict:
    """{module reached from ``start``: the module it was reached from} (``start`` maps to None)."""
    prev, todo = {start: None}, [start]
    while todo:
        m = todo.pop()
        for t in sorted(graph.get(m, ())):
            if t not in prev:
                prev[t] = m
                todo.append(t)
    return prev


def path_to(prev: dict, goal: str) -> list:
    """The import path :func:`reachable` found to ``goal`` (empty if it found none)."""
    if goal not in prev:
        return []
    path = [goal]
    while prev[path[-1]] is not None:
        path.append(prev[path[-1]])
    return path[::-1]


def reaches(graph: dict, start: str, goal: str) -> list:
    """An import path from ``start`` to ``goal`` (empty if there is none)."""
    return path_to(reachable(graph, start), goal) if goal != start else []


def stage_of(module: str, stages=STAGES):
    """Index of the stage ``module`` belongs to (None: in no stage)."""
    for i, (_, members) in enumerate(stages):
        if any(module == m or module.startswith(m + ".") for m in members):
            return i
    return None


def upward_paths(graph: dict, stages=STAGES) -> list:
    """Import paths from a module of a stage to a module of a later stage (empty when the layers hold)."""
    found = []
    for m in sorted(graph):
        i = stage_of(m, stages)
        if i is None:
            continue
        prev = reachable(graph, m)
        for t in sorted(prev):
            j = stage_of(t, stages)
            if j is not None and j > i:
                found.append(path_to(prev, t))
    return found


def test_the_graph_sees_function_level_imports():
    """The checker itself: a lazy import inside a function is an edge (so a dodged circle is still found)."""
    g = import_graph()
    assert "simgap.systems" in g["simgap.dataset"]          # module level
    assert set(g) >= {a for pair in CIRCLES for a in pair}
    src = ast.parse("def f():\n    from .collect import x\n")
    assert any(isinstance(n, ast.ImportFrom) and n.module == "collect" for n in ast.walk(src))
    assert reaches({"a": {"b"}, "b": {"c"}, "c": {"a"}}, "a", "c") == ["a", "b", "c"]
    assert reaches({"a": {"b"}, "b": set()}, "b", "a") == []


def test_the_stage_rule_sees_an_arrow_through_a_free_module():
    """The checker of the stages: an upward arrow is found directly and through a module in no stage
    (a helper both import); a downward one is allowed; every stage names modules that exist."""
    stages = [("low", ["p.low"]), ("high", ["p.high"])]
    assert upward_paths({"p.low.a": {"p.util"}, "p.util": {"p.high.b"}, "p.high.b": set()}, stages) == [
        ["p.low.a", "p.util", "p.high.b"]]
    assert upward_paths({"p.low.a": {"p.high"}, "p.high": set()}, stages) == [["p.low.a", "p.high"]]
    assert upward_paths({"p.high.b": {"p.low.a"}, "p.low.a": set()}, stages) == []
    mods = import_graph()
    for name, members in STAGES:
        assert all(m in mods for m in members), name
    for low, high in GONE_ARROWS:
        assert stage_of(low) < stage_of(high)


@pytest.mark.parametrize("low,high", GONE_ARROWS, ids=[f"{a}->{b}" for a, b in GONE_ARROWS])
def test_no_upward_arrow(low, high):
    """The named arrows that ran back up stay gone: no module of ``low`` reaches a module of ``high``."""
    g = import_graph()
    paths = [reaches(g, m, t) for m in sorted(g) if m == low or m.startswith(low + ".")
             for t in sorted(g) if t == high or t.startswith(high + ".")]
    paths = [p for p in paths if p]
    assert not paths, f"upward import: {' -> '.join(paths[0])} ({len(paths)} such paths)"


def test_stages_import_only_earlier_stages():
    """System -> Dataset -> Certificate -> Abstraction/Controller -> Rollouts -> per-run statement:
    no module of a stage reaches a later stage's module, directly or through modules in no stage."""
    paths = upward_paths(import_graph())
    shown = "\n".join(" -> ".join(p) for p in paths[:10])
    assert not paths, (f"{len(paths)} upward import paths (a stage imports a later one; move the shared "
                       f"piece down to the earlier stage, or pass it in from the caller):\n{shown}")


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

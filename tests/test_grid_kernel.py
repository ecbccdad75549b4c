"""The grid kernel (simgap.synthesis.grid_kernel, generated C from simgap.compile): a system file's
posts are the numpy step's bits, its abstraction tables the numpy loop's, and SCOTS's examples as
system files (simgap/synthesis/scots/) win SCOTS's cells."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from simgap import compile as C
from simgap.errors import SimgapError
from simgap.system_file import load_system_file, model_trees, system_from_spec
from simgap.synthesis.abstraction import build_abstraction
from simgap.synthesis.controller import synthesize
from simgap.synthesis.grid import UniformGrid
from simgap.synthesis.grid_kernel import grid_kernel
from simgap.synthesis.spec import Box, Spec

REPO = Path(__file__).resolve().parents[1]
SCOTS = REPO / "simgap" / "synthesis" / "scots"
SPECS = REPO / "examples" / "scots"

if C.c_compiler() is None:
    pytest.skip("no C compiler: the grid kernel is not built here (the numpy path runs)", allow_module_level=True)


def _kernel(s, monkeypatch):
    monkeypatch.setenv("SIMGAP_JIT", "1")
    k = grid_kernel(s, 0)
    # grid_kernel returns None when it declines a file (a state formula with a function it does not
    # hoist, a periodic dimension, hold > 1): these files must take the compiled path
    assert k is not None, f"{s.name}: the grid kernel declined the file"
    return k


def _bits(a):
    return np.ascontiguousarray(a, dtype=np.float64).view(np.uint64)


@pytest.mark.parametrize("name", ["dcdc.toml", "vehicle.toml"])
def test_posts_are_the_numpy_steps_bits(name, rng, monkeypatch):
    """On random states of X (and beyond it) under every input, the compiled posts equal the numpy
    step's (SIMGAP_JIT=0) bit for bit: RK4 substeps, stage order and the hoisted input terms (the
    vehicle's arctan(tan(steer)/2), evaluated by numpy per input)."""
    s = load_system_file(SCOTS / name)
    k = _kernel(s, monkeypatch)
    span = s.x_hi - s.x_lo
    X = rng.uniform(s.x_lo - 0.2 * span, s.x_hi + 0.2 * span, (3999, s.n))  # not a multiple of the lanes
    J = rng.integers(0, len(s.inputs), 3999)
    got = k.posts(s, X, J)
    monkeypatch.setenv("SIMGAP_JIT", "0")
    want = s.f(X, s.inputs[J])
    assert np.array_equal(_bits(got), _bits(want))
    # a wrong kernel is caught: one substep fewer moves the posts by far more than a bit
    k.substeps -= 1
    assert not np.array_equal(_bits(k.posts(s, X, J)), _bits(want))


def test_posts_with_steps_and_a_discrete_map(rng, monkeypatch):
    """steps > 1 repeats the period; a discrete map (dt in a formula) compiles too."""
    spec = {"name": "dmap", "states": ["p", "q"], "inputs": ["a"], "x_lo": [-1.0, -1.0], "x_hi": [1.0, 1.0],
            "tau": 0.1, "input_set": [[-1.0], [0.5], [1.0]],
            "dynamics": {"kind": "discrete", "p": "p + dt*q + 0.5*dt^2*a", "q": "where(a > 0, q + dt*a, cos(q)*q)"},
            "bounds": {"jacobian": [[1, "dt"], [0, 1]]}}
    s = system_from_spec(spec).with_steps(3)
    k = _kernel(s, monkeypatch)
    X = rng.uniform(-1, 1, (500, 2))
    J = rng.integers(0, 3, 500)
    got = k.posts(s, X, J)
    monkeypatch.setenv("SIMGAP_JIT", "0")
    assert np.array_equal(_bits(got), _bits(s.f(X, s.inputs[J])))


@pytest.mark.parametrize("name,eta,inv", [("dcdc.toml", 0.004, ()), ("vehicle.toml", 0.8, ()),
                                          ("vehicle.toml", 0.4, (0, 1))])
def test_tables_equal_the_numpy_loop(name, eta, inv, monkeypatch):
    """The whole abstraction of a reduced grid: offsets (dtype included) and valid flags of the
    compiled pass equal build_abstraction's numpy loop, per cell and with shared boxes (classes
    over the heading only)."""
    s = load_system_file(SCOTS / name)
    g = UniformGrid(s.x_lo, s.x_hi, eta)
    tabs = {}
    for mode in ("0", "1"):
        monkeypatch.setenv("SIMGAP_JIT", mode)
        ab = build_abstraction(s, g, invariant_dims=inv)
        tabs[mode] = ab
    a, b = tabs["0"], tabs["1"]
    assert a.off_lo.dtype == b.off_lo.dtype
    assert np.array_equal(a.off_lo, b.off_lo) and np.array_equal(a.off_hi, b.off_hi)
    assert np.array_equal(a.ok, b.ok) and 0 < a.ok.sum() < a.ok.size


def test_dcdc_file_wins_scots_cells(monkeypatch):
    """SCOTS's dcdc as a system file (800 x 799 points in SCOTS, 801 x 801 cells here) wins
    SCOTS's 593,089 cells, with the compiled pass and the growth of bounds.growth integrated as
    SCOTS's radius_post."""
    monkeypatch.setenv("SIMGAP_JIT", "auto")
    s = load_system_file(SCOTS / "dcdc.toml")
    r = synthesize(s, Spec(kind="invariance", safe=Box([1.15, 5.45], [1.55, 5.85])), [0.0005, 0.0005])
    assert r.stats["winning"] == 593089


@pytest.mark.slow
def test_vehicle_file_wins_scots_cells(monkeypatch):
    """SCOTS's vehicle as a system file, per cell (no translation invariance declared): SCOTS's
    48,018 winning cells and 35,772,302 transitions."""
    monkeypatch.setenv("SIMGAP_JIT", "auto")
    s = load_system_file(SCOTS / "vehicle.toml")
    spec = Spec.from_dict(json.loads((SPECS / "vehicle_spec.json").read_text()))
    r = synthesize(s, spec, [0.2, 0.2, 0.2], strict_domain=False, invariant_dims=())
    assert (r.stats["winning"], r.stats["transitions"]) == (48018, 35772302)


def test_hoisting_and_refusals():
    """State-free sub-trees are hoisted (any function); a function of the state without numpy's
    bits compiled is refused by name (the numpy loop then runs)."""
    s = load_system_file(SCOTS / "vehicle.toml")
    trees = model_trees(s)["trees"]
    src, hoisted = C.grid_source(trees, 3, 2)
    assert any(t[0] == "fn" and t[1] == "arctan" for t in hoisted)  # alpha, per input
    assert "atan" not in src and "tan(" not in src.replace("_", " ")
    bad = [("fn", "tan", ("var", 2)), ("var", 0), ("var", 1)]
    with pytest.raises(SimgapError, match="tan"):
        C.grid_source(bad, 3, 2)
    with pytest.raises(SimgapError, match="not allowed"):
        C.grid_source([("call", "system", ("var", 0)), ("var", 0), ("var", 1)], 3, 2)


def test_source_holds_no_text_of_the_file(tmp_path):
    """Names and formula text never reach the C source (only node kinds, numbers and indices)."""
    text = (SCOTS / "dcdc.toml").read_text().replace("xc", "system_rm_rf").replace('"il"', '"evil_state"')
    text = text.replace("il =", "evil_state =").replace("*il", "*evil_state").replace(")*il", ")*evil_state")
    p = tmp_path / "d.toml"
    p.write_text(text)
    s = load_system_file(p)
    src, _ = C.grid_source(model_trees(s)["trees"], 2, 1)
    assert "system_rm_rf" not in src and "evil" not in src

"""The compiler (simgap.compile): interval kernels enclose what the numpy interval path encloses and
every point Jacobian; point kernels give the numpy step's bits; hostile trees are refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from simgap import compile as C
from simgap.errors import SimgapError
from simgap.system_file import load_system_file, model_trees
from simgap.synthesis.interval_map import ABS_WIDEN, REL_WIDEN, IntervalMap

pytest.importorskip("numba")

REPO = Path(__file__).resolve().parents[1]
FILES = ["assets/experiments/reacher/reacher.toml", "assets/experiments/cartpole/cartpole_ct.toml",
         "examples/arm/arm.toml"]
#: the default suite compiles the reacher's kernels (about 10 s CPU the first time, then loaded from
#: the disk cache); the other files' first compiles run with the slow tests
SLOW = pytest.mark.slow
CASES = [FILES[0]] + [pytest.param(f, marks=SLOW) for f in FILES[1:]]


def _boxes(s, rng, B, rel=0.05):
    """Random boxes in X with input boxes inside U's hull, and a random gain K."""
    c = rng.uniform(s.x_lo, s.x_hi, (B, s.n))
    h = rng.uniform(0, rel, (B, s.n)) * (s.x_hi - s.x_lo)
    ulo, uhi = s.inputs.min(axis=0), s.inputs.max(axis=0)
    uc = rng.uniform(ulo, uhi, (B, s.m))
    hu = rng.uniform(0, rel, (B, s.m)) * (uhi - ulo)
    K = rng.normal(size=(s.m, s.n))
    return c - h, c + h, uc - hu, uc + hu, K


def _kernel(s, trees=None):
    t = model_trees(s)
    k = C.interval_kernel(trees if trees is not None else t["trees"], s.n, s.m)
    return lambda xl, xh, ul, uh, K: k(xl, xh, ul, uh, K, t["tau"], t["substeps"], int(s.steps), t["continuous"],
                                       REL_WIDEN, ABS_WIDEN)


@pytest.mark.parametrize("path", CASES)
def test_interval_kernel_encloses_numpy(path, rng):
    """The compiled enclosure contains the numpy path's unwidened one (sound where it is) and is no
    wider than the numpy one widened twice (not vacuous)."""
    s = load_system_file(REPO / path)
    xl, xh, ul, uh, K = _boxes(s, rng, 300)
    lo, hi, Dc, Dr = _kernel(s)(xl, xh, ul, uh, K)
    nlo, nhi, nDc, nDr = IntervalMap(s).closed_loop(xl, xh, ul, uh, K)
    assert np.isfinite(Dr).all() and np.isfinite(nDr).all()
    wid = REL_WIDEN * np.abs(nDc) + ABS_WIDEN
    assert np.all(Dc - Dr <= nDc - nDr + wid) and np.all(Dc + Dr >= nDc + nDr - wid)
    assert np.all(Dc - Dr >= nDc - nDr - 2 * wid) and np.all(Dc + Dr <= nDc + nDr + 2 * wid)
    span = REL_WIDEN * np.maximum(np.abs(nlo), np.abs(nhi)) + ABS_WIDEN
    assert np.all(lo <= nlo + span) and np.all(hi >= nhi - span)
    assert np.all(lo >= nlo - span) and np.all(hi <= nhi + span)


def _jacobian_violations(s, kernel, rng, boxes=40, points=30):
    """Central-difference Jacobians of g(x) = f(x, u* + K (x - x*)) at points of each box, against the
    enclosure: entries outside [Dc - Dr, Dc + Dr] by more than the difference's error (1e-5)."""
    c = rng.uniform(s.x_lo + 0.1 * (s.x_hi - s.x_lo), s.x_hi - 0.1 * (s.x_hi - s.x_lo), (boxes, s.n))
    h = 0.05 * (s.x_hi - s.x_lo) * np.ones((boxes, s.n))
    us = s.inputs.mean(axis=0)
    K = 0.1 * rng.normal(size=(s.m, s.n))
    hu = h @ np.abs(K).T
    _, _, Dc, Dr = kernel(c - h, c + h, us - hu, us + hu, K)
    x = c[:, None] + h[:, None] * rng.uniform(-1, 1, (boxes, points, s.n))      # (boxes, points, n)
    x = x.reshape(-1, s.n)
    xs = np.repeat(c, points, axis=0)
    eps = 1e-6
    J = np.empty((x.shape[0], s.n, s.n))
    for j in range(s.n):  # one column per direction, vectorized over all points
        e = np.zeros(s.n)
        e[j] = eps
        g = [s.f(x + d * e, us + (x + d * e - xs) @ K.T) for d in (1.0, -1.0)]
        J[:, :, j] = (g[0] - g[1]) / (2 * eps)
    lo = np.repeat(Dc - Dr, points, axis=0)
    hi = np.repeat(Dc + Dr, points, axis=0)
    return int(((J < lo - 1e-5) | (J > hi + 1e-5)).sum())


@pytest.mark.parametrize("path", CASES[:2])
def test_point_jacobians_inside(path, rng):
    s = load_system_file(REPO / path)
    assert _jacobian_violations(s, _kernel(s), rng) == 0


def _drop_term(tree):
    """The tree with the right operand of its first sum of two state-dependent terms replaced by 0."""
    def walk(t):
        if t[0] == "add" and t[2][0] != "const":
            return ("add", t[1], ("const", 0.0)), True
        for i, c in enumerate(t):
            if isinstance(c, tuple):
                new, done = walk(c)
                if done:
                    return t[:i] + (new,) + t[i + 1:], True
        return t, False
    return walk(tree)[0]


def test_a_dropped_term_is_caught(rng):
    """A kernel with one term missing (the cart-pole's affine correction of v) misses point Jacobians."""
    s = load_system_file(REPO / FILES[1])
    trees = list(model_trees(s)["trees"])
    trees[2] = _drop_term(trees[2])
    assert trees[2] != model_trees(s)["trees"][2]
    assert _jacobian_violations(s, _kernel(s, trees), rng) > 0


@pytest.mark.parametrize("path", CASES + [pytest.param(f, marks=SLOW) for f in ("examples/racecar/racecar.toml",
                                                                                 "examples/husky/husky.toml")])
def test_point_kernel_bit_identical(path, rng):
    s = load_system_file(REPO / path)
    t = model_trees(s)
    x = rng.uniform(s.x_lo, s.x_hi, (5000, s.n))
    x[:3] = [s.x_lo, s.x_hi, 1e6 * s.x_hi]
    u = s.inputs[rng.integers(0, len(s.inputs), 5000)]
    step = C.point_kernel(t["trees"], s.n, s.m)
    for tau in (s.base_tau, 3 * s.base_tau):
        got = step(x, u, tau, t["substeps"], t["continuous"])
        want = np.ascontiguousarray(s.step(x, u, tau))
        assert np.array_equal(got.view(np.uint64), want.view(np.uint64))


def test_point_kernel_refuses_inexact_functions():
    tree = ("fn", "exp", ("var", 0))
    assert "exp" in C.point_exact([tree])
    with pytest.raises(SimgapError, match="bit-identical"):
        C.point_source([tree], 1, 0)
    assert "power 3" in C.point_exact([("pow", ("var", 0), 3)])


@pytest.mark.parametrize("tree, why", [
    (("const", "1); import os; os.system('x')  #"), "not a finite number"),
    (("const", float("inf")), "not a finite number"),
    (("var", "0]; import os; x = y[0"), "not a column"),
    (("fn", "__import__", ("var", 0)), "not compiled here"),
    (("fn", "eval", ("var", 0)), "not compiled here"),
    (("call", ("var", 0)), "not allowed"),
    (("pow", ("var", 0), "2); import os; (x"), "not a finite number"),
    (("cmp", "==", ("var", 0), ("var", 0)), "comparison"),
    ("x1", "not an expression node"),
])
def test_hostile_trees_refused(tree, why):
    """Only allow-listed node kinds with numbers and integer columns become source."""
    with pytest.raises(SimgapError, match=why):
        C.interval_source([tree], 1, 0)
    with pytest.raises(SimgapError, match=why):
        C.point_source([tree], 1, 0)


def test_shared_subtrees_emitted_once():
    x = ("var", 0)
    big = ("mul", ("fn", "sin", x), ("fn", "sin", x))
    src = C.interval_source([("add", big, big)], 1, 0)
    assert src.count("_isin(") - C._INTERVAL_PRELUDE.count("_isin(") == 1


def test_interval_map_uses_kernel(monkeypatch, rng):
    """SIMGAP_JIT=1: IntervalMap.closed_loop is the compiled one (the same enclosure); 0: numpy."""
    s = load_system_file(REPO / FILES[0])     # the kernel of the first test: loaded, not compiled again
    xl, xh, ul, uh, K = _boxes(s, rng, 50)
    monkeypatch.setenv("SIMGAP_JIT", "0")
    im = IntervalMap(s)
    ref = im.closed_loop(xl, xh, ul, uh, K)
    assert im.twin.fn is None
    monkeypatch.setenv("SIMGAP_JIT", "1")
    got = im.closed_loop(xl, xh, ul, uh, K)
    assert im.twin.fn is not None
    np.testing.assert_allclose(got[2], ref[2], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(got[3], ref[3], rtol=1e-9, atol=1e-12)


def test_values_kernel_matches_term_interval(rng, monkeypatch):
    """Basis.value_bounds compiled (SIMGAP_JIT=1) against Term.interval in numpy: the same bounds up to
    the C library's last bits, and a box's points inside."""
    from simgap.certify.basis import Basis
    s = load_system_file(REPO / FILES[2])
    extra = ["sin(theta)", "cos(theta)*omega", "exp(torque/10)", "sqrt(omega^2 + 1)", "tanh(omega)", "abs(theta)",
             "sign(omega)", "theta^-2", "tan(theta/4)", "omega^3/(1 + theta^2)"]
    z = s.n + s.m
    c = rng.uniform(-1, 1, (400, z))
    h = rng.uniform(0, 0.5, (400, z))
    monkeypatch.setenv("SIMGAP_JIT", "0")
    b = Basis.polynomial(s, 2, extra)
    want = b.value_bounds(c - h, c + h)
    assert b.twin.fn is None
    monkeypatch.setenv("SIMGAP_JIT", "1")
    got = b.value_bounds(c - h, c + h)
    assert b.twin.fn is not None
    for g, w in zip(got, want):
        same = (g == w) | (np.isnan(g) & np.isnan(w))
        with np.errstate(invalid="ignore"):
            close = np.abs(g - w) <= 1e-14 * np.abs(w)
        assert np.all(same | close)
    pts = c + h * rng.uniform(-1, 1, (400, z))
    P = np.stack([t.eval(pts) for t in b.terms], axis=1)
    ok = np.isfinite(P)
    assert np.all((got[0] <= P + 1e-12 * np.abs(P))[ok]) and np.all((got[1] >= P - 1e-12 * np.abs(P))[ok])


def test_system_file_step_compiled_same_bits(monkeypatch, rng):
    """A system file's step under SIMGAP_JIT=1 is the point kernel (exp-free file) with the numpy step's
    bits; a file with a power the kernel cannot match stays on numpy."""
    for path, compiled in (("assets/experiments/reacher/reacher.toml", True), ("examples/duffing/duffing.toml", False)):
        monkeypatch.setenv("SIMGAP_JIT", "0")
        s = load_system_file(REPO / path)
        x = rng.uniform(s.x_lo, s.x_hi, (3000, s.n))
        u = s.inputs[rng.integers(0, len(s.inputs), 3000)]
        want = s.with_steps(3).f(x, u)
        monkeypatch.setenv("SIMGAP_JIT", "1")
        got = s.with_steps(3).f(x, u)
        assert np.array_equal(got, want)
        comp = [c.cell_contents for c in s.step.__closure__ if isinstance(c.cell_contents, object)
                and type(c.cell_contents).__name__ == "_CompiledStep"][0]
        assert (comp.twin is not None and comp.twin.fn is not None) == compiled and comp.exact == compiled


def test_twin_policy(monkeypatch):
    """auto: numpy until the rows reach the break-even; a kernel in the disk cache is loaded early
    (or at once when numba is imported); 0: never; 1: at once; a declared job counts. (Loading is
    replaced by a stand-in: the policy, not numba, is under test.)"""
    import sys
    from types import SimpleNamespace
    from simgap import jit
    loads, cached = [], {"yes": False}
    monkeypatch.setattr(C, "load", lambda source: loads.append(source) or SimpleNamespace(values="kernel"))
    monkeypatch.setattr(C, "is_cached", lambda source: cached["yes"])
    monkeypatch.delitem(sys.modules, "numba", raising=False)
    src = (C.values_source, ([("mul", ("var", 0), ("var", 1))], 2))
    monkeypatch.setenv("SIMGAP_JIT", "0")
    t = C.Twin(*src, "values", 1000)
    assert t.get(10 ** 9) is None and not loads
    monkeypatch.setenv("SIMGAP_JIT", "auto")
    assert t.get(40) is None and t.cached is None       # below 1/20: the cache is not even looked at
    assert t.get(600) is None and t.cached is False and t.done == 640
    assert t.get(360) == "kernel" and len(loads) == 1   # 1000 rows: compiled
    cached["yes"] = True
    t2 = C.Twin(*src, "values", 1000)
    assert t2.get(10) is None and t2.get(40) == "kernel"  # 50 rows and in the cache: loaded
    t3 = C.Twin(*src, "values", 1000)
    with jit.expected_work(5000):
        assert t3.get(1) == "kernel"
    # the numpy seconds count too (a long formula costs far more per row): few rows, but the time a
    # compile costs, compiles; the time a load costs loads a cached kernel
    cached["yes"] = False
    t5 = C.Twin(*src, "values", 1000)
    t5.spent(C.AUTO_SECONDS - 0.1)
    assert t5.get(1) is None
    t5.spent(0.2)
    assert t5.get(1) == "kernel"
    cached["yes"] = True
    t6 = C.Twin(*src, "values", 1000)
    t6.spent(C.LOAD_SECONDS * 0.9)
    assert t6.get(1) is None
    t6.spent(C.LOAD_SECONDS * 0.2)
    assert t6.get(1) == "kernel"
    monkeypatch.setenv("SIMGAP_JIT", "1")
    assert C.Twin(*src, "values", 10 ** 9).get(0) == "kernel"
    import pickle  # a twin travels without its kernel
    t4 = pickle.loads(pickle.dumps(t3))
    assert t4.fn is None and t4.make() == t3.make()


def test_nan_endpoints_stay_nan():
    """inf - inf inside a formula (exp overflowing on both ends, plus an unbounded quotient) gives a
    NaN endpoint; squaring it must not turn it into a finite interval (min and max drop NaNs)."""
    x, u = ("var", 0), ("var", 1)
    big = ("fn", "exp", ("mul", ("const", 1000.0), ("add", ("const", 1.0), ("mul", ("const", 0.0), x))))
    unb = ("div", x, u)                          # u's box contains 0: (-inf, inf)
    half = ("add", unb, ("neg", big))            # (-inf, inf) + (-inf, -inf) = (-inf, NaN)
    # numba's max(inf, NaN) is inf: without the NaN guard, (-inf, NaN)^2 was [inf, inf] and 0 times
    # it [0, 0], a finite bound of an undefined value
    trees = [("mul", ("const", 0.0), ("pow", half, 2)), ("mul", ("const", 0.0), ("fn", "abs", half)),
             ("pow", ("add", big, unb), 2), ("fn", "sqrt", ("add", big, unb))]
    lo, hi = C.values_kernel(trees, 2)(np.array([[0.5, -1.0]]), np.array([[0.6, 1.0]]))
    assert not np.isfinite(lo).any() and not np.isfinite(hi).any()

"""Compiled kernels against their numpy twins: the same bits, and the policy that picks one
(simgap.jit). The built-in examples' compiled step is the C kernel generated from their system files
(simgap/synthesis/scots/); the index and the games are C (game_kernels); box_offsets is numba."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.synthesis import UniformGrid, build_abstraction
from simgap.synthesis import examples as ex
from simgap import jit

pytest.importorskip("numba")
if __import__("simgap.compile", fromlist=["c_compiler"]).c_compiler() is None:
    pytest.skip("no C compiler: the compiled steps and games are not built here", allow_module_level=True)


def _vehicle_batch(rng, B=20000):
    x = rng.uniform([0, 0, -3.5], [10, 10, 3.5], (B, 3))
    x[:4, 2] = [1e6, -1e9, 0.0, 3.141592653589793]  # large angles: the C library's reduction
    u = ex.vehicle_inputs()[rng.integers(0, 49, B)]
    u[:3] = [[0.7, 1.2], [-0.3, -1.5], [1.0, 0.0]]  # off the grid, steep steering
    return x, u


def test_vehicle_kernel_bit_identical(rng, monkeypatch):
    x, u = _vehicle_batch(rng)
    monkeypatch.setenv("SIMGAP_JIT", "0")
    want = ex.vehicle_step(x, u, 0.3)
    got = ex._vehicle_compiled(x, u, 0.3)
    assert np.array_equal(got, want)
    for tau in (0.6, 0.05):  # other periods (with_steps), the same bits
        assert np.array_equal(ex._vehicle_compiled(x, u, tau), ex.vehicle_step(x, u, tau))
    # inputs off the grid, every row its own: the C library's tan/atan differ from numpy's for
    # about 1 % of arguments, so the kernel takes numpy's input terms
    u2 = rng.uniform(-1.5, 1.5, (20000, 2))
    assert np.array_equal(ex._vehicle_compiled(x, u2, 0.3), ex.vehicle_step(x, u2, 0.3))
    monkeypatch.setenv("SIMGAP_JIT", "1")
    assert np.array_equal(ex.vehicle_step(x, u, 0.3), want)  # the step dispatches to the kernel


def test_vehicle_kernel_divides_as_numpy():
    """Non-finite states give numpy's inf/nan through the compiled step (C arithmetic, no
    exception), rows of other inputs alongside unchanged."""
    from simgap.runge_kutta import rk4_integrate
    x = np.array([[1.0, 2.0, 0.5], [np.nan, 0.0, 0.0], [np.inf, 1.0, 0.2]])
    u = np.array([[0.3, 0.6], [0.3, 0.6], [-0.9, 0.0]])
    with np.errstate(all="ignore"):
        want = rk4_integrate(ex._vehicle_rhs_prepared, x, u, 0.3, ex.VEHICLE_NINT, prepare=ex._vehicle_input_terms)
    got = ex._vehicle_compiled(x, u, 0.3)
    assert np.array_equal(got, want, equal_nan=True) and np.isfinite(got[0]).all() and np.isnan(got[1, 0])


def test_dcdc_kernel_bit_identical(rng, monkeypatch):
    """The converter's compiled step (generated from scots/dcdc.toml) gives the bits of its numpy
    step, at its period and at another."""
    s = ex.dcdc_system()
    x = rng.uniform([1.0, 5.3], [1.7, 6.0], (20001, 2))
    u = s.inputs[rng.integers(0, 2, 20001)]
    monkeypatch.setenv("SIMGAP_JIT", "0")
    want = {tau: s.step(x, u, tau) for tau in (0.5, 1.5)}
    monkeypatch.setenv("SIMGAP_JIT", "1")
    for tau in (0.5, 1.5):
        assert np.array_equal(s.step(x, u, tau), want[tau])
    assert not np.array_equal(want[0.5], want[1.5])


def test_dcdc_numpy_by_mode_bit_identical(rng):
    """The numpy step with the rows grouped by mode (examples._dcdc_numpy) gives the bits of the
    plain RK4 of examples._dcdc_rhs (np.where over both modes), special values included, and a
    column-major RK4 the bits of a row-major one."""
    from simgap.runge_kutta import rk4_integrate
    s = ex.dcdc_system()
    x = rng.uniform([1.0, 5.3], [1.7, 6.0], (20000, 2))
    x[:6] = [[np.inf, 1.0], [0.0, -0.0], [np.nan, 2.0], [-0.0, np.inf], [1e308, 1e308], [-1e-320, 5.0]]
    u = s.inputs[rng.integers(0, 2, 20000)]
    with np.errstate(all="ignore"):
        for tau in (0.5, 1.5):
            want = rk4_integrate(ex._dcdc_rhs, x, u, tau, 5)
            got = ex._dcdc_numpy(x, u, tau)
            assert np.array_equal(np.ascontiguousarray(got).view(np.int64), want.view(np.int64))
            c = rk4_integrate(ex._dcdc_rhs, np.ascontiguousarray(x), u, tau, 5)
            assert np.array_equal(c.view(np.int64), want.view(np.int64))
        alt = s.inputs[np.tile([0, 1], 10000)]  # the abstraction's blocks: strided slices per mode
        assert np.array_equal(np.ascontiguousarray(ex._dcdc_numpy(x, alt, 0.5)).view(np.int64),
                              rk4_integrate(ex._dcdc_rhs, x, alt, 0.5, 5).view(np.int64))
        assert np.array_equal(ex._dcdc_numpy(x[:7], u[:7] * 0 + 1.0, 0.5), rk4_integrate(ex._dcdc_rhs, x[:7], u[:7] * 0 + 1.0, 0.5, 5),
                              equal_nan=True)  # one mode only
        assert np.array_equal(ex._dcdc_numpy(x[0], u[0], 0.5), rk4_integrate(ex._dcdc_rhs, x[:1], u[:1], 0.5, 5),
                              equal_nan=True)  # one row, 1-D


def test_equality_is_sensitive_to_the_summation_order(rng):
    """Mutation check: an RK4 weighting each slope on its own, x + h (k0/6 + k1/3 + k2/3 + k3/6)
    (the same method, other rounding), differs from the kernel in the last bits, so the
    equalities above would catch a kernel that reorders its operations."""
    x, u = _vehicle_batch(rng, 4000)

    def weighted(x, u, tau, nint):
        h = tau / nint
        for _ in range(nint):
            k0 = ex._vehicle_rhs(x, u)
            k1 = ex._vehicle_rhs(x + h / 2 * k0, u)
            k2 = ex._vehicle_rhs(x + h / 2 * k1, u)
            k3 = ex._vehicle_rhs(x + h * k2, u)
            x = x + h * (k0 / 6 + k1 / 3 + k2 / 3 + k3 / 6)
        return x
    other = weighted(x, u, 0.3, 10)
    got = ex._vehicle_compiled(x, u, 0.3)
    assert np.allclose(other, got, rtol=0, atol=1e-12)
    assert not np.array_equal(other, got)


@pytest.mark.parametrize("case", ["dcdc", "vehicle", "vehicle_shared", "dcdc_int16"])
def test_abstraction_same_with_and_without_kernels(case, monkeypatch):
    """Every cell integrated on a part of each grid (and the vehicle's shared boxes, and offsets
    beyond int8): the same offset tables and valid pairs from the compiled RK4 and boxes."""
    if case == "dcdc":
        s = ex.dcdc_system(x_lo=(1.15, 5.45), x_hi=(1.25, 5.55))
        g = UniformGrid(s.x_lo, s.x_hi, ex.DCDC_ETA)
        kw = dict(growth=ex.dcdc_growth())
    elif case == "dcdc_int16":  # a fine grid: the boxes move by more than 127 cells per step
        s = ex.dcdc_system(x_lo=(1.15, 5.45), x_hi=(1.152, 5.452))
        g = UniformGrid(s.x_lo, s.x_hi, (ex.DCDC_ETA[0] / 40, ex.DCDC_ETA[1] / 40))
        kw = dict(growth=ex.dcdc_growth())
    else:
        s = ex.vehicle_system()
        g = UniformGrid([0.0, 0.0, -3.5], [2.0, 2.0, 3.5], ex.VEHICLE_ETA)
        kw = dict(growth=ex.vehicle_growth, invariant_dims=(0, 1) if case == "vehicle_shared" else ())
    out = []
    for mode in ("0", "1"):
        monkeypatch.setenv("SIMGAP_JIT", mode)
        ab = build_abstraction(s, g, **kw)
        out.append((ab.off_lo, ab.off_hi, ab.ok))
    assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(*out))
    if case == "dcdc_int16":  # every box leaves this small domain: the offsets are compared
        assert out[0][0].dtype == np.int16 and np.abs(out[0][0]).max() > 127
    else:
        assert out[0][2].sum() > (100 if case != "vehicle_shared" else 10)


def test_policy(monkeypatch):
    monkeypatch.setenv("SIMGAP_JIT", "2")
    with pytest.raises(SimgapError, match="SIMGAP_JIT='2'.*0, 1, auto"):
        jit.use_compiled()
    monkeypatch.setenv("SIMGAP_JIT", "0")
    with jit.expected_work(10 ** 9):
        assert not jit.use_compiled()
    monkeypatch.setenv("SIMGAP_JIT", "1")
    assert jit.use_compiled()
    monkeypatch.setenv("SIMGAP_JIT", "auto")
    monkeypatch.setattr(sys, "modules", {k: v for k, v in sys.modules.items() if k != "numba"})
    assert not jit.use_compiled(100)  # nothing declared
    with jit.expected_work(99):
        assert not jit.use_compiled(100)
    with jit.expected_work(100):
        assert jit.use_compiled(100)
    assert not jit.use_compiled(100)  # the declaration ends with its block


def test_small_jobs_do_not_import_numba():
    """A small synthesis (auto mode) stays on the numpy path: numba is never imported."""
    code = ("import sys\nfrom simgap.synthesis import synthesize\nfrom simgap.synthesis import examples as ex\n"
            "s = ex.dcdc_system(x_lo=(1.15, 5.45), x_hi=(1.25, 5.55))\n"
            "r = synthesize(s, ex.dcdc_spec(), ex.DCDC_ETA, growth=ex.dcdc_growth())\n"
            "print('numba' in sys.modules, r.stats['transitions'] > 1000)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                       env={**__import__("os").environ, "SIMGAP_JIT": "auto"})
    assert p.stdout.split() == ["False", "True"]


def test_kernel_load_defers_numbas_blas_probe():
    """Loading a kernel does not import scipy.linalg (numba's import-time BLAS probe, 0.23 s and
    28 MB: jit._defer_blas_probe); numba's BLAS-backed functions still compile and import it."""
    code = ("import sys\nimport numpy as np\nfrom simgap.synthesis import kernels\n"
            "lo, hi, ok = np.zeros((4, 2), np.int8), np.zeros((4, 2), np.int8), np.zeros(4, np.bool_)\n"
            "f = np.ones(2)\n"
            "kernels.box_offsets(np.ones((4, 2)), np.ones((4, 2)) * 0.1, f * 1e-12, f, f * 0, f * -10, f * 10,\n"
            "                    np.zeros((4, 2), np.int32), np.zeros(2, np.bool_), 100.0, lo, hi, ok)\n"
            "print('scipy.linalg' in sys.modules)\n"
            "import numba\n"
            "f = numba.njit(lambda a, b: np.dot(a, b))\n"
            "a = np.arange(3.0)\n"
            "print(f(a, a) == np.dot(a, a), 'scipy.linalg' in sys.modules)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert p.stdout.split() == ["False", "True", "True"]


@pytest.mark.parametrize("case", ["vehicle", "periodic"])
def test_reach_game_same_with_and_without_kernel(case, monkeypatch):
    """The compiled level of the worklist reach game (kernels.reach_level) wins the same cells at
    the same levels with the same valid inputs as the numpy level (corner index, no shared boxes;
    a bounded grid and one with a periodic heading)."""
    from simgap.synthesis import Box, Spec, label_cells, solve_reach
    inf = np.inf
    if case == "vehicle":
        s = ex.vehicle_system()
        g = UniformGrid([0.0, 0.0, -3.5], [3.0, 3.0, 3.5], ex.VEHICLE_ETA)
        spec = Spec(kind="reach_avoid", target=Box([2.0, 0.4, -inf], [2.6, 1.0, inf]),
                    obstacles=(Box([1.0, 0.0, -inf], [1.2, 2.0, inf]),))
        kw = dict(growth=ex.vehicle_growth)
    else:
        s = ex.vortex_system()
        g = UniformGrid(s.x_lo, [5.0, 5.0, np.pi], ex.VORTEX_ETA, periodic=s.angle_dims)
        spec = Spec(kind="reach_avoid", target=Box([2.0, 2.0, -inf], [3.0, 3.0, inf]))
        kw = dict(growth=ex.vortex_growth())
    monkeypatch.setenv("SIMGAP_JIT", "0")
    blocked, target = label_cells(g, spec, s.x_lo, s.x_hi)
    ab = build_abstraction(s, g, **kw)
    assert ab.corner_index is not None
    res = {}
    for mode in ("0", "1"):
        monkeypatch.setenv("SIMGAP_JIT", mode)
        res[mode] = solve_reach(ab, target, blocked, method="worklist")
    a, b = res["0"], res["1"]
    assert np.array_equal(a.steps, b.steps) and np.array_equal(a.valid_packed, b.valid_packed)
    assert a.iterations == b.iterations and a.info["pairs_tested"] == b.info["pairs_tested"]
    assert a.iterations > 3 and (a.steps > 0).sum() > 50


def test_reach_kernel_counts_every_transition_once(monkeypatch):
    """Mutation check of the kernel's inputs: with one corner offset dropped (a wrong index) the
    compiled game visits fewer transitions and finds fewer valid inputs, so the equalities above would
    catch a kernel that misses predecessors."""
    from simgap.synthesis import Box, Spec, label_cells, solve_reach
    s = ex.vehicle_system()
    g = UniformGrid([0.0, 0.0, -3.5], [3.0, 3.0, 3.5], ex.VEHICLE_ETA)
    spec = Spec(kind="reach_avoid", target=Box([2.0, 0.4, -np.inf], [2.6, 1.0, np.inf]))
    monkeypatch.setenv("SIMGAP_JIT", "1")
    blocked, target = label_cells(g, spec, s.x_lo, s.x_hi)
    ab = build_abstraction(s, g, growth=ex.vehicle_growth)
    good = solve_reach(ab, target, blocked, method="worklist")
    ci = ab.corner_index
    ci.fits = ci.fits.copy()
    ci.fits[1] = False  # the corner offset (0, ..., 0, 1) never fits: its transitions are lost
    bad = solve_reach(ab, target, blocked, method="worklist")
    assert bad.info["pairs_tested"] < good.info["pairs_tested"]
    bits = lambda r: np.unpackbits(r.valid_packed).sum()  # noqa: E731
    assert bits(bad) < bits(good)  # pairs whose count never reaches 0: fewer valid inputs
    assert bad.winning.sum() < good.winning.sum()


@pytest.mark.parametrize("case", ["dcdc", "periodic"])
def test_invariance_game_same_with_and_without_kernel(case, monkeypatch):
    """The compiled round of the invariance worklist (game_kernels.inv_level) keeps the same cells
    with the same valid inputs, chosen inputs, rounds and dropped pairs as the numpy rounds (a
    bounded grid and one with a periodic heading)."""
    from simgap.synthesis import Box, Spec, label_cells, solve_invariance
    inf = np.inf
    if case == "dcdc":
        s = ex.dcdc_system()
        g = UniformGrid(s.x_lo, s.x_hi, (0.002, 0.002))
        spec, kw = ex.dcdc_spec(), dict(growth=ex.dcdc_growth())
    else:
        s = ex.vortex_system()
        g = UniformGrid(s.x_lo, s.x_hi, (0.4, 0.4, 2 * np.pi / 16), periodic=s.angle_dims)
        spec = Spec(kind="invariance", safe=Box([2.0, 2.0, -inf], [8.0, 8.0, inf]))
        kw = dict(growth=ex.vortex_growth())
    monkeypatch.setenv("SIMGAP_JIT", "0")
    blocked, _ = label_cells(g, spec, s.x_lo, s.x_hi)
    ab = build_abstraction(s, g, **kw)
    assert ab.corner_index is not None
    res = {}
    for mode in ("0", "1"):
        monkeypatch.setenv("SIMGAP_JIT", mode)
        res[mode] = solve_invariance(ab, ~blocked, blocked, method="worklist")
    a, b = res["0"], res["1"]
    assert np.array_equal(a.winning, b.winning) and np.array_equal(a.valid_packed, b.valid_packed)
    assert np.array_equal(a.chosen, b.chosen)
    assert a.iterations == b.iterations and a.info["pairs_tested"] == b.info["pairs_tested"]
    assert a.iterations > 2 and 0 < a.winning.sum() < (~blocked).sum()
    assert np.unique(a.chosen[a.winning]).size > 1  # the margins decide between inputs somewhere


@pytest.mark.parametrize("case", ["vehicle", "periodic"])
def test_corner_index_same_with_and_without_kernels(case, monkeypatch):
    """The compiled two-pass build of the predecessor index gives the numpy build's arrays (the
    same order of pairs within each corner's row, the same codes, per-cell tables)."""
    from simgap.synthesis.corner_index import CornerIndex
    monkeypatch.setenv("SIMGAP_JIT", "0")
    if case == "vehicle":
        s = ex.vehicle_system()
        g = UniformGrid([0.0, 0.0, -3.5], [3.0, 3.0, 3.5], ex.VEHICLE_ETA)
        ab = build_abstraction(s, g, growth=ex.vehicle_growth)
    else:
        s = ex.vortex_system()
        g = UniformGrid(s.x_lo, [5.0, 5.0, np.pi], ex.VORTEX_ETA, periodic=s.angle_dims)
        ab = build_abstraction(s, g, growth=ex.vortex_growth())
    a = CornerIndex.build(ab)
    monkeypatch.setenv("SIMGAP_JIT", "1")
    b = CornerIndex.build(ab)
    for k in ("indptr", "q", "code", "emax", "usable", "cell_boxes", "cell_transitions", "fits"):
        x, y = getattr(a, k), getattr(b, k)
        assert x.dtype == y.dtype and np.array_equal(x, y), k
    assert a.size > 10000


def test_input_rows_periodic_and_general(rng):
    """The input rows of a step: periodic blocks (whole cells, all inputs each) by comparisons,
    anything else by the sort; every row equals its representative exactly."""
    from simgap.runge_kutta import _input_rows
    U = ex.vehicle_inputs()
    for u in (U[np.tile(np.arange(49), 334)], U[np.tile(np.arange(49), 3)][:120],  # periodic, cut
              U[rng.integers(0, 49, 5000)], np.array([[1.0], [2.0], [2.0], [1.0], [2.0], [2.0], [1.0]]),
              np.array([[1.0, 2.0], [1.0, 3.0], [1.0, 2.0], [1.0, 2.0]]), U[:1]):
        uu, inv = _input_rows(u)
        assert inv.shape == (u.shape[0],) and np.array_equal(uu[inv], u)
    uu, inv = _input_rows(U[np.tile(np.arange(49), 334)])
    assert uu.shape == (49, 2)

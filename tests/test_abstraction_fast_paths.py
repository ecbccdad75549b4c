"""The abstraction's fast paths give the results of the plain computation, bit for bit."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.synthesis import UniformGrid, build_abstraction, rk4_integrate, state_independent, synthesize
from simgap.synthesis import examples as ex


def _plain_rk4(rhs, x, u, tau, nint):
    """The textbook expression, SCOTS's operation order."""
    h = tau / nint
    x = np.array(x, dtype=float)
    for _ in range(nint):
        k0 = rhs(x, u)
        k1 = rhs(x + h / 2 * k0, u)
        k2 = rhs(x + h / 2 * k1, u)
        k3 = rhs(x + h * k2, u)
        x = x + (h / 6) * (k0 + 2 * k1 + 2 * k2 + k3)
    return x


@pytest.mark.parametrize("rhs", [
    ex._vehicle_rhs,
    lambda x, u: x,                                   # returns its argument (a reused buffer)
    lambda x, u: np.sin(x) * u[:, :1] - 0.3 * x ** 2,
    lambda x, u: np.broadcast_to(u[:1, :1], x.shape),  # a read-only broadcast
])
def test_rk4_in_place_equals_the_expression(rhs, rng):
    x = rng.normal(size=(500, 3))
    u = rng.normal(size=(500, 2))
    assert np.array_equal(rk4_integrate(rhs, x, u, 0.3, 7), _plain_rk4(rhs, x, u, 0.3, 7))


def _dcdc_small():
    s = ex.dcdc_system()
    return s, UniformGrid(s.x_lo, s.x_hi, (0.002, 0.002))


def _same(a, b):
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("off_lo", "off_hi", "ok"))


def test_state_independent_growth_is_evaluated_once_per_input():
    s, grid = _dcdc_small()
    base = ex.dcdc_growth()
    rows = []

    def counted(r, x, u, tau):
        rows.append(len(r))
        return base(r, x, u, tau)

    plain = build_abstraction(s, grid, growth=counted, block=4096)  # not declared: per pair
    assert sum(rows) == grid.size * 2
    rows.clear()
    fast = build_abstraction(s, grid, growth=state_independent(counted), block=4096)
    assert rows == [2]  # one call, one row per input
    assert _same(plain, fast)

    class Model:  # a bound method cannot carry the mark itself
        def growth(self, r, x, u, tau):
            rows.append(len(r))
            return base(r, x, u, tau)
    rows.clear()
    assert _same(build_abstraction(s, grid, growth=state_independent(Model().growth), block=4096), plain)
    assert rows == [2]
    # with a box-dependent gap the radius differs per cell: evaluated per pair again
    rows.clear()

    class Gap:
        def gamma_upper_box(self, lo, hi, u):
            return 1e-4 * np.abs(hi)

    build_abstraction(s, grid, growth=counted, gap=Gap(), block=4096)
    assert sum(rows) == grid.size * 2


def test_old_growth_signature_still_works_with_a_warning():
    s, grid = _dcdc_small()
    g4 = ex.dcdc_growth()
    with pytest.warns(DeprecationWarning, match="tau"):
        old = build_abstraction(s, grid, growth=lambda r, x, u: g4(r, x, u, s.tau))
    assert _same(old, build_abstraction(s, grid, growth=g4))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the current signature: no warning
        build_abstraction(s, grid, growth=g4)
    # at another period a growth without tau cannot be right: refused
    with pytest.raises(SimgapError, match="tau"):
        build_abstraction(s.with_steps(2), grid, growth=lambda r, x, u: g4(r, x, u, s.tau))


def test_dcdc_winning_domain():
    """SCOTS's boost converter at 801 x 801 cells: the domain measured before the fast paths."""
    res = synthesize(ex.dcdc_system(), ex.dcdc_spec(), ex.DCDC_ETA, growth=ex.dcdc_growth(), invariant_dims=())
    assert res.stats["cells"] == 641_601
    assert res.stats["winning"] == 593_089 and res.stats["transitions"] == 3_788_008


def test_synthesis_does_not_load_value_iterations_compiler():
    """numba (about 0.5 s CPU and 110 MB with a kernel loaded) is for value iteration's kernel
    and for large syntheses only (simgap.jit: a small one stays on numpy); the plugin
    registry's metadata scan is for plugin names only."""
    import subprocess
    import sys
    code = ("import sys\n"
            "from simgap.synthesis import synthesize, examples as ex\n"
            "synthesize(ex.dcdc_system(), ex.dcdc_spec(), (0.004, 0.004), growth=ex.dcdc_growth(), invariant_dims=())\n"
            # the plugin registry's importlib.metadata (email, csv, zipfile, ...: about 40 ms per
            # process) only when a name is looked up among the plugins
            "from simgap.systems import get_system\n"
            "get_system('pendulum')\n"
            "assert 'importlib.metadata' not in sys.modules, 'importlib.metadata was loaded'\n"
            "import simgap.perrun.value_iteration\n"
            "assert 'numba' not in sys.modules, 'numba was loaded'\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr


@pytest.mark.parametrize("kw", [dict(hold=3), dict(hold=2, gap=[2e-4, 2e-4, 4e-4])])
def test_live_pairs_on_distinct_boxes_equal_the_pass_over_all_inputs(kw, monkeypatch):
    """Inputs that share a box share every test: the pass over distinct boxes changes nothing."""
    from simgap.maps import load_map
    from simgap.synthesis import games, label_cells, solve_invariance, solve_reach
    from simgap.systems import get_system
    s = get_system("turtlebot").with_steps(10)
    spec = load_map("arena").spec(s)
    grid = UniformGrid(s.x_lo, s.x_hi, 0.2, periodic=s.angle_dims)
    blocked, cells = label_cells(grid, spec, s.x_lo, s.x_hi)
    ab = build_abstraction(s, grid, invariant_dims=(0, 1), compose_hold=True, **kw)
    dist = games.DistinctBoxes.of(ab)
    assert dist is not None and dist.D < ab.n_inputs / 2  # the case this is for
    assert np.array_equal(dist.mult.sum(axis=1), np.full(ab.n_classes, ab.n_inputs))
    fast = games.live_pairs(ab, blocked, ~blocked, ~blocked)
    res = solve_reach(ab, cells, blocked, method="sat")
    inv = solve_invariance(ab, ~blocked, blocked, method="sat")
    monkeypatch.setattr(games.DistinctBoxes, "of", classmethod(lambda cls, ab: None))
    plain = games.live_pairs(ab, blocked, ~blocked, ~blocked)
    assert np.array_equal(fast[0], plain[0]) and fast[1:] == plain[1:]
    assert fast[1] > 0 and fast[0].any() and not fast[0].all()
    ref = solve_reach(ab, cells, blocked, method="sat")
    assert np.array_equal(res.steps, ref.steps) and np.array_equal(res.valid_packed, ref.valid_packed)
    assert res.info["pairs_tested"] == ref.info["pairs_tested"]
    assert res.winning.sum() > cells.sum() or "gap" in kw  # (with the gap nothing is won beyond the target)
    ref_inv = solve_invariance(ab, ~blocked, blocked, method="sat")
    assert np.array_equal(inv.winning, ref_inv.winning) and np.array_equal(inv.valid_packed, ref_inv.valid_packed)
    assert np.array_equal(inv.chosen, ref_inv.chosen) and 0 < inv.winning.sum() < (~blocked).sum()


def test_rk4_prepare_is_bit_identical_to_the_plain_right_hand_side(rng):
    """Input-only terms computed once per step (``prepare``) give the bits of the plain rhs."""
    from simgap.synthesis import rk4_step
    x = rng.uniform([0, 0, -3.5], [10, 10, 3.5], size=(700, 3))
    u = ex.vehicle_inputs()[rng.integers(0, 49, 700)]
    want = _plain_rk4(ex._vehicle_rhs, x, u, 0.3, 10)  # SCOTS's rhs, every term per call
    assert np.array_equal(ex.vehicle_step(x, u, 0.3), want)
    assert np.array_equal(rk4_step(ex._vehicle_rhs_prepared, 10, prepare=ex._vehicle_input_terms)(x, u, 0.3), want)

    def prep(uu):
        return np.tan(uu[:, :1])

    def rhs_p(xx, t):
        return np.sin(xx) * t - 0.3 * xx

    def rhs(xx, uu):
        return rhs_p(xx, prep(uu))
    assert np.array_equal(rk4_integrate(rhs_p, x, u, 0.2, 4, prepare=prep), _plain_rk4(rhs, x, u, 0.2, 4))
    with pytest.raises(SimgapError, match="prepare"):
        rk4_step(rhs, 4, prepare=1.0)


def _reference_corner_index(ab):
    """indptr, q, code of the corner index the plain way: a stable sort of all usable pairs by
    their lo corner's flat id (pairs in input-major order)."""
    g = ab.grid
    N, M = g.size, ab.n_inputs
    shape = np.array(g.shape)
    lo = g.ids_to_multi(np.arange(N))[:, None, :] + ab.off_lo.astype(np.int64)
    ext = ab.off_hi.astype(np.int64) - ab.off_lo + 1
    usable = ab.ok.copy()
    for d in range(g.n):
        if g.periodic_mask[d]:
            lo[..., d] %= shape[d]
            ext[..., d] = np.minimum(ext[..., d], shape[d])
        else:
            usable &= (lo[..., d] >= 0) & (lo[..., d] + ext[..., d] <= shape[d])
    key = (lo * g.strides).sum(axis=-1)
    pos = np.flatnonzero(usable.T.ravel())  # input-major positions u * N + c
    k = key.T.ravel()[pos]
    order = np.argsort(k, kind="stable")
    emax = ext[usable].max(axis=0)
    code = np.zeros(usable.shape, dtype=np.int64)
    for d in range(g.n):
        code = code * emax[d] + ext[..., d] - 1
    q = ((pos % N) * M + pos // N)[order]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(k, minlength=N))])
    return indptr, q, code.reshape(-1)[q]


@pytest.mark.parametrize("case", ["dcdc", "vortex"])
def test_corner_index_counting_sort_equals_a_stable_sort_of_all_pairs(case):
    """The chunked counting sort places every pair where one stable sort of all pairs does,
    across block and chunk boundaries (and with a periodic heading: vortex)."""
    from simgap.synthesis.corner_index import CornerIndex
    if case == "dcdc":
        s, grid = _dcdc_small()
        ab = build_abstraction(s, grid, growth=ex.dcdc_growth())
    else:
        s = ex.vortex_system()
        grid = UniformGrid(s.x_lo, s.x_hi, (0.5, 0.5, 2 * np.pi / 16), periodic=s.angle_dims)
        ab = build_abstraction(s, grid, growth=ex.vortex_growth())
    indptr, q, code = _reference_corner_index(ab)
    assert q.size > 10_000 and np.any(np.diff(indptr) > 1)  # rows with several pairs to order
    for kw in ({}, dict(block=97, chunk=1000)):
        ci = CornerIndex.build(ab, **kw)
        assert np.array_equal(ci.indptr, indptr)
        assert np.array_equal(ci.q, q)  # same pairs, same order within every row
        assert np.array_equal(ci.code, code)


def test_corner_index_covers_the_worklist_games_pairs():
    """The worklist game runs on the corner index wherever it runs at all (no second, slower
    game past 2^24 pairs)."""
    from simgap.synthesis.corner_index import CornerIndex
    from simgap.synthesis.fixed_point import _WORKLIST_MAX_PAIRS
    assert CornerIndex.MAX_PAIRS >= _WORKLIST_MAX_PAIRS


def test_offsets_stored_as_int8_until_one_does_not_fit():
    """Offsets go to int8 tables that become int16 when a later block needs it: the values
    written before the switch are kept (same tables as one block computed at once, and as the
    plain formula)."""
    from simgap.systems import System
    s = System(name="doubling", state_names=("x",), input_names=("u",), x_lo=(0.0,), x_hi=(1.0,),
               inputs=np.array([[0.0], [1.0]]), base_tau=1.0, step=lambda x, u, tau: x * (1.0 + u))
    grid = UniformGrid(s.x_lo, s.x_hi, 0.001)  # x -> 2x moves cell i by i cells: > 127 from i = 128
    growth = state_independent(lambda r, x, u, tau: r * (1.0 + u))
    small_blocks = build_abstraction(s, grid, growth=growth, block=64)
    one_block = build_abstraction(s, grid, growth=growth, block=1 << 20)
    assert small_blocks.off_lo.dtype == np.int16 and _same(small_blocks, one_block)
    i = np.arange(grid.size)
    x = grid.first[0] + i * grid.eta[0]
    r = grid.eta[0] / 2 + 1e-10 * grid.eta[0]
    for j, k in ((0, 1.0), (1, 2.0)):
        lo = np.floor((k * x - k * r - 1e-10 * grid.eta[0] - grid.first[0] + grid.eta[0] / 2) / grid.eta[0]) - i
        use = small_blocks.ok[:, j]
        assert use.sum() > 300 and np.array_equal(small_blocks.off_lo[use, j, 0], lo[use])
    fits = build_abstraction(s, UniformGrid(s.x_lo, s.x_hi, 0.01), growth=growth, block=64)
    assert fits.off_lo.dtype == np.int8

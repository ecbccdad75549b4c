"""Games: the worklist (predecessor counters) against the summed-area-table game, the
predecessor index against brute force, the growth bound's tau, and the public API."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.synthesis import (Box, Spec, UniformGrid, build_abstraction, rk4_growth, rk4_integrate,
                              rk4_step, solve_invariance, solve_reach, synthesize)
from simgap.synthesis.controller import label_cells
from simgap.synthesis import examples as ex
from simgap.synthesis.games import Predecessors, _unpack, _valid_shared, live_pairs
from simgap.systems import System, get_system, input_grid


def _drift():
    """x' = u + 0.3 sin(y) on [0, 2] x [-pi, pi) with y an angle: f - x does not depend on x (invariant,
    bounded) but does on y; the second variant drops the sin (y invariant too, and periodic)."""
    def rhs(x, u):
        return np.stack([u[:, 0] + 0.3 * np.sin(x[:, 1]), u[:, 1]], axis=1)
    return System(name="drift", state_names=("x", "y"), input_names=("a", "b"),
                  x_lo=(0.0, -np.pi), x_hi=(2.0, np.pi), inputs=input_grid([-1, -1], [1, 1], [3, 3]),
                  base_tau=0.25, step=rk4_step(rhs, 4), angle_dims=(1,))


DRIFT_L = np.array([[0.0, 0.3], [0.0, 0.0]])


def _cases():
    """(system, spec, eta, growth, invariant_dims, hold): class and generic paths, periodic
    class and invariant dimensions, held inputs (intermediate hulls)."""
    tb = dataclasses.replace(get_system("turtlebot"), x_lo=np.array([0.0, 0.0, -np.pi]),
                             x_hi=np.array([1.5, 1.5, np.pi]), inputs=input_grid([-1, -1], [1, 1], [5, 5]))
    tb_spec = Spec(kind="reach_avoid", target=Box([0.2, 0.2, -np.inf], [0.5, 0.5, np.inf]),
                   obstacles=(Box([0.7, 0.0, -np.inf], [0.8, 0.9, np.inf]),))
    dr_spec = Spec(kind="reach_avoid", target=Box([1.5, -0.5], [1.9, 0.5]),
                   obstacles=(Box([0.8, -3.0], [1.0, 1.0]),))
    return [
        (tb, tb_spec, (0.05, 0.05, 2 * np.pi / 32), None, (0, 1), 10),  # class path, theta periodic
        (_drift(), dr_spec, (0.05, 2 * np.pi / 30), rk4_growth(DRIFT_L, 4), (), 2),  # generic, held
        (_drift(), dr_spec, (0.05, 2 * np.pi / 30), rk4_growth(DRIFT_L, 4), (0,), 1),
        (dataclasses.replace(_drift(), inputs=input_grid([-0.2, -1], [0.2, 1], [3, 3])),
         Spec(kind="invariance", safe=Box([0.3, -np.inf], [1.7, np.inf])),
         (0.05, 2 * np.pi / 30), rk4_growth(DRIFT_L, 4), (0,), 1),
        # one class per cell, no held input: the corner index without a pass over all pairs
        (ex.dcdc_system(), ex.dcdc_spec(), (0.002, 0.002), ex.dcdc_growth(), (), 1),
        (dataclasses.replace(_drift(), inputs=input_grid([-0.2, -1], [0.2, 1], [3, 3])),
         Spec(kind="invariance", safe=Box([0.3, -np.inf], [1.7, np.inf])),
         (0.05, 2 * np.pi / 30), rk4_growth(DRIFT_L, 4), (), 1),
    ]


def _abstraction(sysm, spec, eta, growth, inv, hold):
    grid = UniformGrid(sysm.x_lo, sysm.x_hi, eta, periodic=sysm.angle_dims)
    blocked, cells = label_cells(grid, spec, sysm.x_lo, sysm.x_hi)
    ab = build_abstraction(sysm, grid, growth=growth, hold=hold, invariant_dims=inv, gap=[0.0002] * sysm.n,
                           compose_hold=True)
    return ab, blocked, cells


@pytest.mark.parametrize("case", range(6))
def test_worklist_game_equals_sat_game(case):
    ab, blocked, cells = _abstraction(*_cases()[case])
    if _cases()[case][1].kind == "reach_avoid":
        a = solve_reach(ab, cells, blocked, method="worklist")
        b = solve_reach(ab, cells, blocked, method="sat")
        assert a.info["method"] == "worklist" and b.info["method"] == "sat"
        assert 0 < (a.winning & ~a.target).sum() < ab.grid.size - cells.sum()
        assert a.steps.max() >= 3  # several levels
    else:
        a = solve_invariance(ab, cells, blocked, method="worklist")
        b = solve_invariance(ab, cells, blocked, method="sat")
        assert 0 < a.winning.sum() < cells.sum()  # the game removed cells
        assert np.array_equal(a.chosen, b.chosen)
    assert np.array_equal(a.winning, b.winning)
    assert np.array_equal(a.steps, b.steps)
    assert np.array_equal(a.valid_packed, b.valid_packed)


@pytest.mark.parametrize("case", [0, 1, 2, 4])
def test_predecessors_equal_brute_force(case, rng):
    ab, blocked, cells = _abstraction(*_cases()[case])
    g = ab.grid
    N, M = g.size, ab.n_inputs
    live, _, _ = live_pairs(ab, blocked, ~blocked, test_keep=False)
    live = _unpack(live, M)
    one_class = len(ab.class_dims) == g.n
    pre = Predecessors(ab, live if one_class else ab.ok.reshape(-1))
    # brute force: the cells of every live pair's box (wrapped), restricted to some targets
    mi = g.ids_to_multi(np.arange(N))
    k = ab.cell_class(mi)
    r = rng.choice(N, 40, replace=False)
    shape = np.array(g.shape)
    c, u = np.nonzero(live.reshape(N, M))
    lo = mi[c] + ab.off_lo[k[c], u]
    hi = mi[c] + ab.off_hi[k[c], u]
    want = []
    for rd in g.ids_to_multi(r):  # 40 targets, vectorized over the pairs
        inside = np.ones(c.size, bool)
        for d in range(g.n):
            if g.periodic_mask[d]:
                inside &= ((rd[d] - lo[:, d]) % shape[d]) <= np.minimum(hi[:, d] - lo[:, d], shape[d] - 1)
            else:
                inside &= (rd[d] >= lo[:, d]) & (rd[d] <= hi[:, d])
        want.append(c[inside] * M + u[inside])
    want = np.concatenate(want)
    indexes = [pre] + ([ab.corner_index] if one_class else [])
    assert not one_class or ab.corner_index is not None  # built with the abstraction (small boxes)
    assert len(want) > 100
    for index in indexes:
        got = index.pairs(r)
        got = got[live[got]]
        assert np.array_equal(np.sort(got), np.sort(want))  # one entry per transition, none missing


def test_growth_receives_the_sampling_period_of_with_steps(rng):
    """A growth bound for x' = a x is exp(a tau) r: after with_steps(4) it must grow over 4 base
    periods. Sampled images of a cell must stay inside its successor box."""
    a = 0.8

    def rhs(x, u):
        return a * x + u

    sysm = System(name="expo", state_names=("x",), input_names=("u",), x_lo=(-1.0,), x_hi=(1.0,),
                  inputs=np.array([[-0.5], [0.0], [0.5]]), base_tau=0.1, step=rk4_step(rhs, 10))
    growth = rk4_growth(np.array([[a]]), 10)
    for steps in (1, 4):
        s = sysm.with_steps(steps)
        grid = UniformGrid(s.x_lo, s.x_hi, 0.01)
        ab = build_abstraction(s, grid, growth=growth)
        ids = rng.integers(0, grid.size, 400)
        j = rng.integers(0, 3, 400)
        x = grid.points(ids) + (rng.random((400, 1)) - 0.5) * grid.eta * 0.999
        xn = s.f(x, s.inputs[j])
        lo = grid.ids_to_multi(ids) + ab.off_lo[ids, j]
        hi = grid.ids_to_multi(ids) + ab.off_hi[ids, j]
        cell = np.floor((xn - grid.first) / grid.eta + 0.5)
        ok = ab.ok[ids, j]
        assert ok.sum() > 100
        assert np.all((cell[ok] >= lo[ok]) & (cell[ok] <= hi[ok])), f"steps={steps}"
    # a growth bound written without tau is refused with a message that says why
    with pytest.raises(SimgapError, match="tau"):
        build_abstraction(sysm.with_steps(4), UniformGrid(sysm.x_lo, sysm.x_hi, 0.01),
                          growth=lambda r, x, u: r)


def test_rk4_helpers():
    # x' = -x: RK4 is exp(-t) to 1e-7 with 20 substeps (error h^4 / 120); r' = L r likewise
    x = np.array([[1.0, 2.0]])
    out = rk4_integrate(lambda x, u: -x, x, None, 1.0, 20)
    assert np.allclose(out, x * np.exp(-1.0), rtol=1e-7, atol=0)
    assert not np.allclose(rk4_integrate(lambda x, u: -x, x, None, 1.0, 2), x * np.exp(-1.0), rtol=1e-7, atol=0)
    g = rk4_growth(np.array([[-1.0, 0.5], [0.0, -2.0]]), 20)
    r = g(np.array([[1.0, 1.0]]), None, np.zeros((1, 1)), 0.5)
    from scipy.linalg import expm
    assert np.allclose(r, expm(0.5 * np.array([[-1.0, 0.5], [0.0, -2.0]])) @ [1.0, 1.0], rtol=1e-7, atol=0)
    with pytest.raises(SimgapError, match="off-diagonal"):
        rk4_growth(np.array([[0.0, -1.0], [0.0, 0.0]]))
    with pytest.raises(SimgapError, match="nint"):
        rk4_step(lambda x, u: x, nint=0)


def test_public_api_invariance_in_python():
    """The docs/synthesis.md example: an invariance Spec and Box built in Python."""
    sysm = get_system("pendulum")
    spec = Spec(kind="invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    res = synthesize(sysm, spec, eta=(0.004, 0.01), gap=[1e-4, 1e-3])
    assert res.stats["winning"] > 300 and res.stats["game_method"] in ("worklist", "sat")
    with pytest.raises(SimgapError, match="game method"):
        synthesize(sysm, spec, eta=(0.004, 0.01), method="fast")


@pytest.mark.parametrize("case", [2, 3])
def test_shared_valid_pairs_by_broadcasting_equal_the_pass_over_all_pairs(case):
    ab, blocked, cells = _abstraction(*_cases()[case])
    blocked = blocked | ~cells if _cases()[case][1].kind == "invariance" else blocked
    want = live_pairs(ab, blocked, ~blocked, test_keep=False)
    got = _valid_shared(ab, blocked)
    assert 0 < want[1] < ab.grid.size * ab.n_inputs  # some pairs leave the grid, some do not
    assert np.array_equal(got[0], want[0]) and got[1:] == want[1:]

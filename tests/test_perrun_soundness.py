"""Per-run certificates that cannot overclaim (issue 22): regressions and Monte-Carlo soundness.

Every probability check is p_emp >= p_cert - 3 SE with SE = max(sqrt(p (1 - p) / R), 1 / R) from R
seeded closed-loop runs (simgap.perrun.validation). The interval checks compare each row's bounds
with the Monte-Carlo transition frequencies of runs started at the cell's corners (the bounds
claim to hold for EVERY x in the cell). bench/mutations.py (group "perrun") applies the wrong
implementations these tests are meant to catch.
"""

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.perrun import value_iteration as vi
from simgap.perrun.imdp import IMDPOptions, box_unsafe, build_imdp, cell_labels
from simgap.perrun.translation import build_imdp_translation
from simgap.perrun.validation import empirical, sample_in_cells, success_counts
from simgap.simulators.base import SimulatorConfig
from simgap.simulators.numpy_sim import NumpySimulator
from simgap.synthesis.grid import UniformGrid
from simgap.synthesis.spec import Box, Spec
from simgap.systems import System, input_grid

R = 4000


def _walk_step(x, u, dt):
    return x + dt * u


def _flip_step(x, u, dt):
    """(p, q): p+ = p + dt u (translation invariant along p), q+ = -q (every run's q changes sign each period)."""
    return np.stack([x[:, 0] + dt * u[:, 0], -x[:, 1]], axis=1)


def _contract_step(x, u, dt):
    """(p, q): p+ = 0.6 p + dt u, q+ = -0.6 q: the k-period map contracts, so single-cell end boxes occur."""
    return np.stack([0.6 * x[:, 0] + dt * u[:, 0], -0.6 * x[:, 1]], axis=1)


WALK5 = System(name="walk", state_names=("p",), input_names=("a",), x_lo=(-1,), x_hi=(1,),
               inputs=input_grid([-1], [1], [5]), base_tau=0.1, step=_walk_step)
FLIP = System(name="flip", state_names=("p", "q"), input_names=("a",), x_lo=(-1, -0.55), x_hi=(1, 1.05),
              inputs=input_grid([-1], [1], [3]), base_tau=0.1, step=_flip_step)
CONTRACT = System(name="contract", state_names=("p", "q"), input_names=("a",), x_lo=(-1, -0.5), x_hi=(1, 1.0),
                  inputs=input_grid([-1], [1], [3]), base_tau=0.1, step=_contract_step)


def _sim(system, **noise):
    return NumpySimulator(SimulatorConfig("numpy", system.name, noise=noise), system=system)


def _mc(sim, spec, ctl, x0s, horizon, seed=11):
    """(p_cert, p_emp, SE) at the states x0s: R seeded closed-loop runs of ``ctl`` over ``horizon`` periods."""
    x0s = np.atleast_2d(np.asarray(x0s, float))
    k = success_counts(lambda x, t: ctl.input_index(x, t), ctl.hold, sim, spec, x0s, R, horizon, seed=seed)
    e = empirical(k, R)
    return ctl.certified(x0s), np.array(e["p_emp"]), np.maximum(np.array(e["se"]), 1 / R)


def _domain(ctl, count=15, seed=3):
    return sample_in_cells(ctl.grid, np.flatnonzero(ctl.p_cert > 0), count, np.random.default_rng(seed))


def _assert_sound(pc, pe, se):
    bad = pe < pc - 3 * se
    assert not bad.any(), f"p_cert above p_emp + 3 SE at {np.flatnonzero(bad)}: p_cert {pc[bad]}, p_emp {pe[bad]}"


# ----------------------------------------------------------------------------------------------
# 1. reach-avoid horizon, H not a multiple of k
# ----------------------------------------------------------------------------------------------

REACH = Spec("reach_avoid", target=Box([0.5], [0.9]))


@pytest.fixture(scope="module")
def reach():
    sim = _sim(WALK5, process_std=0.01)
    return sim, build_imdp(sim, REACH, IMDPOptions(eta=[0.02], hold=10, n_runs=1000, pilot_runs=100, seed=1))


def test_reach_avoid_horizon_is_rounded_down(reach):
    """Walk x+ = x + 0.1 u + N(0, 0.01^2), u in {-1, -0.5, 0, 0.5, 1}, target [0.5, 0.9], k = 10, H = 15:
    from x0 = -0.9 the target takes two holds (>= 18 periods for any input sequence that ends in it), so
    the truth within 15 periods is 0. Rounding H up to 2 holds certified ~0.95 there."""
    sim, im = reach
    ctl = vi.synthesize_imdp(im, 15, "reach_avoid")
    pc, pe, se = _mc(sim, REACH, ctl, [[-0.9]], 15)
    assert pe[0] < 0.01
    _assert_sound(pc, pe, se)
    assert ctl.steps == 1 and ctl.meta["certified_periods"] == 10
    with pytest.raises(SimgapError, match="shorter than one hold of 10 periods"):
        vi.synthesize_imdp(im, 9, "reach_avoid")


def test_reach_avoid_is_sound_and_not_vacuous(reach):
    """Monte Carlo at x0 and in the domain, for H = 20 (two whole holds) and H = 25 (not a multiple of k)."""
    sim, im = reach
    for H in (20, 25):
        ctl = vi.synthesize_imdp(im, H, "reach_avoid")
        x0s = np.concatenate([[[-0.9], [-0.4]], _domain(ctl)])
        pc, pe, se = _mc(sim, REACH, ctl, x0s, H)
        _assert_sound(pc, pe, se)
        assert pc[0] > 0.5 and pc[1] > 0.9, pc[:2]       # non-vacuous: two holds reach from -0.9


def test_invariance_horizon_not_a_multiple_of_the_hold():
    """A walk drifting right at 0.05 per period (one input), safe [-1, 1], k = 10, H = 15, from x0 = 0.3:
    safe for 10 periods, out of X at period 15 (truth 0). Rounding 15 down to one hold certified ~1."""
    drift = System(name="walk", state_names=("p",), input_names=("a",), x_lo=(-1,), x_hi=(1,),
                   inputs=np.array([[0.5]]), base_tau=0.1, step=_walk_step)
    sim = _sim(drift, process_std=0.005)
    spec = Spec("invariance", safe=Box([-1], [1]))
    im = build_imdp(sim, spec, IMDPOptions(eta=[0.02], hold=10, n_runs=500, pilot_runs=50, seed=2))
    ctl = vi.synthesize_imdp(im, 15, "invariance")
    assert ctl.steps == 2 and ctl.meta["certified_periods"] == 20
    x0s = np.concatenate([[[0.3], [-0.9]], _domain(ctl)])
    pc, pe, se = _mc(sim, spec, ctl, x0s, 15)
    assert pe[0] < 0.01 and pc[1] > 0.8                   # the truth at 0.3 is 0; far left it is certified
    _assert_sound(pc, pe, se)


# ----------------------------------------------------------------------------------------------
# 2. the spec kind is explicit; a target narrower than a cell is refused
# ----------------------------------------------------------------------------------------------

def test_a_target_holding_no_whole_cell_is_refused():
    """Walk, target [0.505, 0.52], eta 0.02: no cell lies in the target. It was solved as invariance
    (p_cert 0.85 where the truth is 0.10); now the build refuses it and names the cell size."""
    sim = _sim(WALK5, process_std=0.01)
    narrow = Spec("reach_avoid", target=Box([0.505], [0.52]))
    with pytest.raises(SimgapError, match=r"holds no whole allowed cell .*eta = \[0.02\]"):
        build_imdp(sim, narrow, IMDPOptions(eta=[0.02], hold=5, n_runs=100, pilot_runs=10, seed=1))
    # the value iteration takes the kind from its caller, and checks it against the build's spec
    inv = build_imdp(sim, Spec("invariance", safe=Box([-0.8], [0.8])),
                     IMDPOptions(eta=[0.02], hold=5, n_runs=100, pilot_runs=10, seed=1))
    with pytest.raises(SimgapError, match="built for a invariance specification, not reach_avoid"):
        vi.synthesize_imdp(inv, 30, "reach_avoid")
    inv.meta.pop("spec")
    with pytest.raises(SimgapError, match="no target cell"):
        vi.synthesize_imdp(inv, 30, "reach_avoid")
    with pytest.raises(SimgapError, match="kind must be one of"):
        vi.synthesize_imdp(inv, 30, "reach")


# ----------------------------------------------------------------------------------------------
# 3. runs that leave X between the ends of a hold (per cell and translation-invariant)
# ----------------------------------------------------------------------------------------------

FLIP_SPEC = Spec("invariance", safe=Box([-1, -0.55], [1, 1.05]))


@pytest.mark.parametrize("construction", ["per_cell", "translation"])
def test_runs_leaving_x_mid_hold_are_sink_runs(construction):
    """(p, q), p+ = p + 0.1 u + noise, q+ = -q, X = [-1, 1] x [-0.55, 1.05], hold 2: from q = 0.8 every
    run is outside X after one period and back at the end of the hold (truth 0). The translation
    construction checked intermediate periods only along p: 0 sink runs, p_cert 0.94 over two holds."""
    sim = _sim(FLIP, process_std=[0.01, 0.0])
    o = IMDPOptions(eta=[0.1, 0.1], hold=2, n_runs=400, pilot_runs=40, seed=1)
    im = build_imdp(sim, FLIP_SPEC, o) if construction == "per_cell" else build_imdp_translation(sim, FLIP_SPEC, o, (0,))
    ctl = vi.synthesize_imdp(im, 4, "invariance")
    x0s = np.concatenate([[[0.0, 0.8], [0.0, -0.12]], _domain(ctl)])
    pc, pe, se = _mc(sim, FLIP_SPEC, ctl, x0s, 4)
    assert pe[0] == 0.0 and pc[1] > 0.8, (pc[:2], pe[:2])  # truth 0 at q = 0.8; certified at q = -0.12
    _assert_sound(pc, pe, se)


# ----------------------------------------------------------------------------------------------
# 4. the angle seam in box_unsafe
# ----------------------------------------------------------------------------------------------

def test_box_unsafe_wraps_angle_dimensions():
    """Heading box [3.0, 3.2] against an obstacle's heading range [-pi, -3.0]: 3.2 is -3.083, inside it."""
    pi = np.pi
    x_lo, x_hi = np.array([0.0, -pi]), np.array([1.0, pi])
    obst = Spec("reach_avoid", target=Box([0.7, -np.inf], [1.3, np.inf]), obstacles=(Box([0.2, -pi], [0.4, -3.0]),))
    lo, hi = np.array([[0.25, 3.0], [0.25, 2.0], [0.6, 3.0]]), np.array([[0.3, 3.2], [0.3, 2.5], [0.7, 3.2]])
    assert box_unsafe(obst, lo, hi, x_lo, x_hi, (1,)).tolist() == [True, False, False]
    # the safe set of an invariance spec, modulo 2 pi: [3.0, 3.2] is inside [-pi, pi], not inside [-1, 1]
    for safe_hi, want in ((pi, False), (1.0, True)):
        s = Spec("invariance", safe=Box([0.0, -safe_hi], [1.0, safe_hi]))
        assert box_unsafe(s, lo[:1], hi[:1], x_lo, x_hi, (1,)).tolist() == [want]
    # against brute force: random boxes and obstacle ranges, points of the box wrapped to [-pi, pi)
    rng = np.random.default_rng(0)
    B = 400
    c, w = rng.uniform(-4, 4, B), rng.uniform(0, 2.5, B)
    a = rng.uniform(-pi, pi, B)
    b = np.minimum(a + rng.uniform(0, 2, B), pi)
    for i in range(B):
        spec = Spec("reach_avoid", target=Box([0.9, -pi], [1.0, pi]), obstacles=(Box([0.0, a[i]], [1.0, b[i]]),))
        got = box_unsafe(spec, np.array([[0.5, c[i] - w[i]]]), np.array([[0.5, c[i] + w[i]]]), x_lo, x_hi, (1,))[0]
        t = np.linspace(c[i] - w[i], c[i] + w[i], 4001)
        t = (t + pi) % (2 * pi) - pi
        want = bool(np.any((t >= a[i]) & (t <= b[i])))
        assert got == want or abs(min(abs(t - a[i]).min(), abs(t - b[i]).min())) < 2e-3, (i, got, want)
    # the cell labels use it: the seam cell [-pi - eta/2, -pi + eta/2] of a 2 pi / 16 heading grid meets a
    # heading range [3.0, pi] (unwrapped it does not)
    grid = UniformGrid(x_lo, x_hi, [0.25, 2 * pi / 16], periodic=(1,))
    seam_obst = Spec("reach_avoid", target=Box([0.6, -np.inf], [0.9, np.inf]), obstacles=(Box([0.45, 3.0], [0.55, pi]),))
    live, target = cell_labels(grid, seam_obst, x_lo, x_hi, (1,))
    ids = grid.x_to_ids(np.array([[0.5, pi - 0.01], [0.5, -pi + 0.01], [0.5, 0.0], [0.25, pi - 0.01]]))
    assert live[ids].tolist() == [False, False, True, True] and target.any()


# ----------------------------------------------------------------------------------------------
# 6. shared runs over several pilot batches
# ----------------------------------------------------------------------------------------------

def test_shared_runs_over_several_batches_keep_their_successors():
    """Noise-free walk (deterministic runs) with shared runs: the rows must not depend on how the
    pairs are batched. With the pilot's support left unsorted across batches, real successors
    were not found by the binary search and their runs became sink runs."""
    walk3 = System(name="walk", state_names=("p",), input_names=("a",), x_lo=(-1,), x_hi=(1,),
                   inputs=input_grid([-1], [1], [3]), base_tau=0.1, step=_walk_step)
    sim = _sim(walk3)
    spec = Spec("invariance", safe=Box([-0.8], [0.8]))
    o = dict(eta=[0.02], hold=5, n_runs=10, pilot_runs=10, seed=1, share=20, lipschitz=[[[1.0]], [[0.0]]])
    one = build_imdp(sim, spec, IMDPOptions(**o))
    many = build_imdp(sim, spec, IMDPOptions(**o, batch_runs=200))
    sink = lambda im: im.k_hi[im.col == im.C]   # noqa: E731
    assert sink(one).sum() < sink(one).size * 10          # some rows have real successors
    np.testing.assert_array_equal(sink(many), sink(one))
    np.testing.assert_array_equal(many.col, one.col)

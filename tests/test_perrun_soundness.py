"""Per-run certificates that cannot overclaim (issue 22): regressions and Monte-Carlo soundness.

Every probability check is p_emp >= p_cert - 3 SE with SE = max(sqrt(p (1 - p) / R), 1 / R) from R
seeded closed-loop runs (simgap.perrun.validation). The interval checks compare each row's bounds
with the Monte-Carlo transition frequencies of runs started at the cell's corners (the bounds
claim to hold for EVERY x in the cell). bench/mutations.py (group "perrun") applies the wrong
implementations these tests are meant to catch.
"""

import dataclasses

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.perrun import value_iteration as vi
from simgap.perrun.imdp import IMDPOptions, box_unsafe, cell_labels
from simgap.perrun.sampling import build_imdp
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
    # one chunk of every (anchor, input) group, simulated in batches of 20 pairs (the sort must hold
    # within a chunk: chunks of their own are sorted by construction)
    many = build_imdp(sim, spec, IMDPOptions(**o, batch_runs=200, chunk_size=1000))
    assert many.meta["sampling"]["chunks"] == 1
    sink = lambda im: im.k_hi[im.col == im.C]   # noqa: E731
    assert sink(one).sum() < sink(one).size * 10          # some rows have real successors
    np.testing.assert_array_equal(sink(many), sink(one))
    np.testing.assert_array_equal(many.col, one.col)


# ----------------------------------------------------------------------------------------------
# The rows themselves: every interval holds for runs from the corners of its cell
# ----------------------------------------------------------------------------------------------

def _row_violations(im, sim, spec, rows, runs, seed=0, z=4.5):
    """Monte-Carlo check of the interval MDP's claim for every x in a cell: from each corner of the
    cell of each row (cell c, input a), ``runs`` runs of k periods with a held; a run goes to the
    sink if a state along the way violates the spec or it ends outside the row's successors, else to
    its end cell j. Returns the entries whose bound is off by more than z SE (SE >= 1 / runs):
    p_j < lo_j, p_j > hi_j, p_sink > hi_sink. ``z`` = 4.5 keeps the false-alarm rate small over
    thousands of comparisons (a correct bound also has its Clopper-Pearson slack)."""
    g, C, M, k, n = im.grid, im.C, im.M, im.hold, im.grid.n
    cell, a = rows // M, rows % M
    corners = np.array(list(np.ndindex(*(2,) * n))) - 0.5              # (2^n, n) in units of eta
    x0 = (g.points(cell)[:, None, :] + corners[None] * g.eta).reshape(-1, n)   # (rows * 2^n, n)
    ri = np.repeat(np.arange(len(rows)), len(corners))
    x = np.repeat(x0, runs, axis=0)
    u = np.repeat(im.inputs[np.repeat(a, len(corners))], runs, axis=0)
    rng = np.random.default_rng(seed)
    sink = np.zeros(len(x), bool)
    for _ in range(k):
        x = sim.step(x, u, rng)
        sink |= spec.violated(x, sim.system.x_lo, sim.system.x_hi)
    end = g.x_to_ids(x)
    bad = []
    for i, r in enumerate(rows):        # a few hundred rows; each row's runs are one vectorized block
        sl = slice(im.row_ptr[r], im.row_ptr[r + 1])
        col, lo, hi = im.col[sl], im.lo[sl].astype(float), im.hi[sl].astype(float)
        for q in np.flatnonzero(ri == i):
            e = end[q * runs:(q + 1) * runs]
            s = sink[q * runs:(q + 1) * runs] | ~np.isin(e, col[col < C])
            p = np.array([np.mean((e == j) & ~s) if j < C else np.mean(s) for j in col])
            se = np.maximum(np.sqrt(p * (1 - p) / runs), 1 / runs)
            off = (p > hi + z * se) | ((col < C) & (p < lo - z * se))
            bad += [(int(r), x0[q].tolist(), int(j), float(lo[m]), float(p[m]), float(hi[m])) for m, j in
                    zip(np.flatnonzero(off), col[off])]
    return bad


def _some_rows(im, count, seed=0):
    rows = np.flatnonzero(np.repeat(im.live, im.M))
    return np.sort(np.random.default_rng(seed).choice(rows, min(count, rows.size), replace=False))


CONTRACT_SPEC = Spec("invariance", safe=Box([-1, -0.5], [1, 1.0]))


@pytest.fixture(scope="module")
def contract():
    """(p, q), p+ = 0.6 p + 0.1 u, q+ = -0.6 q, noise 0.02 / 0.01, hold 2: the widened end box (0.6 of a
    cell) often fits in one cell, so the successor lower bounds are estimated and used; from q ~ 0.8
    part of the runs leave X at the first period (q ~ -0.48 against -0.5) and are back at the end."""
    sim = _sim(CONTRACT, process_std=[0.02, 0.01])
    im = build_imdp(sim, CONTRACT_SPEC, IMDPOptions(eta=[0.1, 0.1], hold=2, n_runs=1000, pilot_runs=100, seed=1))
    return sim, im


def test_lower_bound_family_is_active_and_sound(contract):
    sim, im = contract
    assert im.meta["split"]["lo"] > 0 and (im.lo > 0.2).sum() > 100      # the family is estimated and used
    ctl = vi.synthesize_imdp(im, 9, "invariance")                         # 5 holds, H not a multiple of k
    x0s = np.concatenate([[[0.0, 0.8], [0.0, 0.3]], _domain(ctl, 20)])
    pc, pe, se = _mc(sim, CONTRACT_SPEC, ctl, x0s, 9)
    _assert_sound(pc, pe, se)
    assert pc[1] > 0.9 and 0.0 < pe[0] < 0.99                             # non-vacuous; real failures at q = 0.8
    # the value iteration uses them: with lo = 0 p_cert is nowhere higher and somewhere lower (on this
    # system by < 0.001: the successors of a row have nearly equal values, so the adversary gains little)
    im0 = dataclasses.replace(im, lo=np.zeros_like(im.lo))
    d = ctl.p_cert - vi.synthesize_imdp(im0, 9, "invariance").p_cert
    assert d.min() >= -1e-12 and d.max() > 0


def test_every_interval_holds_at_the_corners_of_its_cell(contract):
    """Lower, upper and sink bounds of 150 rows against 2000 runs from each corner of the row's cell."""
    sim, im = contract
    rows = _some_rows(im, 150)
    bad = _row_violations(im, sim, CONTRACT_SPEC, rows, 2000)
    assert not bad, f"{len(bad)} bounds violated, e.g. (row, x, col, lo, p_mc, hi) {bad[:4]}"


@pytest.mark.parametrize("construction", ["per_cell", "translation"])
def test_every_interval_holds_when_runs_leave_x_mid_hold(construction):
    sim = _sim(FLIP, process_std=[0.01, 0.0])
    o = IMDPOptions(eta=[0.1, 0.1], hold=2, n_runs=400, pilot_runs=40, seed=1)
    im = build_imdp(sim, FLIP_SPEC, o) if construction == "per_cell" else build_imdp_translation(sim, FLIP_SPEC, o, (0,))
    bad = _row_violations(im, sim, FLIP_SPEC, _some_rows(im, 150), 1000)
    assert not bad, f"{len(bad)} bounds violated, e.g. (row, x, col, lo, p_mc, hi) {bad[:4]}"


def test_support_and_split_come_from_the_pilot_alone(contract):
    """The support T(c, a) and the union bound's split must be fixed before the main runs (the bounds
    are valid only then): with the same pilot, a different number of main runs changes neither."""
    sim, im = contract
    other = build_imdp(sim, CONTRACT_SPEC, IMDPOptions(eta=[0.1, 0.1], hold=2, n_runs=100, pilot_runs=100, seed=1))
    np.testing.assert_array_equal(other.row_ptr, im.row_ptr)
    np.testing.assert_array_equal(other.col, im.col)
    assert other.meta["split"] == im.meta["split"] and other.meta["n_runs"] == 100
    # and main runs outside the pilot's support are sink runs: with one pilot run, interior rows have some
    one = build_imdp(sim, CONTRACT_SPEC, IMDPOptions(eta=[0.1, 0.1], hold=2, n_runs=100, pilot_runs=1, seed=1))
    r = one.grid.x_to_ids(np.array([[0.0, 0.3]]))[0] * one.M + 1
    sink = one.k_hi[one.row_ptr[r]:one.row_ptr[r + 1]][-1]
    assert one.col[one.row_ptr[r + 1] - 1] == one.C and 0 < sink < 100


def test_a_reach_avoid_horizon_shorter_than_a_hold_is_refused_before_sampling(tmp_path, capsys):
    """`simgap synthesize --level run` on a reach-avoid experiment with horizon < hold: refused with the
    reason before the interval MDP is sampled (exit 2, no output file)."""
    from pathlib import Path

    from simgap.cli import main

    toml = Path(__file__).parent / "data" / "perrun_turtle_tiny.toml"
    bad = tmp_path / "short.toml"
    text = toml.read_text()
    assert "hold = 1" in text
    bad.write_text(text.replace("hold = 1", "hold = 3"))
    out = tmp_path / "c.npz"
    assert main(["synthesize", "--level", "run", "--spec", str(bad), "--horizon", "2", "--out", str(out)]) == 2
    assert "shorter than one hold of 3 periods" in capsys.readouterr().err and not out.exists()

"""Interval MDP from samples and pessimistic value iteration: exact greedy, Monte-Carlo soundness, bugs caught."""

import numpy as np
import pytest
from scipy import stats
from scipy.optimize import linprog

from simgap.errors import SimgapError
from simgap.perrun import value_iteration as vi
from simgap.perrun.imdp import IMDP, Allocation, IMDPOptions, reallocate
from simgap.perrun.sampling import build_imdp
from simgap.perrun.validation import empirical, sample_in_cells, success_counts
from simgap.simulators.base import SimulatorConfig
from simgap.simulators.numpy_sim import NumpySimulator
from simgap.synthesis.grid import UniformGrid
from simgap.synthesis.spec import Box, Spec
from simgap.systems import System, input_grid


def _walk_step(x, u, dt):
    return x + dt * u


WALK = System(name="walk", state_names=("p",), input_names=("a",), x_lo=(-1,), x_hi=(1,),
              inputs=input_grid([-1], [1], [3]), base_tau=0.1, step=_walk_step)
SPEC = Spec("invariance", safe=Box([-0.8], [0.8]))
H = 30


def _tiny(rows):
    """An IMDP with one cell per row, one input, successors given as (cols, lo, hi) per row."""
    C = len(rows)
    col = np.concatenate([r[0] for r in rows]).astype(np.int32)
    lo = np.concatenate([r[1] for r in rows]).astype(np.float32)
    hi = np.concatenate([r[2] for r in rows]).astype(np.float32)
    ptr = np.concatenate([[0], np.cumsum([len(r[0]) for r in rows])])
    return IMDP(grid=UniformGrid([0], [C - 1], 1.0), inputs=np.zeros((1, 1)), hold=1, live=np.ones(C, bool),
                target=np.zeros(C, bool), row_ptr=ptr, col=col, lo=lo, hi=hi)


def test_pessimistic_expectation_by_hand_and_by_lp():
    # by hand: V = (0.2, 0.9), sink 0; lo = (0.1, 0.3, 0), hi = (0.6, 0.8, 0.2): free 0.6 -> sink 0.2, cell0 0.4
    im = _tiny([([0, 1, 2], [0.1, 0.3, 0.0], [0.6, 0.8, 0.2]), ([1], [1.0], [1.0])])
    q = vi.pessimistic_q(im, np.array([0.2, 0.9]))
    assert q[0] == pytest.approx(0.5 * 0.2 + 0.3 * 0.9, abs=1e-6) and q[1] == pytest.approx(0.9, abs=1e-6)
    # random rows against the LP min sum p V s.t. lo <= p <= hi, sum p = 1
    rng = np.random.default_rng(0)
    C, rows = 30, []
    for _ in range(C):
        k = rng.integers(1, 6)
        cols = np.append(rng.choice(C, k, replace=False), C)
        p = rng.dirichlet(np.ones(k + 1))
        rows.append((cols, np.maximum(p - rng.random(k + 1) * 0.2, 0), np.minimum(p + rng.random(k + 1) * 0.2, 1)))
    im = _tiny(rows)
    V = rng.random(C)
    q = vi.pessimistic_q(im, V)
    for r, (cols, lo, hi) in enumerate(rows):
        v = np.append(V, 0.0)[cols]
        lp = linprog(v, A_eq=np.ones((1, len(cols))), b_eq=[1.0],
                     bounds=list(zip(im.lo[im.row_ptr[r]:im.row_ptr[r + 1]], im.hi[im.row_ptr[r]:im.row_ptr[r + 1]])))
        assert q[r] == pytest.approx(lp.fun, abs=1e-6)


@pytest.fixture(scope="module")
def walk():
    sim = NumpySimulator(SimulatorConfig("numpy", "walk", noise={"process_std": 0.08}), system=WALK)
    im = build_imdp(sim, SPEC, IMDPOptions(eta=[0.02], hold=5, n_runs=1000, pilot_runs=100, seed=1))
    return sim, im


def _check(sim, ctl, seed=4, R=2000):
    rng = np.random.default_rng(3)
    x0s = np.concatenate([[[0.0]], [[-0.74]], sample_in_cells(ctl.grid, np.flatnonzero(ctl.p_cert > 0), 20, rng)])
    k = success_counts(lambda x, t: ctl.input_index(x, t), ctl.hold, sim, SPEC, x0s, R, H, seed=seed)
    e = empirical(k, R)
    p_emp, se = np.array(e["p_emp"]), np.maximum(np.array(e["se"]), 1 / R)
    return ctl.certified(x0s), p_emp, se


def test_p_cert_is_sound_and_not_vacuous(walk):
    sim, im = walk
    ctl = vi.synthesize_imdp(im, H, "invariance")
    assert ctl.steps == 6 and ctl.policy.shape == (6, im.C)
    p_cert, p_emp, se = _check(sim, ctl)
    assert np.all(p_emp >= p_cert - 3 * se), (p_cert, p_emp)
    assert p_cert[0] > 0.3 and p_emp[1] < 0.99            # non-vacuous; a state with real failures
    # a longer horizon never certifies more
    assert np.all(vi.synthesize_imdp(im, 2 * H, "invariance").p_cert <= ctl.p_cert + 1e-12)


def test_an_optimistic_adversary_is_caught(walk, monkeypatch):
    """Pouring the free mass onto the HIGHEST values (a sort-direction bug) must fail the Monte-Carlo check."""
    sim, im = walk
    real = vi.pessimistic_q
    monkeypatch.setattr(vi, "pessimistic_q", lambda imdp, V, rows: real(imdp, 1.0 - V, rows) * -1 + 1.0)
    ctl = vi.synthesize_imdp(im, H, "invariance")
    p_cert, p_emp, se = _check(sim, ctl)
    assert np.any(p_emp < p_cert - 3 * se)


def test_bad_input(walk):
    sim, im = walk
    with pytest.raises(SimgapError, match="horizon must be >= 1"):
        vi.synthesize_imdp(im, 0, "invariance")
    with pytest.raises(SimgapError, match="hold must be >= 1"):
        build_imdp(sim, SPEC, IMDPOptions(eta=[0.1], hold=0))
    with pytest.raises(SimgapError, match="beta must be in"):
        build_imdp(sim, SPEC, IMDPOptions(eta=[0.1], beta=1.5))


def _spent_beta(im: IMDP) -> float:
    """Total failure probability the intervals spend, read back from counts and bounds alone.

    A one-sided Clopper-Pearson upper bound hi at count k has level P(Bin(N, hi) <= k); a lower
    bound lo at count k > 0 has level P(Bin(N, lo) >= k); trivial bounds (hi = 1, lo = 0) spend
    nothing. The union bound is sound only if the sum is <= beta, whatever the split claims."""
    N = im.meta["n_runs"]
    hi = im.hi.astype(float)
    spent = stats.binom.cdf(im.k_hi, N, hi)[hi < 1].sum()
    has_lo = im.lo > 0
    return float(spent + stats.binom.sf(im.k_lo[has_lo] - 1, N, im.lo[has_lo].astype(float)).sum())


def test_the_union_bound_spends_at_most_beta(walk, monkeypatch):
    sim, im = walk
    beta = im.meta["beta"]
    assert sum(im.meta["split"].values()) <= 1 + 1e-12
    assert 0.8 * beta < _spent_beta(im) <= beta           # the split is used, and not overspent
    for split in [(1.0, 0.0, 0.0), (0.5, 0.25, 0.25), (0.2, 0.4, 0.4)]:
        assert _spent_beta(reallocate(im, beta, split)) <= beta
    # with no widening (L = 0: end boxes are points) the pilot sees single-cell ends and all
    # three families are estimated; the spent beta still stays within beta
    points = build_imdp(sim, SPEC, IMDPOptions(eta=[0.02], hold=5, n_runs=500, pilot_runs=50, lipschitz=0.0, seed=2))
    assert points.meta["split"]["lo"] > 0 and np.any(points.lo > 0)
    assert 0.8 * beta < _spent_beta(points) <= beta
    assert im.meta["split"]["lo"] == 0 and im.meta["split"]["sink"] == pytest.approx(0.95)  # widened: lo never > 0
    # reallocating with the build's own split reproduces its intervals
    same = reallocate(im, beta, tuple(im.meta["split"].values()))
    assert np.array_equal(same.lo, im.lo) and np.array_equal(same.hi, im.hi)
    # a wrong allocation (every family at beta / its own count: 2 beta in total) is detected
    monkeypatch.setattr(Allocation, "levels", lambda self, b, n_rows, n_sup: {"sink": b / n_rows, "lo": b / n_sup,
                                                                               "hi": b / n_sup})
    bad = build_imdp(sim, SPEC, IMDPOptions(eta=[0.02], hold=5, n_runs=1000, pilot_runs=100, seed=1))
    assert _spent_beta(bad) > 1.5 * beta


def test_the_split_is_checked():
    with pytest.raises(SimgapError, match="sums to 1.1 > 1"):
        Allocation.of((0.5, 0.3, 0.3))
    with pytest.raises(SimgapError, match="each >= 0"):
        Allocation.of((1.2, -0.1, -0.1))
    with pytest.raises(SimgapError, match="three shares"):
        Allocation.of((1.0,))
    a = Allocation.of((0.9, 0.05, 0.05))
    lev = a.levels(0.01, 100, 1000)
    assert lev == pytest.approx({"sink": 0.009 / 100, "lo": 0.0005 / 1000, "hi": 0.0005 / 1000})


def test_progress_is_reported_and_changes_nothing(walk):
    """The long parts report progress: sampling in pairs over both passes, rollouts in periods; the
    counts are the same with and without a callback (progress does not touch the random streams)."""
    sim, im = walk
    seen = []
    opts = IMDPOptions(eta=[0.02], hold=5, n_runs=1000, pilot_runs=100, seed=1, batch_runs=20_000)  # several batches
    im2 = build_imdp(sim, SPEC, opts, on_progress=lambda d, t: seen.append((d, t)))
    P = int(im.live.sum()) * im.M
    assert seen[-1] == (2 * P, 2 * P) and len(seen) > 2
    assert all(a[0] <= b[0] for a, b in zip(seen, seen[1:])) and {t for _, t in seen} == {2 * P}
    np.testing.assert_array_equal(im2.k_hi, build_imdp(sim, SPEC, opts).k_hi)
    ctl = vi.synthesize_imdp(im, H, "invariance")
    ticks = []
    x0s = np.array([[0.0], [0.3]])
    k1 = success_counts(lambda x, t: ctl.input_index(x, t), ctl.hold, sim, SPEC, x0s, 300, H, seed=2, max_batch=300,
                        on_progress=lambda d, t: ticks.append((d, t)))
    k2 = success_counts(lambda x, t: ctl.input_index(x, t), ctl.hold, sim, SPEC, x0s, 300, H, seed=2, max_batch=300)
    np.testing.assert_array_equal(k1, k2)
    assert ticks[-1] == (2 * H, 2 * H) and all(a[0] <= b[0] for a, b in zip(ticks, ticks[1:]))


def test_shared_runs_are_sound_cheap_and_need_the_residual_term():
    """Cells sharing one anchor's runs (share), on a walk whose simulator pushes outward
    (x += 0.6 x dt, not in the nominal model): (1) the box the construction uses contains the run
    from every sampled x of a cell far from the anchor, with the same noise, at every period; with
    the residual's Lipschitz term dropped (Lr = 0) it does not; (2) the whole interval MDP is sound
    against Monte Carlo; (3) the simulator cost is divided by the block size."""
    import dataclasses
    from simgap.perrun.imdp import residual_lipschitz, shared_box
    sim = NumpySimulator(SimulatorConfig("numpy", "walk", noise={"process_std": 0.08}, effects={"linear": [[0.6]]}),
                         system=WALK)
    k, half = 5, np.array([0.01])
    Ln, Lr, _ = residual_lipschitz(sim, k, half, np.random.default_rng(0))
    assert Lr[0, 0] > 0.2                                   # the outward push, seen per realization
    rng = np.random.default_rng(1)
    xs, xc = np.array([[0.0]]), np.array([[0.6], [-0.45]])  # anchor, two cell centers far from it
    B = 4000
    x = np.repeat(xc, B, axis=0) + rng.uniform(-half, half, (2 * B, 1))
    u = np.repeat(WALK.inputs[[0, 2]], B, axis=0)
    for L_res, holds in ((Lr, True), (0 * Lr, False)):
        shift, r = shared_box(WALK, np.repeat(xc, B, axis=0), np.repeat(xs, 2 * B, axis=0), u, k, Ln, L_res, half)
        y, ya, inside = x.copy(), np.repeat(xs, 2 * B, axis=0), True
        for t in range(k):
            noise = sim.draw_noise(2 * B, rng)
            y, ya = sim.step_with_noise(y, u, noise), sim.step_with_noise(ya, u, noise)
            inside &= bool(np.all(np.abs(y - (ya + shift[:, t])) <= r + 1e-12))
        assert inside == holds
    opts = IMDPOptions(eta=[0.02], hold=k, n_runs=1000, pilot_runs=100, seed=1, share=20)
    im = build_imdp(sim, SPEC, opts)
    assert im.meta["anchors"] == 5 and im.meta["samples"] == 5 * 3 * 1100 * k     # 5 anchors x 3 inputs
    pc, pe, se = _check(sim, vi.synthesize_imdp(im, H, "invariance"))
    assert np.all(pe >= pc - 3 * se), (pc, pe)
    assert pc.max() > 0.3
    per_cell = build_imdp(sim, SPEC, dataclasses.replace(opts, share=None))
    assert per_cell.meta["samples"] == int(per_cell.live.sum()) * 3 * 1100 * k


def test_share_is_checked():
    with pytest.raises(SimgapError, match="share"):
        IMDPOptions(eta=[0.1], share=0).validate(1)
    with pytest.raises(SimgapError, match="share"):
        IMDPOptions(eta=[0.1], share=[2, 2]).validate(1)
    with pytest.raises(SimgapError, match="lipschitz"):
        IMDPOptions(eta=[0.1], share=2, lipschitz=-1.0).validate(1)


@pytest.mark.parametrize("share", [20, None])
def test_rows_hold_every_true_successor(share):
    """The construction as wired in build_imdp (shared runs, and per cell): on a noise-free walk whose simulator pushes
    outward (x += 0.6 x dt, not in the nominal model), the true k-period run from every sampled x of
    every cell ends in a successor its row admits (hi > 0), unless the row sends every run to the
    sink (count N: the widened boxes were unsafe or left the support); a run that leaves the safe set
    needs that. Fails if the runs are not shifted to the cell, or widened without the residual's
    |x_c - x_s| term (both checked)."""
    sim = NumpySimulator(SimulatorConfig("numpy", "walk", effects={"linear": [[0.6]]}), system=WALK)
    k = 5
    im = build_imdp(sim, SPEC, IMDPOptions(eta=[0.02], hold=k, n_runs=10, pilot_runs=10, seed=1, share=share))
    C, M = im.C, im.M
    rows = np.repeat(np.arange(C * M), np.diff(im.row_ptr))
    succ = (im.col < C) & (im.hi > 0)
    admitted = rows[succ] * (C + 1) + im.col[succ]
    all_sink = np.zeros(C * M, dtype=bool)
    all_sink[rows[(im.col == C) & (im.k_hi == 10)]] = True
    cells = np.flatnonzero(im.live)
    S = 50
    rng = np.random.default_rng(2)
    c = np.repeat(cells, M * S)
    a = np.tile(np.repeat(np.arange(M), S), cells.size)
    x = im.grid.points(c) + rng.uniform(-0.01, 0.01, (c.size, 1))
    left = np.zeros(c.size, dtype=bool)
    for _ in range(k):
        x = sim.step(x, WALK.inputs[a], rng)
        left |= SPEC.violated(x, WALK.x_lo, WALK.x_hi)
    end = im.grid.x_to_ids(x)
    col = np.where(left | (end < 0) | ~(im.live | im.target)[np.maximum(end, 0)], C, end)
    r = c * M + a
    ok = all_sink[r] | ((col < C) & np.isin(r * (C + 1) + col, admitted))
    assert ok.all(), f"{int((~ok).sum())} of {ok.size} true runs not admitted"
    assert not all_sink[r].all()                 # not vacuous: most rows have real successors


def test_validation_states_in_a_seam_cell_are_inside_x():
    """A heading cell centered on -pi straddles the seam: its sampled states must be wrapped into X, or the
    validation counts them as runs that failed at t = 0 (seen on the TurtleBot: p_emp 0 against p_cert 0.63)."""
    g = UniformGrid([0.0, -np.pi], [1.0, np.pi], [0.5, np.pi / 8], periodic=(1,))
    seam = np.flatnonzero(np.isclose(g.points(np.arange(g.size))[:, 1], -np.pi))
    x = sample_in_cells(g, seam, 2000, np.random.default_rng(0))
    assert np.all((x[:, 1] >= -np.pi) & (x[:, 1] < np.pi)) and (x[:, 1] > 3.0).mean() > 0.3
    np.testing.assert_array_equal(g.x_to_ids(x) >= 0, True)

"""Interval-MDP abstraction from simulator samples.

States are the cells of a :class:`~simgap.synthesis.grid.UniformGrid` over X plus one sink
``C`` (value 0: unsafe, obstacle, outside X, or any cell outside the sampled support). Actions
are the inputs U, each held for ``hold`` = k sampling periods (one abstract step = k periods).
For every live cell c (safe, not target) and input a the abstraction stores, sparsely, an
interval [lo, hi] on the probability that one k-period run from ANY x in the cell ends in each
successor cell.

Construction (per (c, a), all vectorized over pairs x runs):

1. Lipschitz widening. ASSUMPTION (per realization): for every noise draw w, the k-period
   trajectory x -> y_t(x, u, w), t = 1..k, is Lipschitz
   along each coordinate: |y_t,i(x) - y_t,i(x + s e_j)| <= L_ij |s| (L: Wood-Zhang estimates from
   common-random-number slopes, or given). So the run from any x in the cell stays in the box
   y_t(x_c, w) +- rho, rho_i = sum_j L_ij eta_j / 2, around the run from the center x_c.
2. Pilot runs (N0, independent of step 3) fix the support T(c, a): the cells the widened end
   boxes of the pilot runs touch.
3. Main runs (N). Per run: the set S of cells its widened end box touches; the run is a "sink
   run" if any widened box along the k periods leaves the safe set / X or meets an obstacle,
   or S leaves T(c, a) or contains a non-live cell. For every x in the cell and successor j in T:
       P_x(j) >= P(S = {j}, no sink)  and  P_x(j) <= P(j in S),   P_x(sink) <= P(sink run),
   estimated by one-sided Clopper-Pearson bounds on n_in(j), n_hit(j), n_sink out of N.
4. Union bound with a stated split (:class:`Allocation`): the bounds form three families, the
   sink upper bounds (one per row), the successor lower bounds and the successor upper bounds
   (one per support entry each). Family f gets the share w_f of beta, w_sink + w_lo + w_hi <= 1,
   and each of its n_f bounds is taken at level beta w_f / n_f, so all of them hold at once with
   probability >= 1 - beta sum_f w_f >= 1 - beta (Bonferroni: any split fixed before the main
   runs is valid; n_f comes from the independent pilot). A family with share 0 is not estimated:
   its bounds are the trivial lo = 0 / hi = 1, true with probability 1, at no cost in beta.
   Clopper-Pearson is exact, so at zero counts hi = 1 - (beta w_f / n_f)^(1/N) ~ ln(n_f / (beta w_f)) / N.

Shared runs (``share``): the k-period runs from one anchor cell x_s per block of cells serve every
cell c of the block. ASSUMPTION (per realization, coordinate-wise): the residual
z_t(x, w) = y_t(x, u, w) - ynom_t(x, u) of the run against the nominal model is Lr-Lipschitz, and the
nominal k-period map Ln-Lipschitz (:func:`residual_lipschitz`, common random numbers). Then the run
from any x in cell c stays in y_t(x_s, w) + ynom_t(x_c) - ynom_t(x_s) +- (Ln eta/2 + Lr (|x_c - x_s| +
eta/2)) (:func:`shared_box`), and steps 2-4 use these boxes. Each row still rests on N i.i.d. runs
(Bonferroni needs no independence between rows); the simulator cost drops by the block size, the
bookkeeping (pairs x runs x periods) stays.

Memory: entries (col int32, lo/hi float32 rounded outward, the int32 counts behind them) in CSR
over rows c*M + a.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..certify.lipschitz import wood_zhang
from ..errors import SimgapError
from ..synthesis.grid import UniformGrid
from ..synthesis.spec import Spec
from .orderstats import cp_lower, cp_upper



@dataclass
class IMDP:
    """Sparse interval MDP (see module docstring). Rows r = c * M + a; the sink is column C."""

    grid: UniformGrid
    inputs: np.ndarray          # (M, m)
    hold: int                   # k sampling periods per abstract step
    live: np.ndarray            # (C,) bool: sampled cells (safe, not target)
    target: np.ndarray          # (C,) bool: reach-avoid target cells (value 1, absorbing)
    row_ptr: np.ndarray         # (C*M + 1,) int64
    col: np.ndarray             # (nnz,) int32 successor cell, C = sink
    lo: np.ndarray              # (nnz,) float32 lower probability bound
    hi: np.ndarray              # (nnz,) float32 upper probability bound
    meta: dict = field(default_factory=dict)
    k_lo: Optional[np.ndarray] = None   # (nnz,) int32 count behind lo (n_in; -1 for the sink: no lower bound)
    k_hi: Optional[np.ndarray] = None   # (nnz,) int32 count behind hi (n_hit; n_sink for the sink)

    @property
    def C(self) -> int:
        return self.grid.size

    @property
    def M(self) -> int:
        return self.inputs.shape[0]

    @property
    def nnz(self) -> int:
        return int(self.col.size)

    def nbytes(self) -> int:
        return int(self.row_ptr.nbytes + self.col.nbytes + self.lo.nbytes + self.hi.nbytes)


# ----------------------------------------------------------------------------------------------
# Union bound
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Allocation:
    """Bonferroni split of the failure probability beta over the three families of one-sided bounds.

    sink, lo, hi : shares w_f >= 0 of beta, w_sink + w_lo + w_hi <= 1. With n_f bounds in family f,
    each is taken at level beta w_f / n_f; the probability that any bound fails is at most
    sum_f n_f (beta w_f / n_f) = beta sum_f w_f <= beta. Share 0: the family is not estimated
    (trivial bounds lo = 0, hi = 1).
    """

    sink: float
    lo: float
    hi: float

    @classmethod
    def of(cls, split) -> "Allocation":
        try:
            w = [float(v) for v in split]
        except (TypeError, ValueError):
            raise SimgapError(f"split must be three shares (sink, lo, hi) of beta, got {split!r}") from None
        if len(w) != 3 or not all(np.isfinite(w)) or min(w) < 0 or w[0] <= 0:
            raise SimgapError(f"split must be three shares (sink, lo, hi) of beta, each >= 0 and the sink's > 0, "
                              f"got {split!r}")
        if sum(w) > 1.0 + 1e-12:
            raise SimgapError(f"split {split!r} sums to {sum(w):g} > 1: the union bound would exceed beta")
        return cls(*w)

    def after_pilot(self, single_seen: bool) -> "Allocation":
        """The split to use when the pilot runs are in: if no pilot run ended with its widened box in
        one cell, the lower bounds would be ~0 everywhere and their share goes to the sink family
        (a choice made from the pilot alone, fixed before the main runs: still valid)."""
        return self if single_seen or self.lo == 0 else Allocation(self.sink + self.lo, 0.0, self.hi)

    def levels(self, beta: float, n_rows: int, n_support: int) -> dict:
        """Per-bound level of each family: beta w_f / n_f (0 for a family that is not estimated)."""
        n = {"sink": n_rows, "lo": n_support, "hi": n_support}
        return {f: float(beta) * getattr(self, f) / max(n[f], 1) for f in n}


def intervals(k_lo: np.ndarray, k_hi: np.ndarray, is_sink: np.ndarray, N: int, levels: dict):
    """(lo, hi) float64 one-sided Clopper-Pearson bounds at the family levels (:class:`Allocation`).

    Successor entries: lo from k_lo (n_in), hi from k_hi (n_hit); sink entries: lo = 0, hi from k_hi
    (n_sink). A family at level 0 gets its trivial bound (lo = 0 / hi = 1)."""
    lo = np.zeros(k_lo.shape)
    if levels["lo"] > 0:
        lo = np.where(is_sink, 0.0, cp_lower(np.maximum(k_lo, 0), N, levels["lo"]))
    hi_succ = cp_upper(k_hi, N, levels["hi"]) if levels["hi"] > 0 else np.ones(k_hi.shape)
    hi = np.where(is_sink, cp_upper(k_hi, N, levels["sink"]), hi_succ)
    return lo, hi


def float32_outward(lo: np.ndarray, hi: np.ndarray):
    """Round lo down and hi up to float32 (stays sound); exact zeros stay zero, hi stays <= 1."""
    lo32 = np.nextafter(lo.astype(np.float32), np.float32(0))
    lo32[lo == 0] = 0
    hi32 = np.minimum(np.nextafter(hi.astype(np.float32), np.float32(2)), np.float32(1))
    return lo32, hi32


def reallocate(imdp: "IMDP", beta: float, split) -> "IMDP":
    """The same counts with another union-bound split (e.g. to compare allocations; a reported
    certificate must use a split fixed before its main runs)."""
    a = Allocation.of(split)
    is_sink = imdp.col == imdp.C
    lev = a.levels(beta, int(is_sink.sum()), int((~is_sink).sum()))
    lo32, hi32 = float32_outward(*intervals(imdp.k_lo, imdp.k_hi, is_sink, int(imdp.meta["n_runs"]), lev))
    meta = dict(imdp.meta, beta=float(beta), split=dataclasses.asdict(a), levels=lev,
                bounds=_bound_count(a, int(is_sink.sum()), int((~is_sink).sum())))
    return dataclasses.replace(imdp, lo=lo32, hi=hi32, meta=meta)


def _bound_count(a: Allocation, n_rows: int, n_support: int) -> int:
    return n_rows * (a.sink > 0) + n_support * ((a.lo > 0) + (a.hi > 0))


P_CERT_CONDITION = ("conditional on the estimated Lipschitz constants: Wood-Zhang estimates from common-random-number "
                    "secants at several distances, not proven bounds (a feature narrower than the secants and the "
                    "containment check sample can break p_cert; docs/per-run.md, assumptions table), and on the "
                    "Markov assumption: the simulator's randomness, per-run parameters included, is drawn afresh "
                    "every sampling period")

UNION_BOUND = ("Bonferroni over all one-sided Clopper-Pearson bounds; family f (sink, lo, hi) gets the "
               "share split[f] of beta, each of its bounds level beta split[f] / (its count)")


def assemble(grid: UniformGrid, inputs: np.ndarray, hold: int, live: np.ndarray, target: np.ndarray,
             rows: np.ndarray, col: np.ndarray, k_lo: np.ndarray, k_hi: np.ndarray, alloc: Allocation,
             n_runs: int, beta: float, meta: dict) -> IMDP:
    """The CSR interval MDP from per-entry counts (rows c*M + a, any order; col C = the sink).

    ``alloc`` must have been fixed before the main runs (from the pilot); the per-bound levels come
    from the number of sink rows and support entries. ``meta`` is completed with the union bound."""
    t0 = time.perf_counter()
    C, M = grid.size, inputs.shape[0]
    order = np.argsort(rows, kind="stable")
    rows = rows[order]
    col, k_lo, k_hi = col[order].astype(np.int32), k_lo[order].astype(np.int32), k_hi[order].astype(np.int32)
    row_ptr = np.zeros(C * M + 1, np.int64)
    np.cumsum(np.bincount(rows, minlength=C * M), out=row_ptr[1:])
    return assemble_csr(grid, inputs, hold, live, target, row_ptr, col, k_lo, k_hi, alloc, n_runs, beta, meta, t0)


#: entries per block when the bounds are computed (bounds the float64 temporaries: ~100 MB)
INTERVAL_BLOCK = 1 << 20


def assemble_csr(grid: UniformGrid, inputs: np.ndarray, hold: int, live: np.ndarray, target: np.ndarray,
                 row_ptr: np.ndarray, col: np.ndarray, k_lo: np.ndarray, k_hi: np.ndarray, alloc: Allocation,
                 n_runs: int, beta: float, meta: dict, t0: Optional[float] = None) -> IMDP:
    """The interval MDP from counts already in CSR order (int32 ``col``, ``k_lo``, ``k_hi``, taken as they
    are); the bounds are computed in blocks of :data:`INTERVAL_BLOCK` entries, so the peak memory is the
    interval MDP plus one block (the same numbers as in one go: every bound is elementwise)."""
    t0 = time.perf_counter() if t0 is None else t0
    C = grid.size
    n_rows = int(np.count_nonzero(col == C))
    n_support = int(col.size) - n_rows
    levels = alloc.levels(float(beta), n_rows, n_support)
    lo32, hi32 = np.empty(col.size, np.float32), np.empty(col.size, np.float32)
    for a in range(0, col.size, INTERVAL_BLOCK):
        b = slice(a, a + INTERVAL_BLOCK)
        lo32[b], hi32[b] = float32_outward(*intervals(k_lo[b], k_hi[b], col[b] == C, int(n_runs), levels))
    meta = dict(meta, n_runs=int(n_runs), beta=float(beta), split=dataclasses.asdict(alloc), levels=levels,
                bounds=_bound_count(alloc, n_rows, n_support), union_bound=UNION_BOUND,
                p_cert_conditional_on=meta.get("p_cert_conditional_on", P_CERT_CONDITION))
    if "seconds" in meta:  # the CSR and the bounds count as the intervals phase
        meta["seconds"] = dict(meta["seconds"], intervals=meta["seconds"].get("intervals", 0.0) + time.perf_counter() - t0)
    return IMDP(grid=grid, inputs=inputs.copy(), hold=int(hold), live=live, target=target, row_ptr=row_ptr, col=col,
                lo=lo32, hi=hi32, meta=meta, k_lo=k_lo, k_hi=k_hi)


# ----------------------------------------------------------------------------------------------
# Labels
# ----------------------------------------------------------------------------------------------

def _circle(lo, hi, a, b, period, meet: bool):
    """Along one angle dimension of period P: does [lo, hi] + P m meet (``meet``) or lie inside [a, b]
    for some integer m? Closed form, any widths and infinite a, b allowed."""
    with np.errstate(invalid="ignore"):
        if meet:   # lo + P m <= b and hi + P m >= a
            return np.ceil((a - hi) / period) <= np.floor((b - lo) / period)
        # a <= lo + P m, hi + P m <= b; a range of a whole period or more is the circle
        return (np.ceil((a - lo) / period) <= np.floor((b - hi) / period)) | (b - a >= period)


def box_unsafe(spec: Spec, lo: np.ndarray, hi: np.ndarray, x_lo: np.ndarray, x_hi: np.ndarray,
               angle_dims=()) -> np.ndarray:
    """(B,) bool: the box [lo, hi] is not entirely allowed (leaves X or the safe set, meets an obstacle).

    Angle dimensions are never bounded by X and are compared with the safe set and the obstacles
    modulo their period x_hi - x_lo (the simulators wrap them): a heading box [3.0, 3.2] meets an
    obstacle's heading range [-pi, -3.0]."""
    n = lo.shape[1]
    ang = np.zeros(n, dtype=bool)
    ang[list(angle_dims)] = True
    period = np.where(ang, np.asarray(x_hi, float) - np.asarray(x_lo, float), 1.0)

    def along(a, b, meet):  # (B, n) per-dimension meet / inside, angle dims on the circle
        flat = ((hi >= a) & (lo <= b)) if meet else ((lo >= a) & (hi <= b))
        return np.where(ang, _circle(lo, hi, a, b, period, meet), flat)

    bad = np.any(((lo < x_lo) | (hi > x_hi)) & ~ang, axis=1)
    if spec.kind == "invariance":
        bad |= ~np.all(along(spec.safe.lo, spec.safe.hi, False), axis=1)
    for b in spec.obstacles:
        bad |= np.all(along(b.lo, b.hi, True), axis=1)
    return bad


def cell_labels(grid: UniformGrid, spec: Spec, x_lo, x_hi, angle_dims=()):
    """(live, target) (C,) bool: live = the whole cell is allowed and not target; target = inside the target box.

    A reach-avoid target that holds no whole allowed cell is refused (value iteration would have
    nothing to reach), with the cell size in the message."""
    ids = np.arange(grid.size)
    c = grid.points(ids)
    h = grid.eta / 2
    allowed = ~box_unsafe(spec, c - h, c + h, x_lo, x_hi, angle_dims)
    target = np.zeros(grid.size, dtype=bool)
    if spec.kind == "reach_avoid":
        target = allowed & grid.cells_inside(spec.target.lo, spec.target.hi)
        if not target.any():
            raise SimgapError(f"reach-avoid target [{', '.join(f'{v:g}' for v in spec.target.lo)}] .. "
                              f"[{', '.join(f'{v:g}' for v in spec.target.hi)}] holds no whole allowed cell of the "
                              f"interval-MDP grid (cell size eta = {[float(f'{e:.6g}') for e in grid.eta]}): a run "
                              f"could never be certified to reach it; use a smaller eta or a larger target")
    return allowed & ~target, target


# ----------------------------------------------------------------------------------------------
# Sampling
# ----------------------------------------------------------------------------------------------

#: secant distances are drawn log-uniformly in [h / SECANT_SPREAD, h] (h = eta / 2): a single
#: distance is blind to a ripple whose period divides it (docs/per-run.md, "What the checks catch")
SECANT_SPREAD = 64.0


def _crn_pairs(s, j: int, h: float, n_pairs: int, runs: int, rng: np.random.Generator):
    """Start states, inputs and distances of B = n_pairs x runs common-random-number pairs.

    Returns (X (2 B, n), U (2 B, m), d (B,)): the pairs' first ends (x, u uniform in X x U, runs
    times each), then their second ends (x + d e_j, the same u); the distance d of each pair is
    log-uniform in [h / SECANT_SPREAD, h] (several distances, not only h)."""
    lo, hi = s.x_lo.copy(), s.x_hi.copy()
    hi[j] -= h
    x = lo + rng.random((n_pairs, s.n)) * (hi - lo)
    d = h * SECANT_SPREAD ** -rng.random(n_pairs)
    x2 = x.copy()
    x2[:, j] += d
    u = s.inputs[rng.integers(0, len(s.inputs), n_pairs)]
    return (np.repeat(np.concatenate([x, x2]), runs, axis=0), np.repeat(np.concatenate([u, u]), runs, axis=0),
            np.repeat(d, runs))


def secant_slopes(sim, hold: int, j: int, h_j: float, rng: np.random.Generator, n_pairs: int = 300,
                  runs: int = 20, residual: bool = False) -> dict:
    """Slopes of the B = n_pairs x runs common-random-number pairs along dimension j (see
    :func:`trajectory_lipschitz`): ``{"slope": (B, n)}`` = max_t |y_t(x) - y_t(x')| / d, or with
    ``residual`` ``{"nominal", "residual"}`` = the same for the nominal map and for the residual
    z_t = y_t - ynom_t (see :func:`residual_lipschitz`)."""
    s = sim.system
    n = s.n
    B = n_pairs * runs
    X, U, d = _crn_pairs(s, j, h_j, n_pairs, runs, rng)
    Xn = X.copy()
    slope, sl_n = np.zeros((B, n)), np.zeros((B, n))
    for _ in range(hold):
        noise = {k: np.concatenate([v, v]) for k, v in sim.draw_noise(B, rng).items()}
        X = sim.step_with_noise(X, U, noise)
        if residual:
            Xn = s.f(Xn, U)
            Z = s.diff(X, Xn)
            sl_n = np.maximum(sl_n, np.abs(s.diff(Xn[:B], Xn[B:])) / d[:, None])
            slope = np.maximum(slope, np.abs(s.diff(Z[:B], Z[B:])) / d[:, None])
        else:
            slope = np.maximum(slope, np.abs(s.diff(X[:B], X[B:])) / d[:, None])
    return {"nominal": sl_n, "residual": slope} if residual else {"slope": slope}


def lipschitz_from_slopes(system, slopes: dict, residual: bool = False):
    """Wood-Zhang estimates from :func:`secant_slopes` per column j (``slopes``: j -> its dict).

    Returns (L, how) with the identity's columns where no slopes were given, or with ``residual``
    (Ln, Lr, how). Each estimate uses its own generator [7, i, j(, residual)]: no state is shared."""
    n, names = system.n, system.state_names
    how = {}
    if not residual:
        L = np.eye(n)
        for j in sorted(slopes):
            for i in range(n):
                wz = wood_zhang(slopes[j]["slope"][:, i], np.random.default_rng([7, i, j]))
                L[i, j] = wz.estimate
                how[f"d{names[i]}/d{names[j]}"] = wz.to_dict()
        return L, how
    Ln, Lr = np.zeros((n, n)), np.zeros((n, n))
    for j in sorted(slopes):
        for i in range(n):
            for L, tag in ((Ln, "nominal"), (Lr, "residual")):
                wz = wood_zhang(slopes[j][tag][:, i], np.random.default_rng([7, i, j, tag == "residual"]))
                L[i, j] = wz.estimate
                how[f"{tag} d{names[i]}/d{names[j]}"] = wz.to_dict()
    return Ln, Lr, how


def trajectory_lipschitz(sim, hold: int, h: np.ndarray, rng: np.random.Generator, n_pairs: int = 300,
                         runs: int = 20, dims=None) -> tuple[np.ndarray, dict]:
    """Per-coordinate constants L (n, n) of the k-period trajectory map, common random numbers.

    L[i, j] bounds |y_t,i(x) - y_t,i(x + s e_j)| / |s| for every period t <= k and every noise draw:
    pairs (x, x + d e_j), d log-uniform in [h_j / SECANT_SPREAD, h_j], u uniform from U, the same
    noise per period at both ends; slopes max_t |y_t,i(x) - y_t,i(x')| / d; Wood-Zhang estimate per
    (i, j). ``dims``: estimate only these columns j (the others are left at the identity's). The
    columns draw one after the other from ``rng`` (:mod:`simgap.perrun.sampling` gives each its own).
    """
    dims = range(sim.system.n) if dims is None else dims
    return lipschitz_from_slopes(sim.system, {j: secant_slopes(sim, hold, j, h[j], rng, n_pairs, runs) for j in dims})


def trajectories(sim, x: np.ndarray, u: np.ndarray, k: int, rng, tick=lambda: None) -> np.ndarray:
    """(B, k, n) states of ``sim`` after each of the k periods with u held (``tick()`` after each period)."""
    out = np.empty((x.shape[0], k, x.shape[1]))
    y = x
    for t in range(k):
        y = out[:, t] = sim.step(y, u, rng)
        tick()
    return out


def nominal_trajectory(system, x: np.ndarray, u: np.ndarray, hold: int) -> np.ndarray:
    """(B, k, n) nominal states y_t(x) = f^t(x, u), t = 1..k, with u held."""
    out = np.empty((x.shape[0], hold, x.shape[1]))
    y = x
    for t in range(hold):
        y = out[:, t] = system.f(y, u)
    return out


def shared_box(system, x_cells: np.ndarray, x_anchor: np.ndarray, u: np.ndarray, hold: int, Ln: np.ndarray,
               Lr: np.ndarray, half: np.ndarray):
    """(shift (B, k, n), rho (B, n)): the run from ANY x in the cell of center x_c stays in
    y_t(x_s, w) + shift_t +- rho for the run from the anchor x_s with the same noise, t = 1..k.

    shift_t = ynom_t(x_c) - ynom_t(x_s) and rho = Ln eta/2 + Lr (|x_c - x_s| + eta/2), because
    y_t(x, w) = ynom_t(x) + z_t(x, w) with |ynom_t(x) - ynom_t(x_c)| <= Ln |x - x_c| and
    |z_t(x, w) - z_t(x_s, w)| <= Lr |x - x_s| (coordinate-wise; :func:`residual_lipschitz`)."""
    shift = system.diff(nominal_trajectory(system, x_cells, u, hold), nominal_trajectory(system, x_anchor, u, hold))
    rho = half @ np.asarray(Ln).T + (np.abs(system.diff(x_cells, x_anchor)) + half) @ np.asarray(Lr).T
    return shift, rho


def residual_lipschitz(sim, hold: int, h: np.ndarray, rng: np.random.Generator, n_pairs: int = 300,
                       runs: int = 20) -> tuple[np.ndarray, np.ndarray, dict]:
    """Per-coordinate constants (Ln, Lr) of the nominal k-period map and of the residual, common random numbers.

    Ln[i, j] bounds |ynom_t,i(x) - ynom_t,i(x + s e_j)| / |s| and Lr[i, j] the same for the residual
    z_t(x, w) = y_t(x, u, w) - ynom_t(x, u) (the simulator's run minus the nominal model's), for every
    period t <= k and noise draw: pairs (x, x + d e_j), d log-uniform in [h_j / SECANT_SPREAD, h_j],
    u uniform from U, the same noise per period at both ends; Wood-Zhang estimate per (i, j). The residual is what sharing runs between
    cells needs: it is small where the model is good, whatever the dynamics (docs/per-run.md).
    """
    s = sim.system
    return lipschitz_from_slopes(s, {j: secant_slopes(sim, hold, j, h[j], rng, n_pairs, runs, residual=True)
                                     for j in range(s.n)}, residual=True)


def block_anchors(grid: UniformGrid, cells: np.ndarray, share: np.ndarray) -> np.ndarray:
    """(len(cells),) the anchor cell of each cell's block of ``share`` cells per dimension: the block's middle cell."""
    mi = grid.ids_to_multi(cells)
    start = mi // share * share
    return grid.multi_to_ids(start + np.minimum(share, np.asarray(grid.shape) - start) // 2)


def _hits(grid: UniformGrid, y: np.ndarray, rho: np.ndarray):
    """Cells touched by the boxes y +- rho: (sample index, cell id or -1 outside the grid, single) arrays.

    ``single`` (B,) bool: the box touches exactly one cell.
    """
    B, n = y.shape
    shape = np.asarray(grid.shape)
    # clipped to one index beyond the grid on each side (that one stands for "outside"), and a
    # periodic span to one turn: a huge widening costs no more memory than the grid
    per = grid.periodic_mask
    lo_mi = np.floor((y - rho - grid.first) / grid.eta + 0.5)
    hi_mi = np.floor((y + rho - grid.first) / grid.eta + 0.5)
    lo_mi = np.where(per, lo_mi, np.clip(lo_mi, -1, shape)).astype(np.int64)
    hi_mi = np.where(per, hi_mi, np.clip(hi_mi, -1, shape)).astype(np.int64)
    span = np.where(per, np.minimum(hi_mi - lo_mi + 1, shape), hi_mi - lo_mi + 1)
    W = span.max(axis=0)
    offs = np.stack(np.meshgrid(*[np.arange(w) for w in W], indexing="ij"), axis=-1).reshape(-1, n)
    mi = lo_mi[:, None, :] + offs[None, :, :]                      # (B, P, n)
    valid = np.all(offs[None, :, :] < span[:, None, :], axis=2)    # (B, P)
    inside = np.ones(valid.shape, dtype=bool)
    for d in range(n):
        if grid.periodic_mask[d]:
            mi[:, :, d] %= shape[d]
        else:
            inside &= (mi[:, :, d] >= 0) & (mi[:, :, d] < shape[d])
    ids = np.where(inside, np.clip(mi, 0, shape - 1) @ grid.strides, -1)
    b, p = np.nonzero(valid)
    return b, ids[b, p], np.prod(span, axis=1) == 1


def _simulate(sim, spec, x, u, hold, rho, rng, x_lo, x_hi, angle_dims):
    """k periods with u held from x: (end states, sink flag: some widened box along the way was unsafe)."""
    bad = np.zeros(len(x), dtype=bool)
    y = x
    for _ in range(hold):
        y = sim.step(y, u, rng)
        bad |= box_unsafe(spec, y - rho, y + rho, x_lo, x_hi, angle_dims)
    return y, bad


@dataclass
class IMDPOptions:
    """Options of :func:`simgap.perrun.sampling.build_imdp`.

    eta : cell widths (state units); hold : k periods per abstract step; n_runs : N main runs per
    (cell, input); pilot_runs : N0 support runs; beta : failure probability of all intervals;
    lipschitz : (n, n) per-coordinate L_ij of the k-period map (None: estimated, see trajectory_lipschitz);
    with ``share``, the pair (Ln, Lr) of the nominal map and the residual (see residual_lipschitz);
    split : shares of beta for the (sink, lo, hi) bound families, summing to <= 1 (see :class:`Allocation`);
    share : cells per block along each dimension (an int or one per dimension) whose cells share the
    runs of one anchor cell, shifted by the nominal model and widened by the residual's Lipschitz
    constant (module docstring, "Shared runs"); None or 1: runs per cell;
    chunk_size : pairs (with ``share``: (anchor, input) groups) per chunk of the sampling (default
    :meth:`units_per_chunk`); with batch_runs it
    fixes how the random streams are cut, so both are part of the sampling's configuration.
    """

    eta: object
    hold: int = 10
    n_runs: int = 2000
    pilot_runs: int = 200
    beta: float = 0.01
    lipschitz: Optional[object] = None
    seed: int = 0
    batch_runs: int = 1 << 19
    split: tuple = (0.9, 0.05, 0.05)
    share: Optional[object] = None
    chunk_size: Optional[int] = None

    def units_per_chunk(self, n_units: int, unit_pairs: int = 1) -> int:
        """Units (pairs; with shared runs, (anchor, input) groups of up to ``unit_pairs`` pairs) per chunk
        of the sampling (:mod:`simgap.perrun.sampling`): ``chunk_size``, or one batch of main runs but at
        least ~64 chunks (a function of the options alone, never of the executor)."""
        if self.chunk_size is not None:
            return int(self.chunk_size)
        return max(1, min(int(self.batch_runs) // (int(self.n_runs) * max(1, int(unit_pairs))), -(-int(n_units) // 64)))

    def validate(self, n: int):
        if int(self.hold) < 1:
            raise SimgapError(f"hold must be >= 1 sampling period, got {self.hold}")
        if int(self.n_runs) < 10 or int(self.pilot_runs) < 1:
            raise SimgapError(f"need n_runs >= 10 and pilot_runs >= 1, got {self.n_runs}, {self.pilot_runs}")
        if not 0.0 < float(self.beta) < 1.0:
            raise SimgapError(f"beta must be in (0, 1), got {self.beta}")
        shared = False
        if self.share is not None:
            try:
                b = np.broadcast_to(np.asarray(self.share, float), (n,))
            except (TypeError, ValueError):
                b = np.zeros(n)
            if not np.all(np.isfinite(b)) or not np.all(np.mod(b, 1) == 0) or np.any(b < 1):
                raise SimgapError(f"share must be whole numbers of cells >= 1 (one, or one per state dimension: {n}), "
                                  f"got {self.share!r}")
            shared = bool(np.any(b > 1))
        if self.lipschitz is not None:
            shape = (2, n, n) if shared else (n, n)
            try:
                L = np.broadcast_to(np.asarray(self.lipschitz, float), shape)
            except (TypeError, ValueError):
                L = np.full(shape, np.nan)
            if not np.all(np.isfinite(L)) or np.any(L < 0):
                raise SimgapError(f"lipschitz must be >= 0 and finite{' ((nominal, residual) with share)' if shared else ''}, "
                                  f"got {self.lipschitz!r}")
        Allocation.of(self.split)
        if self.chunk_size is not None and (isinstance(self.chunk_size, bool) or int(self.chunk_size) != self.chunk_size
                                            or int(self.chunk_size) < 1):
            raise SimgapError(f"chunk_size must be a whole number of pairs >= 1, got {self.chunk_size!r}")
        if int(self.batch_runs) < 1:
            raise SimgapError(f"batch_runs must be >= 1, got {self.batch_runs!r}")


@dataclass
class Layout:
    """What the sampling is laid out on, a function of (system, spec, options) alone (workers rebuild it).

    Pairs p = 0..P-1 are (cells[p // M], p % M); ``order`` is the sampling order of the pairs (chunks
    are consecutive runs of it): the identity per cell, group-major (anchor, input) with shared runs,
    so that a batch simulates each of its anchors once for all the block's cells."""

    grid: UniformGrid
    live: np.ndarray
    target: np.ndarray
    good: np.ndarray            # live | target: successors kept as columns; others go to the sink
    cells: np.ndarray           # live cell ids (the sampled rows' cells)
    centers: np.ndarray
    M: int
    order: np.ndarray
    starts: np.ndarray          # positions in ``order`` where a unit of chunking starts: every pair, or every group
    share: Optional[np.ndarray] = None
    anchor: Optional[np.ndarray] = None     # per live cell: its block's anchor cell (shared runs)
    group: Optional[np.ndarray] = None      # per pair: anchor * M + input

    @property
    def C(self) -> int:
        return self.grid.size

    @property
    def P(self) -> int:
        return self.cells.size * self.M

    @property
    def unit_pairs(self) -> int:
        """The most pairs in one unit of chunking (1, or the cells of a block)."""
        return 1 if self.share is None else int(np.prod(self.share))

    def chunk_bounds(self, S: int) -> np.ndarray:
        """(n_chunks + 1,) positions in ``order``: chunk c is order[b[c]:b[c + 1]], S units each."""
        return np.append(self.starts[::S], self.P).astype(np.int64)


def layout(system, spec: Spec, options: "IMDPOptions") -> Layout:
    """The :class:`Layout` of ``options`` (validated) for ``spec`` on ``system``."""
    o = options
    o.validate(system.n)
    ad = tuple(system.angle_dims)
    grid = UniformGrid(system.x_lo, system.x_hi, o.eta, periodic=ad)
    share = None if o.share is None else np.broadcast_to(np.asarray(o.share), (system.n,)).astype(np.int64)
    if share is not None and np.all(share == 1):
        share = None
    live, target = cell_labels(grid, spec, system.x_lo, system.x_hi, ad)
    M = system.inputs.shape[0]
    cells = np.flatnonzero(live)
    lay = Layout(grid=grid, live=live, target=target, good=live | target, cells=cells, centers=grid.points(cells),
                 M=M, order=np.arange(cells.size * M), starts=np.arange(cells.size * M), share=share)
    if share is not None:
        lay.anchor = block_anchors(grid, cells, share)
        lay.group = lay.anchor.repeat(M) * M + np.tile(np.arange(M), cells.size)
        lay.order = np.argsort(lay.group, kind="stable")
        g = lay.group[lay.order]
        lay.starts = np.flatnonzero(np.r_[True, g[1:] != g[:-1]]) if g.size else np.zeros(0, np.int64)
    return lay


def count_pairs(sim, spec: Spec, lay: Layout, widening: dict, pp: np.ndarray, o: "IMDPOptions",
                rng_pilot: np.random.Generator, rng_main: np.random.Generator) -> dict:
    """Pilot support and main-run counts of the pairs ``pp`` (steps 2 and 3 of the module docstring).

    ``widening``: ``{"rho": (n,)}`` per cell, or ``{"Ln", "Lr"}`` (n, n) with shared runs. The pilot
    runs draw from ``rng_pilot`` and the main runs from ``rng_main``, in batches of at most
    ``o.batch_runs`` runs (whole pairs). Returns ``key`` (sorted support keys pair * (C + 1) + cell,
    int64), ``n_hit`` and ``n_in`` on it, ``pairs`` (= pp) with their ``n_sink``, ``single_seen``
    (some pilot run's widened end box in one cell, no sink) and ``simulated`` runs (k periods each).
    """
    s = sim.system
    grid, M, C = lay.grid, lay.M, lay.C
    ad = tuple(s.angle_dims)
    k, N, N0 = int(o.hold), int(o.n_runs), int(o.pilot_runs)
    half = grid.eta / 2
    simulated = [0]

    if lay.share is None:
        rho = np.asarray(widening["rho"], float)

        def run_pairs(q, runs, rng):  # runs from every pair's own cell center
            x = np.repeat(lay.centers[q // M], runs, axis=0)
            u = np.repeat(s.inputs[q % M], runs, axis=0)
            y, bad = _simulate(sim, spec, x, u, k, rho, rng, s.x_lo, s.x_hi, ad)
            simulated[0] += len(x)
            b, ids, single = _hits(grid, y, rho)
            return b, ids, single, bad
    else:
        Ln, Lr = np.asarray(widening["Ln"], float), np.asarray(widening["Lr"], float)
        x_anchor = grid.points(lay.anchor)

        def run_pairs(q, runs, rng):  # runs from the anchors, shifted to every pair's cell
            ug, inv = np.unique(lay.group[q], return_inverse=True)
            xa, ua = grid.points(ug // M), s.inputs[ug % M]
            traj = trajectories(sim, np.repeat(xa, runs, axis=0), np.repeat(ua, runs, axis=0), k, rng)
            simulated[0] += len(ug) * runs
            shift, r = shared_box(s, lay.centers[q // M], x_anchor[q // M], s.inputs[q % M], k, Ln, Lr, half)
            Y = traj.reshape(len(ug), runs, k, s.n)[inv] + shift[:, None]        # (B, runs, k, n)
            r = np.repeat(r, runs, axis=0)
            bad = np.zeros(len(q) * runs, dtype=bool)
            for t in range(k):
                y = s.wrap(Y[:, :, t].reshape(-1, s.n))
                bad |= box_unsafe(spec, y - r, y + r, s.x_lo, s.x_hi, ad)
            b, ids, single = _hits(grid, y, r)
            return b, ids, single, bad

    # ----- pilot: the support T(c, a) of these pairs (sorted keys pair * (C+1) + cell) -------------
    per = max(1, int(o.batch_runs) // N0)
    sup, single_seen = [], False
    for a in range(0, len(pp), per):
        q = pp[a:a + per]
        b, ids, single, bad = run_pairs(q, N0, rng_pilot)
        keep = (ids >= 0) & lay.good[np.maximum(ids, 0)] & ~bad[b]
        single_seen |= bool(np.any(single & ~bad))
        sup.append(np.unique(q[b[keep] // N0] * (C + 1) + ids[keep]))
    # sorted: with shared runs the pairs go anchor-major, so batches are not in key order (searchsorted needs it)
    support = np.sort(np.concatenate(sup)) if sup else np.zeros(0, np.int64)

    # ----- main runs -> counts on the support ------------------------------------------------------
    n_hit = np.zeros(support.size, np.int64)
    n_in = np.zeros(support.size, np.int64)
    n_sink = np.zeros(len(pp), np.int64)
    per = max(1, int(o.batch_runs) // N)
    for a in range(0, len(pp), per):
        q = pp[a:a + per]
        b, ids, single, bad = run_pairs(q, N, rng_main)
        key = q[b // N] * (C + 1) + np.maximum(ids, 0)
        posc = np.minimum(np.searchsorted(support, key), max(support.size - 1, 0))
        ok = (ids >= 0) & (support[posc] == key) if support.size else np.zeros(b.size, bool)
        sink_run = bad.copy()
        sink_run[b[~ok]] = True                          # a hit outside T(c,a), outside the grid or non-live
        n_sink[a:a + len(q)] = sink_run.reshape(len(q), N).sum(axis=1)
        hit = ok                                         # j in S (counted even for sink runs: upper bound)
        np.add.at(n_hit, posc[hit], 1)
        inn = ok & single[b] & ~sink_run[b]
        np.add.at(n_in, posc[inn], 1)
    # counts <= N fit int32 (what the interval MDP keeps); the keys need int64 (pairs x (C + 1))
    return {"key": support.astype(np.int64), "n_hit": n_hit.astype(np.int32), "n_in": n_in.astype(np.int32),
            "pairs": np.asarray(pp, np.int64), "n_sink": n_sink.astype(np.int32),
            "single_seen": np.bool_(single_seen), "simulated": np.int64(simulated[0])}

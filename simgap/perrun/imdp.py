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
    is_sink = col == C
    n_rows, n_support = int(is_sink.sum()), int((~is_sink).sum())
    levels = alloc.levels(float(beta), n_rows, n_support)
    lo32, hi32 = float32_outward(*intervals(k_lo, k_hi, is_sink, int(n_runs), levels))
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


def trajectory_lipschitz(sim, hold: int, h: np.ndarray, rng: np.random.Generator, n_pairs: int = 300,
                         runs: int = 20, dims=None) -> tuple[np.ndarray, dict]:
    """Per-coordinate constants L (n, n) of the k-period trajectory map, common random numbers.

    L[i, j] bounds |y_t,i(x) - y_t,i(x + s e_j)| / |s| for every period t <= k and every noise draw:
    pairs (x, x + d e_j), d log-uniform in [h_j / SECANT_SPREAD, h_j], u uniform from U, the same
    noise per period at both ends; slopes max_t |y_t,i(x) - y_t,i(x')| / d; Wood-Zhang estimate per
    (i, j). ``dims``: estimate only
    these columns j (the others are left at the identity's).
    """
    s = sim.system
    n = s.n
    L = np.eye(n)
    how = {}
    B = n_pairs * runs
    for j in range(n) if dims is None else dims:
        X, U, d = _crn_pairs(s, j, h[j], n_pairs, runs, rng)
        slope = np.zeros((B, n))
        for _ in range(hold):
            noise = {k: np.concatenate([v, v]) for k, v in sim.draw_noise(B, rng).items()}
            X = sim.step_with_noise(X, U, noise)
            slope = np.maximum(slope, np.abs(s.diff(X[:B], X[B:])) / d[:, None])
        for i in range(n):
            wz = wood_zhang(slope[:, i], np.random.default_rng([7, i, j]))
            L[i, j] = wz.estimate
            how[f"d{s.state_names[i]}/d{s.state_names[j]}"] = wz.to_dict()
    return L, how


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
    n = s.n
    Ln, Lr = np.zeros((n, n)), np.zeros((n, n))
    how = {}
    B = n_pairs * runs
    for j in range(n):
        X, U, d = _crn_pairs(s, j, h[j], n_pairs, runs, rng)
        Xn = X.copy()
        sl_n, sl_r = np.zeros((B, n)), np.zeros((B, n))
        for _ in range(hold):
            noise = {k: np.concatenate([v, v]) for k, v in sim.draw_noise(B, rng).items()}
            X = sim.step_with_noise(X, U, noise)
            Xn = s.f(Xn, U)
            Z = s.diff(X, Xn)
            sl_n = np.maximum(sl_n, np.abs(s.diff(Xn[:B], Xn[B:])) / d[:, None])
            sl_r = np.maximum(sl_r, np.abs(s.diff(Z[:B], Z[B:])) / d[:, None])
        for i in range(n):
            for L, sl, tag in ((Ln, sl_n, "nominal"), (Lr, sl_r, "residual")):
                wz = wood_zhang(sl[:, i], np.random.default_rng([7, i, j, tag == "residual"]))
                L[i, j] = wz.estimate
                how[f"{tag} d{s.state_names[i]}/d{s.state_names[j]}"] = wz.to_dict()
    return Ln, Lr, how


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
    """Options of :func:`build_imdp`.

    eta : cell widths (state units); hold : k periods per abstract step; n_runs : N main runs per
    (cell, input); pilot_runs : N0 support runs; beta : failure probability of all intervals;
    lipschitz : (n, n) per-coordinate L_ij of the k-period map (None: estimated, see trajectory_lipschitz);
    with ``share``, the pair (Ln, Lr) of the nominal map and the residual (see residual_lipschitz);
    split : shares of beta for the (sink, lo, hi) bound families, summing to <= 1 (see :class:`Allocation`);
    share : cells per block along each dimension (an int or one per dimension) whose cells share the
    runs of one anchor cell, shifted by the nominal model and widened by the residual's Lipschitz
    constant (module docstring, "Shared runs"); None or 1: runs per cell.
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


def build_imdp(sim, spec: Spec, options: IMDPOptions, log=None, on_progress=None) -> IMDP:
    """Sample ``sim`` and build the interval MDP of ``spec`` (see module docstring).

    ``on_progress(done, total)``: after every batch, in (cell, input) pairs of both passes (2 x pairs)."""
    t0 = time.perf_counter()
    s = sim.system
    o = options
    o.validate(s.n)
    grid = UniformGrid(s.x_lo, s.x_hi, o.eta, periodic=tuple(s.angle_dims))
    ad = tuple(s.angle_dims)
    k, N, N0 = int(o.hold), int(o.n_runs), int(o.pilot_runs)
    rng = np.random.default_rng([o.seed, 0])
    half = grid.eta / 2
    share = None if o.share is None else np.broadcast_to(np.asarray(o.share), (s.n,)).astype(np.int64)
    if share is not None and np.all(share == 1):
        share = None
    if share is None:
        if o.lipschitz is None:
            L, how = trajectory_lipschitz(sim, k, half, np.random.default_rng([o.seed, 1]))
        else:
            L, how = np.broadcast_to(np.asarray(o.lipschitz, float), (s.n, s.n)).copy(), "given"
        rho = L @ half                                   # |y_i(x) - y_i(x_c)| <= sum_j L_ij |x_j - c_j|
    elif o.lipschitz is None:
        Ln, Lr, how = residual_lipschitz(sim, k, half, np.random.default_rng([o.seed, 1]))
    else:
        Ln, Lr = np.broadcast_to(np.asarray(o.lipschitz, float), (2, s.n, s.n)).copy()
        how = "given"
    live, target = cell_labels(grid, spec, s.x_lo, s.x_hi, ad)
    C, M = grid.size, s.inputs.shape[0]
    cells = np.flatnonzero(live)
    P = cells.size * M                                   # sampled pairs, pair p = (cells[p // M], p % M)
    centers = grid.points(cells)
    good = live | target                                 # successors kept as columns; others go to the sink
    t_lip = time.perf_counter() - t0
    simulated = [0]                                      # runs simulated (k periods each)

    def run_cells(pp, runs, rng):  # runs from every pair's own cell center
        x = np.repeat(centers[pp // M], runs, axis=0)
        u = np.repeat(s.inputs[pp % M], runs, axis=0)
        y, bad = _simulate(sim, spec, x, u, k, rho, rng, s.x_lo, s.x_hi, ad)
        simulated[0] += len(x)
        b, ids, single = _hits(grid, y, rho)
        return b, ids, single, bad

    order = np.arange(P)
    if share is not None:
        # anchors: the middle cell of each block of share cells; the pairs go group-major (anchor,
        # input) so that one batch simulates each of its anchors once for all the block's cells
        anchor = block_anchors(grid, cells, share)
        x_anchor = grid.points(anchor)
        group = anchor.repeat(M) * M + np.tile(np.arange(M), cells.size)
        order = np.argsort(group, kind="stable")

        def run_shared(pp, runs, rng):  # runs from the anchors, shifted to every pair's cell
            ug, inv = np.unique(group[pp], return_inverse=True)
            xa, ua = grid.points(ug // M), s.inputs[ug % M]
            traj = trajectories(sim, np.repeat(xa, runs, axis=0), np.repeat(ua, runs, axis=0), k, rng)
            simulated[0] += len(ug) * runs
            shift, r = shared_box(s, centers[pp // M], x_anchor[pp // M], s.inputs[pp % M], k, Ln, Lr, half)
            Y = traj.reshape(len(ug), runs, k, s.n)[inv] + shift[:, None]        # (B, runs, k, n)
            r = np.repeat(r, runs, axis=0)
            bad = np.zeros(len(pp) * runs, dtype=bool)
            for t in range(k):
                y = s.wrap(Y[:, :, t].reshape(-1, s.n))
                bad |= box_unsafe(spec, y - r, y + r, s.x_lo, s.x_hi, ad)
            b, ids, single = _hits(grid, y, r)
            return b, ids, single, bad

    run_pairs = run_cells if share is None else run_shared

    # ----- pass 1: pilot support T(c, a) (sorted keys pair * (C+1) + cell) -------------------------
    per = max(1, o.batch_runs // N0)
    sup, single_seen = [], False
    for a in range(0, P, per):
        pp = order[a:a + per]
        b, ids, single, bad = run_pairs(pp, N0, rng)
        keep = (ids >= 0) & good[np.maximum(ids, 0)] & ~bad[b]
        single_seen |= bool(np.any(single & ~bad))
        sup.append(np.unique(pp[b[keep] // N0] * (C + 1) + ids[keep]))
        if on_progress:
            on_progress(min(P, a + per), 2 * P)
    # sorted: with shared runs the pairs go anchor-major, so batches are not in key order (searchsorted needs it)
    support = np.sort(np.concatenate(sup)) if sup else np.zeros(0, np.int64)
    alloc = Allocation.of(o.split).after_pilot(single_seen)
    levels = alloc.levels(float(o.beta), P, support.size)   # fixed by the pilot, before the main runs
    n_bounds = _bound_count(alloc, P, support.size)
    t_pilot = time.perf_counter() - t0 - t_lip
    if log:
        log(f"imdp: {cells.size} live cells x {M} inputs, support {support.size} entries; "
            f"{n_bounds} one-sided bounds, levels " + ", ".join(f"{f} {v:.3g}" for f, v in levels.items()))

    # ----- pass 2: main runs -> counts on the support ---------------------------------------------
    n_hit = np.zeros(support.size, np.int64)
    n_in = np.zeros(support.size, np.int64)
    n_sink = np.zeros(P, np.int64)
    per = max(1, o.batch_runs // N)
    for a in range(0, P, per):
        pp = order[a:a + per]
        b, ids, single, bad = run_pairs(pp, N, rng)
        key = pp[b // N] * (C + 1) + np.maximum(ids, 0)
        posc = np.minimum(np.searchsorted(support, key), max(support.size - 1, 0))
        ok = (ids >= 0) & (support[posc] == key) if support.size else np.zeros(b.size, bool)
        sink_run = bad.copy()
        sink_run[b[~ok]] = True                          # a hit outside T(c,a), outside the grid or non-live
        n_sink[pp] += sink_run.reshape(len(pp), N).sum(axis=1)
        hit = ok                                         # j in S (counted even for sink runs: upper bound)
        np.add.at(n_hit, posc[hit], 1)
        inn = ok & single[b] & ~sink_run[b]
        np.add.at(n_in, posc[inn], 1)
        if on_progress:
            on_progress(P + min(P, a + per), 2 * P)
    t_main = time.perf_counter() - t0 - t_lip - t_pilot

    # ----- intervals, CSR ------------------------------------------------------------------------
    pair_of = support // (C + 1)
    rows = np.concatenate([cells[pair_of // M] * M + pair_of % M, cells.repeat(M) * M + np.tile(np.arange(M), cells.size)])
    col = np.concatenate([support % (C + 1), np.full(P, C)])
    k_lo = np.concatenate([n_in, np.full(P, -1)])
    k_hi = np.concatenate([n_hit, n_sink])
    meta = {"pilot_runs": N0, "lipschitz_how": how, "live_cells": int(cells.size), "seed": int(o.seed),
            "simulator": sim.config.to_dict(), "spec": spec.to_dict(),
            "seconds": {"lipschitz": t_lip, "pilot": t_pilot, "main": t_main,
                        "intervals": time.perf_counter() - t0 - t_lip - t_pilot - t_main},
            "samples": int(simulated[0] * k)}
    if share is None:
        meta.update(lipschitz=L.tolist(), rho=rho.tolist(),
                    assumption="per realization: the k-period trajectory map is L-Lipschitz (common random numbers)")
    else:
        rho_max = half @ Ln.T + (np.abs(s.diff(centers, x_anchor)).max(axis=0) + half) @ Lr.T
        meta.update(lipschitz={"nominal": Ln.tolist(), "residual": Lr.tolist()}, rho=rho_max.tolist(),
                    share=share.tolist(), anchors=int(np.unique(anchor).size),
                    assumption="per realization: the residual y_t(x, w) - ynom_t(x) of the k-period run is "
                               "Lr-Lipschitz and the nominal k-period map Ln-Lipschitz (coordinate-wise, common "
                               "random numbers); the runs of one anchor cell per block serve every cell of the "
                               "block, shifted by the nominal model and widened by Ln eta/2 + Lr (|x_c - x_s| + eta/2)")
    return assemble(grid, s.inputs, k, live, target, rows, col, k_lo, k_hi, alloc, N, o.beta, meta)

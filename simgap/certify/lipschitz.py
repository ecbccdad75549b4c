"""Lipschitz constants in x of Assumption 2: L_f^(i), Lhat_fhat^(i), L_2^(i) (per state dimension).

Theorem 1 needs, for ||x - x_r|| <= eps,
    |gap_i(x) - gap_i(x_r)| <= (L_f + Lhat_fhat) ||x - x_r||,   gap_i = E fhat_i - f_i,
    |q^T p(x) - q^T p(x_r)| <= L_2 ||x - x_r||.

Two readings of L_f and Lhat_fhat (``mode``):

* ``"increment"`` (default): Lipschitz constants of the increments f_i(x,u) - x_i and
  mean fhat_i(x,u) - x_i. Valid for Theorem 1 because the identity cancels in the gap:
  gap_i = (E fhat_i - x_i) - (f_i - x_i), so the triangle inequality gives the bound above with
  the increment constants. It is what the paper's printed TurtleBot constants are
  (L_f^(1) = 0.0151 is tau*|u1|*|sin| scale, not ~1), and it is much tighter (~tau vs ~1).
* ``"state"``: the proof read literally: Lipschitz constants of f_i and of the mean of fhat_i
  (both about 1: each adds about eps to gamma). L_f is analytic from ``System.lipschitz_f``
  when the system gives a Jacobian bound, otherwise estimated.

Estimation (Wood & Zhang 1996): slopes |h(a) - h(b)| / ||a - b|| over pairs of neighbouring
cover points (same input), random batches of pairs, the maximum of each batch, a reverse
Weibull (``scipy.stats.weibull_max``) fitted to the batch maxima; its location parameter (the
upper end point of the slope distribution) is the estimate. No finite-sample guarantee; slopes
between empirical means also carry noise of order sqrt(2) sigma / (sqrt(N1hat) h), which
inflates the estimate (conservative).

L_2 (``l2="analytic"``, default) is a SOUND bound: sup over X x U of ||grad_x q^T p||_2 from
interval forward differentiation of the basis terms on a grid of sub-boxes of X.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import SimgapError

#: pairs and runs per pair of the simulator estimate of Lhat_fhat (``lhat="simulator"``)
LHAT_PAIRS, LHAT_RUNS = 2000, 100


def load_fitting_modules() -> None:
    """Import scipy.stats (1-2 s the first time in a process under load) before an estimate is
    printed, so that the estimate covers what follows it: the audit's t quantiles and the
    certificate's Weibull fits (:func:`wood_zhang`) need it, and no cost model prices a module's
    first import."""
    import scipy.stats  # noqa: F401


@dataclass
class WoodZhang:
    estimate: float
    max_slope: float
    n_slopes: int
    n_batches: int
    batch_size: int
    fit_ok: bool

    def to_dict(self):
        return dict(self.__dict__)


def wood_zhang(slopes: np.ndarray, rng: np.random.Generator, n_batches: int = 200,
               batch_size: int = 500) -> WoodZhang:
    """Wood & Zhang (1996) estimate of the Lipschitz constant from sampled slopes (>= 0)."""
    s = np.asarray(slopes, dtype=float).ravel()
    s = s[np.isfinite(s)]
    if s.size == 0:
        raise SimgapError("Lipschitz estimation: no neighbouring data pairs (is the cover a single point?)")
    bs = int(min(batch_size, s.size))
    idx = rng.integers(0, s.size, size=(n_batches, bs))
    maxima = s[idx].max(axis=1)
    smax = float(s.max())
    top = float(maxima.max())
    if smax == 0.0:
        return WoodZhang(0.0, 0.0, s.size, n_batches, bs, True)
    if maxima.max() - maxima.min() <= 1e-9 * top:
        return WoodZhang(smax, smax, s.size, n_batches, bs, True)  # constant slope: nothing to fit
    try:
        with np.errstate(all="ignore"):
            from scipy import stats  # imported here: its import takes seconds, the cost estimates come first
            c, loc, scale = stats.weibull_max.fit(maxima)
        ok = bool(np.isfinite(loc) and loc >= top - 1e-12 * top and loc <= 10.0 * smax)
    except Exception:  # scipy's optimizer can fail on degenerate samples: fall back, recorded
        ok, loc = False, smax
    est = float(loc) if ok else smax
    return WoodZhang(max(est, smax), smax, s.size, n_batches, bs, ok)


def neighbour_pairs(dataset, radius_factor: float = 1.0 + 1e-6):
    """Pairs of rows (ra, rb) with the same input whose cover points are within 2 eps.

    Returns (ra, rb, dist) with dist = ||x_a - x_b|| (Euclidean, angle dims wrapped).
    """
    ci, ii = dataset.cover_index.astype(np.int64), dataset.input_index.astype(np.int64)
    N, M = int(ci.max()) + 1, int(ii.max()) + 1
    rowmap = np.full((N, M), -1, dtype=np.int64)
    rowmap[ci, ii] = np.arange(dataset.K)
    C = np.zeros((N, dataset.system.n))
    C[ci] = dataset.x
    from scipy.spatial import cKDTree
    tree = cKDTree(C)
    pr = tree.query_pairs(2.0 * dataset.epsilon * radius_factor, output_type="ndarray")
    if pr.size == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    ra = rowmap[pr[:, 0]].ravel()
    rb = rowmap[pr[:, 1]].ravel()
    keep = (ra >= 0) & (rb >= 0)
    ra, rb = ra[keep], rb[keep]
    dist = np.linalg.norm(dataset.system.diff(dataset.x[ra], dataset.x[rb]), axis=1)
    ok = dist > 0
    return ra[ok], rb[ok], dist[ok]


def slopes_of(values: np.ndarray, pairs, system, angle_diff: bool = True) -> np.ndarray:
    """|h(a) - h(b)| / ||a - b|| per pair and dimension for values (K, n) -> (P, n)."""
    ra, rb, dist = pairs
    d = system.diff(values[ra], values[rb]) if angle_diff else values[ra] - values[rb]
    return np.abs(d) / dist[:, None]


def l2_analytic(basis, q: np.ndarray, system, splits: int | None = None, inputs=None) -> float:
    """Sound sup over X x U of ||grad_x q^T p(x,u)||_2 by interval differentiation on sub-boxes."""
    n = system.n
    if splits is None:
        splits = max(2, int(round(4096 ** (1.0 / n))))
    U = system.inputs if inputs is None else np.atleast_2d(inputs)
    edges = [np.linspace(l, h, splits + 1) for l, h in zip(system.x_lo, system.x_hi)]
    grids = np.meshgrid(*[np.arange(splits)] * n, indexing="ij")
    cell = np.stack([g.ravel() for g in grids], axis=1)  # (S^n, n)
    lo = np.stack([edges[j][cell[:, j]] for j in range(n)], axis=1)
    hi = np.stack([edges[j][cell[:, j] + 1] for j in range(n)], axis=1)
    S = len(lo)
    zlo = np.concatenate([np.repeat(lo, len(U), axis=0), np.tile(U, (S, 1))], axis=1)
    zhi = np.concatenate([np.repeat(hi, len(U), axis=0), np.tile(U, (S, 1))], axis=1)
    best = 0.0
    step = 200_000
    for a in range(0, len(zlo), step):  # bounded memory; each chunk vectorized
        g = basis.grad_x_bound(q, zlo[a:a + step], zhi[a:a + step])
        best = max(best, float(np.sqrt((g ** 2).sum(axis=1)).max()))
    return best


def crn_cost(n_pairs: int, runs: int, system, rate_per_worker=None, workers: int = 1, gap_rows: float = 0.0) -> dict:
    """Work, peak memory and time of :func:`fhat_slopes_crn` before it runs.

    2 x n_pairs x runs simulator rows in one batch (both ends of every pair share their draws):
    states, inputs, next states and noise in float64 (a factor 4 for the simulator's work arrays).
    ``gap_rows``: the gap's own Lipschitz runs (:func:`gap_slopes_crn`, lipschitz_term = "gap"),
    one batch per axis, smaller than the first; they add to the time, not to the peak memory.
    ``seconds`` = rows / (rate x workers) at a measured rate [runs/s of one worker]."""
    fhat_rows = 2.0 * float(n_pairs) * float(runs)
    rows = fhat_rows + float(gap_rows)
    memory = fhat_rows * (3 * system.n + system.m) * 8 * 4
    secs = rows / (rate_per_worker * max(1, workers)) if rate_per_worker else None
    return {"pairs": int(n_pairs), "runs": int(runs), "rows": rows, "gap_rows": float(gap_rows), "memory": memory,
            "seconds": secs, "rate": rate_per_worker, "workers": int(workers)}


def crn_cost_text(c: dict) -> str:
    """:func:`crn_cost` as the line ``simgap certify --lhat simulator`` prints first."""
    from ..checks import available_memory, human_bytes
    from ..cover import format_duration
    t = ("time unknown" if c["seconds"] is None else
         f"about {format_duration(c['seconds'])} at {c['rate']:,.0f} runs/s per worker x {c['workers']} "
         "(calibrated here)")
    gap = (f" + {c['gap_rows']:,.0f} for the gap's own Lipschitz term" if c.get("gap_rows") else "")
    return (f"estimate: Lhat_fhat from the simulator, {c['pairs']:,} pairs x {c['runs']:,} runs x 2 ends{gap} = "
            f"{c['rows']:,.0f} simulator runs; {t}; peak memory about {human_bytes(c['memory'])} "
            f"({human_bytes(available_memory())} available)")


def check_crn_cost(c: dict) -> None:
    """Refuse :func:`fhat_slopes_crn` work over the machine's memory (or a command's time limit)."""
    from ..checks import check_sim_work
    check_sim_work(c["rows"], c["memory"], f"Lhat_fhat from the simulator ({c['pairs']:,} pairs x {c['runs']:,} runs)",
                   "use --lhat data", c["rate"], c["workers"])


def check_pair_distance(system, h: float, dims=None) -> None:
    """Refuse a pair distance h that leaves no room for a pair (x, x + h d) inside X.

    :func:`fhat_slopes_crn` draws x in X shrunk by h along every covered dimension in ``dims``
    (default all), so each needs a width x_hi - x_lo > 2 h. h is the cover's epsilon, known before
    any collection, so this runs before it (:func:`simgap.pipeline.check_experiment`)."""
    dims = list(range(system.n)) if dims is None else [int(j) for j in dims]
    width = (system.x_hi - system.x_lo)[dims]
    bad = [j for j, w in zip(dims, width) if not w > 2 * h]
    if bad:
        j = bad[0]
        w = float(system.x_hi[j] - system.x_lo[j])
        raise SimgapError(f"lhat = \"simulator\": its pair distance h = the cover's epsilon = {h:g}, but X is only "
                          f"{w:g} wide along {system.state_names[j]} (pairs need a width > 2 h = {2 * h:g}): set a "
                          f"smaller epsilon ([collect] epsilon, --epsilon) below {w / 2:g}, or declare "
                          f"{system.state_names[j]} invariant, or use lhat = \"data\"")


def fhat_slopes_crn(sim, rng: np.random.Generator, h: float, n_pairs: int = LHAT_PAIRS, runs: int = LHAT_RUNS,
                    increment: bool = True, dims=None, inputs=None, on_progress=None) -> np.ndarray:
    """Slopes of the empirical mean of fhat with COMMON random numbers, (n_pairs, n).

    The quantity in the paper's proof of Theorem 1 is the Lipschitz constant of
    x -> (1/N) sum_k fhat(x, u, w_k) with the SAME draws w_k at x and x_r. Slopes between the
    data set's means (independent draws per row) add noise of order sqrt(2) sigma/(sqrt(N) h);
    here each pair (x, x + h d) (d a random unit direction, u uniform from U) is simulated with
    the same ``runs`` noise draws at both ends, so that noise cancels.

    ``dims`` (default all): the covered state dimensions; d lies in their span. Theorem 1 moves
    x only along covered dimensions (declared-invariant ones are not covered and the gap does
    not depend on them), so a direction with components elsewhere would dilute the slope.
    ``inputs`` (default the system's U): the inputs u is drawn from (the data's, which gamma covers).
    ``on_progress(rows_done, rows)``: the 2 n_pairs runs rows go in parts (the same numbers);
    :func:`crn_cost` prices them beforehand.
    """
    s = sim.system
    dims = list(range(s.n)) if dims is None else sorted(int(j) for j in dims)
    if not dims:
        raise SimgapError("Lipschitz (simulator): no covered dimension to draw pairs along")
    check_pair_distance(s, h, dims)
    lo, hi = s.x_lo.copy(), s.x_hi.copy()
    lo[dims] += h
    hi[dims] -= h
    x = lo + rng.random((n_pairs, s.n)) * (hi - lo)
    d = np.zeros((n_pairs, s.n))
    d[:, dims] = rng.standard_normal((n_pairs, len(dims)))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x2 = x + h * d
    U = s.inputs if inputs is None else np.atleast_2d(np.asarray(inputs, float))
    u = U[rng.integers(0, len(U), n_pairs)]
    m1, m2 = crn_pair_means(sim, x, x2, u, u, runs, rng, increment, on_progress)
    return np.abs(s.diff(m1, m2)) / h


# ----- the gap's own Lipschitz matrix (beyond the paper) -----------------------------------------
#
# Theorem 1 only needs |g_i(x) - g_i(x_r)| for the gap g_i = E fhat_i - f_i itself. On a grid
# cover every x in X lies in a cell of its cover point x_r: |x_j - x_r,j| <= eps_j per covered
# dimension j (half the cell width; 0 along declared-invariant dimensions, along which x is moved
# onto the cover). Moving one coordinate at a time inside that cell (mean-value theorem),
#     |g_i(x) - g_i(x_r)| <= sum_j L_ij eps_j,   L_ij = sup |d g_i / d x_j|,
# and L_ij <= L_f + Lhat_fhat (each side of the gap is Lipschitz with those constants). Both sides
# follow the same physics, so their slopes largely cancel in g: L_ij is often far below them.


@dataclass
class AxisGrid:
    """The data's cover as a grid: per covered dimension its sorted values and radius eps_j.

    ``radii`` (n,): eps_j = the largest distance from a point of X to the nearest grid value
    along j (half the largest gap between neighbouring values, the distance to X's edges, the
    seam gap for a full-turn angle); 0 along dimensions that are not covered.
    ``neighbours[j]`` = (ra, rb, h): rows that differ only in dimension j, by one grid step h
    (same input), the seam pair included for a full-turn angle.
    """

    dims: list
    radii: np.ndarray
    neighbours: dict
    values: dict
    input_radii: np.ndarray


def axis_grid(dataset, dims, input_dims=(), by_point: bool = False) -> AxisGrid:
    """Read the data's rows as a grid over the covered state ``dims`` (see :class:`AxisGrid`) and,
    for continuous inputs, over the input dimensions ``input_dims`` too (keys n + k in ``radii``'s
    extension ``input_radii`` and in ``neighbours``). Inputs not in the grid are matched exactly
    (neighbours share the input). ``by_point``: rows are matched by their cover point instead of by
    their state values, so only the inputs get neighbours (the states get their values and radii, no
    neighbours): for a cover whose points are no grid over the states (one point per period along a
    tube: a grid over their values would have prod_j (distinct values along j) cells, 234^14 at 14
    states)."""
    s = dataset.system
    n = s.n
    Z = np.concatenate([dataset.x, dataset.u], axis=1)
    cols = list(dims) + [n + k for k in input_dims]
    radii = np.zeros(n + s.m)
    values, inv = {}, {}
    for j in cols:
        v, k = np.unique(Z[:, j], return_inverse=True)
        values[j], inv[j] = v, k.ravel()
        gaps = np.diff(v)
        if _full_turn(s, j):
            radii[j] = 0.5 * np.append(gaps, v[0] + 2 * np.pi - v[-1]).max()
        elif j < n:
            radii[j] = max(0.5 * gaps.max(initial=0.0), v[0] - s.x_lo[j], s.x_hi[j] - v[-1])
        else:  # an input: the continuous range is the grid's hull
            radii[j] = 0.5 * gaps.max(initial=0.0)
    keyed = [j for j in cols if j >= n] if by_point else cols  # the dimensions rows are matched along
    shape = [len(values[j]) for j in keyed]
    lin = np.ravel_multi_index([inv[j] for j in keyed], shape) if keyed else np.zeros(len(Z), np.int64)
    ui = dataset.input_index.astype(np.int64)  # inputs outside the grid are matched exactly
    if by_point:
        pt = dataset.cover_index.astype(np.int64)
        other = pt if input_dims else pt * (int(ui.max(initial=0)) + 1) + ui
    else:
        other = np.zeros(len(Z), np.int64) if input_dims else ui
    rowmap = np.full((int(np.prod(shape)), int(other.max()) + 1), -1, dtype=np.int64)
    rowmap[lin, other] = np.arange(len(Z))
    if np.count_nonzero(rowmap >= 0) != len(Z):
        raise SimgapError("the data's rows are not one per (cover point, input) on a grid: the gap's Lipschitz "
                          "matrix needs a grid cover")
    none = np.zeros(0, np.int64)
    neighbours = {j: (none, none, np.zeros(0)) for j in cols if j not in keyed}
    for a, j in enumerate(keyed):
        c, k, per = shape[a], inv[j], _full_turn(s, j)
        step = np.prod(shape[a + 1:], dtype=np.int64)
        nxt = np.where(k + 1 < c, lin + step, (lin - (c - 1) * step) if (per and c > 2) else -1)
        ra = np.nonzero(nxt >= 0)[0]
        rb = rowmap[nxt[ra], other[ra]]
        ra, rb = ra[rb >= 0], rb[rb >= 0]
        d = Z[rb, j] - Z[ra, j]
        h = np.abs(s.diff(dataset.x[rb], dataset.x[ra])[:, j]) if j < n else np.abs(d)
        neighbours[j] = (ra, rb, h)
    return AxisGrid(dims=cols, radii=radii[:n], neighbours=neighbours, values=values,
                    input_radii=radii[n:])


def _full_turn(system, j: int) -> bool:
    return j < system.n and j in system.angle_dims and bool(np.isclose(system.x_hi[j] - system.x_lo[j], 2 * np.pi))


def gap_slopes_data(dataset, grid: AxisGrid, j: int) -> tuple:
    """Slopes |g(a) - g(b)| / h of the observed gap between axis neighbours along j, (P, n), and
    the noise-only slopes sqrt((s_a^2 + s_b^2) / N1hat) / h, (P, n): the sd of a pair's slope
    when g is flat (empirical means carry independent noise per row)."""
    s = dataset.system
    ra, rb, h = grid.neighbours[j]
    g = s.diff(dataset.mean, dataset.f_nom)
    sl = np.abs(g[ra] - g[rb]) / h[:, None]
    noise = np.sqrt((dataset.var[ra] + dataset.var[rb]) / max(int(dataset.n_runs), 1)) / h[:, None]
    return sl, noise


def crn_pair_means(sim, x1, x2, u1, u2, runs: int, rng: np.random.Generator, increment: bool = True,
                   on_progress=None, spread: bool = False):
    """Means of fhat (angles unwrapped about x: compare them with ``System.diff``) or of fhat - x
    (``increment``) at (x1, u1) and (x2, u2) over ``runs`` COMMON noise draws per pair
    (``on_progress(rows_done, rows)`` while the runs are simulated); with ``spread`` also the standard
    error of their difference, (P, n): the sample sd over the runs of the per-run difference between
    the two ends, / sqrt(runs). Common random numbers make it small when the simulator responds
    smoothly to its noise; where it does not (contacts, slip events), it is the noise left in the slopes."""
    s = sim.system
    P = len(x1)
    X = np.repeat(np.concatenate([x1, x2]), runs, axis=0)
    U = np.repeat(np.concatenate([u1, u2]), runs, axis=0)
    noise = sim.draw_noise(P * runs, rng)
    noise = {k: np.concatenate([v, v]) for k, v in noise.items()}  # the same draws at both ends
    if on_progress is None:
        nxt = sim.step_with_noise(X, U, noise)
    else:
        nxt = sim.step_with_noise_in_parts(X, U, noise, lambda done: on_progress(done, X.shape[0]))
    # average per-run increments, wrapped one run at a time: a plain mean of wrapped angles is
    # wrong by up to pi where the runs' next angles straddle the seam (+-pi)
    base = s.diff(nxt, X).reshape(2, P, runs, s.n)
    m = base.mean(axis=2)
    if not increment:  # the mean next state, unwrapped about x (s.diff of two of them wraps)
        m = m + np.stack([x1, x2])
    if not spread:
        return m[0], m[1]
    d = s.diff(base[1], base[0])
    se = d.std(axis=1, ddof=1) / np.sqrt(runs) if runs > 1 else np.zeros((P, s.n))
    return m[0], m[1], se


def gap_slopes_crn(sim, nominal, rng: np.random.Generator, direction: str, k: int, h_max: float, n_pairs: int,
                   runs: int, inputs: np.ndarray, lo=None, hi=None, on_progress=None, box=None) -> np.ndarray:
    """Slopes of the gap g = E fhat - f (f the ``nominal`` model) along state (``direction="x"``) or
    input (``"u"``) axis k, from pairs simulated with common random numbers, (n_pairs, n), and each
    slope's standard error from the noise the common draws did not cancel (n_pairs, n).

    Pair distances are log-uniform in [h_max / 8, h_max] (several distances, so a slope that only
    shows at one scale is not missed by construction); x uniform in X (shrunk by h along k), u
    drawn from ``inputs`` (for ``"u"``: uniform in the input box [lo, hi] shrunk by h).
    ``box`` = (x_lo, x_hi): where x is drawn (default the simulator's X; a local certificate passes its
    region: its gamma is stated there only, and beyond it the simulator may do what the region never
    sees, a joint limit). ``on_progress(rows_done, rows)`` while the 2 n_pairs runs rows are simulated."""
    s = sim.system
    h = h_max * 2.0 ** (-3.0 * rng.random(n_pairs))
    xlo, xhi = (s.x_lo.copy(), s.x_hi.copy()) if box is None else (np.array(box[0], float), np.array(box[1], float))
    x1 = xlo + rng.random((n_pairs, s.n)) * (xhi - xlo)
    if direction == "x":
        x1[:, k] = xlo[k] + rng.random(n_pairs) * (xhi[k] - xlo[k] - h)
        x2 = x1.copy()
        x2[:, k] += h
        u1 = inputs[rng.integers(0, len(inputs), n_pairs)]
        u2 = u1
    else:
        x2 = x1
        u1 = lo + rng.random((n_pairs, len(lo))) * (hi - lo)
        u1[:, k] = lo[k] + rng.random(n_pairs) * (hi[k] - lo[k] - h)
        u2 = u1.copy()
        u2[:, k] += h
    m1, m2, se = crn_pair_means(sim, x1, x2, u1, u2, runs, rng, increment=False, on_progress=on_progress,
                                spread=True)
    g1 = s.diff(m1, nominal.f(x1, u1))
    g2 = s.diff(m2, nominal.f(x2, u2))
    return np.abs(g2 - g1) / h[:, None], se / h[:, None]


def l2_partials(basis, q: np.ndarray, system, inputs, splits: int | None = None, u_box=None) -> tuple:
    """Sound sups over X x U from one interval differentiation on sub-boxes of X (as :func:`l2_analytic`):
    (||grad_x q^T p||_2 (the paper's L_2), |d q^T p / d x_j| per j (n,), |d q^T p / d u_k| per k (m,)).

    The state partials are taken at the finite ``inputs``; the input partials over the whole input
    box ``u_box`` = (lo, hi) when given (continuous inputs; one more pass over u-intervals), else at
    the finite inputs."""
    n, m = system.n, system.m
    if splits is None:
        splits = max(2, int(round(4096 ** (1.0 / n))))
    edges = [np.linspace(l, h, splits + 1) for l, h in zip(system.x_lo, system.x_hi)]
    grids = np.meshgrid(*[np.arange(splits)] * n, indexing="ij")
    cell = np.stack([g.ravel() for g in grids], axis=1)
    lo = np.stack([edges[j][cell[:, j]] for j in range(n)], axis=1)
    hi = np.stack([edges[j][cell[:, j] + 1] for j in range(n)], axis=1)

    def sweep(ulo, uhi, dims):
        S, M = len(lo), len(ulo)
        zlo = np.concatenate([np.repeat(lo, M, axis=0), np.tile(ulo, (S, 1))], axis=1)
        zhi = np.concatenate([np.repeat(hi, M, axis=0), np.tile(uhi, (S, 1))], axis=1)
        norm, best = 0.0, np.zeros(len(dims))
        for a in range(0, len(zlo), 200_000):  # bounded memory; each chunk vectorized
            g = basis.grad_bound(q, zlo[a:a + 200_000], zhi[a:a + 200_000], dims)
            norm = max(norm, float(np.sqrt((g[:, :n] ** 2).sum(axis=1)).max())) if dims[0] == 0 else norm
            best = np.maximum(best, g.max(axis=0))
        return norm, best

    U = np.atleast_2d(inputs)
    if u_box is None:
        norm, best = sweep(U, U, list(range(n + m)))
        return norm, best[:n], best[n:]
    norm, best_x = sweep(U, U, list(range(n)))
    _, best_u = sweep(np.atleast_2d(u_box[0]), np.atleast_2d(u_box[1]), list(range(n, n + m)))
    return norm, best_x, best_u

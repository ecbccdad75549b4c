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


def crn_cost(n_pairs: int, runs: int, system, rate_per_worker=None, workers: int = 1) -> dict:
    """Work, peak memory and time of :func:`fhat_slopes_crn` before it runs.

    2 x n_pairs x runs simulator rows in one batch (both ends of every pair share their draws):
    states, inputs, next states and noise in float64 (a factor 4 for the simulator's work arrays).
    ``seconds`` = rows / (rate x workers) at a measured rate [runs/s of one worker]."""
    rows = 2.0 * float(n_pairs) * float(runs)
    memory = rows * (3 * system.n + system.m) * 8 * 4
    secs = rows / (rate_per_worker * max(1, workers)) if rate_per_worker else None
    return {"pairs": int(n_pairs), "runs": int(runs), "rows": rows, "memory": memory, "seconds": secs,
            "rate": rate_per_worker, "workers": int(workers)}


def crn_cost_text(c: dict) -> str:
    """:func:`crn_cost` as the line ``simgap certify --lhat simulator`` prints first."""
    from ..checks import available_memory, human_bytes
    from ..cover import format_duration
    t = ("time unknown" if c["seconds"] is None else
         f"about {format_duration(c['seconds'])} at {c['rate']:,.0f} runs/s per worker x {c['workers']} "
         "(calibrated here)")
    return (f"estimate: Lhat_fhat from the simulator, {c['pairs']:,} pairs x {c['runs']:,} runs x 2 ends = "
            f"{c['rows']:,.0f} simulator runs; {t}; peak memory about {human_bytes(c['memory'])} "
            f"({human_bytes(available_memory())} available)")


def check_crn_cost(c: dict) -> None:
    """Refuse :func:`fhat_slopes_crn` work over the machine's memory (or a command's time limit)."""
    from ..checks import check_sim_work
    check_sim_work(c["rows"], c["memory"], f"Lhat_fhat from the simulator ({c['pairs']:,} pairs x {c['runs']:,} runs)",
                   "use --lhat data", c["rate"], c["workers"])


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
    lo, hi = s.x_lo.copy(), s.x_hi.copy()
    lo[dims] += h
    hi[dims] -= h
    if np.any(lo > hi) or np.any(lo[dims] >= hi[dims]):
        raise SimgapError(f"Lipschitz (simulator): pair distance h={h:g} too large for X")
    x = lo + rng.random((n_pairs, s.n)) * (hi - lo)
    d = np.zeros((n_pairs, s.n))
    d[:, dims] = rng.standard_normal((n_pairs, len(dims)))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x2 = x + h * d
    U = s.inputs if inputs is None else np.atleast_2d(np.asarray(inputs, float))
    u = U[rng.integers(0, len(U), n_pairs)]
    X = np.repeat(np.concatenate([x, x2]), runs, axis=0)
    U = np.repeat(np.concatenate([u, u]), runs, axis=0)
    noise = sim.draw_noise(n_pairs * runs, rng)
    noise = {k: np.concatenate([v, v]) for k, v in noise.items()}  # the same draws at both ends
    if on_progress is None:
        nxt = sim.step_with_noise(X, U, noise)
    else:
        nxt = sim.step_with_noise_in_parts(X, U, noise, lambda done: on_progress(done, X.shape[0]))
    base = s.diff(nxt, X) if increment else nxt
    m = base.reshape(2, n_pairs, runs, s.n).mean(axis=2)
    return np.abs(s.diff(m[0], m[1])) / h

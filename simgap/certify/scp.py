"""The scenario convex program SCP-N1hat of the paper (one LP per state dimension i).

    min_{q, eta} eta
    s.t.  q^T p(x_r, u) <= eta                         for all K pairs (x_r, u)
          g(x_r, u) + delta_1 <= q^T p(x_r, u)          for all K pairs

with g(x_r, u) = |mean_k fhat_i(x_r, u, w_k) - f_i(x_r, u)| the observed gap (wrapped for angles).

The minimizer is not unique (with a constant term in the basis the optimum is always
eta* = max_r (g_r + delta_1), reached by many q). A documented second stage makes the result
reproducible and as tight as possible on average:

    min_q  mean_r q^T p(x_r, u)   s.t.  g + delta_1 <= q^T p <= eta* + tol_eta

Solving: constraint generation (default). The optimum has about as many active constraints as
variables, so we solve on a few hundred rows, add the most violated rows of the full set, and
repeat until no row is violated by more than ``tol`` (relative to the data scale; it must not
be below the solver's own feasibility tolerance, about 1e-7, or the loop never terminates).
``method="full"`` solves the whole LP at once (same optimum, 10-40x slower at paper scale).
The returned q is then made exactly feasible: any remaining violation v > 0 of the lower
constraint is reported as ``repair`` and added to gamma by the certificate.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import SimgapError

SOLVERS = ("HIGHS", "CLARABEL")


@dataclass
class ScpResult:
    """Solution of SCP-N1hat for one dimension (q in original units)."""

    q: np.ndarray
    eta: float                 # max_r q^T p(x_r, u) of the returned q
    eta_star: float            # optimum of stage 1
    repair: float              # max(0, max_r g_r + delta_1 - q^T p_r) after solving
    status: str
    solver: str
    method: str
    rounds: int
    n_rows_used: int
    seconds: float
    stages: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"eta": self.eta, "eta_star": self.eta_star, "repair": self.repair, "status": self.status,
                "solver": self.solver, "method": self.method, "rounds": self.rounds,
                "n_rows_used": self.n_rows_used, "seconds": self.seconds, "stages": self.stages}


class DependentTerms(SimgapError):
    """The design matrix's column ``column`` is a linear combination of the columns ``on`` (0-based)
    on the data: q would not be unique. :func:`simgap.certify.pipeline.certify` names the terms."""

    def __init__(self, column: int, on: list):
        self.column, self.on = int(column), [int(j) for j in on]
        super().__init__(f"scenario program: basis term {self.column} is linearly dependent on terms {self.on} on "
                         "the data (q would not be unique); remove it")


def dependent_column(P: np.ndarray):
    """(j, on): the first column of ``P`` that is (numerically) a linear combination of the columns
    before it, and those of them with a non-negligible coefficient.

    One QR factorization P = Q R without pivoting: |R_jj| is the part of column j orthogonal to
    columns 0..j-1; below numpy's rank tolerance (largest singular value x max(K, z) x eps) the
    column is dependent, with coefficients R[:j, :j]^-1 R[:j, j]. Falls back to the smallest |R_jj|."""
    R = np.linalg.qr(P, mode="r")
    d = np.abs(np.diag(R))
    tol = np.linalg.svd(R, compute_uv=False)[0] * max(P.shape) * np.finfo(float).eps
    small = np.flatnonzero(d <= tol)
    j = int(small[0]) if small.size else int(np.argmin(d))
    if j == 0:
        return 0, []
    coef = np.linalg.solve(R[:j, :j], R[:j, j])
    return j, [int(i) for i in np.flatnonzero(np.abs(coef) > 1e-6 * np.abs(coef).max())]


def _lp(c, A, b, solver):
    """min c^T v s.t. A v <= b via cvxpy. Returns (v, status)."""
    import cvxpy as cp

    v = cp.Variable(A.shape[1])
    prob = cp.Problem(cp.Minimize(c @ v), [A @ v <= b])
    try:
        prob.solve(solver=solver)
    except cp.error.SolverError as e:
        raise SimgapError(f"scenario program: solver {solver} failed: {e}") from None
    status = prob.status
    if status in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE):
        raise SimgapError("scenario program is infeasible: no q makes q^T p(x_r,u) >= gap + delta_1 at every "
                          "data row (add a constant term '1' to the basis, or more terms)")
    if status in (cp.UNBOUNDED, cp.UNBOUNDED_INACCURATE):
        raise SimgapError("scenario program is unbounded (the basis terms are linearly dependent on the data)")
    if status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or v.value is None:
        raise SimgapError(f"scenario program: solver {solver} returned status {status!r}")
    return np.asarray(v.value, dtype=float), status


def _stage1_rows(Ps, G, W):
    # variables v = [q (p), eta]; rows: Ps q - eta <= 0 and -Ps q <= -G
    p = Ps.shape[1]
    PW = Ps[W]
    A = np.block([[PW, -np.ones((len(W), 1))], [-PW, np.zeros((len(W), 1))]])
    b = np.concatenate([np.zeros(len(W)), -G[W]])
    c = np.zeros(p + 1)
    c[-1] = 1.0
    return c, A, b


def _stage2_rows(Ps, G, W, cap, cobj):
    PW = Ps[W]
    A = np.vstack([PW, -PW])
    b = np.concatenate([np.full(len(W), cap), -G[W]])
    return cobj, A, b


def solve_scp(P: np.ndarray, g: np.ndarray, delta1: float = 0.0, *, method: str = "cg",
              solver: str = "HIGHS", secondary: bool = True, tol: float = 1e-6,
              tol_eta: float = 1e-6, initial_rows: int = 300, add_per_round: int = 100,
              max_rounds: int = 200, seed: int = 0, closed_form: bool = True,
              top_gap_rows: int = 100) -> ScpResult:
    """Solve SCP-N1hat for one state dimension.

    Parameters
    ----------
    P : (K, z) design matrix, P[r, l] = p^(l)(x_r, u_r).
    g : (K,) observed gaps |mean - f| (units of the state dimension).
    delta1 : delta_1i >= 0 (0 for the deterministic baseline).
    method : "cg" (constraint generation, default) or "full".
    solver : "HIGHS" or "CLARABEL" (through cvxpy).
    secondary : run the second stage (min mean q^T p with eta <= eta* + tol_eta).
    closed_form : with a constant basis term, stage 1's optimum is eta* = max_r (g_r + delta1) exactly
        (see the code); False solves stage 1 as an LP anyway (for checking).
    tol, tol_eta : relative to max(g + delta1): the violation accepted by constraint generation
        (keep >= 1e-7, the solvers' feasibility tolerance) and the slack on eta* in stage 2.

    Returns
    -------
    ScpResult with q in the units of P and g.
    """
    t0 = time.perf_counter()
    solver = str(solver).upper()
    if solver not in SOLVERS:
        raise SimgapError(f"unknown LP solver {solver!r}; choose one of {', '.join(SOLVERS)}")
    if method not in ("cg", "full"):
        raise SimgapError(f"unknown scenario-program method {method!r}; choose 'cg' or 'full'")
    P = np.asarray(P, dtype=float)
    g = np.asarray(g, dtype=float)
    if P.ndim != 2 or g.shape != (P.shape[0],) or P.shape[0] == 0:
        raise SimgapError(f"scenario program: need P (K, z) and g (K,), got {P.shape} and {g.shape}")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(g))):
        raise SimgapError("scenario program: NaN or inf in the design matrix or the gaps")
    if not (np.isfinite(delta1) and delta1 >= 0):
        raise SimgapError(f"scenario program: delta_1 must be >= 0, got {delta1}")
    if tol < 1e-7:
        raise SimgapError(f"scenario program: tol {tol:g} is below the solvers' feasibility tolerance 1e-7")
    K, z = P.shape
    # scaling: columns to max |.| = 1, right-hand side to max = 1 (solver tolerances become relative)
    cs = np.abs(P).max(axis=0)
    if np.any(cs == 0):
        raise SimgapError(f"scenario program: basis term(s) {np.flatnonzero(cs == 0).tolist()} are zero on all data")
    Ps = P / cs
    G = g + delta1
    gs = float(G.max()) if G.max() > 0 else 1.0
    G = G / gs
    sample = Ps[np.random.default_rng(seed).choice(K, min(K, 5000), replace=False)]
    if np.linalg.matrix_rank(sample) < z and np.linalg.matrix_rank(Ps) < z:
        col, on = dependent_column(Ps)
        raise DependentTerms(col, on)

    rng = np.random.default_rng(seed)
    if method == "full":
        W = np.arange(K)
    else:
        init = [int(np.argmax(G))] + [int(i) for i in np.argmax(Ps, axis=0)] + [int(i) for i in np.argmin(Ps, axis=0)]
        init += rng.choice(K, size=min(K, initial_rows), replace=False).tolist()
        # the largest gaps are the likely active lower constraints
        init += np.argpartition(-G, min(K - 1, top_gap_rows))[:top_gap_rows].tolist() if top_gap_rows else []
        W = np.unique(init)

    def run(build, check):
        nonlocal W
        rounds = 0
        while True:
            rounds += 1
            c, A, b = build(W)
            v, status = _lp(c, A, b, solver)
            viol = check(v)
            bad = np.flatnonzero(viol > tol)
            if bad.size == 0 or method == "full":
                return v, status, rounds
            if rounds >= max_rounds:
                raise SimgapError(f"scenario program: constraint generation did not converge in {max_rounds} rounds")
            top = bad[np.argsort(viol[bad])[::-1][:add_per_round]]
            W = np.union1d(W, top)

    def viol1(v):
        s = Ps @ v[:-1]
        return np.maximum(G - s, s - v[-1])

    ta = time.perf_counter()
    const_cols = np.flatnonzero(np.all(Ps == Ps[:1], axis=0))
    if len(const_cols) and closed_form:
        # a constant basis term: eta >= q^T p_r >= G_r for every r gives eta* >= max G, and
        # q = (max G) * e_const attains it, so stage 1 has this closed-form optimum
        c0 = int(const_cols[0])
        eta_star = float(G.max())
        qs = np.zeros(z)
        qs[c0] = eta_star / Ps[0, c0]
        st1, r1 = "optimal (closed form: constant basis term)", 0
    else:
        v1, st1, r1 = run(lambda W: _stage1_rows(Ps, G, W), viol1)
        eta_star, qs = float(v1[-1]), v1[:-1]
    status, rounds = st1, r1
    stages = {"stage1": {"rounds": r1, "status": st1, "seconds": time.perf_counter() - ta}}
    if secondary:
        cap = eta_star + tol_eta * max(1.0, abs(eta_star))
        cobj = Ps.mean(axis=0)
        tb = time.perf_counter()

        def viol2(v):
            s = Ps @ v
            return np.maximum(G - s, s - cap)

        qs, st2, r2 = run(lambda W: _stage2_rows(Ps, G, W, cap, cobj), viol2)
        stages["stage2"] = {"rounds": r2, "status": st2, "seconds": time.perf_counter() - tb}
        status = st2
        rounds += r2
    q = qs / cs * gs
    fit = P @ q
    repair = float(max(0.0, np.max(g + delta1 - fit)))
    return ScpResult(q=q, eta=float(np.max(fit)), eta_star=eta_star * gs, repair=repair, status=str(status),
                     solver=solver, method=method, rounds=rounds, n_rows_used=int(len(W)),
                     seconds=time.perf_counter() - t0, stages=stages)

"""Robust invariant ellipsoids: a linear feedback and a set E the certified gap cannot push it out of.

For an invariance specification (stay in the safe box S) the grid abstraction scales
exponentially with the state dimension; this synthesis scales polynomially. It returns

    u(x) = u* + K (x - x*),      E = {x : (x - x*)^T P (x - x*) <= 1},

and a PROOF (:func:`verify_invariant`, separate from the design) that for every x in E and every
disturbance w with |w_i| <= w_max_i, where w_max = sup of the certified gap gamma over E's
bounding box and u(E)'s range,

    (1) E lies in S intersected with X,
    (2) u(x) lies in the input range [u_lo, u_hi] for every x in E,
    (3) f(x, u(x)) + w lies in E.

By the paper's Theorem 1 the mean map m+ = E fhat(m, u(m)) = f(m, u(m)) + w(m) with
|w_i(m)| <= gamma_i(m, u(m)) <= w_max_i then stays in E, hence in S, exactly as for a grid
controller. docs/synthesis.md ("Invariant sets") states each condition and why it implies
invariance.

The proof of (3) (e = x - x*, r = f(x*, u*) - x* the equilibrium's residual):

    f(x, u(x)) - x* = M e + r,   M = int_0^1 J_g(x* + s e) ds  in  [A0 - R, A0 + R]

(mean-value form: the segment from x* to x lies in E, hence in E's bounding box, over which
:class:`~simgap.synthesis.interval_map.IntervalMap` encloses the closed loop's Jacobian J_g). So
with |e_j| <= h_j = sqrt((P^-1)_jj) on E,

    ||e+||_P <= ||P^1/2 A0 P^-1/2||_2 + max over |v| <= R h + |r| + w_max of ||v||_P,

and the second term is a convex function's maximum over a box, attained at one of its vertices
(enumerated for n <= 16; for larger n bounded by sqrt(b^T |P| b)). (3) holds when the sum is <= 1.
The margin is the largest factor s by which w_max could be multiplied with the sum still <= 1.

The design (:func:`design_ellipsoid`) is a convex program in cvxpy: Q = P^-1 maximizing det Q (as det(Q)^(1/n))
subject to the contraction A Q A^T <= rho^2 Q of the linearization A = A_f + B_f K (an LMI),
Q_ii <= (half-width of S around x*)^2, (K Q K^T)_jj <= (input half-range around u*)^2 and
Q >= (n / beta^2) diag(d^2) (then ||d'||_P <= beta for every |d'| <= d), with d the disturbance
(gap plus nonlinear remainder) measured on the previous candidate. Several contraction rates rho
are tried; only a candidate that passes :func:`verify_invariant` is kept.
"""

from __future__ import annotations

import functools
import resource
import time
import warnings
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import SimgapError
from ..systems import System
from .interval_map import IntervalMap
from .spec import Spec

#: candidate contraction rates, as fractions of the way from the LQR loop's spectral radius to 1
RHO_FRACTIONS = (0.1, 0.3, 0.5, 0.7, 0.85)
#: design rounds per rate (the disturbance is re-measured on each candidate)
ROUNDS = 3
#: scales c of each designed ellipsoid that are verified (E_c = x* + c (E - x*)): the nonlinear
#: remainder shrinks with c, the gap's share grows as 1/c
SCALES = tuple(0.8 ** k for k in range(32))
#: an equilibrium's residual |f(x*, u*) - x*| may be at most this fraction of the safe box's width
EQ_TOL = 1e-6
#: vertices of the disturbance box are enumerated up to this dimension (2^(n-1) of them)
MAX_VERTEX_DIM = 16
SOLVERS = ("CLARABEL", "SCS")
GAP_FALLBACK_NOTE = ("max of gamma_upper_box over the certificate's inputs that bracket u(E): inputs between "
                     "grid values are NOT covered (the certificate has no input Lipschitz term)")


# ---------------------------------------------------------------------------------------
# equilibrium, linearization, LQR
# ---------------------------------------------------------------------------------------

def input_range(system: System, gap=None):
    """(u_lo, u_hi): the hull of the system's inputs, restricted to those the gap is certified for."""
    from .abstraction import certified_input_mask
    U = system.inputs
    keep = certified_input_mask(system, gap) if gap is not None and hasattr(gap, "gamma_upper_box") else None
    if keep is not None:
        if not keep.any():
            raise SimgapError("the certificate covers none of the system's inputs")
        U = U[keep]
    return U.min(axis=0), U.max(axis=0)


def find_equilibrium(system: System, lo, hi, u_lo, u_hi, x_star=None, u_star=None):
    """(x*, u*, residual r = f(x*, u*) - x*): the given pair checked, or one found near the centre of
    [lo, hi] x [u_lo, u_hi] by least squares on f(x, u) - x. SimgapError when the pair lies outside
    the boxes or is not an equilibrium (residual above EQ_TOL times the box width, printed)."""
    n, m = system.n, system.m
    names = system.state_names
    tol = EQ_TOL * (hi - lo)
    if (x_star is None) != (u_star is None):
        raise SimgapError("invariant set: give both x_star and u_star, or neither (simgap then finds an equilibrium)")
    if x_star is not None:
        x_star = np.asarray(x_star, dtype=float).ravel()
        u_star = np.asarray(u_star, dtype=float).ravel()
        if x_star.shape != (n,) or u_star.shape != (m,):
            raise SimgapError(f"invariant set: x_star needs {n} values and u_star {m}, got {x_star.size} and {u_star.size}")
        out = np.flatnonzero((x_star < lo) | (x_star > hi))
        if out.size:
            i = int(out[0])
            raise SimgapError(f"invariant set: the equilibrium x_star {x_star.tolist()} lies outside the safe set: "
                              f"{names[i]} = {x_star[i]:g} not in [{lo[i]:g}, {hi[i]:g}]")
        outu = np.flatnonzero((u_star < u_lo) | (u_star > u_hi))
        if outu.size:
            j = int(outu[0])
            raise SimgapError(f"invariant set: u_star {u_star.tolist()} lies outside the input range "
                              f"[{u_lo[j]:g}, {u_hi[j]:g}] of {system.input_names[j]}")
    else:
        from scipy.optimize import least_squares
        z0 = np.concatenate([0.5 * (lo + hi), 0.5 * (u_lo + u_hi)])
        zlo, zhi = np.concatenate([lo, u_lo]), np.concatenate([hi, u_hi])
        flat = zhi <= zlo  # a fixed input or state: least_squares needs lo < hi
        zlo_, zhi_ = np.where(flat, zlo - 1e-12, zlo), np.where(flat, zhi + 1e-12, zhi)
        sol = least_squares(lambda z: system.f(z[None, :n], z[None, n:])[0] - z[:n], z0, bounds=(zlo_, zhi_),
                            xtol=1e-15, ftol=1e-15, gtol=1e-15)
        z = np.clip(sol.x, zlo, zhi)
        x_star, u_star = z[:n], z[n:]
    r = system.f(x_star[None], u_star[None])[0] - x_star
    bad = np.flatnonzero(np.abs(r) > tol)
    if bad.size:
        what = "the given" if x_star is not None else "no equilibrium found in the safe set; the closest"
        raise SimgapError(f"invariant set: {what} pair x* = {np.round(x_star, 6).tolist()}, u* = "
                          f"{np.round(u_star, 6).tolist()} is not an equilibrium of the nominal model: residual "
                          f"f(x*, u*) - x* = {np.array2string(r, precision=3)} (tolerance "
                          f"{np.array2string(tol, precision=2)}, {EQ_TOL:g} of the safe box's width)")
    return x_star, u_star, r


def linearize(system: System, x_star, u_star):
    """(A, B): central differences of f at (x*, u*), steps 1e-6 x max(1, scale of X / U)."""
    n, m = system.n, system.m
    hx = 1e-6 * np.maximum(1.0, system.x_hi - system.x_lo)
    hu = 1e-6 * np.maximum(1.0, np.ptp(system.inputs, axis=0))
    Z = np.concatenate([np.eye(n) * hx, -np.eye(n) * hx])
    X = x_star + Z
    fx = system.f(X, np.repeat(u_star[None], 2 * n, axis=0))
    A = ((fx[:n] - fx[n:]) / (2 * hx)[:, None]).T   # row j: the step in x_j
    W = np.concatenate([np.eye(m) * hu, -np.eye(m) * hu])
    fu = system.f(np.repeat(x_star[None], 2 * m, axis=0), u_star + W)
    B = ((fu[:m] - fu[m:]) / (2 * hu)[:, None]).T
    return A, B


def check_stabilizable(A, B, names=None) -> None:
    """SimgapError naming the first mode with |lambda| >= 1 that B cannot reach (PBH test)."""
    n = A.shape[0]
    lam, V = np.linalg.eig(A)
    for k, l in enumerate(lam):
        if abs(l) < 1 - 1e-9:
            continue
        M = np.concatenate([A - l * np.eye(n), B], axis=1)
        s = np.linalg.svd(M, compute_uv=False)
        if s[-1] <= 1e-9 * max(1.0, s[0]):
            v = np.real_if_close(V[:, k]).round(3).tolist()
            raise SimgapError(f"invariant set: the linearization is not stabilizable: its mode lambda = {l:.4g} "
                              f"(|lambda| = {abs(l):.4g} >= 1, eigenvector {v}"
                              + (f" over {list(names)}" if names is not None else "") + ") cannot be moved by the input")


def lqr_gain(A, B, q, r):
    """K of the discrete LQR u = K (x - x*) (sign included) with weights diag(q), diag(r)."""
    from scipy.linalg import solve_discrete_are
    try:
        X = solve_discrete_are(A, B, np.diag(q), np.diag(r))
    except (np.linalg.LinAlgError, ValueError) as e:
        raise SimgapError(f"invariant set: the discrete Riccati equation has no stabilizing solution ({e})") from None
    return -np.linalg.solve(B.T @ X @ B + np.diag(r), B.T @ X @ A)


def spectral_radius(A) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(A))))


# ---------------------------------------------------------------------------------------
# P-norms of boxes
# ---------------------------------------------------------------------------------------

@functools.lru_cache(maxsize=8)
def _signs(n: int) -> np.ndarray:
    """(2^(n-1), n) sign patterns with the first entry +1 (v and -v have the same P-norm)."""
    k = np.arange(2 ** (n - 1))[:, None]
    bits = (k >> np.arange(n - 1)[None, :]) & 1
    return np.concatenate([np.ones((k.shape[0], 1)), 1.0 - 2.0 * bits], axis=1)


def _quad(V, P, W) -> np.ndarray:
    """(k,) rows v_k^T P w_k (a BLAS product; einsum over three operands is far slower here)."""
    return ((V @ P) * W).sum(axis=1)


def box_pnorm(P, b) -> float:
    """max over |v| <= b (elementwise) of sqrt(v^T P v): a convex function's maximum over a box is at a
    vertex; vertices enumerated for n <= MAX_VERTEX_DIM, else the upper bound sqrt(b^T |P| b)."""
    b = np.asarray(b, dtype=float)
    if not np.all(np.isfinite(b)):
        return np.inf
    if b.size <= MAX_VERTEX_DIM:
        V = _signs(b.size) * b
        return float(np.sqrt(max(0.0, _quad(V, P, V).max())))
    return float(np.sqrt(b @ np.abs(P) @ b))


def gap_scale(P, a, c, budget) -> float:
    """Largest s >= 0 with max over |v| <= a + s c of ||v||_P <= budget (a, c >= 0); inf if c = 0
    and a fits, 0 if a alone does not fit."""
    a, c = np.asarray(a, dtype=float), np.asarray(c, dtype=float)
    if budget <= 0 or not np.all(np.isfinite(a)) or box_pnorm(P, a) > budget:
        return 0.0
    if not np.any(c > 0):
        return np.inf
    if a.size <= MAX_VERTEX_DIM:
        S = _signs(a.size)
        A_, C_ = S * a, S * c
        qa = _quad(C_, P, C_)
        qb = 2 * _quad(A_, P, C_)
        qc = _quad(A_, P, A_) - budget ** 2
    else:
        Pa = np.abs(P)
        qa, qb, qc = np.array([c @ Pa @ c]), np.array([2 * a @ Pa @ c]), np.array([a @ Pa @ a - budget ** 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        roots = np.where(qa > 0, (-qb + np.sqrt(np.maximum(qb ** 2 - 4 * qa * qc, 0.0))) / (2 * qa), np.inf)
    return float(max(0.0, roots.min()))


# ---------------------------------------------------------------------------------------
# the gap over a box
# ---------------------------------------------------------------------------------------

def gap_bound(gap, n: int, lo, hi, u_lo, u_hi):
    """(w_max (n,), how): a sound upper bound of gamma_i over [lo, hi] x [u_lo, u_hi].

    ``gap``: None (nominal: 0), a constant vector, or a certificate: its ``gamma_sup`` (inputs
    between grid values covered) when it was certified for continuous inputs, else the fallback
    GAP_FALLBACK_NOTE describes (labelled: it does not cover the inputs between grid values).
    """
    if gap is None:
        return np.zeros(n), "none (nominal model)"
    if not hasattr(gap, "gamma_upper_box"):
        g = np.asarray(gap, dtype=float).ravel()
        g = np.full(n, float(g[0])) if g.size == 1 else g
        if g.shape != (n,) or not np.all(np.isfinite(g)) or np.any(g < 0):
            raise SimgapError(f"gap: a constant gamma needs 1 or {n} finite values >= 0, got {np.asarray(gap).tolist()}")
        return g, "a given constant bound per period (not a certificate)"
    lo, hi = np.asarray(lo, float)[None], np.asarray(hi, float)[None]
    u_lo, u_hi = np.asarray(u_lo, float), np.asarray(u_hi, float)
    if hasattr(gap, "require_inside"):  # gamma's sup over a box outside the certificate's region is refused
        gap.require_inside(lo[0], hi[0], "the invariant set's bounding box")
    if getattr(gap, "continuous", False):  # certified between the grid's inputs too (its input Lipschitz term)
        return np.asarray(gap.gamma_sup(lo[0], hi[0], u_lo, u_hi), dtype=float).ravel(), \
            "gamma_sup over E's bounding box and u(E)'s range (inputs between grid values included)"
    # a certificate made for its grid inputs only: the fallback below, labelled
    U = np.atleast_2d(np.asarray(gap.inputs, dtype=float))
    keep = np.ones(U.shape[0], dtype=bool)
    for j in range(U.shape[1]):  # per input dimension the grid values that bracket [u_lo, u_hi]
        vals = np.unique(U[:, j])
        below, above = vals[vals <= u_lo[j]], vals[vals >= u_hi[j]]
        a = below.max() if below.size else vals.min()
        b = above.min() if above.size else vals.max()
        keep &= (U[:, j] >= a) & (U[:, j] <= b)
    Uk = U[keep]
    g = np.asarray(gap.gamma_upper_box(np.repeat(lo, len(Uk), axis=0), np.repeat(hi, len(Uk), axis=0), Uk),
                   dtype=float).max(axis=0)
    return g, f"{GAP_FALLBACK_NOTE} ({len(Uk)} inputs)"


# ---------------------------------------------------------------------------------------
# verification: the proof
# ---------------------------------------------------------------------------------------

@dataclass
class Verification:
    """The result of :func:`verify_invariant` (all in state units per period, P-norms unitless)."""

    ok: bool
    conditions: list                  # [{name, value, limit, ok, what}]
    contraction: float                # ||P^1/2 A0 P^-1/2||_2
    remainder: np.ndarray             # R h: the Jacobian enclosure's radius times E's half-widths
    residual: np.ndarray              # f(x*, u*) - x*
    w_max: np.ndarray                 # the gap's bound over E
    gap_how: str
    nonlinear_norm: float             # max over |v| <= R h + |r| of ||v||_P
    total: float                      # contraction + max over |v| <= R h + |r| + w_max of ||v||_P
    gap_scale: float                  # largest s with invariance for s * w_max (inf without a gap)
    box_lo: np.ndarray
    box_hi: np.ndarray
    u_lo: np.ndarray
    u_hi: np.ndarray

    def failed(self) -> list:
        return [c for c in self.conditions if not c["ok"]]

    def to_dict(self) -> dict:
        f = lambda a: np.asarray(a, dtype=float).tolist()
        return {"ok": bool(self.ok), "conditions": self.conditions, "contraction": self.contraction,
                "nonlinear_norm": self.nonlinear_norm, "total": self.total,
                "gap_scale": "inf" if np.isinf(self.gap_scale) else self.gap_scale,
                "remainder": f(self.remainder), "residual": f(self.residual), "w_max": f(self.w_max),
                "gap_how": self.gap_how, "box_lo": f(self.box_lo), "box_hi": f(self.box_hi),
                "u_lo": f(self.u_lo), "u_hi": f(self.u_hi)}


def verify_invariant(system: System, x_star, u_star, K, P, safe_lo, safe_hi, u_lo, u_hi, gap=None,
                     imap: Optional[IntervalMap] = None) -> Verification:
    """Prove (or refute the proof of) conditions (1)-(3) of the module docstring for E, u(x), gap.

    Independent of how P and K were found. ``gap``: None (nominal), a constant vector or a
    certificate (:func:`gap_bound`). The state box is S intersected with X.
    """
    return verify_scaled(system, x_star, u_star, K, P, safe_lo, safe_hi, u_lo, u_hi, gap, imap, (1.0,))[0]


def verify_scaled(system: System, x_star, u_star, K, P, safe_lo, safe_hi, u_lo, u_hi, gap=None,
                  imap: Optional[IntervalMap] = None, scales=(1.0,)) -> list:
    """:func:`verify_invariant` for the ellipsoids E_c = {e^T (P / c^2) e <= 1}, c in ``scales``
    (one batched interval evaluation); a list of Verification, one per scale."""
    n, m = system.n, system.m
    x_star, u_star = np.asarray(x_star, float), np.asarray(u_star, float)
    K, P = np.asarray(K, float).reshape(m, n), np.asarray(P, float)
    P = 0.5 * (P + P.T)
    lo = np.maximum(np.asarray(safe_lo, float), system.x_lo)
    hi = np.minimum(np.asarray(safe_hi, float), system.x_hi)
    u_lo, u_hi = np.asarray(u_lo, float), np.asarray(u_hi, float)
    ev = np.linalg.eigvalsh(P)
    if not np.all(ev > 0):
        raise SimgapError("invariant set: P is not positive definite")
    Q1 = np.linalg.inv(P)
    h1 = np.sqrt(np.diag(Q1))                                      # |e_j| <= c h1_j on E_c
    hu1 = np.sqrt(np.maximum(np.einsum("ji,ik,jk->j", K, Q1, K), 0.0))  # |K_j e| <= c hu1_j on E_c
    c = np.asarray(scales, dtype=float)
    blo, bhi = x_star - c[:, None] * h1, x_star + c[:, None] * h1
    ulo_E, uhi_E = u_star - c[:, None] * hu1, u_star + c[:, None] * hu1
    imap = imap if imap is not None else IntervalMap(system)
    _, _, Jc, Jr = imap.closed_loop(blo, bhi, ulo_E, uhi_E, K)
    r = system.f(x_star[None], u_star[None])[0] - x_star
    A_lin = None
    try:  # a second centre for the mean-value form: the linearization at x* (both are valid bounds)
        A_f, B_f = linearize(system, x_star, u_star)
        A_lin = A_f + B_f @ K
    except Exception:  # the midpoint form alone is still a proof
        A_lin = None
    return [_check(system, x_star, u_star, P / ci ** 2, ci * h1, ci * hu1, lo, hi, u_lo, u_hi, Jc[k], Jr[k], A_lin, r,
                   gap) for k, ci in enumerate(c)]


def _pnorm_matrix(P, A) -> float:
    """||P^1/2 A P^-1/2||_2."""
    ev, U_ = np.linalg.eigh(P)
    Ph = np.sqrt(ev)
    return float(np.linalg.norm(((U_ * Ph) @ U_.T) @ A @ ((U_ / Ph) @ U_.T), 2))


def _check(system, x_star, u_star, P, h, hu, lo, hi, u_lo, u_hi, Jc, Jr, A_lin, r, gap) -> Verification:
    """Conditions (1)-(3) for one ellipsoid, given the enclosure [Jc +- Jr] over its bounding box."""
    n = system.n
    blo, bhi = x_star - h, x_star + h
    ulo_E, uhi_E = u_star - hu, u_star + hu
    conds = []

    def cond(name, value, limit, what):
        conds.append({"name": name, "value": float(value), "limit": float(limit), "ok": bool(value <= limit),
                      "what": what})

    # (1) E in S and X: the bounding box of an ellipsoid is x* +- sqrt(diag P^-1), exactly
    room = np.minimum(x_star - lo, hi - x_star)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(room > 0, h / room, np.inf)
    i = int(np.argmax(ratio))
    cond("E inside the safe set", ratio[i], 1.0,
         f"largest half-width over room: {system.state_names[i]} +- {h[i]:.4g} around {x_star[i]:.4g} in "
         f"[{lo[i]:g}, {hi[i]:g}]")
    for a in system.angle_dims:  # f wraps angles to [-pi, pi): E must not reach the seam
        cond(f"E away from the angle seam ({system.state_names[a]})", max(abs(blo[a]), abs(bhi[a])) / np.pi,
             1.0 - 1e-12, "angles are wrapped after each period")
    # (2) u(E) in the input range: u_j - u*_j = K_j e ranges over +- sqrt(K_j P^-1 K_j^T) on E
    uroom = np.minimum(u_star - u_lo, u_hi - u_star)
    with np.errstate(divide="ignore", invalid="ignore"):
        uratio = np.where(uroom > 0, hu / uroom, np.where(hu > 0, np.inf, 0.0))
    j = int(np.argmax(uratio))
    cond("u(E) inside the input range", uratio[j], 1.0,
         f"{system.input_names[j]} = {u_star[j]:.4g} +- {hu[j]:.4g} in [{u_lo[j]:g}, {u_hi[j]:g}]")

    # (3) invariance: e+ = M e + r + w with M in [A0 - R, A0 + R]; two centres A0 are tried (the
    # enclosure's midpoint, and the linearization with R widened by |Jc - A_lin|); the one that proves (3),
    # else the one with the larger gap margin, is kept (each is a valid bound on its own)
    w, how = gap_bound(gap, n, blo, bhi, ulo_E, uhi_E)
    best = None
    for A0, R in ((Jc, Jr),) + (((A_lin, Jr + np.abs(Jc - A_lin)),) if A_lin is not None else ()):
        contraction = _pnorm_matrix(P, A0)
        with np.errstate(invalid="ignore"):
            rem = R @ h
        rem = np.where(np.isfinite(rem), rem, np.inf)
        base = rem + np.abs(r)
        nl = box_pnorm(P, base)
        total = contraction + box_pnorm(P, base + w)
        cand = (total, contraction, rem, nl, gap_scale(P, base, w, 1.0 - contraction))
        if best is None or (total <= 1.0, cand[4], -total) > (best[0] <= 1.0, best[4], -best[0]):
            best = cand
    total, contraction, rem, nl, scale = best
    cond("f(x, u(x)) + w stays in E", total, 1.0,
         f"contraction {contraction:.6f} + nonlinear remainder and residual {nl:.3g} + gap -> {total:.6f}")
    ok = all(c["ok"] for c in conds)
    return Verification(ok=ok, conditions=conds, contraction=contraction, remainder=rem, residual=r, w_max=w,
                        gap_how=how, nonlinear_norm=nl, total=total, gap_scale=scale, box_lo=blo, box_hi=bhi,
                        u_lo=ulo_E, u_hi=uhi_E)


# ---------------------------------------------------------------------------------------
# design: one convex program per contraction rate
# ---------------------------------------------------------------------------------------

def design_ellipsoid(A_cl, K, x_star, u_star, lo, hi, u_lo, u_hi, rho: float, d, solver: str = "CLARABEL",
                     objective: str = "volume", cache: Optional[dict] = None):
    """(P or None, solver status): the largest-volume ellipsoid (module docstring's program), or with
    ``objective="gap"`` the one that tolerates the largest multiple t of the disturbance d
    (maximize t subject to Q >= t (n / beta^2) diag(d^2) and the same constraints).

    ``cache``: a dict kept by the caller across calls with the same A_cl, K, boxes and solver; rho
    and d are cvxpy parameters, so each program is compiled once and solved again with new values.
    """
    import cvxpy as cp
    n = A_cl.shape[0]
    room = np.minimum(x_star - lo, hi - x_star)
    uroom = np.minimum(u_star - u_lo, u_hi - u_star)
    if np.any(room <= 0):
        return None, "x* on the boundary of the safe set"
    d = np.asarray(d, dtype=float)
    nz = d > 0
    objective = objective if nz.any() else "volume"
    key = (objective, bool(nz.any()))
    cache = {} if cache is None else cache
    if key not in cache:
        Q = cp.Variable((n, n), symmetric=True)
        rho2 = cp.Parameter(nonneg=True)
        Dd = cp.Parameter((n, n), PSD=True)
        AQ = A_cl @ Q
        cons = [cp.bmat([[rho2 * Q, AQ], [AQ.T, Q]]) >> 0, cp.diag(Q) <= room ** 2]
        for j in range(K.shape[0]):
            if np.any(K[j] != 0):
                cons.append(K[j] @ Q @ K[j] <= uroom[j] ** 2)
        if objective == "gap":
            t = cp.Variable(nonneg=True)
            cons.append(Q - t * Dd >> 0)
            prob = cp.Problem(cp.Maximize(t), cons)
        else:
            if nz.any():
                cons.append(Q >> Dd)
            # max det(Q)^(1/n) (the log det's maximizer) through a lower-triangular L with
            # [[Q, L], [L^T, diag(L)]] >= 0, det Q >= prod diag(L): power cones instead of log_det's
            # exponential cones, on which Clarabel stops without progress for some systems
            L = cp.Variable((n, n))
            cons += [cp.upper_tri(L) == 0, cp.bmat([[Q, L], [L.T, cp.diag(cp.diag(L))]]) >> 0]
            prob = cp.Problem(cp.Maximize(cp.geo_mean(cp.diag(L))), cons)
        cache[key] = (prob, Q, rho2, Dd)
    prob, Q, rho2, Dd = cache[key]
    rho2.value = rho ** 2
    Dd.value = np.diag(np.where(nz, nz.sum() / (1.0 - rho) ** 2 * d ** 2, 0.0))
    tried = []
    for name in (solver,) + tuple(x for x in SOLVERS if x != solver and x in cp.installed_solvers()):
        # the other solver when the first one fails (Clarabel stops with "insufficient progress" on some
        # badly conditioned programs that SCS solves); the proof decides either way
        try:
            with warnings.catch_warnings():  # "may be inaccurate": the status says it, and the proof decides
                warnings.simplefilter("ignore", UserWarning)
                # as a fallback SCS gets a bounded number of iterations (unbounded, it took 75 s on a
                # program near the contraction limit); an inaccurate design is still checked by the proof
                prob.solve(solver=name, **({"max_iters": 2000} if name == "SCS" and name != solver else {}))
        except cp.error.SolverError:
            tried.append(f"{name}: solver error")
            continue
        if prob.status in ("optimal", "optimal_inaccurate") and Q.value is not None:
            break
        tried.append(f"{name}: {prob.status}")
    else:
        return None, "; ".join(tried)
    status = str(prob.status) + (f" ({name}; {'; '.join(tried)})" if tried else "")
    Qv = 0.5 * (Q.value + Q.value.T)
    # the solver meets the box constraints to its tolerance only: scale E into them exactly
    hu2 = np.einsum("ji,ik,jk->j", K, Qv, K)
    with np.errstate(divide="ignore"):
        c = min(1.0, float(np.min(room ** 2 / np.diag(Qv))),
                float(np.min(np.where(hu2 > 0, uroom ** 2 / np.maximum(hu2, 1e-300), np.inf))))
    Qv = Qv * c * (1 - 1e-9)
    ev = np.linalg.eigvalsh(Qv)
    if ev.min() <= 1e-14 * max(1.0, ev.max()):
        return None, "degenerate ellipsoid (P^-1 not positive definite)"
    return np.linalg.inv(Qv), status


# ---------------------------------------------------------------------------------------
# synthesis front end
# ---------------------------------------------------------------------------------------

@dataclass
class InvariantSetResult:
    """``controller`` (None when no candidate was proved), the proof of the kept candidate, stats."""

    controller: object
    verification: Optional[Verification]
    stats: dict = field(default_factory=dict)

    @property
    def empty(self) -> bool:
        return self.controller is None

    def summary(self) -> str:
        s = self.stats
        lines = [f"system        {s['system']} (tau = {s['tau']:g} s), invariant-set synthesis",
                 f"equilibrium   x* = {s['x_star']}, u* = {s['u_star']} (residual {s['residual_max']:.2g})",
                 f"feedback      K = {s['K']} ({s['K_how']}); linearization's closed loop spectral radius "
                 f"{s['spectral_radius']:.6f}",
                 f"gap           {s['gap_how']}",
                 f"candidates    {s['candidates']} designs ({s['solver']}), {s['proved']} proved"]
        v = s.get("verification")
        if v is not None:
            lines.append(f"proof         contraction {v['contraction']:.6f} + remainder/residual {v['nonlinear_norm']:.3g} "
                         f"+ gap -> {v['total']:.6f} (<= 1 needed)")
            lines.append(f"gap over E    w_max = {np.round(v['w_max'], 6).tolist()} per period")
        if not self.empty:
            lines.append(f"set E         semi-axes (bounding box half-widths) {s['half_widths']}, volume {s['volume']:.4g}")
            lines.append(f"margin        gamma could be {s['gap_scale_text']} x larger with E still invariant")
            if s.get("x0_inside") is not None:
                lines.append(f"x0            {'inside' if s['x0_inside'] else 'OUTSIDE'} E")
        else:
            lines.append(f"note          {s['diagnosis']}")
        lines.append(f"time          {s['seconds']:.3f} s, peak memory {s['peak_rss_mb']:.0f} MB (process max RSS)")
        return "\n".join(lines)


def _weights(value, size: int, what: str) -> np.ndarray:
    """One LQR weight or ``size`` of them, as a vector; SimgapError naming ``what`` otherwise."""
    try:
        v = np.asarray(value, dtype=float).ravel()
    except (TypeError, ValueError):
        raise SimgapError(f"invariant set: {what} must be numbers, got {value!r}") from None
    if v.size not in (1, size) or not np.all(np.isfinite(v)):
        raise SimgapError(f"invariant set: {what} = {value!r}: need one finite weight or {size}, got {v.size}")
    return np.broadcast_to(v, (size,)).copy()


def _parse_matrix(K, m, n):
    try:
        Kg = np.asarray(K, dtype=float)
    except (TypeError, ValueError):  # also a ragged list of rows
        raise SimgapError(f"invariant set: K must be a {m} x {n} matrix of numbers (rows of equal length), "
                          f"got {K!r}") from None
    if Kg.ndim == 1 and m == 1:
        Kg = Kg[None]
    if Kg.shape != (m, n):
        raise SimgapError(f"invariant set: K must have shape {m} x {n} (inputs x states), got {list(Kg.shape)}")
    if not np.all(np.isfinite(Kg)):
        raise SimgapError("invariant set: K must be finite")
    return Kg


def synthesize_invariant_set(system: System, spec: Spec, gap=None, *, x_star=None, u_star=None, K=None,
                             lqr_q=None, lqr_r=None, solver: str = "CLARABEL", x0=None, log=None) -> InvariantSetResult:
    """Design and prove a robust invariant ellipsoid with a linear feedback (module docstring).

    Parameters
    ----------
    system : System
        The nominal model f (a system file: its formulas are differentiated in intervals).
    spec : Spec
        An ``invariance`` specification without obstacles (the safe box S).
    gap : None, constant vector (n,), or a Certificate
        The certified gap gamma per period (state units); None: the nominal model alone.
    x_star, u_star : optional
        The equilibrium; default: found by least squares near the centre of S.
    K : (m, n), optional
        The feedback gain (u = u* + K (x - x*)); default: discrete LQR of the linearization with
        Bryson's weights diag(1 / half-width^2) (``lqr_q``, ``lqr_r`` override them).
    solver : "CLARABEL" or "SCS"
        cvxpy's semidefinite solver.
    x0 : optional
        An initial state recorded in the controller (and reported inside E or not).
    log : callable(str), optional
        Receives a line per design round (the contraction rate, the gap measured, proved or not), an
        estimate after the first, and (:class:`~simgap.progress.StageLog`) a line at least every 10 s.

    Returns
    -------
    InvariantSetResult
        ``controller`` is None when no candidate passes :func:`verify_invariant`;
        ``stats['diagnosis']`` then names the failing condition and by how much.
    """
    from ..progress import StageLog
    if not isinstance(log, StageLog):
        log = StageLog("", log)
    with log:
        return _synthesize_invariant_set(system, spec, gap, x_star, u_star, K, lqr_q, lqr_r, solver, x0, log)


def _synthesize_invariant_set(system, spec, gap, x_star, u_star, K, lqr_q, lqr_r, solver, x0, log):
    import cvxpy as cp
    t0 = time.perf_counter()
    if spec.kind != "invariance":
        raise SimgapError(f"the invariant-set synthesis handles invariance specifications only, not {spec.kind!r} "
                          f"(use the grid synthesis for reach-avoid)")
    if spec.obstacles:
        raise SimgapError("the invariant-set synthesis handles a safe box without obstacles")
    if solver not in SOLVERS:
        raise SimgapError(f"invariant set: solver must be one of {', '.join(SOLVERS)}, got {solver!r}")
    if solver not in cp.installed_solvers():
        raise SimgapError(f"invariant set: cvxpy's solver {solver} is not installed (installed: "
                          f"{', '.join(cp.installed_solvers())})")
    from ..checks import one_of
    for key, weights in (("lqr_q", lqr_q), ("lqr_r", lqr_r)):
        one_of({"K": K, key: weights}, "the feedback gain", "K is used as given; lqr_q / lqr_r design it otherwise")
    if gap is not None and hasattr(gap, "check_system"):
        gap.check_system(system)
    if gap is not None and hasattr(gap, "require_inside"):  # a local certificate: E lies in S, S in its region
        gap.require_inside(np.maximum(spec.safe.lo, system.x_lo), np.minimum(spec.safe.hi, system.x_hi),
                           "the invariant-set synthesis's safe set (E lies in it)")
    imap = IntervalMap(system)  # refuses models without interval derivatives before any work
    n, m = system.n, system.m
    lo = np.maximum(spec.safe.lo, system.x_lo)
    hi = np.minimum(spec.safe.hi, system.x_hi)
    if np.any(lo >= hi):
        raise SimgapError("invariant set: the safe box does not overlap X")
    u_lo, u_hi = input_range(system, gap)
    x_star, u_star, r = find_equilibrium(system, lo, hi, u_lo, u_hi, x_star, u_star)
    A, B = linearize(system, x_star, u_star)
    room = np.minimum(x_star - lo, hi - x_star)
    uroom = np.minimum(u_star - u_lo, u_hi - u_star)
    if np.any(room <= 0):
        i = int(np.argmin(room))
        raise SimgapError(f"invariant set: the equilibrium lies on the safe set's boundary in {system.state_names[i]}")
    if np.any(uroom <= 0):
        raise SimgapError(f"invariant set: u* = {u_star.tolist()} lies on the boundary of the input range "
                          f"[{u_lo.tolist()}, {u_hi.tolist()}]: no room for feedback. Levers: a wider input range "
                          f"(the system's inputs, all certified) or another x_star / u_star")
    if K is None:
        check_stabilizable(A, B, system.state_names)
        q = 1.0 / room ** 2 if lqr_q is None else _weights(lqr_q, n, "lqr_q")
        rr = 1.0 / uroom ** 2 if lqr_r is None else _weights(lqr_r, m, "lqr_r")
        if np.any(q < 0) or np.any(rr <= 0):
            raise SimgapError("invariant set: LQR weights need q >= 0 and r > 0")
        K, K_how = lqr_gain(A, B, q, rr), "discrete LQR of the linearization"
    else:
        K, K_how = _parse_matrix(K, m, n), "given"
    A_cl = A + B @ K
    rho0 = spectral_radius(A_cl)
    if rho0 >= 1:
        raise SimgapError(f"invariant set: K does not stabilize the linearization at x*: the closed loop's spectral "
                          f"radius is {rho0:.6g} >= 1")

    cands, statuses = [], []

    programs: dict = {}  # compiled once per objective, solved again for each rho and d

    rounds = {"done": 0, "max": len(RHO_FRACTIONS) * (ROUNDS + 1)}

    def attempt(rho, d, objective):
        t1 = time.perf_counter()
        log.doing(f"ellipsoid design at contraction rate {rho:.4f} ({objective}), then its proof at "
                  f"{len(SCALES)} scales")
        P, status = design_ellipsoid(A_cl, K, x_star, u_star, lo, hi, u_lo, u_hi, rho, d, solver, objective,
                                     programs)
        statuses.append(status)
        if P is None:
            return None
        vs = verify_scaled(system, x_star, u_star, K, P, lo, hi, u_lo, u_hi, gap, imap, SCALES)
        cands.extend((P / c ** 2, v, rho) for c, v in zip(SCALES, vs))
        rounds["done"] += 1
        best = max(v.gap_scale for v in vs)
        log(f"rate {rho:.4f} ({objective}): {'proved' if any(v.ok for v in vs) else 'not proved'}, margin "
            f"{'any' if np.isinf(best) else f'{best:.3g}'} ({time.perf_counter() - t1:.1f} s)")
        if rounds["done"] == 1:
            log(f"estimate: at most {rounds['max'] - 1} more rounds of about {time.perf_counter() - t1:.1f} s "
                f"each (fewer when a rate proves)")
        return vs

    for frac in RHO_FRACTIONS:
        rho = rho0 + frac * (1.0 - rho0)
        d = np.zeros(n)
        proved = False
        for _ in range(ROUNDS):
            vs = attempt(rho, d, "volume")
            if vs is None:
                break
            if any(v.ok for v in vs):
                proved = True
                break
            # the gap (and residual) measured on the candidate closest to a proof; the nonlinear
            # remainder is left to the scaling (it shrinks with the set, the gap does not)
            vb = max(vs, key=lambda v: (v.gap_scale, -v.total))
            d_new = np.abs(vb.residual) + vb.w_max
            if not np.all(np.isfinite(d_new)) or not np.any(d_new > d):
                break
            d = np.maximum(d, d_new)
        if not proved and np.any(d > 0):  # the design that tolerates the largest multiple of the gap
            attempt(rho, d, "gap")
    proved = [c for c in cands if c[1].ok]
    stats = {"system": system.name, "tau": system.tau, "x_star": np.round(x_star, 9).tolist(),
             "u_star": np.round(u_star, 9).tolist(), "residual_max": float(np.abs(r).max()),
             "K": np.round(K, 6).tolist(), "K_how": K_how, "spectral_radius": rho0, "solver": solver,
             "candidates": len(cands), "proved": len(proved), "spec_kind": "invariance",
             "solver_statuses": sorted(set(statuses)),
             "A": A.tolist(), "B": B.tolist()}
    if not cands:
        raise SimgapError(f"invariant set: solver {solver} found no ellipsoid (statuses: "
                          f"{', '.join(sorted(set(statuses)))})")
    if proved:  # the largest volume among the proved candidates
        P, v, rho = max(proved, key=lambda c: -np.linalg.slogdet(c[0])[1])
    else:       # the closest to a proof: for the diagnosis
        P, v, rho = max(cands, key=lambda c: (c[1].gap_scale, -c[1].total))
    stats["gap_how"] = v.gap_how
    stats["verification"] = v.to_dict()
    stats["rho_design"] = rho
    Q = np.linalg.inv(P)
    stats["half_widths"] = np.round(np.sqrt(np.diag(Q)), 6).tolist()
    stats["semi_axes"] = np.sort(1.0 / np.sqrt(np.linalg.eigvalsh(P)))[::-1].round(6).tolist()
    from math import gamma as _G, pi
    stats["volume"] = float(pi ** (n / 2) / _G(n / 2 + 1) / np.sqrt(np.linalg.det(P)))
    stats["gap_scale"] = None if np.isinf(v.gap_scale) else v.gap_scale  # None: no gap (strict JSON)
    stats["gap_scale_text"] = "any factor (no gap)" if np.isinf(v.gap_scale) else f"{v.gap_scale:.4g}"
    ctrl = None
    if v.ok:
        from .ellipsoid_controller import EllipsoidController
        meta = {"stats": stats, "gap": _describe_gap(gap), "margins": {
            "gap_scale": "inf" if np.isinf(v.gap_scale) else v.gap_scale,
            "what": "the largest factor s such that E stays invariant under s * w_max (w_max: the gap's bound over E)"}}
        if x0 is not None:
            x0 = np.asarray(x0, dtype=float)
            meta["x0"] = x0.tolist()
        ctrl = EllipsoidController(x_star, u_star, K, P, system=system, spec=spec, meta=meta)
        if x0 is not None:
            stats["x0_inside"] = bool(ctrl.winning(x0[None])[0])
    else:
        stats["diagnosis"] = diagnose(system, v)
    stats["seconds"] = time.perf_counter() - t0
    stats["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return InvariantSetResult(ctrl, v, stats)


def diagnose(system: System, v: Verification) -> str:
    """Which condition of the closest candidate fails and by how much."""
    bad = v.failed()
    parts = []
    for c in bad:
        if c["name"].startswith("f(x, u(x))"):
            budget = 1.0 - v.contraction
            if budget <= 0 or v.nonlinear_norm >= budget:
                parts.append(f"no invariant ellipsoid even without a gap: the contraction {v.contraction:.6f} plus the "
                             f"nonlinear remainder and residual {v.nonlinear_norm:.4g} exceed 1 ({c['value']:.6f})")
            else:
                s = v.gap_scale
                need = ", ".join(f"gamma_{nm} <= {s * w:.3g} (the gap gives {w:.3g})"
                                 for nm, w in zip(system.state_names, v.w_max) if w > 0)
                parts.append(f"the gap is too large for invariance: the contraction {v.contraction:.6f} and the "
                             f"nonlinear remainder {v.nonlinear_norm:.3g} leave {budget - v.nonlinear_norm:.4g} of the "
                             f"unit ellipsoid; gamma would have to be at most {s:.3g} x the gap's bound over E: "
                             f"{need} per period")
        else:
            parts.append(f"{c['name']} fails: {c['value']:.4g} > {c['limit']:g} ({c['what']})")
    return ("no invariant set proved; best candidate: " + "; ".join(parts) + "; levers: the input range (the "
            "system's inputs), X and the safe set (E must fit in both), K (or lqr_q / lqr_r), x_star / u_star, and a "
            "smaller gamma (more runs N1hat, a [collect] region around x*, a refined model: docs/synthesis.md)")


def _describe_gap(gap) -> dict:
    if gap is None:
        return {"kind": "none"}
    if hasattr(gap, "digest"):
        return {"kind": "certificate", "digest": gap.digest, "system": getattr(gap, "system_name", None)}
    return {"kind": "constant", "gamma": np.asarray(gap, dtype=float).ravel().tolist()}

"""Box tubes: a time-varying linear feedback along a nominal trajectory, and a PROOF that the mean
state reaches a box around an equilibrium and stays there.

The controller (``t`` counts periods from x0):

    u_t(x) = u_nom(t) + K (x - x_nom(t))     for t < T0,
    u_t(x) = u* + K (x - x*)                 for t >= T0,

with x_nom(t+1) = f(x_nom(t), u_nom(t)) the nominal plan from x_nom(0) = x0 (the saturated linear
loop u_nom = clip(u* + K (x_nom - x*)) inside the input range shrunk by a margin that leaves room
for the feedback) and T0 the period where the plan is within a small distance of x*.

What :func:`verify_tube` proves, for the mean map m_{t+1} = f(m_t, u_t(m_t)) + w_t with
|w_{t,i}| <= w_max_i(t) = sup of the certified gap gamma_i over the region the state and input can
be in at t (:func:`~simgap.synthesis.invariant_set.gap_bound`, its semantics unchanged), from
m_0 = x0:

    (T) for t <= T0: m_t - x_nom(t) in the zonotope Z_t, whose box hull x_nom(t) +- h_t lies in the
        safe set S and X, and u_t(m_t) in the input range;
    (I) for t >= T0: m_t - x* in the box [-H, H], which lies in S, X (and the target box), and
        u* + K [-H, H] in the input range.

Proof of (T) (mean-value form). With e = x - x_nom(t) and g_t(x) = f(x, u_t(x)),

    e_{t+1} = g_t(x) - g_t(x_nom(t)) + r_t + w_t,   g_t(x) - g_t(x_nom) = M e,
    M = int_0^1 J_{g_t}(x_nom + s e) ds,

r_t = f(x_nom(t), u_nom(t)) - x_nom(t+1) (floating point; widened). The integral is split into k
equal pieces ("shells"): on s in [(i-1)/k, i/k] the point x_nom + s e lies in the box
x_nom + (i/k) [-h_t, h_t] and its input in u_nom + (i/k) [-|K G_t| 1, |K G_t| 1], over which
:class:`~simgap.synthesis.interval_map.IntervalMap` encloses J_g in [Jc_i +- Jr_i]; so
M in [Mc +- Mr] with Mc, Mr the averages over i (k = 1 is the plain interval Jacobian over the whole
box; k -> inf halves the remainder, the second-order Taylor bound). Then

    M e = Mc e + (M - Mc) e,   |(M - Mc) e| <= Mr h_t   (the remainder),

and Z_{t+1} = Mc Z_t (+) box(Mr h_t + |r_t| + w_t): the linear part maps generators exactly (no
wrapping), the remainder and the gap enter as a box each period (Girard's order reduction keeps at
most ORDER x n generators, an enclosure).

Proof of (I) (an outer approximation of the minimal robust invariant set, Rakovic et al. 2005).
On the box x* + [-H, H] (inputs u* + |K| H), the same mean-value form around x* gives
e_{t+1} = A e_t + delta_t with A = Mc and |delta_t| <= d = Mr H + |r*| + w_H. Pick s with
|A^s| d <= alpha d componentwise, alpha < 1. By induction on t >= T0: if e_k in [-H, H] for
T0 <= k < t, then with j = t - T0

    |e_t| <= |A^j G'| 1 + sum_{i<j} |A^i| d = v_j + S_j,

Z' = (x_nom(T0) - x*) + Z_{T0} = G' B. need = max over j < J (2000) of v_j + S_j, and for j >= J
alpha^floor(J/s) max_{i<s} c_i d + (1 - alpha)^-1 S_s (c_i = max(v_i / d)), since
|A^(qs+i)| <= |A^i| |A^s|^q and |A^s|^q d <= alpha^q d. (I) holds when need <= H.

The tolerable gap: :func:`tolerable_scale` is the largest factor s such that the proof still holds
with every w_max(t) multiplied by s (the tube and H re-designed for each s): "certified gamma vs
tolerable gamma". The gap is refused outside a certificate's ``region`` when it has one.
"""

from __future__ import annotations

import functools
import resource
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import SimgapError
from ..sets import Zonotope
from ..systems import System
from .interval_map import IntervalMap
from ..checks import one_of
from .noise_tube import NoiseTube, check_horizon, noise_proxy, why_no_statement
from .invariant_set import (_describe_gap, _parse_matrix, _weights, check_stabilizable, find_equilibrium, gap_bound,
                            input_range, linearize, lqr_gain, spectral_radius)
from .spec import Spec

#: pieces of the mean-value integral (1 = the interval Jacobian over the whole box)
SHELLS = 16
#: generators kept per state dimension (Girard's reduction beyond). Reduction boxes the smallest
#: generators, which A then rotates (wrapping): on the cart-pole (spectral radius 0.98, T0 313)
#: 20 per dimension tolerated 0.011 x the gap, 80 0.077, 250 (no reduction there) 0.10
ORDER = 250
#: default fraction of each input's half-range kept free for the feedback along the plan
INPUT_MARGIN = 0.3
#: the plan ends when |x_nom - x*| <= PLAN_TOL x (half-width of the room around x*)
PLAN_TOL = 1e-3
#: at most this many plan periods
MAX_PLAN = 5000
#: longest s tried in the terminal bound
MAX_S = 400
#: periods after T0 over which the terminal bound follows the initial set and the disturbance sum exactly
TERMINAL_HORIZON = 2000
#: design rounds of the terminal box H (a fixed point of H -> need(H))
H_ROUNDS = 40
#: the smallest disturbance used in the terminal bound, relative to H (alpha needs d > 0)
D_FLOOR = 1e-9
#: rounding of the nominal step (f evaluated in floating point twice)
R_WIDEN = 1e-12


# ---------------------------------------------------------------------------------------
# enclosures
# ---------------------------------------------------------------------------------------

def mean_value_enclosure(imap: IntervalMap, xc, h, uc, hu, K, shells: int = SHELLS):
    """(Mc, Mr) (B, n, n): M = int_0^1 J_g(xc + s e) ds in [Mc +- Mr] for every e with |e| <= h whose
    inputs stay in uc + s hu, as the average of the enclosures over the k nested boxes xc + (i/k) h
    (module docstring). xc, h (B, n); uc, hu (B, m)."""
    xc, h = np.atleast_2d(xc), np.atleast_2d(h)
    uc, hu = np.atleast_2d(uc), np.atleast_2d(hu)
    B = xc.shape[0]
    s = (np.arange(1, int(shells) + 1) / int(shells))[:, None, None]       # (k, 1, 1)
    lo = (xc[None] - s * h[None]).reshape(-1, xc.shape[1])
    hi = (xc[None] + s * h[None]).reshape(-1, xc.shape[1])
    ulo = (uc[None] - s * hu[None]).reshape(-1, uc.shape[1])
    uhi = (uc[None] + s * hu[None]).reshape(-1, uc.shape[1])
    _, _, Jc, Jr = imap.closed_loop(lo, hi, ulo, uhi, K)
    n = xc.shape[1]
    Jc, Jr = Jc.reshape(int(shells), B, n, n), Jr.reshape(int(shells), B, n, n)
    return Jc.mean(axis=0), Jr.mean(axis=0)


def remainder(Mr, h) -> np.ndarray:
    """(B, n) the bound |(M - Mc) e| <= Mr |e| <= Mr h of the linearization's error (a function of
    its own so that the mutation tests can replace it)."""
    return np.einsum("bij,bj->bi", Mr, h)


def _check_region(gap, lo, hi, what):
    """'' or why the box [lo, hi] leaves the certificate's region (a local certificate)."""
    if hasattr(gap, "outside"):  # a certificate says it (a region, or the boxes of a cover along a tube)
        return gap.outside(lo, hi, what)
    reg = getattr(gap, "region", None)
    if reg is None:
        return ""
    rlo, rhi = (np.asarray(reg["lo"], float), np.asarray(reg["hi"], float)) if isinstance(reg, dict) else \
        (np.asarray(reg[0], float), np.asarray(reg[1], float))
    bad = np.flatnonzero((lo < rlo - 1e-12) | (hi > rhi + 1e-12))
    if bad.size:
        i = int(bad[0])
        return (f"{what}: [{lo[i]:.4g}, {hi[i]:.4g}] in state {i} leaves the certificate's region "
                f"[{rlo[i]:g}, {rhi[i]:g}] (gamma holds only there)")
    return ""


def _gap_over(gap, system: System, blo, bhi, ulo, uhi, u_range):
    """gap_bound over the state box clipped to X and the input box clipped to ``u_range`` (the certified
    input range): harmless for the proof, whose conditions separately require the boxes inside the safe
    set (within X) and the inputs inside the range (a box outside either fails the proof anyway), and
    a certificate refuses boxes outside what it covers."""
    blo, bhi = np.clip(blo, system.x_lo, system.x_hi), np.clip(bhi, system.x_lo, system.x_hi)
    if u_range is not None:
        ulo, uhi = np.clip(ulo, u_range[0], u_range[1]), np.clip(uhi, u_range[0], u_range[1])
    return gap_bound(gap, system.n, blo, bhi, ulo, uhi)


def _gap_over_rows(gap, system: System, blo, bhi, ulo, uhi, u_range):
    """(W (k, n), how): :func:`_gap_over` for k boxes (rows); one batched ``gamma_sup`` call for a
    certificate of continuous inputs (the rows are bounded independently: the same values)."""
    k, n = blo.shape
    w0, how = _gap_over(gap, system, blo[0], bhi[0], ulo[0], uhi[0], u_range)
    if k > 1 and getattr(gap, "continuous", False) and hasattr(gap, "gamma_sup"):
        cl, ch = np.clip(blo[1:], system.x_lo, system.x_hi), np.clip(bhi[1:], system.x_lo, system.x_hi)
        vl, vh = ulo[1:], uhi[1:]
        if u_range is not None:
            vl, vh = np.clip(vl, u_range[0], u_range[1]), np.clip(vh, u_range[0], u_range[1])
        W = np.asarray(gap.gamma_sup(cl, ch, vl, vh), dtype=float)
        if W.shape == (k - 1, n):  # a gap object answering one box at a time gets the rows one by one
            return np.concatenate([np.asarray(w0, float).reshape(1, n), W]), how
    return np.array([w0] + [_gap_over(gap, system, blo[j], bhi[j], ulo[j], uhi[j], u_range)[0]
                            for j in range(1, k)], dtype=float).reshape(k, n), how


def terminal_bound(A, d, G0, max_s: int = MAX_S, horizon: int = TERMINAL_HORIZON):
    """(need (n,), alpha, s, mrpi (n,)): the bound of (I) in the module docstring for e+ = A e + delta,
    |delta| <= d > 0, from e in the zonotope G0 B (centre 0):

        |e_j| <= v_j + S_j,  v_j = |A^j G0| 1,  S_j = sum_{i<j} |A^i| d,

    taken exactly for j < J = ``horizon``; for j >= J, with any s such that alpha_s = max(|A^s| d / d)
    < 1: v_j <= alpha_s^floor(J/s) max_{i<s} c_i d (c_i = max(v_i / d)) and S_j <= (1 - alpha_s)^-1
    S_s (the mRPI set's box hull). Every s gives a valid bound; the elementwise minimum is returned
    with the alpha and s of the smallest max need / d. inf when no s <= max_s has alpha_s < 1."""
    return terminal_bound_batch(np.asarray(A, float)[None], np.asarray(d, float)[None], [G0], max_s, horizon)[0]


def terminal_bound_batch(A, d, G0, max_s: int = MAX_S, horizon: int = TERMINAL_HORIZON) -> list:
    """:func:`terminal_bound` for F loops at once: A (F, n, n), d (F, n), G0 a list of F (n, g_f) generator
    matrices (padded with zero generators, which add nothing to |A^j G0| 1). Each loop has its own early
    stop (checked every 25 steps: once some s's bound beyond s is below the exact prefix, the need is the
    prefix) and its own tails; one numpy call per step for all F (the Python loop over j is the cost: up
    to 2000 steps). Returns [(need, alpha, s, mrpi)] * F."""
    A = np.asarray(A, float)
    d = np.asarray(d, float)
    F, n = d.shape
    g = max(np.shape(G)[1] for G in G0)
    AG = np.zeros((F, n, g))
    for f, G in enumerate(G0):
        AG[f, :, :np.shape(G)[1]] = G
    dead = ~(np.isfinite(AG).all(axis=(1, 2)) & np.isfinite(d).all(axis=1))
    J = max(int(horizon), int(max_s))
    Jf = np.full(F, J)
    active = ~dead
    Ak = np.broadcast_to(np.eye(n), (F, n, n)).copy()
    S = np.zeros((F, n))
    prefix = np.zeros((F, n))
    cmax = np.zeros(F)
    Akd = d.copy()
    ta = np.full((F, int(max_s)), np.inf)     # alpha_s per loop (inf: alpha_s >= 1, no tail)
    tc = np.zeros((F, int(max_s)))
    tS = np.zeros((F, int(max_s), n))
    with np.errstate(all="ignore"):
        for j in range(J):
            v = np.abs(AG).sum(axis=2)
            prefix = np.where(active[:, None], np.maximum(prefix, v + S), prefix)
            if j < max_s:
                cmax = np.maximum(cmax, np.max(v / d, axis=1))
            S = S + Akd
            Ak = A @ Ak
            AG = A @ AG
            bad = active & ~(np.isfinite(Ak).all(axis=(1, 2)) & np.isfinite(AG).all(axis=(1, 2)))
            dead |= bad
            active &= ~bad
            Akd = np.einsum("fij,fj->fi", np.abs(Ak), d)
            s = j + 1
            if s <= max_s:
                alpha = np.max(Akd / d, axis=1)
                new = active & (alpha < 1.0)
                ta[new, s - 1], tc[new, s - 1], tS[new, s - 1] = alpha[new], cmax[new], S[new]
            if s % 25 == 0:  # stop a loop once some s's bound beyond s is below its exact prefix
                k = min(s, int(max_s))
                a = ta[:, :k, None]
                sk = np.arange(1, k + 1)[None, :, None]
                bound = a ** (s // sk) * tc[:, :k, None] * d[:, None] + tS[:, :k] / (1.0 - a)
                stop = active & np.isfinite(ta[:, :k]).any(axis=1) & \
                    (np.isfinite(ta[:, :k]) & np.all(bound <= prefix[:, None], axis=2)).any(axis=1)
                Jf[stop] = s
                active &= ~stop
            if not active.any():
                break
    out = []
    for f in range(F):
        if dead[f]:
            out.append((np.full(n, np.inf), np.inf, 0, np.full(n, np.inf)))
            continue
        ok = np.flatnonzero(np.isfinite(ta[f]) & (np.arange(1, int(max_s) + 1) <= Jf[f]))
        if ok.size == 0:
            out.append((np.full(n, np.inf), np.inf, 0, np.full(n, np.inf)))
            continue
        a, c, Ss = ta[f, ok][:, None], tc[f, ok][:, None], tS[f, ok]
        tail = Ss / (1.0 - a)
        ns = np.maximum(prefix[f], a ** (Jf[f] // (ok + 1))[:, None] * c * d[f] + tail)
        score = np.max(ns / d[f], axis=1)
        b = int(np.argmin(score))
        out.append((ns.min(axis=0), float(ta[f, ok[b]]), int(ok[b] + 1), tail.min(axis=0)))
    return out


# ---------------------------------------------------------------------------------------
# the plan and the proof
# ---------------------------------------------------------------------------------------

@dataclass
class TubePlan:
    """What the controller applies and the proof checks: the nominal trajectory x_nom (T0 + 1, n),
    its inputs u_nom (T0, m), the gain K (m, n), the equilibrium (x*, u*) and the terminal box's
    half-widths H (n,)."""

    x_nom: np.ndarray
    u_nom: np.ndarray
    K: np.ndarray
    x_star: np.ndarray
    u_star: np.ndarray
    H: np.ndarray

    @property
    def T0(self) -> int:
        return int(self.u_nom.shape[0])


@dataclass
class TubeVerification:
    """The result of :func:`verify_tube` (state units per period)."""

    ok: bool
    conditions: list                 # [{name, value, limit, ok, what}]
    radii: np.ndarray                # (T0 + 1, n) h_t: the tube's box half-widths around x_nom(t)
    u_radii: np.ndarray              # (T0, m) |K G_t| 1
    w_max: np.ndarray                # (T0, n) the gap's bound per period along the tube
    remainders: np.ndarray           # (T0, n) Mr h_t
    terminal: dict                   # A's spectral radius, alpha, s, d, w_H, remainder, need, H
    gap_how: str
    gap_factor: float = 1.0

    def failed(self) -> list:
        return [c for c in self.conditions if not c["ok"]]

    def to_dict(self) -> dict:
        f = lambda a: np.asarray(a, dtype=float).tolist()
        term = {k: (f(v) if isinstance(v, np.ndarray) else v) for k, v in self.terminal.items()}
        w_all = np.concatenate([self.w_max, np.asarray(self.terminal["w_H"], float)[None]], axis=0)
        return {"ok": bool(self.ok), "conditions": self.conditions, "gap_how": self.gap_how,
                "w_max": f(w_all.max(axis=0)),
                "gap_factor": self.gap_factor, "max_radius": f(self.radii.max(axis=0)),
                "max_w": f(self.w_max.max(axis=0)) if self.w_max.size else None,
                "max_remainder": f(self.remainders.max(axis=0)) if self.remainders.size else None,
                "terminal": term}


def _ratio(width, room):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(room > 0, width / room, np.where(width > 0, np.inf, 0.0))


def tube_phases(system: System, plan: TubePlan, gap, imap: IntervalMap, shells: int = SHELLS,
                factors=(1.0,), keep_sets: bool = False, u_range=None, zbar=None, A_lin=None) -> list:
    """(T)'s propagation for each gap factor f (one batched interval evaluation per period):
    Z_0 = {0}, Z_{t+1} = Mc_t Z_t (+) box(Mr_t h_t + |r_t| + f w_t) (module docstring).

    With ``zbar`` (F, T0 + 1, n) and ``A_lin`` (T0, n, n), the tube of single runs
    (:mod:`.noise_tube`): the state is x_nom(t) + a_t + z_t with |z_t| <= zbar_t (the noise's linear
    response through A_lin) and a_t in Z_t, so every box is widened by zbar_t and the remainder
    gains (|Mc_t - A_lin_t| + Mr_t) zbar_t; the returned half-widths are the widened ones. Returns one
    dict per factor: the last generators G (n, p), the half-widths h_t (T0 + 1, n), the inputs'
    |K G_t| 1 (T0, m), w_t and the remainders (T0, n), the gap's labels and a region message; with
    ``keep_sets`` also every Z_t's generators (``sets``, T0 + 1 arrays (n, p_t)). A tube wider than
    X is not propagated further (its remaining half-widths are inf: the proof fails)."""
    n, m = system.n, system.m
    K = np.asarray(plan.K, float).reshape(m, n)
    x_nom, u_nom = np.asarray(plan.x_nom, float), np.asarray(plan.u_nom, float).reshape(-1, m)
    T0 = u_nom.shape[0]
    fac = np.asarray(factors, dtype=float).ravel()
    F = fac.size
    Zb = np.zeros((F, T0 + 1, n)) if zbar is None else np.broadcast_to(np.asarray(zbar, float), (F, T0 + 1, n))
    absK = np.abs(K)
    Gs = [np.zeros((n, 0)) for _ in range(F)]
    radii, u_radii = np.zeros((F, T0 + 1, n)), np.zeros((F, T0, m))
    W, REM = np.zeros((F, T0, n)), np.zeros((F, T0, n))
    hows, region = [set() for _ in range(F)], [""] * F
    sets = [[G] for G in Gs] if keep_sets else None
    alive = np.ones(F, dtype=bool)
    width = system.x_hi - system.x_lo
    xn_next = system.f(x_nom[:-1], u_nom) if T0 else np.zeros((0, n))
    for t in range(T0):
        ha = np.array([np.abs(G).sum(axis=1) for G in Gs])  # the a-part (the mean's tube without noise)
        h = ha + Zb[:, t]                                     # the box the state can be in
        hu = np.array([np.abs(K @ G).sum(axis=1) for G in Gs]) + Zb[:, t] @ absK.T
        for f in np.flatnonzero(alive & ~np.all(h <= width, axis=1)):  # outside X: the proof fails
            radii[f, t:], u_radii[f, t:], Gs[f], alive[f] = np.inf, np.inf, np.full((n, 1), np.inf), False
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        radii[idx, t], u_radii[idx, t] = h[idx], hu[idx]
        inside = []
        for f in idx:
            msg = _check_region(gap, x_nom[t] - h[f], x_nom[t] + h[f], f"the tube at period {t}")
            if msg:  # gamma is not certified there: no bound (the proof fails with this reason)
                region[f] = region[f] or msg
                W[f, t] = np.inf
            else:
                inside.append(f)
        if inside:  # the gap over every factor's box at once
            w, how = _gap_over_rows(gap, system, x_nom[t] - h[inside], x_nom[t] + h[inside], u_nom[t] - hu[inside],
                                    u_nom[t] + hu[inside], u_range)
            for j, f in enumerate(inside):
                hows[f].add(how)
                W[f, t] = fac[f] * w[j]
        k = idx.size
        Mc, Mr = mean_value_enclosure(imap, np.repeat(x_nom[t][None], k, 0), h[idx], np.repeat(u_nom[t][None], k, 0),
                                      hu[idx], K, shells)
        rem = remainder(Mr, ha[idx])
        if zbar is not None:  # (M - A_lin) z = (M - Mc) z + (Mc - A_lin) z
            rem = rem + np.einsum("bij,bj->bi", np.abs(Mc - A_lin[t]) + Mr, Zb[idx, t])
        r = np.abs(xn_next[t] - x_nom[t + 1]) + R_WIDEN * (1.0 + np.abs(x_nom[t + 1]))
        for j, f in enumerate(idx):
            REM[f, t] = rem[j]
            with np.errstate(invalid="ignore", over="ignore"):
                Gs[f] = Zonotope(np.zeros(n), Mc[j] @ Gs[f]).plus_box(rem[j] + r + W[f, t]).reduce(ORDER).G
            if keep_sets:
                sets[f].append(Gs[f])
    for f in np.flatnonzero(alive):
        radii[f, T0] = np.abs(Gs[f]).sum(axis=1) + Zb[f, T0]
    return [{"G": Gs[f], "radii": radii[f], "u_radii": u_radii[f], "w": W[f], "remainders": REM[f],
             "hows": hows[f], "region": region[f], "sets": sets[f] if keep_sets else None} for f in range(F)]


def tube_phase(system: System, plan: TubePlan, gap, imap: IntervalMap, shells: int = SHELLS,
               gap_factor: float = 1.0, keep_sets: bool = False, u_range=None) -> dict:
    """:func:`tube_phases` for one gap factor."""
    return tube_phases(system, plan, gap, imap, shells, (gap_factor,), keep_sets, u_range)[0]


def terminal_phases(system: System, plan: TubePlan, Gs, Hs, gap, imap: IntervalMap, shells: int = SHELLS,
                    factors=(1.0,), u_range=None, zbar=None, A_lin=None) -> list:
    """(I)'s bound for the boxes x* +- H_f (Hs (F, n)) from Z'_f = (x_nom(T0) - x*) + G_f B (module
    docstring), one batched interval evaluation; one dict per row. With ``zbar`` (F, n) and ``A_lin``
    (n, n) as in :func:`tube_phases` (single runs): H_f is the whole box, the a-part's bound is
    computed for H_f - zbar_f and ``need`` is that bound plus zbar_f."""
    n, m = system.n, system.m
    K = np.asarray(plan.K, float).reshape(m, n)
    xs, us = np.asarray(plan.x_star, float), np.asarray(plan.u_star, float)
    Hs = np.atleast_2d(np.asarray(Hs, float))
    F = Hs.shape[0]
    fac = np.broadcast_to(np.asarray(factors, float), (F,))
    ZT = np.zeros((F, n)) if zbar is None else np.broadcast_to(np.asarray(zbar, float), (F, n))
    Ha = Hs - ZT
    x_end = np.asarray(plan.x_nom, float)[-1]
    HU = Hs @ np.abs(K).T
    Mc, Mr = mean_value_enclosure(imap, np.repeat(xs[None], F, 0), Hs, np.repeat(us[None], F, 0), HU, K, shells)
    REM = remainder(Mr, np.maximum(Ha, 0.0))
    if zbar is not None:
        REM = REM + np.einsum("bij,bj->bi", np.abs(Mc - A_lin) + Mr, ZT)
    r_star = np.abs(system.f(xs[None], us[None])[0] - xs) + R_WIDEN * (1.0 + np.abs(xs))
    rows = []
    for f in range(F):
        H, hu_H = Hs[f], HU[f]
        region = _check_region(gap, xs - H, xs + H, "the terminal box")
        w_H, how = (np.full(n, np.inf), "not certified outside the region") if region else \
            _gap_over(gap, system, xs - H, xs + H, us - hu_H, us + hu_H, u_range)
        w_H = fac[f] * np.asarray(w_H, float)
        d = np.maximum(REM[f] + r_star + w_H, D_FLOOR * np.maximum(H, 1e-300))
        G0 = np.concatenate([Gs[f], (x_end - xs)[:, None]], axis=1)
        rho = spectral_radius(Mc[f]) if np.all(np.isfinite(Mc[f])) else np.inf
        rows.append((d, G0, rho, w_H, how, region, bool(np.all(np.isfinite(d)) and rho < 1 and np.all(Ha[f] >= 0))))
    go = [f for f in range(F) if rows[f][-1]]  # the loops the bound applies to, all at once
    bounds = dict(zip(go, terminal_bound_batch(Mc[go], np.array([rows[f][0] for f in go]), [rows[f][1] for f in go])
                      if go else []))
    out = []
    for f, (d, G0, rho, w_H, how, region, _) in enumerate(rows):
        need, alpha, s_, tail = bounds.get(f, (np.full(n, np.inf), np.inf, 0, np.full(n, np.inf)))
        out.append({"spectral_radius": rho, "alpha": alpha, "s": int(s_), "d": d, "w_H": w_H, "remainder": REM[f],
                    "residual": r_star, "need": need + ZT[f], "H": Hs[f].copy(), "mrpi_hull": tail,
                    "u_radius": HU[f], "how": how, "region": region})
    return out


def judge(system: System, plan: TubePlan, H, ph: dict, term: dict, lo, hi, u_lo, u_hi, target_lo=None,
          target_hi=None) -> list:
    """The conditions of (T) and (I) (module docstring) from a tube and a terminal bound:
    [{name, value, limit, ok, what}]."""
    m = system.m
    xs, us, H = np.asarray(plan.x_star, float), np.asarray(plan.u_star, float), np.asarray(H, float)
    x_nom, u_nom = np.asarray(plan.x_nom, float), np.asarray(plan.u_nom, float).reshape(-1, m)
    conds = []

    def cond(name, value, limit, what):
        conds.append({"name": name, "value": float(value), "limit": float(limit), "ok": bool(value <= limit),
                      "what": what})

    radii, u_radii = ph["radii"], ph["u_radii"]
    rlo, rhi = x_nom - radii, x_nom + radii
    worst = np.minimum(rlo - lo, hi - rhi)
    t_, i_ = np.unravel_index(int(np.argmin(worst)), worst.shape)
    cond("tube inside the safe set", -float(worst[t_, i_]), 0.0,
         f"period {t_}: {system.state_names[i_]} in [{rlo[t_, i_]:.4g}, {rhi[t_, i_]:.4g}], safe [{lo[i_]:g}, "
         f"{hi[i_]:g}] (value: how far outside)")
    if u_nom.shape[0]:
        ulow, uhig = u_nom - u_radii, u_nom + u_radii
        uw = np.minimum(ulow - u_lo, u_hi - uhig)
        t_, j_ = np.unravel_index(int(np.argmin(uw)), uw.shape)
        cond("tube inputs inside the input range", -float(uw[t_, j_]), 0.0,
             f"period {t_}: {system.input_names[j_]} in [{ulow[t_, j_]:.4g}, {uhig[t_, j_]:.4g}], range "
             f"[{u_lo[j_]:g}, {u_hi[j_]:g}]")
    hu_H, need = term["u_radius"], term["need"]
    cond("terminal box inside the safe set", float(np.max(_ratio(H, np.minimum(xs - lo, hi - xs)))), 1.0,
         f"x* +- H = {np.round(xs, 6).tolist()} +- {np.round(H, 6).tolist()}")
    if target_lo is not None:
        tl, th = np.asarray(target_lo, float), np.asarray(target_hi, float)
        cond("terminal box inside the target", float(np.max(_ratio(H, np.minimum(xs - tl, th - xs)))), 1.0,
             f"target [{tl.tolist()}, {th.tolist()}]")
    cond("terminal inputs inside the input range", float(np.max(_ratio(hu_H, np.minimum(us - u_lo, u_hi - us)))),
         1.0, f"u* +- |K| H = {np.round(us, 6).tolist()} +- {np.round(hu_H, 6).tolist()}")
    for a in system.angle_dims:  # f wraps angles to [-pi, pi): no box may reach the seam
        reach = max(np.max(np.abs(np.concatenate([rlo[:, a], rhi[:, a]]))), abs(xs[a]) + H[a])
        cond(f"away from the angle seam ({system.state_names[a]})", reach / np.pi, 1.0 - 1e-12,
             "angles are wrapped after each period")
    cond("terminal bound inside H", float(np.max(_ratio(need, H))), 1.0,
         f"need {np.array2string(need, precision=4)} <= H {np.array2string(H, precision=4)} (alpha "
         f"{term['alpha']:.4g}, s {term['s']}, spectral radius {term['spectral_radius']:.6f})")
    region_msg = ph["region"] or term["region"]
    cond("boxes inside the certificate's region", 0.0 if not region_msg else 1.0, 0.0, region_msg or "no region")
    return conds


def _verification(ph, term, conds, gap_factor) -> TubeVerification:
    terminal = {k: v for k, v in term.items() if k not in ("how", "region")}
    return TubeVerification(ok=all(c["ok"] for c in conds), conditions=conds, radii=ph["radii"],
                            u_radii=ph["u_radii"], w_max=ph["w"], remainders=ph["remainders"], terminal=terminal,
                            gap_how="; ".join(sorted(ph["hows"] | {term["how"]})), gap_factor=float(gap_factor))


def verify_tube(system: System, plan: TubePlan, safe_lo, safe_hi, u_lo, u_hi, gap=None, *,
                target_lo=None, target_hi=None, imap: Optional[IntervalMap] = None, shells: int = SHELLS,
                gap_factor: float = 1.0, _phase: Optional[dict] = None) -> TubeVerification:
    """Prove (or refute the proof of) (T) and (I) of the module docstring for ``plan``.

    Independent of how the plan was made: the tube Z_t is propagated here from Z_0 = {0}. ``gap``:
    None, a constant vector or a certificate (:func:`~simgap.synthesis.invariant_set.gap_bound`);
    ``gap_factor`` multiplies its bound (the tolerable-gap search). The safe box is S intersected
    with X; with ``target_lo``/``target_hi`` the terminal box must also lie in the target.
    (``_phase``: (T)'s propagation already computed for this plan, gap and factor; the design's
    loops over H only.)
    """
    imap = imap if imap is not None else IntervalMap(system)
    lo = np.maximum(np.asarray(safe_lo, float), system.x_lo)
    hi = np.minimum(np.asarray(safe_hi, float), system.x_hi)
    u_lo, u_hi = np.asarray(u_lo, float), np.asarray(u_hi, float)
    ph = _phase if _phase is not None else tube_phase(system, plan, gap, imap, shells, gap_factor,
                                                      u_range=(u_lo, u_hi))
    H = np.asarray(plan.H, float)
    term = terminal_phases(system, plan, [ph["G"]], H[None], gap, imap, shells, (gap_factor,), (u_lo, u_hi))[0]
    conds = judge(system, plan, H, ph, term, lo, hi, u_lo, u_hi, target_lo, target_hi)
    return _verification(ph, term, conds, gap_factor)


# ---------------------------------------------------------------------------------------
# design
# ---------------------------------------------------------------------------------------

#: input-weight factors 10^c tried for the box-tolerant gain
GAIN_EXPONENTS = (-3.0, -2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0)


def gain_family(A, B, x_star, u_star, room, uroom, gap, system: System) -> list:
    """[(score, c, K)], best first: the LQR gains with q = 1 / room^2 (Bryson over the target box) and
    r = 10^c / uroom^2 (c in GAIN_EXPONENTS) that stabilize the linearization, each scored by how large a
    multiple of the gap d at x* (its sup over the target box and the input range) its linear loop A + B K
    tolerates by the box hull of the minimal RPI set, h = sum_k |(A + B K)^k| d (2000 terms): the largest
    s with s h <= room and s |K| h <= uroom. A design heuristic only: the proof decides."""
    n = A.shape[0]
    try:
        d, _ = _gap_over(gap, system, x_star - room, x_star + room, u_star - uroom, u_star + uroom, None)
        d = np.asarray(d, float)
    except SimgapError:
        d = np.zeros(n)
    d = np.maximum(np.where(np.isfinite(d), d, 0.0), 1e-6 * room)
    out = []
    for c in GAIN_EXPONENTS:
        K = lqr_gain(A, B, 1.0 / room ** 2, 10.0 ** c / uroom ** 2)
        Acl = A + B @ K
        if spectral_radius(Acl) >= 1:
            continue
        h, Ak = np.zeros(n), np.eye(n)
        for _ in range(2000):
            h += np.abs(Ak) @ d
            Ak = Acl @ Ak
        score = min(float(np.min(room / h)), float(np.min(uroom / np.maximum(np.abs(K) @ h, 1e-300))))
        out.append((score, c, K))
    if not out:
        raise SimgapError("box tube: no LQR gain of the family stabilizes the linearization")
    return sorted(out, key=lambda t: -t[0])


def gain_how(c, score) -> str:
    return (f"discrete LQR, Bryson's weights over the target box with the input weight x 10^{c:g} (linear mRPI "
            f"estimate: {score:.3g} x the gap at x*)")


def plan_nominal(system: System, x0, x_star, u_star, K, u_lo, u_hi, margin: float = INPUT_MARGIN,
                 tol=None, max_steps: int = MAX_PLAN):
    """(x_nom (T0 + 1, n), u_nom (T0, m)): the saturated linear loop u = clip(u* + K (x - x*)) in the
    input range shrunk by ``margin`` x its half-range on each side, from x0 until |x - x*| <= tol."""
    x = np.asarray(x0, float).copy()
    half = 0.5 * (u_hi - u_lo)
    a, b = u_lo + margin * half, u_hi - margin * half
    a, b = np.minimum(a, u_star), np.maximum(b, u_star)
    xs, us = [x.copy()], []
    for _ in range(int(max_steps)):
        if np.all(np.abs(x - x_star) <= tol):
            break
        u = np.clip(u_star + K @ (x - x_star), a, b)
        with np.errstate(all="ignore"):
            x = system.f(x[None], u[None])[0]
        if not (np.all(np.isfinite(x)) and np.all(x >= system.x_lo) and np.all(x <= system.x_hi)):
            raise SimgapError(f"box tube: the nominal plan from x0 leaves X at period {len(us) + 1} (state "
                              f"{np.round(x, 4).tolist()}): the saturated loop cannot bring x0 to x*. Levers: the "
                              f"plan's pace ([synthesis] plan_input_weight: larger for gentler inputs, smaller for "
                              f"firmer ones; or K_plan), a smaller input_margin (now {margin:g}), a wider input range "
                              f"(the system's inputs), a larger X (the system's x_lo / x_hi, if the overshoot is "
                              f"harmless) or an x0 closer to x*")
        xs.append(x.copy())
        us.append(u)
    else:
        raise SimgapError(f"box tube: the nominal plan from x0 does not reach x* within {max_steps} periods "
                          f"(at the end |x - x*| = {np.round(np.abs(x - x_star), 6).tolist()}); the saturated "
                          f"loop may not converge from x0. Levers: a faster plan ([synthesis] plan_input_weight "
                          f"smaller, or K_plan), a smaller input_margin (now {margin:g}) or a wider input range "
                          f"(the system's inputs)")
    return np.array(xs), np.array(us).reshape(-1, np.size(u_star))


def _room(plan, lo, hi, target_lo, target_hi):
    room = np.minimum(plan.x_star - lo, hi - plan.x_star)
    if target_lo is not None:
        room = np.minimum(room, np.minimum(plan.x_star - target_lo, target_hi - plan.x_star))
    return room


def design_H_batch(system, plan: TubePlan, lo, hi, u_lo, u_hi, gap, imap, shells, factors, target_lo=None,
                   target_hi=None, phases=None, zbar=None, zbar_T=None, A_lin=None, A_star=None) -> list:
    """The terminal box for each gap factor: iterate H <- max(H, 1.02 need(H)) from 1e-6 x room until the
    proof holds, need(H) <= H without it (H cannot help), or H reaches the room (one last try there).
    One batched interval evaluation per round; returns a TubeVerification per factor. (Single runs,
    :mod:`.noise_tube`: ``zbar`` (F, T0 + 1, n) and ``A_lin`` (T0, n, n) for the tube, ``zbar_T``
    (F, n) and ``A_star`` (n, n) for the terminal box, as in :func:`tube_phases`.)"""
    fac = np.asarray(factors, float).ravel()
    F = fac.size
    phases = phases if phases is not None else tube_phases(system, plan, gap, imap, shells, fac,
                                                           u_range=(u_lo, u_hi), zbar=zbar, A_lin=A_lin)
    room = _room(plan, lo, hi, target_lo, target_hi)
    ZT = np.zeros((F, system.n)) if zbar_T is None else np.broadcast_to(np.asarray(zbar_T, float), (F, system.n))
    H = 1e-6 * room + ZT
    done, capped = np.zeros(F, dtype=bool), np.zeros(F, dtype=bool)
    out = [None] * F
    for _ in range(H_ROUNDS):
        act = np.flatnonzero(~done)
        if act.size == 0:
            break
        terms = terminal_phases(system, plan, [phases[f]["G"] for f in act], H[act], gap, imap, shells, fac[act],
                                (u_lo, u_hi), None if zbar_T is None else ZT[act], A_star)
        for term, f in zip(terms, act):
            conds = judge(system, plan, H[f], phases[f], term, lo, hi, u_lo, u_hi, target_lo, target_hi)
            out[f] = _verification(phases[f], term, conds, fac[f])
            need = term["need"]
            if out[f].ok or capped[f] or not np.all(np.isfinite(need)) or np.all(need <= H[f]):
                done[f] = True
                continue
            H[f] = np.maximum(H[f], 1.02 * need)
            if np.any(H[f] > room):
                H[f], capped[f] = np.minimum(H[f], room), True
    return out


def design_H(system, plan: TubePlan, lo, hi, u_lo, u_hi, gap, imap, shells, gap_factor, target_lo, target_hi):
    """:func:`design_H_batch` for one factor; sets ``plan.H`` to the box found."""
    v = design_H_batch(system, plan, lo, hi, u_lo, u_hi, gap, imap, shells, (gap_factor,), target_lo, target_hi)[0]
    plan.H = np.asarray(v.terminal["H"], float).copy()
    return v


def tolerable_scale(system, plan: TubePlan, lo, hi, u_lo, u_hi, gap, imap, shells, target_lo=None,
                    target_hi=None, passes: int = 3) -> float:
    """Largest s such that the proof holds with the gap's bound multiplied by s (H re-designed for each
    s), by batched grids: 4^k for k = -10..10, then ``passes`` - 1 rounds of 8 geometric points between
    the largest factor proved and 4 x it (resolution 4^(1/9^2) = 1.7 % for 3 passes); inf without a gap
    (or beyond 4^10), 0 if even 4^-10 fails."""
    if gap is None:
        return np.inf
    p = TubePlan(plan.x_nom, plan.u_nom, plan.K, plan.x_star, plan.u_star, plan.H.copy())
    return largest_proved(lambda grid: [v.ok for v in design_H_batch(system, p, lo, hi, u_lo, u_hi, gap, imap,
                                                                      shells, grid, target_lo, target_hi)], passes)


def coarse_margin(system, plan: TubePlan, lo, hi, u_lo, u_hi, gap, imap, shells, target_lo=None,
                  target_hi=None) -> float:
    """The largest gap factor of the grid 2^(k/4), k = -10..10 (0.18 .. 5.7, steps of 19 %), the proof holds
    with, in ONE batched search (inf: all of them; 0: none): enough to rank designs against each other
    (:mod:`.tube_design`), a fraction of :func:`tolerable_scale`'s cost."""
    if gap is None:
        return np.inf
    grid = 2.0 ** (np.arange(-10, 11) / 4.0)
    p = TubePlan(plan.x_nom, plan.u_nom, plan.K, plan.x_star, plan.u_star, plan.H.copy())
    oks = np.array([v.ok for v in design_H_batch(system, p, lo, hi, u_lo, u_hi, gap, imap, shells, grid, target_lo,
                                                 target_hi)])
    return np.inf if oks.all() else float(grid[oks].max()) if oks.any() else 0.0


def largest_proved(proves, passes: int = 3) -> float:
    """The largest s > 0 for which ``proves`` (a batch: array of s -> list of bools, monotone in s) holds,
    by grids: 4^k for k = -10..10, then ``passes`` - 1 rounds of 8 geometric points between the largest
    s proved and 4 x it (resolution 4^(1/9^2) = 1.7 % for 3 passes); inf beyond 4^10, 0 below 4^-10."""
    grid = 4.0 ** np.arange(-10, 11)
    best = 0.0
    for k in range(int(passes)):
        oks = np.asarray(proves(grid), dtype=bool)
        if oks.any():
            best = max(best, float(grid[oks].max()))
        if k == 0:
            if not oks.any():
                return 0.0
            if oks[-1]:
                return np.inf
            step = 4.0
        else:
            step = step ** (1.0 / 9.0)
        grid = best * step ** (np.arange(1, 9) / 9.0)  # the interval (best, best x step) not yet ruled out
    return best


def noise_tube(system, plan: TubePlan, lo, hi, u_lo, u_hi, gap, imap, shells: int, horizon: int,
               target_lo=None, target_hi=None, passes: int = 3):
    """(NoiseTube or None, reason): the per-run statement of :mod:`.noise_tube` for runs of
    ``horizon`` periods: the largest lam for which the proof of ``plan`` holds with every box widened
    by lam times the noise response's proxy (searched as :func:`tolerable_scale`; the terminal box
    re-designed for each lam, the plan and K unchanged)."""
    why = why_no_statement(gap)
    if why is not None:
        return None, why
    n, m = system.n, system.m
    K = np.asarray(plan.K, float).reshape(m, n)
    x_nom, u_nom = np.asarray(plan.x_nom, float), np.asarray(plan.u_nom, float).reshape(-1, m)
    T0 = plan.T0
    T = max(int(horizon), T0 + 1)
    sigma = np.sqrt(np.array([float(d.Mhat) for d in gap.dims]))
    # the fixed matrices of the noise's linear response: the closed loop's Jacobian at the plan, then at x*
    A_lin = mean_value_enclosure(imap, x_nom[:-1], np.zeros((T0, n)), u_nom, np.zeros((T0, m)), K, 1)[0] \
        if T0 else np.zeros((0, n, n))
    A_star = mean_value_enclosure(imap, plan.x_star[None], np.zeros((1, n)), plan.u_star[None], np.zeros((1, m)),
                                  K, 1)[0][0]
    if not (np.all(np.isfinite(A_lin)) and np.all(np.isfinite(A_star))):
        return None, "the closed loop's Jacobian along the plan is not finite"
    proxy = noise_proxy(np.concatenate([A_lin, np.repeat(A_star[None], T - T0, axis=0)]), sigma)  # (T + 1, n)
    tube_proxy, term_proxy = proxy[:T0 + 1], proxy[T0:].max(axis=0)
    p = TubePlan(plan.x_nom, plan.u_nom, plan.K, plan.x_star, plan.u_star, np.asarray(plan.H, float).copy())

    def design(lams):
        lams = np.asarray(lams, float)
        return design_H_batch(system, p, lo, hi, u_lo, u_hi, gap, imap, shells, np.ones(lams.size), target_lo,
                              target_hi, zbar=lams[:, None, None] * tube_proxy[None], A_lin=A_lin,
                              zbar_T=lams[:, None] * term_proxy[None], A_star=A_star)

    lam = largest_proved(lambda grid: [v.ok for v in design(grid)], passes)
    if lam <= 0:
        return None, "the tube's proof fails for any noise (4^-10 x the noise's proxy already)"
    if not np.isfinite(lam):
        return None, "the proof holds for any noise bound (no noise in the certificate)"
    v = design([lam])[0]
    if not v.ok:  # cannot happen (the search proved lam with the same design); never state it unproved
        return None, "the tube's proof at the noise bound found does not hold again"
    nt = NoiseTube(lam=float(lam), sigma=sigma, radii=np.asarray(v.radii, float),
                   H=np.asarray(v.terminal["H"], float), beta_cert=float(1.0 - gap.sup_confidence()), horizon=T,
                   extra={"max_proxy": proxy.max(axis=0).tolist()})
    return nt, ""


# ---------------------------------------------------------------------------------------
# front end
# ---------------------------------------------------------------------------------------

@dataclass
class BoxTubeResult:
    """``controller`` (None when no tube was proved), the proof, stats."""

    controller: object
    verification: Optional[TubeVerification]
    stats: dict = field(default_factory=dict)

    @property
    def empty(self) -> bool:
        return self.controller is None

    def summary(self) -> str:
        s = self.stats
        lines = [f"system        {s['system']} (tau = {s['tau']:g} s), box-tube synthesis (reach and stay)",
                 f"equilibrium   x* = {s['x_star']}, u* = {s['u_star']} (residual {s['residual_max']:.2g})",
                 f"feedback      K = {s['K']} ({s['K_how']}); spectral radius {s['spectral_radius']:.6f}",
                 f"plan          {s['T0']} periods from x0 = {s['x0']} (input margin {s['input_margin']:g}; pace "
                 f"x{s['plan_input_weight']:g}: {s.get('pace_how', 'given')})",
                 f"gap           {s['gap_how']}"]
        v = s.get("verification")
        if v is not None:
            t = v["terminal"]
            lines.append(f"tube          max half-widths {np.round(v['max_radius'], 6).tolist()}")
            lines.append(f"terminal box  x* +- H, H = {np.round(t['H'], 6).tolist()} (need "
                         f"{np.round(t['need'], 6).tolist()}, alpha {t['alpha']:.4g}, s {t['s']}; the smallest "
                         f"proved: {np.round(s['H_min'], 6).tolist()})")
            lines.append(f"gap at x*     w_max = {np.round(t['w_H'], 6).tolist()} per period; remainder "
                         f"{np.round(t['remainder'], 6).tolist()}")
        if not self.empty:
            lines.append(f"margin        gamma could be {s['gap_scale_text']} x larger with the proof still holding")
            nt = s.get("noise_tube")
            if nt is not None:
                lines.append("per run       " + (f"none: {nt['none']}" if "none" in nt else
                                                 f"P(a run stays in the noise tube for {nt['horizon']} periods) >= "
                                                 f"{nt['p_run']:.4g} (1 - beta_noise {nt['beta_noise']:.3g} - beta_cert "
                                                 f"{nt['beta_cert']:.3g}; the noise's response within {nt['lam']:.3g} "
                                                 f"x its proxy)"))
        else:
            lines.append(f"note          {s['diagnosis']}")
            if s.get("levers_text"):
                lines.append("levers        what gamma would have to lose per state, and what each lever needs:")
                lines.extend("              " + t for t in s["levers_text"])
        lines.append(f"time          {s['seconds']:.3f} s, peak memory {s['peak_rss_mb']:.0f} MB (process max RSS)")
        return "\n".join(lines)


def _box_tube_messages(fn):
    """Refusals raised by the helpers shared with the invariant-set method (equilibrium, LQR, K's
    shape) start "invariant set:"; here they name the method the user asked for."""
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except SimgapError as e:
            if str(e).startswith("invariant set:"):
                raise SimgapError("box tube:" + str(e)[len("invariant set:"):]) from None
            raise
    return wrapped


@_box_tube_messages
def synthesize_box_tube(system: System, spec: Spec, gap=None, *, x0, x_star=None, u_star=None, K=None,
                        lqr_q=None, lqr_r=None, target_lo=None, target_hi=None, shells: int = SHELLS,
                        input_margin: float = INPUT_MARGIN, margin_search: bool = True,
                        terminal: str = "largest", K_plan=None, plan_input_weight: Optional[float] = None,
                        per_run: bool = True, horizon: Optional[int] = None, log=None) -> BoxTubeResult:
    """Design and prove a box tube from x0 to a box around x* (module docstring).

    Parameters
    ----------
    system : System
        The nominal model f (a system file: its formulas are differentiated in intervals).
    spec : Spec
        An ``invariance`` specification without obstacles (the safe box S, never left).
    gap : None, constant vector (n,), or a Certificate
        The certified gap gamma per period (state units); None: the nominal model alone.
    x0 : (n,)
        The initial state (the tube starts at it exactly).
    x_star, u_star
        The equilibrium (default: least squares inside the target box, else the safe box).
    K : (m, n), optional
        The feedback gain. Default: among the LQR gains with Bryson's weights over the target box and the
        input range, the input weight scaled by 10^c (c in GAIN_EXPONENTS), the one whose tube tolerates the
        largest gap factor by the proof (with a gap and ``margin_search``; else the best by the linear mRPI
        estimate of :func:`gain_family`); with ``lqr_q``/``lqr_r`` the LQR with those weights.
    K_plan : (m, n), optional
        The gain of the nominal plan (default: the LQR with Bryson's weights over the safe box, a
        gentle loop that keeps the plan in X).
    plan_input_weight : float > 0, optional
        The plan's pace: multiplies the default plan's input weight: larger, a slower plan with smaller
        velocities (more room around it for the noise of single runs; more periods T0). Default: chosen
        among :data:`~simgap.synthesis.tube_design.PACES` by what each proves
        (:mod:`~simgap.synthesis.tube_design`; with ``margin_search=False`` the fastest pace that proves).
    target_lo, target_hi : optional
        The target box the state must reach and stay in (default: no target beyond S; the terminal
        box x* +- H is reported).
    shells : int
        Pieces of the mean-value integral (module docstring).
    input_margin : float in [0, 1)
        Fraction of each input's half-range the plan leaves for the feedback.
    margin_search : bool
        Also search the tolerable gap factor (a bisection of proofs; off in benchmarks of the design).
    terminal : "largest" or "smallest"
        The terminal box: the smallest H with need(H) <= H (the tightest statement about the mean), or
        the largest lam x room (lam = 1, 1/2, ..., 1/128; room: to the safe or target box) that still
        proves (noisy runs then rarely leave it). Both are reported.
    per_run : bool
        With a certificate that bounds the noise (sub-Gaussian, per-period noise), also the per-run
        statement of :mod:`.noise_tube` (the noise the proof tolerates; the controller carries its
        tube, the rollouts evaluate P(a run stays in it for T periods)) for runs of ``horizon``
        periods (default 2 T0 + 1, the rollouts' default).
    log : callable(str), optional
        Receives a line per design step (K, each pace, the proof, the margin, the per-run bound) and,
        from a :class:`~simgap.progress.StageLog`, a line at least every 10 s while a step runs.
    """
    t0 = time.perf_counter()
    from ..progress import StageLog
    if not isinstance(log, StageLog):
        log = StageLog("", log)
    with log:
        res = _synthesize_box_tube(system, spec, gap, x0, x_star, u_star, K, lqr_q, lqr_r, target_lo, target_hi,
                                   shells, input_margin, margin_search, terminal, K_plan, plan_input_weight, per_run,
                                   horizon, log)
    res.stats["seconds"] = time.perf_counter() - t0
    return res


def _synthesize_box_tube(system, spec, gap, x0, x_star, u_star, K, lqr_q, lqr_r, target_lo, target_hi, shells,
                         input_margin, margin_search, terminal, K_plan, plan_input_weight, per_run, horizon,
                         log) -> BoxTubeResult:
    if spec.kind != "invariance" or spec.obstacles:
        raise SimgapError("the box-tube synthesis handles an invariance specification (a safe box without "
                          "obstacles; the target box is given by target_lo / target_hi)")
    if int(shells) != shells or shells < 1:
        raise SimgapError(f"box tube: shells must be an integer >= 1, got {shells!r}")
    if terminal not in ("largest", "smallest"):
        raise SimgapError(f"box tube: terminal must be \"largest\" or \"smallest\", got {terminal!r}")
    if not 0.0 <= float(input_margin) < 1.0:
        raise SimgapError(f"box tube: input_margin must be in [0, 1), got {input_margin!r}")
    for key, weights in (("lqr_q", lqr_q), ("lqr_r", lqr_r)):
        one_of({"K": K, key: weights}, "the feedback gain", "K is used as given; lqr_q / lqr_r design it otherwise")
    if horizon is not None:  # priced before any work: the per-run statement's cost grows as horizon^2
        check_horizon(horizon, system.n)
    if gap is not None and hasattr(gap, "check_system"):
        gap.check_system(system)
    imap = IntervalMap(system)
    n, m = system.n, system.m
    x0 = np.asarray(x0, dtype=float).ravel()
    if x0.shape != (n,):
        raise SimgapError(f"box tube: x0 needs {n} values, got {x0.tolist()}")
    lo = np.maximum(spec.safe.lo, system.x_lo)
    hi = np.minimum(spec.safe.hi, system.x_hi)
    if np.any(lo >= hi):
        raise SimgapError("box tube: the safe box does not overlap X")
    if np.any(x0 < lo) or np.any(x0 > hi):
        i = int(np.flatnonzero((x0 < lo) | (x0 > hi))[0])
        raise SimgapError(f"box tube: x0 = {x0.tolist()} is outside the safe set ({system.state_names[i]} = "
                          f"{x0[i]:g} not in [{lo[i]:g}, {hi[i]:g}])")
    if (target_lo is None) != (target_hi is None):
        raise SimgapError("box tube: give both target_lo and target_hi, or neither")
    if target_lo is not None:
        target_lo, target_hi = np.asarray(target_lo, float), np.asarray(target_hi, float)
        if target_lo.shape != (n,) or target_hi.shape != (n,) or np.any(target_lo >= target_hi):
            raise SimgapError(f"box tube: target_lo / target_hi need {n} values each with lo < hi")
    msg = _check_region(gap, x0, x0, "x0")
    if msg:
        raise SimgapError(f"box tube: {msg}; start inside it or collect over a larger region")
    u_lo, u_hi = input_range(system, gap)
    if x_star is None and target_lo is not None:  # look for the equilibrium in the target
        x_star, u_star, r = find_equilibrium(system, np.maximum(lo, target_lo), np.minimum(hi, target_hi), u_lo,
                                             u_hi)
    else:
        x_star, u_star, r = find_equilibrium(system, lo, hi, u_lo, u_hi, x_star, u_star)
    A, B = linearize(system, x_star, u_star)
    room = np.minimum(x_star - lo, hi - x_star)
    if target_lo is not None:
        room = np.minimum(room, np.minimum(x_star - target_lo, target_hi - x_star))
    uroom = np.minimum(u_star - u_lo, u_hi - u_star)
    if np.any(room <= 0) or np.any(uroom <= 0):
        raise SimgapError(f"box tube: the equilibrium x* = {x_star.tolist()}, u* = {u_star.tolist()} lies on the "
                          f"boundary of the safe/target box or of the input range [{u_lo.tolist()}, "
                          f"{u_hi.tolist()}]: no room. Levers: a wider safe set or target box, a wider input range "
                          f"(the system's inputs, all certified), or x_star / u_star")
    sroom = np.minimum(x_star - lo, hi - x_star)
    if K is None or K_plan is None:
        check_stabilizable(A, B, system.state_names)
    if plan_input_weight is not None and not (np.isfinite(plan_input_weight) and plan_input_weight > 0):
        raise SimgapError(f"box tube: plan_input_weight must be a number > 0, got {plan_input_weight!r}")
    if K is None:
        if lqr_q is not None or lqr_r is not None:
            q = 1.0 / room ** 2 if lqr_q is None else _weights(lqr_q, n, "lqr_q")
            rr = 1.0 / uroom ** 2 if lqr_r is None else _weights(lqr_r, m, "lqr_r")
            if np.any(q < 0) or np.any(rr <= 0):
                raise SimgapError("box tube: LQR weights need q >= 0 and r > 0")
            K, K_how = lqr_gain(A, B, q, rr), "discrete LQR of the linearization (given weights)"
        else:
            K = None  # chosen below, by the proof
    else:
        K, K_how = _parse_matrix(K, m, n), "given"
    shells = int(shells)
    T_run = None if horizon is None else int(horizon)
    family = None
    if K is None:
        family = gain_family(A, B, x_star, u_star, room, uroom, gap, system)
        K, K_how = family[0][2], gain_how(family[0][1], family[0][0]) + ", chosen for box tolerance"

    def plan_for(pace, K):
        """The nominal plan at a pace (the plan's input weight factor), or the given K_plan (pace None),
        with the tube's gain K and its terminal box at the certified gap (design_H)."""
        if pace is None:
            Kp = _parse_matrix(K_plan, m, n)
            if spectral_radius(A + B @ Kp) >= 1:
                raise SimgapError("box tube: K_plan does not stabilize the linearization at x*")
        else:  # Bryson's weights over the safe box (gentle: the plan must stay in X), the input's x pace
            try:
                Kp = lqr_gain(A, B, 1.0 / sroom ** 2, float(pace) / uroom ** 2)
            except SimgapError as e:
                raise SimgapError(f"box tube: plan_input_weight = {pace!r}: the plan's LQR (input weight "
                                  f"plan_input_weight x Bryson's) has no stabilizing solution "
                                  f"({str(e).split(' (', 1)[-1]}; use a weight nearer 1 (0.1 .. 100), or give "
                                  "K_plan") from None
            if spectral_radius(A + B @ Kp) >= 1:
                raise SimgapError(f"box tube: K_plan (designed with plan_input_weight = {pace!r}) does not "
                                  "stabilize the linearization at x*; use a plan_input_weight nearer 1 (0.1 .. 100), "
                                  "or give K_plan")
        x_nom, u_nom = plan_nominal(system, x0, x_star, u_star, Kp, u_lo, u_hi, float(input_margin),
                                    tol=PLAN_TOL * room)
        plan = TubePlan(x_nom, u_nom, K, x_star, u_star, np.zeros(n))
        v = design_H(system, plan, lo, hi, u_lo, u_hi, gap, imap, shells, 1.0, target_lo, target_hi)
        return plan, v

    def horizon_of(plan):
        return 2 * plan.T0 + 1 if T_run is None else T_run

    from .tube_design import PACES, Candidate, best_candidate, why_chosen
    paces = (None,) if K_plan is not None else (PACES if plan_input_weight is None else (float(plan_input_weight),))
    rank = margin_search and gap is not None
    designs = {}
    state = {"rank": rank}  # switched off once a design proves every factor of the coarse grid (below)

    def evaluate(pace, K, gain=None):
        """A Candidate (plan, proof at the certified gap, and when ranking: the coarse margin and the
        coarse per-run bound); its design kept in ``designs``."""
        c = Candidate(pace=1.0 if pace is None else pace, gain=gain, extra={"horizon": T_run})
        t1 = time.perf_counter()
        try:
            plan, v = plan_for(pace, K)
        except SimgapError as e:
            c.error = str(e).removeprefix("box tube: ")
        else:
            c.T0, c.proved = plan.T0, bool(v.ok)
            designs[id(c)] = (plan, v, K)
            # enough to rank designs against each other (a plan the runs outlast ranks as unproved: no margin)
            if state["rank"] and (T_run is None or plan.T0 < T_run):
                c.margin = coarse_margin(system, plan, lo, hi, u_lo, u_hi, gap, imap, shells, target_lo, target_hi)
                if v.ok and per_run and why_no_statement(gap) is None:
                    nt_c, _ = noise_tube(system, plan, lo, hi, u_lo, u_hi, gap, imap, shells, horizon_of(plan),
                                         target_lo, target_hi, passes=2)
                    c.lam = None if nt_c is None else nt_c.lam
        c.seconds = time.perf_counter() - t1
        log(c.row())
        return c

    # ----- 1. the pace (given, or the best of PACES) with the heuristic's (or the given) K -----
    cands = []
    search = len(paces) > 1
    n_gains = min(len(family) - 1, 3) if family is not None and rank and len(family) > 1 else 0
    for k, pace in enumerate(paces):
        log.doing(f"pace x{1.0 if pace is None else pace:g} ({k + 1} of {len(paces)}): plan, terminal box"
                  + (", margin, per-run bound" if rank else ""))
        c = evaluate(pace, K, None if family is None else family[0][1])
        cands.append(c)
        if k == 0 and rank and c.proved and c.margin is not None and np.isinf(c.margin):
            # every factor of the coarse grid proves (a gap far below what the tube tolerates, the deterministic
            # baseline's): the ranking cannot tell designs apart; the fastest pace that proves, the heuristic's K
            rank = state["rank"] = False
            n_gains = 0
            log("the proof holds at every gap factor up to 5.7: designs not ranked (the fastest pace that proves, "
                "the linear estimate's gain)")
        if k == 0 and rank and (search or n_gains):
            log(f"estimate: about {(len(paces) - 1 + n_gains + 2) * c.seconds:.0f} s more for "
                f"{len(paces) - 1} more paces, about {n_gains} more gains and the chosen design's full searches (the "
                f"first design took {c.seconds:.1f} s; slower paces have longer plans)")
        if search and not rank and c.proved:  # no ranking asked for: the fastest pace that proves
            break
        if search and T_run is not None and c.T0 is not None and c.T0 >= T_run:
            if k + 1 < len(paces):  # slower paces have longer plans still
                log(f"paces x{', x'.join(f'{p:g}' for p in paces[k + 1:])} not tried: slower still")
            break
        if search and len(cands) >= 2 and c.proved and cands[-2].proved and \
                c.score(n, T_run or 0)[:3] <= cands[-2].score(n, T_run or 0)[:3] and k + 1 < len(paces):
            # a slower pace that proves no more than the previous one: slower still only adds periods
            log(f"paces x{', x'.join(f'{p:g}' for p in paces[k + 1:])} not tried: x{c.pace:g} proved no more "
                f"than x{cands[-2].pace:g}")
            break
    best = best_candidate(cands, n, T_run or 0)
    if best.error:
        raise SimgapError(f"box tube: {best.error}" + ("" if len(cands) == 1 else
                          f" (paces tried: {', '.join(c.row() for c in cands)})"))
    pace_how = ("given (K_plan)" if paces == (None,) else f"given (plan_input_weight = {best.pace:g})"
                if not search else why_chosen(best, cands) if rank else
                "the fastest pace that proves (" + ("no gap" if gap is None else "the gap is far below what it "
                                                    "tolerates") + ": nothing to rank designs by)")
    if search:
        log(f"pace: x{best.pace:g}, {pace_how}")

    # ----- 2. K at that pace: the LQR family climbed by the proof from the heuristic's pick -----
    if n_gains:
        pace = None if paces == (None,) else best.pace
        by_c = sorted(family, key=lambda t: t[1])       # the family along its input-weight exponent c
        cs = [t[1] for t in by_c]
        tried = {family[0][1]: best}
        key = lambda c: tried[c].score(n, T_run or 0)  # noqa: E731

        def at(i):
            c_exp = cs[i]
            if c_exp not in tried:
                log.doing(f"K with input weight x 10^{c_exp:g} at pace x{best.pace:g}")
                tried[c_exp] = evaluate(pace, by_c[i][2], c_exp)
                cands.append(tried[c_exp])
            return tried[c_exp]

        # hill-climb along c (the margin is close to unimodal in the input weight): both neighbours of the
        # heuristic's pick, then on in the better direction while a step improves
        i0 = cs.index(family[0][1])
        for step in (-1, 1):
            if 0 <= i0 + step < len(cs):
                at(i0 + step)
        i = max((j for j in (i0 - 1, i0, i0 + 1) if 0 <= j < len(cs)), key=lambda j: key(cs[j]))
        if i != i0:
            step = i - i0
            while 0 <= i + step < len(cs) and key(at(i + step).gain) > key(cs[i]):
                i += step
        chosen = tried[cs[i]]
        j = [t[1] for t in family].index(chosen.gain)
        K_how = gain_how(family[j][1], family[j][0]) + (
            f", chosen by the proof among the {len(tried)} gains tried (margin {chosen.margin:.3g}"
            + ("" if chosen.lam is None else f", per-run bound {chosen.lam:.3g}") + ")")
        best = chosen
    plan, v, K = designs[id(best)]
    rho0 = spectral_radius(A + B @ K)
    if rho0 >= 1:
        raise SimgapError(f"box tube: K does not stabilize the linearization at x*: spectral radius {rho0:.6g} >= 1")
    log(f"feedback K: {K_how}; spectral radius {rho0:.4f}")

    H_min = plan.H.copy()
    if v.ok and terminal == "largest":
        # the largest box lam x room (lam = 1, 1/2, ..., 1/128) that still proves (one batched evaluation):
        # a weaker claim about the mean than H_min, but noisy runs then rarely leave it
        log.doing("terminal box: the largest that proves")
        ph = tube_phase(system, plan, gap, imap, shells, u_range=(u_lo, u_hi))
        room_t = _room(plan, lo, hi, target_lo, target_hi)
        cands_H = np.maximum(H_min, (0.5 ** np.arange(8))[:, None] * room_t * (1 - 1e-9))
        terms = terminal_phases(system, plan, [ph["G"]] * len(cands_H), cands_H, gap, imap, shells,
                                u_range=(u_lo, u_hi))
        for Hc, term in zip(cands_H, terms):
            if all(c["ok"] for c in judge(system, plan, Hc, ph, term, lo, hi, u_lo, u_hi, target_lo, target_hi)):
                plan.H = Hc
                break
    if v.ok:  # the proof again from the plan alone (design_H reused (T)'s propagation across its rounds)
        log.doing(f"the proof of the chosen tube ({plan.T0} periods)")
        v = verify_tube(system, plan, lo, hi, u_lo, u_hi, gap, target_lo=target_lo, target_hi=target_hi,
                        imap=imap, shells=shells)
        log(f"proof: {'holds' if v.ok else 'FAILS'} over {plan.T0} periods and the terminal box "
            f"H = {np.round(plan.H, 6).tolist()}")
    stats = {"system": system.name, "tau": system.tau, "x_star": np.round(x_star, 9).tolist(),
             "u_star": np.round(u_star, 9).tolist(), "residual_max": float(np.abs(r).max()),
             "K": np.round(K, 6).tolist(), "K_how": K_how, "spectral_radius": rho0, "T0": plan.T0,
             "x0": x0.tolist(), "input_margin": float(input_margin), "shells": shells,
             "spec_kind": "reach_and_stay", "gap_how": v.gap_how, "verification": v.to_dict(),
             "target": None if target_lo is None else {"lo": target_lo.tolist(), "hi": target_hi.tolist()},
             "H": plan.H.tolist(), "H_min": H_min.tolist(), "terminal": terminal,
             "plan_input_weight": float(best.pace), "pace_how": pace_how, "designs": [c.to_dict() for c in cands]}
    scale = None
    if margin_search:
        log.doing("the margin: the largest gap factor the proof holds with")
        scale = tolerable_scale(system, plan, lo, hi, u_lo, u_hi, gap, imap, shells, target_lo, target_hi)
        log("margin: " + ("any gap factor (no gap)" if np.isinf(scale) else
                          f"gamma could be {scale:.4g} x its bound with the proof still holding"))
    stats["gap_scale"] = None if scale is None or np.isinf(scale) else scale
    stats["gap_scale_text"] = ("not searched" if scale is None else "any factor (no gap)" if np.isinf(scale)
                               else f"{scale:.4g}")
    nt = None
    if v.ok and per_run:
        log.doing("the per-run statement: the largest noise bound the proof holds with")
        nt, why = noise_tube(system, plan, lo, hi, u_lo, u_hi, gap, imap, shells, horizon_of(plan), target_lo,
                             target_hi)
        stats["noise_tube"] = nt.to_dict() if nt is not None else {"none": why}
        log("per run: " + (f"P(a run stays in the noise tube) >= {nt.to_dict()['p_run']:.4g}" if nt is not None
                           else f"none ({why})"))
    ctrl = None
    if v.ok:
        from .tube_controller import TubeController
        meta = {"stats": stats, "gap": _describe_gap(gap), "x0": x0.tolist(), "margins": {
            "gap_scale": "inf" if scale is not None and np.isinf(scale) else scale,
            "what": "the largest factor s such that the tube proof holds under s * w_max (w_max: the gap's "
                    "bound over each box)"}}
        ctrl = TubeController(plan, v.radii, system=system, spec=spec, meta=meta, noise_tube=nt)
    else:
        stats["diagnosis"] = "no tube proved: " + "; ".join(f"{c['name']} fails ({c['what']})" for c in v.failed())
        if scale is not None and np.isfinite(scale):
            stats["diagnosis"] += (f"; the proof holds with gamma at most {scale:.3g} x its bound" if scale > 0 else
                                   "; not even without the gap")
        stats["diagnosis"] += ("; levers: the plan's pace ([synthesis] plan_input_weight, now "
                               f"{float(best.pace):g}; larger = gentler inputs), the input range (the system's "
                               "inputs), X and the safe set, K (or lqr_q / lqr_r), the terminal box (target_lo / "
                               "target_hi), and a smaller gamma (more runs N1hat, a [collect] region around the tube, "
                               "a refined model: docs/synthesis.md)")
        if gap is not None and scale is not None and np.isfinite(scale):
            from .tube_design import levers
            w_max, left = np.asarray(v.to_dict()["w_max"], float), ""
            if not np.all(np.isfinite(w_max)) and scale > 0:
                # at the certified gap the tube leaves the data's boxes (no gamma there: inf); the tube at the
                # tolerable factor s stays inside, and its gap over the boxes divided by s is the gamma to reduce
                # (the gamma the table shows: over a narrower tube than the one at s = 1)
                left = next((c["what"] for c in v.failed() if c["name"] == "boxes inside the certificate's region"), "")
                vs = design_H_batch(system, plan, lo, hi, u_lo, u_hi, gap, imap, shells, (scale,), target_lo,
                                    target_hi)[0]
                w_max = np.asarray(vs.to_dict()["w_max"], float) / scale
            lv = levers(gap if hasattr(gap, "dims") else None, system, w_max, scale,
                        cands if len(cands) > 1 else [], left=left)
            stats["levers"] = {k: lv[k] for k in ("states", "designs")}
            stats["levers_text"] = lv["text"]
    stats["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return BoxTubeResult(ctrl, v, stats)


__all__ = ["BoxTubeResult", "gain_family", "TubePlan", "TubeVerification", "largest_proved", "mean_value_enclosure", "noise_tube",
           "plan_nominal", "synthesize_box_tube", "terminal_bound", "tolerable_scale", "verify_tube"]

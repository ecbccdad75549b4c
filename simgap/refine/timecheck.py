"""Does the remaining residual, or a selected coefficient, depend on time?

The structure test (:mod:`simgap.refine.structure`) looks at the residual as a function of the
variables (x, u, lagged u); a disturbance that depends on time, or a coefficient that drifts over
the record, is invisible there. Two checks on time-ordered data (rows in time order, episode by
episode, :func:`simgap.refine.data.time_order`):

* **time in the residual** (:func:`time_structure`): the remaining residual e is regressed on the
  probe's degree-2 polynomial in the variables (the baseline) and what that leaves on a time basis:
  Legendre polynomials of degree 1-3 in the position in the record s in [0, 1] (a drift across
  the record), of degree 1-2 in the time since the episode started (within episodes, when there
  are several), and sin / cos of the dominant frequency of e in the clock t and its second
  harmonic (a periodic disturbance; the frequency from the periodogram of the train rows on the
  uniform grid of t, periods between 4 tau and a quarter of the span). The held-out R^2 gained by
  the time basis over the baseline is the share of what is left that time explains; the pieces
  (drift, within-episode, periodic) are reported with their size;
* **a coefficient over the record** (:func:`segment_coefficients`): the selected terms refitted
  on ``segments`` consecutive parts of the record; Cochran's Q of the per-segment estimates
  (least-squares errors inflated by the residual's block length, so correlated noise is not
  taken for variation) against chi^2 with segments - 1 degrees of freedom.
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from .structure import gain_z

#: chi^2 quantile (0.999) for 1..9 degrees of freedom: a coefficient varies over the record beyond this
CHI2_999 = (10.83, 13.82, 16.27, 18.47, 20.52, 22.46, 24.32, 26.12, 27.88)


def _legendre(z: np.ndarray, deg: int) -> list:
    """P_1..P_deg of z mapped to [-1, 1]."""
    lo, hi = float(z.min()), float(z.max())
    w = 2 * (z - lo) / (hi - lo) - 1 if hi > lo else np.zeros_like(z)
    return [np.polynomial.legendre.Legendre.basis(d)(w) for d in range(1, deg + 1)]


def _r2_heldout(A: np.ndarray, e: np.ndarray, held: np.ndarray) -> tuple:
    """(held-out R^2, coefficients) of a ridge-stabilized least-squares fit of e on A (train rows)."""
    tr = ~held
    G = A[tr].T @ A[tr]
    w = np.linalg.solve(G + 1e-9 * np.trace(G) / A.shape[1] * np.eye(A.shape[1]), A[tr].T @ e[tr])
    eh = e[held]
    ss = float(eh @ eh)
    return (1.0 - float(np.sum((eh - A[held] @ w) ** 2)) / ss if ss > 0 else 0.0), w


def dominant_period(e: np.ndarray, t: np.ndarray, tau: float, rows: np.ndarray) -> Optional[float]:
    """Period [s] of the largest periodogram peak of e (on ``rows``) on the uniform grid of t."""
    g = np.round((t[rows] - t.min()) / tau).astype(np.int64)
    n = int(g.max()) + 1
    if n < 16:
        return None
    z = np.bincount(g, weights=e[rows] - e[rows].mean(), minlength=n)
    m = 1 << int(np.ceil(np.log2(n)))
    P = np.abs(np.fft.rfft(z, m)) ** 2
    f = np.fft.rfftfreq(m, d=tau)
    ok = (f >= 4.0 / (n * tau)) & (f <= 1.0 / (4 * tau))
    if not ok.any():
        return None
    f0, df = float(f[ok][np.argmax(P[ok])]), float(f[1] - f[0])
    # refine within +-1 bin (the grid's resolution drifts the phase over a long record)
    fs = f0 + df * np.linspace(-1, 1, 81)
    ph = 2 * np.pi * np.outer(t[rows], fs)
    er = e[rows] - e[rows].mean()
    power = (er @ np.sin(ph)) ** 2 + (er @ np.cos(ph)) ** 2
    return float(1.0 / fs[np.argmax(power)])


def time_structure(e: np.ndarray, t: np.ndarray, episode: np.ndarray, tau: float, held: np.ndarray,
                   resid: Callable, series: bool = True) -> dict:
    """Share of the remaining residual e (rows in time order) that time explains beyond the variables.

    ``resid(M)`` removes from M (K,) or (K, b) its baseline fit in the variables (the probe's degree-2
    polynomial, fitted on train rows): the time basis and e both pass through it, so fitting the
    residualized e on the residualized basis is the joint fit (Frisch-Waugh) with small solves only;
    its held-out gain is divided by the held-out sum of squares of e.
    Returns ``{"r2_gain", "z", "dof", "drift": {...}, "within_episode": {...} | None, "periodic": {...} | None}``
    (z, dof: the whole basis's paired held-out statistic, :func:`simgap.refine.structure.gain_z`)
    (see the module docstring); each piece carries its own held-out gain and its size in the
    residual's units: the drift from the first to the last tenth of the record, the periodic part's
    period and amplitude.
    """
    K = e.size
    e0 = resid(e)
    s = np.arange(K) / max(K - 1, 1)
    pieces = {"drift": np.stack(_legendre(s, 3), axis=1)}
    if int(np.unique(episode).size) > 1:
        first = np.r_[True, episode[1:] != episode[:-1]]
        start = np.maximum.accumulate(np.where(first, t, -np.inf))
        pieces["within_episode"] = np.stack(_legendre(t - start, 2), axis=1)
    period = dominant_period(e0, t, tau, np.flatnonzero(~held))
    if period is not None:
        ph = 2 * np.pi * t / period
        pieces["periodic"] = np.stack([np.sin(ph), np.cos(ph), np.sin(2 * ph), np.cos(2 * ph)], axis=1)
    ss = float(e[held] @ e[held])
    ss0 = float(e0[held] @ e0[held])

    pieces0 = {k: resid(B) for k, B in pieces.items()}

    def gain(B, B0):
        _, w = _r2_heldout(B0, e0, held)
        r = e0[held] - B0[held] @ w
        fitted = B @ w
        return (min(1.0, max(0.0, ss0 - float(r @ r)) / ss) if ss > 0 else 0.0), fitted - fitted.mean(), r

    g_all, _, r_all = gain(np.concatenate(list(pieces.values()), axis=1),
                           np.concatenate(list(pieces0.values()), axis=1))
    z, dof = gain_z(e0[held], r_all, series)
    out = {"r2_gain": g_all, "z": z, "dof": int(dof), "drift": None, "within_episode": None, "periodic": None}
    for name, B in pieces.items():
        g, fitted, _ = gain(B, pieces0[name])
        d = {"r2_gain": g}
        if name == "drift":
            tenth = max(1, K // 10)
            d.update({"first_tenth": float(fitted[:tenth].mean()), "last_tenth": float(fitted[-tenth:].mean())})
        elif name == "periodic":
            d.update({"period": period, "amplitude": float(np.sqrt(2.0) * fitted.std())})
        else:
            d.update({"range": float(np.ptp(fitted))})
        out[name] = d
    return out


def describe_time(ts: dict, unit: str = "") -> str:
    """One line saying what time explains (pieces whose held-out gain is at least 1 %)."""
    parts = []
    p = ts.get("periodic")
    if p and p["r2_gain"] >= 0.01:
        parts.append(f"periodic in t (period {p['period']:.4g} s, amplitude {p['amplitude']:.3g}{unit}, "
                     f"{100 * p['r2_gain']:.0f}% of what is left)")
    d = ts.get("drift")
    if d and d["r2_gain"] >= 0.01:
        parts.append(f"drift over the record (mean {d['first_tenth']:.3g} -> {d['last_tenth']:.3g}{unit}, "
                     f"{100 * d['r2_gain']:.0f}%)")
    w = ts.get("within_episode")
    if w and w["r2_gain"] >= 0.01:
        parts.append(f"varies within episodes (range {w['range']:.3g}{unit}, {100 * w['r2_gain']:.0f}%)")
    return "; ".join(parts) or f"time explains {100 * ts['r2_gain']:.0f}% of what is left"


def segment_coefficients(Z: np.ndarray, y: np.ndarray, block: int, segments: int = 4) -> Optional[dict]:
    """Per-segment least-squares coefficients of y ~ Z over consecutive parts of the record.

    Rows are in time order. Returns ``{"coef": (G, p), "stderr": (G, p), "q": (p,), "varying": (p,)
    bool}`` with Cochran's Q per term against the 0.999 chi^2 quantile; None when a segment is too
    small or singular.
    """
    K, p = Z.shape
    if p == 0 or segments < 2 or K < segments * 20 * p:
        return None
    edges = np.linspace(0, K, segments + 1).astype(int)
    C, S = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        Zg, yg = Z[a:b], y[a:b]
        G = Zg.T @ Zg
        if np.linalg.cond(G) > 1e10:
            return None
        c = np.linalg.solve(G, Zg.T @ yg)
        s2 = float(np.sum((yg - Zg @ c) ** 2)) / max(b - a - p, 1) * max(block, 1)
        C.append(c), S.append(np.sqrt(s2 * np.diag(np.linalg.inv(G))))
    C, S = np.array(C), np.array(S)
    W = 1.0 / np.maximum(S, 1e-300) ** 2
    cw = (W * C).sum(axis=0) / W.sum(axis=0)
    Q = (W * (C - cw) ** 2).sum(axis=0)
    return {"coef": C, "stderr": S, "q": Q, "varying": Q > CHI2_999[min(segments - 2, len(CHI2_999) - 1)]}

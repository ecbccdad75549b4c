"""Compiled kernels (numba; imported only when :mod:`simgap.jit` says so): the RK4 of the reference
systems and the successor boxes of a block of pairs (:func:`box_offsets`). The predecessor index
and the reach game's level are C (:mod:`.game_kernels`), a system file's whole pass too
(:mod:`.grid_kernel`).

Each RK4 kernel integrates x' = F(x, u) over tau with ``nint`` classical RK4 substeps, row by row,
in exactly the operation order of :func:`~simgap.runge_kutta.rk4_integrate` and of the
numpy right-hand side it replaces (SCOTS's order)::

    k0 = F(x);  k1 = F(k0 (h/2) + x);  k2 = F(k1 (h/2) + x);  k3 = F(k2 h + x)
    x <- x + ((((k0 + (k1 + k1)) + (k2 + k2)) + k3) (h/6)),     h = tau / nint

so the results are the same bits (no fast-math: no reassociation, no fused multiply-add; the
transcendental functions are the C library's, as numpy's on this platform; asserted by
tests/test_compiled_kernels.py). Without the per-element temporaries of the numpy path, the
vehicle's step is about 2x faster per row (and evaluates the second and third slopes once: they
are taken at the same heading), the DC-DC converter's about 8x.

Compiled with ``cache=True``: the machine code is stored next to this file (or in numba's user
cache when that is not writable) and loaded by later processes instead of compiled again
(first compile about 1 s per kernel; a cached load about 0.05 s).
"""

from __future__ import annotations

import math

import numpy as np
from ..jit import njit


def _compiled(fn=None, **kw):
    if fn is None:
        return lambda f: _compiled(f, **kw)
    kw.setdefault("error_model", "numpy")  # x / 0 gives inf or nan as numpy does, no exception
    return njit(**kw)(fn)


@_compiled
def vehicle_rk4(X, alpha, ca, v, dth, tau, nint):
    """SCOTS vehicle (``examples._vehicle_rhs_prepared``): x' = (cos(alpha + th) v)/cos(alpha),
    y' = (sin(alpha + th) v)/cos(alpha), th' = dth, on the input terms of
    ``examples._vehicle_input_terms`` per row (alpha = atan(tan(u1)/2), its cosine ca, v = u0,
    dth = u0 tan(u1)), computed by numpy: the C library's tan and atan differ from numpy's in
    the last bit for about 1 % of arguments, its cos and sin do not. X (B, 3) -> (B, 3)."""
    B = X.shape[0]
    h = tau / nint
    h2 = h / 2
    h6 = h / 6
    out = np.empty((B, 3))
    for i in range(B):
        al, c_a, vi, dt = alpha[i], ca[i], v[i], dth[i]
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        pa, pc, ps = math.nan, 0.0, 0.0  # the last slope's angle and its cosine and sine
        for _ in range(nint):
            a = al + x2
            # the first slope's angle is usually the previous substep's last one, bit for bit
            # (x2 + 6 dth h/6 rounds to x2 + dth h for about 97 % of the grid's rows): the same
            # argument gives the same cosine and sine, so they are reused (zero: its sign matters)
            if a == pa and a != 0.0:
                c, sn = pc, ps
            else:
                c, sn = math.cos(a), math.sin(a)
            k0 = c * vi / c_a
            k1 = sn * vi / c_a
            a0, a1, a2 = k0, k1, dt
            # the second and third slopes are evaluated at the same heading, x2 + (h/2) dth
            # (theta' = dth does not depend on the state): the same values, computed once
            a = al + (dt * h2 + x2)
            k0 = math.cos(a) * vi / c_a
            k1 = math.sin(a) * vi / c_a
            a0 += k0 + k0
            a1 += k1 + k1
            a2 += dt + dt
            a0 += k0 + k0
            a1 += k1 + k1
            a2 += dt + dt
            pa = al + (dt * h + x2)
            pc, ps = math.cos(pa), math.sin(pa)
            k0 = pc * vi / c_a
            k1 = ps * vi / c_a
            a0 += k0
            a1 += k1
            a2 += dt
            x0 += a0 * h6
            x1 += a1 * h6
            x2 += a2 * h6
        out[i, 0] = x0
        out[i, 1] = x1
        out[i, 2] = x2
    return out


@_compiled
def dcdc_rk4(X, U, tau, nint, A, b0):
    """Boost DC-DC converter (``examples._dcdc_rhs``): mode 2 (u > 1.5) x' = A[1] x + (b0, 0)
    as (e x0 + f x1) + b0 and g x0 + h x1; mode 1 a x0 + b0 and d x1. A (2, 2, 2), X (B, 2)."""
    B = X.shape[0]
    h = tau / nint
    h2 = h / 2
    h6 = h / 6
    out = np.empty((B, 2))
    for i in range(B):
        x0, x1 = X[i, 0], X[i, 1]
        if U[i, 0] > 1.5:
            e, f, g, hh = A[1, 0, 0], A[1, 0, 1], A[1, 1, 0], A[1, 1, 1]
            for _ in range(nint):
                k0 = (e * x0 + f * x1) + b0
                k1 = g * x0 + hh * x1
                a0, a1 = k0, k1
                t0, t1 = k0 * h2 + x0, k1 * h2 + x1
                k0 = (e * t0 + f * t1) + b0
                k1 = g * t0 + hh * t1
                a0 += k0 + k0
                a1 += k1 + k1
                t0, t1 = k0 * h2 + x0, k1 * h2 + x1
                k0 = (e * t0 + f * t1) + b0
                k1 = g * t0 + hh * t1
                a0 += k0 + k0
                a1 += k1 + k1
                t0, t1 = k0 * h + x0, k1 * h + x1
                k0 = (e * t0 + f * t1) + b0
                k1 = g * t0 + hh * t1
                a0 += k0
                a1 += k1
                x0 += a0 * h6
                x1 += a1 * h6
        else:
            a, d = A[0, 0, 0], A[0, 1, 1]
            for _ in range(nint):
                k0 = a * x0 + b0
                k1 = d * x1
                a0, a1 = k0, k1
                t0, t1 = k0 * h2 + x0, k1 * h2 + x1
                k0 = a * t0 + b0
                k1 = d * t1
                a0 += k0 + k0
                a1 += k1 + k1
                t0, t1 = k0 * h2 + x0, k1 * h2 + x1
                k0 = a * t0 + b0
                k1 = d * t1
                a0 += k0 + k0
                a1 += k1 + k1
                t0, t1 = k0 * h + x0, k1 * h + x1
                k0 = a * t0 + b0
                k1 = d * t1
                a0 += k0
                a1 += k1
                x0 += a0 * h6
                x1 += a1 * h6
        out[i, 0] = x0
        out[i, 1] = x1
    return out


@_compiled(inline="always")
def _offset(v, base, limit):
    """``abstraction._cell_offset`` of one value: floor(v) - base, NaN -> 0 - base, clipped to
    +-limit before and after."""
    v = np.floor(v)
    if v != v:
        v = 0.0
    v = min(max(v, -limit), limit) - base
    return min(max(v, -limit), limit)


@_compiled
def box_offsets(x, r, z, eta, first, dom_lo, dom_hi, mi, inv_mask, limit, lo_out, hi_out, ok_out):
    """The successor boxes of a block of pairs in ``build_abstraction`` (no periodic dimension),
    SCOTS's formula in absolute coordinates: left = (x - r) - z, right = (x + r) + z; the pair is
    valid when x and r are finite and (outside the invariant dimensions) the box stays inside
    (dom_lo, dom_hi); offsets floor((left - first + eta/2) / eta) - mi (and right's), stored
    into ``lo_out``/``hi_out`` (float, or the abstraction's int8/int16 tables: an offset out of
    their range is stored wrapped, and the caller redoes the block with wider tables). Returns
    the least and the greatest offset stored."""
    P, n = x.shape
    vmin = limit
    vmax = -limit
    for i in range(P):
        good = True
        out = False
        for d in range(n):
            xd = x[i, d]
            rd = r[i, d]
            if not (np.isfinite(xd) and np.isfinite(rd)):
                good = False
            left = xd - rd - z[d]
            right = xd + rd + z[d]
            if not inv_mask[d] and (left <= dom_lo[d] or right >= dom_hi[d]):
                out = True
            a = _offset((left - first[d] + eta[d] / 2) / eta[d], mi[i, d], limit)
            b = _offset((right - first[d] + eta[d] / 2) / eta[d], mi[i, d], limit)
            vmin = min(vmin, a, b)
            vmax = max(vmax, a, b)
            lo_out[i, d] = a
            hi_out[i, d] = b
        ok_out[i] = good and not out
    return vmin, vmax

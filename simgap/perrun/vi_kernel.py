"""Compiled row kernel of pessimistic interval value iteration (numba; imported on first use).

For every row r (a (cell, input) pair) with entries t = row_ptr[r] .. row_ptr[r+1]-1 on
successor columns col[t], bounds lo[t] <= p_t <= hi[t] and values V = Vx[col[t]] (the sink's
value 0 appended), the adversary's minimum of sum_t p_t V_t over sum p = 1 is

    Q(r) = sum_t lo_t V_t + sum over entries in ascending V of min(cap_t, mass left) V_t,

cap = hi - lo, mass 1 - sum lo (Givan et al. 2000: fill the lowest values first). Only the
entries below the value at which the mass runs out matter, and among equal values the order is
irrelevant, so a weighted quickselect (three-way partition around a pivot value, recursing into
the side where the mass runs out) gives Q(r) in O(row length) expected time, without sorting the
row and without any array the size of the entries: two scratch vectors of the longest row.

Compiled with ``cache=True``: the machine code is stored next to this file (or in numba's user
cache when that is not writable) and loaded in later processes instead of compiled again.
"""

from __future__ import annotations

import numpy as np
from ..jit import njit


def _compiled(fn):
    return njit()(fn)


@_compiled
def _pour(vs, cs, w, F):
    """sum of min(cap, mass left) * v over the entries in ascending v, mass F > 0 (module docstring)."""
    acc = 0.0
    i0, i1 = 0, w
    while i1 > i0:
        a, b, c = vs[i0], vs[(i0 + i1) // 2], vs[i1 - 1]  # median of three
        p = max(min(a, b), min(max(a, b), c))
        lt, i, gt = i0, i0, i1  # [i0, lt) < p, [lt, i) == p, [gt, i1) > p
        cl = 0.0
        cvl = 0.0
        ce = 0.0
        while i < gt:
            v = vs[i]
            if v < p:
                c_i = cs[i]
                vs[i], cs[i] = vs[lt], cs[lt]
                vs[lt], cs[lt] = v, c_i
                cl += c_i
                cvl += c_i * v
                lt += 1
                i += 1
            elif v > p:
                gt -= 1
                c_i = cs[i]
                vs[i], cs[i] = vs[gt], cs[gt]
                vs[gt], cs[gt] = v, c_i
            else:
                ce += cs[i]
                i += 1
        if F <= cl:  # the mass runs out below p
            i1 = lt
        elif F <= cl + ce:  # ... at p
            return acc + cvl + (F - cl) * p
        else:  # everything up to p is filled; go on above it
            acc += cvl + ce * p
            F -= cl + ce
            i0 = gt
    return acc  # caps exhausted before the mass (sum hi < 1): what the caps hold


@_compiled
def pessimistic_rows(row_ptr, col, lo, hi, Vx, Q):
    """Q[r] for every row (module docstring). lo, hi float32 read as float64; Vx (C+1,) float64."""
    R = row_ptr.size - 1
    wmax = 0
    for r in range(R):
        wmax = max(wmax, row_ptr[r + 1] - row_ptr[r])
    vs = np.empty(wmax)
    cs = np.empty(wmax)
    for r in range(R):
        a = row_ptr[r]
        w = row_ptr[r + 1] - a
        base = 0.0
        slo = 0.0
        for t in range(w):
            l = np.float64(lo[a + t])
            v = Vx[col[a + t]]
            slo += l
            base += l * v
            vs[t] = v
            cs[t] = np.float64(hi[a + t]) - l
        F = 1.0 - slo
        Q[r] = base + _pour(vs, cs, w, F) if F > 0.0 else base

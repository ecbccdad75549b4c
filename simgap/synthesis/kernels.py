"""Compiled kernels (numba; imported only when :mod:`simgap.jit` says so): the successor boxes of a
block of pairs (:func:`box_offsets`), for a system with a compiled step of its own when numba is
loaded anyway. A system file's whole pass is one generated C kernel (:mod:`.grid_kernel`, also the
built-in examples' step since their hand-written RK4 kernels were retired), the predecessor index
and the games are C (:mod:`.game_kernels`).
"""

from __future__ import annotations

import numpy as np
from ..jit import njit


def _compiled(fn=None, **kw):
    if fn is None:
        return lambda f: _compiled(f, **kw)
    kw.setdefault("error_model", "numpy")  # x / 0 gives inf or nan as numpy does, no exception
    return njit(**kw)(fn)


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

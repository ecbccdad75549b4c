"""Predecessors through the lo corners of the successor boxes (one class per cell, small boxes).

Without shared boxes every (cell, input) pair q = c * M + u has its own successor box
[lo(q), lo(q) + ext(q) - 1] (multi-index units). SCOTS inverts this relation with one list entry
per transition. When the boxes are small, one entry per *pair* is enough: the pairs sorted by
the flat id of their box's lo corner (a CSR over the N cells). The pairs whose box holds cell r
have their lo corner at r - a for some a in [0, e_max) (per dimension, e_max the largest
extent; wrapped in periodic dimensions), so a query visits prod(e_max) rows per cell and keeps
the pairs with a < ext(q) in every dimension: exactly one entry per transition (r, q), as
SCOTS's list, at a fraction of the memory and build time (a 1-D stable sort of the pairs'
corner ids, which come in long ascending runs input by input).

The index depends only on the abstraction (the pairs whose image is finite and whose box stays
inside the grid), not on the specification, so :func:`~simgap.synthesis.abstraction.build_abstraction`
builds it, as SCOTS builds its predecessor lists with the abstraction; games filter the pairs
it returns by their own live/open flags.
"""

from __future__ import annotations

from typing import Optional

import numpy as np


def expand_counts(counts: np.ndarray):
    """Rows with ``counts`` items each -> (row of every item, rank of the item in its row)."""
    it = np.int32 if counts.size < 2 ** 31 and counts.sum() < 2 ** 31 else np.int64
    rows = np.repeat(np.arange(counts.size, dtype=it), counts)
    starts = (np.cumsum(counts, dtype=np.int64) - counts).astype(it)
    return rows, np.arange(rows.size, dtype=it) - starts[rows]


class CornerIndex:
    """CSR of the usable pairs by the flat id of their box's normalized lo corner (module docstring).

    Attributes: ``indptr`` (N + 1,) int32, ``q`` (pairs,) int32 pair ids, ``emax`` (n,) the
    largest box extent per dimension, ``offsets`` (prod(emax), n) the corner offsets a.
    """

    #: prod(e_max) above this: the per-transition index (games.Predecessors) answers queries cheaper
    MAX_ROWS = 64

    def __init__(self, indptr, q, emax, ab):
        self.indptr, self.q, self.emax = indptr, q, emax
        g = ab.grid
        self.M, self.n = ab.n_inputs, g.n
        self.shape = np.array(g.shape, dtype=np.int64)
        self.pmask = g.periodic_mask
        self.strides = g.strides.astype(np.int32)
        self.off_lo = ab.off_lo.reshape(-1, g.n)
        self.off_hi = ab.off_hi.reshape(-1, g.n)
        self.offsets = np.stack(np.meshgrid(*[np.arange(int(e), dtype=np.int32) for e in emax],
                                            indexing="ij"), axis=-1).reshape(-1, g.n)
        self.size = q.size

    @classmethod
    def build(cls, ab, block: int = 1 << 16) -> Optional["CornerIndex"]:
        """Index the pairs of ``ab`` (one class per cell) that are finite and stay in the grid;
        None when the boxes are too large for corner queries (prod(e_max) > MAX_ROWS)."""
        g = ab.grid
        N, M, n = g.size, ab.n_inputs, g.n
        shape = np.array(g.shape, dtype=np.int32)
        strides = g.strides.astype(np.int32)
        keys = np.empty((M, N), dtype=np.int32)  # input-major: long ascending runs for the sort
        use = np.empty((M, N), dtype=bool)
        emax = np.zeros(n, dtype=np.int64)
        for s in range(0, N, block):
            e = min(N, s + block)
            mi = np.stack(np.unravel_index(np.arange(s, e, dtype=np.int32), g.shape), axis=1).astype(np.int32)
            usable = ab.ok[s:e].copy()
            key = np.zeros((e - s, M), dtype=np.int32)
            for d in range(n):
                lo = ab.off_lo[s:e, :, d] + mi[:, d, None]
                ext = ab.off_hi[s:e, :, d].astype(np.int32) - ab.off_lo[s:e, :, d] + 1
                if g.periodic_mask[d]:
                    lo %= shape[d]
                    np.minimum(ext, shape[d], out=ext)
                else:
                    usable &= (lo >= 0) & (lo + ext <= shape[d])
                key += lo * strides[d]
                if usable.any():
                    emax[d] = max(emax[d], int(ext[usable].max()))
            keys[:, s:e] = key.T
            use[:, s:e] = usable.T
        if int(np.prod(emax)) > cls.MAX_ROWS:
            return None
        pos = np.flatnonzero(use.ravel())
        del use
        k = keys.ravel()[pos]
        del keys
        order = np.argsort(k, kind="stable")
        pos = pos[order]
        del order
        q = ((pos % N) * M + pos // N).astype(np.int32)  # input-major position -> pair id c * M + u
        indptr = np.zeros(N + 1, dtype=np.int32)
        np.cumsum(np.bincount(k, minlength=N), out=indptr[1:])
        return cls(indptr, q, np.maximum(emax, 1), ab)

    def pairs(self, cells: np.ndarray) -> np.ndarray:
        """Pair ids q = c * M + u of all transitions (c, u) -> r, r in ``cells`` (one per transition)."""
        n = self.n
        mi = np.stack(np.unravel_index(cells, tuple(self.shape)), axis=1).astype(np.int32)
        corner = mi[:, None, :] - self.offsets[None]  # (R, E, n) candidate lo corners
        ok = np.ones(corner.shape[:2], dtype=bool)
        key = np.zeros(corner.shape[:2], dtype=np.int32)
        for d in range(n):
            if self.pmask[d]:
                corner[..., d] %= np.int32(self.shape[d])
            else:
                ok &= corner[..., d] >= 0
            key += corner[..., d] * self.strides[d]
        sel = np.flatnonzero(ok)
        key = key.ravel()[sel]
        start = self.indptr[key]
        rows, t = expand_counts(self.indptr[key + 1] - start)
        q = self.q[start[rows] + t]
        a = self.offsets[sel[rows] % self.offsets.shape[0]]
        keep = np.ones(q.size, dtype=bool)
        for d in range(n):  # r - lo(q) = a must lie inside the box: a < ext(q)
            ext = self.off_hi[q, d].astype(np.int32) - self.off_lo[q, d] + 1
            keep &= a[:, d] < ext
        return q[keep]

    def nbytes(self) -> int:
        return self.indptr.nbytes + self.q.nbytes

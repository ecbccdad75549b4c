"""Predecessors: which pairs and cells can change when some cells change status.

Worklist games (SCOTS's algorithm): a predecessor index inverts the box relation
(:class:`Predecessors` for shared boxes; without them the abstraction's
:class:`~simgap.synthesis.corner_index.CornerIndex`; ``_predecessors`` picks one), so the work
of a level is the number of transitions into the cells changed in the level before.

Summed-area-table games: work per iteration is limited to a frontier (``_frontier``): only
cells within the offset range of the cells that changed in the last iteration can change their
status, so only their pairs are re-tested (a worklist at cell granularity; SCOTS's worklist is
per transition). With many inputs, groups of inputs whose hull box misses the changed cells are
skipped as well (:meth:`~simgap.synthesis.boxes.PairEvaluator.groups_meeting`).
"""

from __future__ import annotations

import numpy as np

from .abstraction import Abstraction
from .corner_index import expand_counts as _expand


class Predecessors:
    """The inverse of the box relation: the (cell, input) pairs whose successor box holds a cell.

    Stored at class granularity (see :class:`~simgap.synthesis.abstraction.Abstraction`): for
    every index r_C of the class dimensions, the CSR list of the (class, input) pairs q whose
    box covers r_C there. The predecessors of cell r are the cells of class k(q) whose index in
    the invariant dimensions lies in ``r_I - [off_hi_I(q), off_lo_I(q)]``. With one class per
    cell (no invariant dimensions) the list is SCOTS's predecessor list: one int32 per
    transition. ``usable`` (K*M,) bool selects the pairs to index.
    """

    def __init__(self, ab: Abstraction, usable: np.ndarray, chunk: int = 1 << 15):
        g = ab.grid
        self.ab, self.M, self.n = ab, ab.n_inputs, g.n
        self.shape = np.array(g.shape, dtype=np.int64)
        self.pmask = g.periodic_mask
        self.cd = list(ab.class_dims)
        self.inv = [d for d in range(g.n) if d not in self.cd]
        self.strides = g.strides
        cshape = self.shape[self.cd]
        K = int(np.prod(cshape)) if self.cd else 1
        self.K = K
        self.cstrides = np.array([int(np.prod(cshape[j + 1:])) for j in range(len(self.cd))], dtype=np.int64)
        # input-major order: the boxes of one input move smoothly with the cell, so the keys of
        # a chunk come in long ascending runs and the stable sort below is nearly linear
        usable = usable.reshape(K, self.M)
        qt = np.int32 if usable.size < 2 ** 31 else np.int64
        qs = np.concatenate([np.flatnonzero(usable[:, u]).astype(qt) * qt(self.M) + qt(u) for u in range(self.M)])
        counts = np.zeros(K, dtype=np.int64)
        for s in range(0, qs.size, chunk):  # pass 1: list lengths
            counts += np.bincount(self._class_keys(qs[s:s + chunk])[0], minlength=K)
        it = np.int32 if counts.sum() < 2 ** 31 else np.int64
        self.indptr = np.zeros(K + 1, dtype=it)
        np.cumsum(counts, out=self.indptr[1:])
        del counts
        self.q = np.empty(int(self.indptr[-1]), dtype=qt)
        fill = self.indptr[:-1].copy()
        for s in range(0, qs.size, chunk):  # pass 2: counting sort, chunk by chunk
            keys, q = self._class_keys(qs[s:s + chunk])
            o = np.argsort(keys, kind="stable")
            keys, q = keys[o], q[o]
            first = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
            rank = np.arange(keys.size) - np.repeat(first, np.diff(np.r_[first, keys.size]))
            self.q[fill[keys] + rank] = q
            fill += np.bincount(keys, minlength=K).astype(it, copy=False)
        self.size = self.q.size

    def _class_keys(self, q: np.ndarray):
        """(class index r_C, q) for every class-dimension cell r_C covered by the boxes of q,
        expanded one dimension at a time (int32 unless the grid is huge)."""
        M, n = self.M, self.n
        if not self.cd:
            return np.zeros(q.size, dtype=np.int64), q
        it = np.int32 if self.K < 2 ** 31 else np.int64
        k = q // M
        kc = np.unravel_index(k, tuple(self.shape[self.cd]))
        flat = q.astype(np.int64) * n
        lo_all, hi_all = self.ab.off_lo.reshape(-1), self.ab.off_hi.reshape(-1)
        key = np.zeros(q.size, dtype=it)
        cols = []
        for j, d in enumerate(self.cd):  # normalized: periodic mod n (extent capped), bounded clipped
            lo = kc[j].astype(it) + lo_all[flat + d]
            hi = kc[j].astype(it) + hi_all[flat + d]
            nd = it(self.shape[d])
            if self.pmask[d]:
                ext = np.minimum(hi - lo + 1, nd)
                lo %= nd
            else:
                lo = np.maximum(lo, 0)
                ext = np.maximum(np.minimum(hi, nd - 1) - lo + 1, 0)
            cols.append((lo, ext))
        for j, d in enumerate(self.cd):
            lo, ext = cols[j]
            rows, t = _expand(ext)
            c = lo[rows] + t.astype(it)
            if self.pmask[d]:
                c %= it(self.shape[d])
            key = key[rows] + c * it(self.cstrides[j])
            q = q[rows]
            cols[j + 1:] = [(a[rows], e[rows]) for a, e in cols[j + 1:]]  # dims still to expand
        return key, q

    def _prepare_cells(self):
        """Per CSR entry arrays for the expansion over the invariant dimensions (int32): the
        pair id of the predecessor with index 0 in every invariant dimension, and the box."""
        ab, M, n = self.ab, self.M, self.n
        it = np.int32 if ab.grid.size * M < 2 ** 31 else np.int64
        self.it = it
        q = self.q.astype(np.int64)
        kc = np.unravel_index(q // M, tuple(self.shape[self.cd])) if self.cd else ()
        base = sum((c * self.strides[d] for c, d in zip(kc, self.cd)), np.zeros(q.size, dtype=np.int64))
        self.ebase = (base * M + q % M).astype(it)
        self.elo = [ab.off_lo.reshape(-1, n)[q, d].astype(np.int32) for d in self.inv]
        self.ehi = [ab.off_hi.reshape(-1, n)[q, d].astype(np.int32) for d in self.inv]
        self.pstride = [int(self.strides[d] * M) for d in self.inv]
        self._ramps = {}

    def _ramp(self, total: int, step: int, dtype) -> np.ndarray:
        """arange(total) * step, cached and grown on demand (the levels reuse it)."""
        key = (step, np.dtype(dtype).str)
        r = self._ramps.get(key)
        if r is None or r.size < total:
            r = np.arange(max(total, 2 * (0 if r is None else r.size), 1024), dtype=dtype) * dtype(step)
            self._ramps[key] = r
        return r[:total]

    def _progression(self, first: np.ndarray, counts: np.ndarray, step: int, it):
        """The rows' arithmetic progressions first + step * [0, counts), concatenated (np.repeat
        and a cached ramp: streaming copies, no gathers)."""
        starts = np.cumsum(counts, dtype=np.int64) - counts
        total = int(starts[-1] + counts[-1]) if counts.size else 0
        if (total + 1) * step >= 2 ** 31 or np.dtype(it) == np.int64:
            it = np.int64
        out = np.repeat(first.astype(it, copy=False) - starts.astype(it) * it(step), counts)
        out += self._ramp(total, step, it)
        return out

    def pairs(self, cells: np.ndarray) -> np.ndarray:
        """Flat pair ids c * M + u of all transitions (c, u) -> r, r in ``cells`` (one per transition)."""
        mi = [c.astype(np.int32) for c in np.unravel_index(cells, tuple(self.shape))]
        kr = np.zeros(cells.size, dtype=np.int64)
        for j, d in enumerate(self.cd):
            kr += mi[d] * self.cstrides[j]
        start = self.indptr[kr]
        counts = self.indptr[kr + 1] - start
        if not self.inv:
            rows, t = _expand(counts)
            return self.q[start[rows] + t]  # one class per cell: q is the pair id
        if not hasattr(self, "ebase"):
            self._prepare_cells()
        idx = self._progression(start, counts, 1, np.int32)  # CSR entries of the cells' class rows
        base = self.ebase.take(idx)  # (take and compress: several times faster than [] here)
        first, ext = [], []
        for j, d in enumerate(self.inv):  # predecessor indices c_d in r_d - [hi_d, lo_d]
            r = np.repeat(mi[d], counts)
            lo, hi = self.elo[j].take(idx), self.ehi[j].take(idx)
            nd = np.int32(self.shape[d])
            if self.pmask[d]:
                e = np.minimum(hi - lo + 1, nd)
                a = r - lo - e + 1
            else:
                a = np.maximum(r - hi, 0)
                e = np.maximum(np.minimum(r - lo, nd - 1) - a + 1, 0)
                base += a.astype(self.it) * self.it(self.pstride[j])
            first.append(a)
            ext.append(e)
        # expand one invariant dimension at a time (no division): a bounded dimension's
        # predecessors are an arithmetic progression per row (its first index is in ``base``);
        # periodic ones wrap
        for j, d in enumerate(self.inv):
            e, ps = ext[j], self.pstride[j]
            if self.pmask[d]:
                rows, t = _expand(e)
                base = base[rows] + (t.astype(self.it, copy=False) + first[j][rows]) % self.it(self.shape[d]) \
                    * self.it(ps)
                ext[j + 1:] = [x[rows] for x in ext[j + 1:]]
                first[j + 1:] = [x[rows] for x in first[j + 1:]]
                continue
            base = self._progression(base, e, ps, self.it)
            ext[j + 1:] = [np.repeat(x, e) for x in ext[j + 1:]]
            first[j + 1:] = [np.repeat(x, e) for x in first[j + 1:]]
        return base


def _frontier(ab: Abstraction, changed: np.ndarray, candidates_mask: np.ndarray, dlo, dhi,
              buf: np.ndarray) -> np.ndarray:
    """Ids of cells c in ``candidates_mask`` with c + delta in ``changed`` (ids) for some delta in
    [dlo, dhi]: every box of c lies in c + [dlo, dhi], so only these cells can change status.

    Few changed cells: the offsets are enumerated per changed cell (cost ~ changed cells times
    the offset range). Many: a separable binary dilation of the mask of the changed cells
    (``buf``, (3, N) bool, reused across levels) with one pass of shifted ORs per offset and
    dimension.
    """
    g = ab.grid
    span = (np.asarray(dhi, dtype=np.int64) - dlo + 1)
    # an enumerated offset costs about 50 times a shifted OR of one cell (measured)
    if changed.size * int(np.prod(span)) * 50 <= g.size * int(span.sum()):
        offs = np.stack(np.meshgrid(*[np.arange(int(l), int(h) + 1) for l, h in zip(dlo, dhi)],
                                    indexing="ij"), axis=-1).reshape(-1, g.n)
        c = g.ids_to_multi(changed)[:, None, :] - offs[None]
        ok = np.ones(c.shape[:2], dtype=bool)
        for d in range(g.n):
            if g.periodic_mask[d]:
                c[..., d] %= g.shape[d]
            else:
                ok &= (c[..., d] >= 0) & (c[..., d] < g.shape[d])
        ids = np.unique(c[ok] @ g.strides)
        return ids[candidates_mask[ids]]
    buf[0] = False
    buf[0, changed] = True
    src = buf[0].reshape(g.shape)
    for d in range(g.n):  # separable dilation into the two other reused buffers, alternately
        D = buf[1 + d % 2].reshape(g.shape)
        D[...] = False
        s = g.shape[d]
        for delta in range(int(dlo[d]), int(dhi[d]) + 1):  # a handful of shifts (offset range)
            dst = [slice(None)] * g.n
            sl = [slice(None)] * g.n
            if g.periodic_mask[d]:  # D[i] |= src[(i + delta) mod s], as two slices
                k = delta % s
                dst[d], sl[d] = slice(0, s - k), slice(k, s)
                D[tuple(dst)] |= src[tuple(sl)]
                if k:
                    dst[d], sl[d] = slice(s - k, s), slice(0, k)
                    D[tuple(dst)] |= src[tuple(sl)]
            else:
                if abs(delta) >= s:
                    continue
                if delta >= 0:  # D[i] |= src[i + delta]
                    dst[d], sl[d] = slice(0, s - delta), slice(delta, s)
                else:
                    dst[d], sl[d] = slice(-delta, s), slice(0, s + delta)
                D[tuple(dst)] |= src[tuple(sl)]
        src = D
    return np.flatnonzero(np.logical_and(src.ravel(), candidates_mask, out=buf[0]))


def _predecessors(ab: Abstraction, live: np.ndarray):
    """The predecessor index: the abstraction's corner index when it has one (one class per
    cell, small boxes), else :class:`Predecessors` (its pairs() may return pairs that are not
    live; the games filter them)."""
    if ab.corner_index is not None:
        return ab.corner_index
    one_class_per_cell = len(ab.class_dims) == ab.grid.n
    return Predecessors(ab, live if one_class_per_cell else ab.ok.reshape(-1))

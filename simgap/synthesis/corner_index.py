"""Predecessors through the lo corners of the successor boxes (one class per cell, small boxes).

Without shared boxes every (cell, input) pair q = c * M + u has its own successor box
[lo(q), lo(q) + ext(q) - 1] (multi-index units). SCOTS inverts this relation with one list entry
per transition. When the boxes are small, one entry per *pair* is enough: the pairs sorted by
the flat id of their box's lo corner (a CSR over the N cells). The pairs whose box holds cell r
have their lo corner at r - a for some a in [0, e_max) (per dimension, e_max the largest
extent; wrapped in periodic dimensions), so a query visits prod(e_max) rows per cell and keeps
the pairs with a < ext(q) in every dimension: exactly one entry per transition (r, q), as
SCOTS's list, at a fraction of the memory and build time (a counting sort of the pairs by
their corner ids, placed chunk by chunk: memory and time linear in the pairs).

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


def _cell_dtypes(M: int):
    """dtypes of the per-cell number of indexed boxes (<= M) and of their summed volumes
    (<= M * CornerIndex.MAX_ROWS): the smallest that hold them (1-2 bytes a cell instead of 8)."""
    boxes = np.uint8 if M <= 255 else np.int32
    trans = np.uint8 if M * CornerIndex.MAX_ROWS <= 255 else np.int16 if M * CornerIndex.MAX_ROWS <= 32767 else np.int32
    return boxes, trans


class CornerIndex:
    """CSR of the usable pairs by the flat id of their box's normalized lo corner (module docstring).

    Attributes: ``indptr`` (N + 1,) int32; ``q`` (pairs,) int32 pair ids and ``code`` (pairs,)
    uint8 their box extents (mixed radix over ``emax``, the largest extent per dimension);
    ``offsets`` (prod(emax), n) the corner offsets a; per cell, for the games' one-off work:
    ``usable`` (N, ceil(M/8)) packed bits of the indexed pairs, ``cell_boxes`` (N,) their number
    and ``cell_transitions`` (N,) the sum of their box volumes (small integer dtypes:
    :func:`_cell_dtypes`; sum them with a wide dtype).
    """

    #: prod(e_max) above this: the per-transition index (games.Predecessors) answers queries cheaper
    MAX_ROWS = 64
    #: more (cell, input) pairs: no index (its build holds about 4 + n bytes per pair, the index
    #: 5 bytes per indexed pair; such games run on summed-area tables, whose memory is bounded).
    #: The worklist game's own limit (``fixed_point._WORKLIST_MAX_PAIRS``).
    MAX_PAIRS = 1 << 26

    def __init__(self, ab, indptr, q, code, emax, usable, cell_boxes, cell_transitions):
        self.indptr, self.q, self.code, self.emax = indptr, q, code, emax
        self.usable, self.cell_boxes, self.cell_transitions = usable, cell_boxes, cell_transitions
        g = ab.grid
        self.M, self.n = ab.n_inputs, g.n
        self.shape = [int(s) for s in g.shape]
        self.pmask = g.periodic_mask
        self.strides = [int(s) for s in g.strides]
        self.offsets = np.stack(np.meshgrid(*[np.arange(int(e), dtype=np.int32) for e in emax],
                                            indexing="ij"), axis=-1).reshape(-1, g.n)
        # fits[a, code]: offset a lies inside a box of extents ``code`` (a_d < ext_d for all d)
        ext = self.offsets + 1  # the codes enumerate the same mixed radix as the offsets
        self.fits = np.all(self.offsets[:, None, :] < ext[None, :, :], axis=2)
        self.size = q.size

    @classmethod
    def build(cls, ab, block: int = 1 << 16, chunk: int = 1 << 16) -> Optional["CornerIndex"]:
        """Index the pairs of ``ab`` (one class per cell) that are finite and stay in the grid;
        None when the boxes are too large for corner queries (prod(e_max) > MAX_ROWS).

        A counting sort: a first pass over blocks of cells computes every pair's corner key
        (input-major, -1 for a pair not indexed), its box extents and the number of pairs per
        key (the CSR's row pointers); a second pass places the pairs chunk by chunk, each pair at
        its key's next free slot (a stable sort of the chunk ranks pairs of equal key). The
        result equals a stable sort of all keys (pairs of one row in input-major order), in
        about 4 + n bytes per pair while building and 5 bytes per indexed pair after."""
        g = ab.grid
        N, M, n = g.size, ab.n_inputs, g.n
        from . import game_kernels
        lib = game_kernels.for_abstraction(ab)
        if lib is not None:
            return cls._build_compiled(ab, lib)
        shape = np.array(g.shape, dtype=np.int32)
        strides = g.strides.astype(np.int32)
        keys = np.empty((M, N), dtype=np.int32)  # input-major: long ascending runs for the chunk sorts
        exts = [np.empty((M, N), dtype=np.uint8) for _ in range(n)]
        counts = np.zeros(N, dtype=np.int32 if N * M < 2 ** 31 else np.int64)
        usable_bits = np.empty((N, (M + 7) // 8), dtype=np.uint8)
        boxes_t, trans_t = _cell_dtypes(M)
        cell_boxes = np.zeros(N, dtype=boxes_t)
        cell_trans = np.zeros(N, dtype=trans_t)  # <= M * MAX_ROWS
        emax = np.zeros(n, dtype=np.int64)
        for s in range(0, N, block):
            e = min(N, s + block)
            ids = np.arange(s, e, dtype=np.int32)
            coord = [(ids // strides[d]) % shape[d] for d in range(n)]  # the cells' multi-indices
            bits = usable_bits[s:e]
            bits[:] = 0
            for u in range(M):  # input by input: contiguous columns of the input-major tables
                usable = ab.ok[s:e, u].copy()
                key = np.zeros(e - s, dtype=np.int32)
                vol = np.ones(e - s, dtype=np.int32)
                for d in range(n):
                    ol = ab.off_lo[s:e, u, d]
                    lo = ol + coord[d]
                    ext = np.subtract(ab.off_hi[s:e, u, d], ol, dtype=np.int32)
                    ext += 1
                    if g.periodic_mask[d]:
                        lo %= shape[d]
                        np.minimum(ext, shape[d], out=ext)
                    else:
                        usable &= lo >= 0
                        lo_ext = lo + ext
                        usable &= lo_ext <= shape[d]
                    lo *= strides[d]
                    key += lo
                    vol *= ext
                    np.minimum(ext, 255, out=exts[d][u, s:e], casting="unsafe")
                if not usable.any():
                    keys[u, s:e] = -1
                    continue
                for d in range(n):
                    emax[d] = max(emax[d], int(np.max(exts[d][u, s:e] * usable)))
                k = key[usable]
                k0 = int(k.min())
                counts[k0:int(k.max()) + 1] += np.bincount(k - k0)
                key[~usable] = -1
                keys[u, s:e] = key
                vol *= usable
                cell_boxes[s:e] += usable
                np.add(cell_trans[s:e], vol, out=cell_trans[s:e], casting="unsafe")  # <= M * MAX_ROWS
                bits[:, u >> 3] |= usable.view(np.uint8) << np.uint8(7 - (u & 7))
        if int(np.prod(emax)) > cls.MAX_ROWS:
            return None
        emax = np.maximum(emax, 1)
        code = exts[0]  # mixed radix over emax, the order of the offsets (in place)
        np.maximum(code, 1, out=code)
        code -= np.uint8(1)
        for d in range(1, n):
            code *= np.uint8(emax[d])
            code += np.maximum(exts[d], 1) - np.uint8(1)
            exts[d] = None
        del exts
        it = np.int32 if N * M < 2 ** 31 else np.int64
        indptr = np.zeros(N + 1, dtype=np.int32)
        np.cumsum(counts, out=indptr[1:])
        del counts
        # the next free slot of every row: the row pointers themselves, advanced as the rows fill
        # (then each holds its row's end, the next row's start: shifted back below)
        nxt = indptr[:-1]
        q = np.empty(int(indptr[-1]), dtype=it)
        code_out = np.empty(q.size, dtype=np.uint8)
        keys, code = keys.reshape(-1), code.reshape(-1)
        for c0 in range(0, keys.size, chunk):
            k = keys[c0:c0 + chunk]
            sel = np.flatnonzero(k >= 0)
            if sel.size == 0:
                continue
            k = k.take(sel)
            o = np.argsort(k, kind="stable")  # pairs of equal key keep their input-major order
            ks = k.take(o)
            first = np.flatnonzero(np.concatenate(([True], ks[1:] != ks[:-1])))
            run = np.diff(np.append(first, ks.size))
            rank = np.arange(ks.size) - np.repeat(first, run)
            dest = nxt.take(ks) + rank
            pos = (sel.take(o) + c0).astype(it)  # input-major position u * N + c
            q[dest] = (pos % it(N)) * it(M) + pos // it(N)  # -> pair id c * M + u
            code_out[dest] = code.take(pos)
            nxt[ks.take(first)] += run  # distinct keys: no repeated index
        del keys, code
        indptr[1:] = indptr[:-1].copy()  # row r's end is row r + 1's start
        indptr[0] = 0
        return cls(ab, indptr, q, code_out, emax, usable_bits, cell_boxes, cell_trans)

    @classmethod
    def _build_compiled(cls, ab, lib) -> Optional["CornerIndex"]:
        """:meth:`build` by two compiled passes over the pairs (:mod:`.game_kernels`: counts, then
        placement in input-major order), with no per-pair keys or extents kept between them:
        the same arrays."""
        from .game_kernels import corner_counts, corner_place
        g = ab.grid
        N, M, n = g.size, ab.n_inputs, g.n
        args = (np.ascontiguousarray(ab.off_lo), np.ascontiguousarray(ab.off_hi), np.ascontiguousarray(ab.ok),
                np.array(g.shape, dtype=np.int64), g.strides.astype(np.int64),
                np.asarray(g.periodic_mask, dtype=np.uint8))
        counts = np.zeros(N, dtype=np.int64)
        usable_bits = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
        boxes_t, trans_t = _cell_dtypes(M)
        cell_boxes = np.zeros(N, dtype=boxes_t)
        cell_trans = np.zeros(N, dtype=trans_t)
        emax = np.zeros(n, dtype=np.int64)
        corner_counts(lib, *args, counts, usable_bits, cell_boxes, cell_trans, emax)
        if int(np.prod(emax)) > cls.MAX_ROWS:
            return None
        emax = np.maximum(emax, 1)
        indptr = np.zeros(N + 1, dtype=np.int32)
        np.cumsum(counts, out=indptr[1:])
        del counts
        q = np.empty(int(indptr[-1]), dtype=np.int32 if N * M < 2 ** 31 else np.int64)
        code = np.empty(q.size, dtype=np.uint8)
        corner_place(lib, *args, emax, indptr, q, code)
        return cls(ab, indptr, q, code, emax, usable_bits, cell_boxes, cell_trans)

    def pairs(self, cells: np.ndarray) -> np.ndarray:
        """Pair ids q = c * M + u of all transitions (c, u) -> r, r in ``cells`` (one per transition)."""
        cells = np.asarray(cells).astype(np.int32, copy=False)
        E = self.offsets.shape[0]
        key = np.zeros((cells.size, E), dtype=np.int32)
        ok = np.ones((cells.size, E), dtype=bool)
        for d in range(self.n):  # candidate lo corners r - a, per dimension
            nd, st = self.shape[d], self.strides[d]
            c = ((cells // np.int32(st)) % np.int32(nd))[:, None] - self.offsets[:, d]
            if self.pmask[d]:
                c %= np.int32(nd)
            else:
                ok &= c >= 0
            c *= np.int32(st)
            key += c
        sel = np.flatnonzero(ok)
        key = key.ravel().take(sel)
        start = self.indptr.take(key)
        rows, t = expand_counts(self.indptr.take(key + 1) - start)
        e = start.take(rows) + t
        fit = self.fits.take((sel.take(rows) % E) * self.fits.shape[1] + self.code.take(e))
        return self.q.take(np.compress(fit, e))  # r - lo(q) = a lies in the box

    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.indptr, self.q, self.code, self.usable, self.cell_boxes,
                                      self.cell_transitions))

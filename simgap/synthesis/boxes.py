"""Index boxes and summed-area tables: "all successors of (c, u) lie in Z" as an O(1) test.

Every successor set is an index box, so "all successors of (c, u) lie in Z" is the O(1) test
``count_Z(box) == volume(box)`` on a summed-area table of Z (2^n lookups). Periodic dimensions
are handled by a SAT of Z tiled three times along them, so a wrapped interval [lo, lo + len)
with 0 <= lo < 2 n_d and len <= n_d is one contiguous range.

:class:`BoxCounter` is the SAT of one mask; :class:`BoxFamily` the per-(class, input) boxes
compiled to corner offsets; :class:`PairEvaluator` the box tests of a game's pairs;
:class:`RowBoxes` the boxes of all pairs of a range of cells; :class:`DistinctBoxes` the
distinct boxes when inputs share them; :func:`pair_volumes` the cells per box.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .abstraction import Abstraction
from .corner_index import expand_counts as _expand


# ---------------------------------------------------------------------------------------
# summed-area tables over index boxes
# ---------------------------------------------------------------------------------------

class BoxCounter:
    """Counts the cells of a boolean grid mask inside many index boxes at once."""

    def __init__(self, shape, periodic_mask, pad=None):
        self.shape = np.array(shape, dtype=np.int64)
        self.dtype = np.int32  # counts < 2^31 (grids are limited to 2^31 cells)
        self.pmask = np.asarray(periodic_mask, dtype=bool)
        self.n = len(shape)
        # periodic dims are tiled 3 times: a box with lo in [0, 2 n_d) and extent <= n_d is one
        # contiguous range (no per-query wrapping). ``pad`` zero cells around bounded dims let
        # boxes that stick out of the grid be counted (the outside counts as empty).
        self.pad = np.zeros(self.n, dtype=np.int64) if pad is None else \
            np.where(self.pmask, 0, np.asarray(pad, dtype=np.int64))
        self.tshape = tuple(int(s * (3 if p else 1) + 2 * q + 1)
                            for s, p, q in zip(self.shape, self.pmask, self.pad))
        self.tstrides = np.array([int(np.prod(self.tshape[d + 1:])) for d in range(self.n)], dtype=np.int64)
        self.table = None

    def set(self, mask_flat: np.ndarray) -> "BoxCounter":
        """Build the SAT of ``mask_flat`` (N,) bool (cumulative sums per axis, in place)."""
        Z = mask_flat.reshape(tuple(self.shape))
        for d in np.flatnonzero(self.pmask):
            Z = np.concatenate([Z, Z, Z], axis=int(d))
        if self.table is None:
            self._T = np.zeros(self.tshape, dtype=self.dtype)  # the zero border stays zero
            self.table = self._T.ravel()
        T = self._T
        if self.pad.any():
            T[...] = 0  # the padding held prefix sums from the last build
        T[tuple(slice(1 + int(q), 1 + int(q) + Z.shape[d]) for d, q in enumerate(self.pad))] = Z
        for d in range(self.n):
            np.cumsum(T, axis=d, out=T, dtype=self.dtype)
        return self

    def normalize(self, lo: np.ndarray, hi: np.ndarray):
        """Bring boxes into table coordinates: periodic lo modulo n_d, full circle clamped.

        Returns (lo, hi, in_grid) as int32 with in_grid False where a bounded dimension leaves
        the grid (those boxes must not be counted).
        """
        lo = lo.astype(np.int32, copy=True)
        hi = hi.astype(np.int32, copy=True)
        lim_lo = np.where(self.pmask, np.iinfo(np.int32).min, 0).astype(np.int32)
        lim_hi = np.where(self.pmask, np.iinfo(np.int32).max, self.shape - 1).astype(np.int32)
        ing = np.all((lo >= lim_lo) & (hi <= lim_hi), axis=-1)
        for d in np.flatnonzero(self.pmask):
            s = int(self.shape[d])
            ext = hi[..., d] - lo[..., d] + 1
            full = ext >= s
            l = np.where(full, 0, lo[..., d] % s)
            lo[..., d] = l
            hi[..., d] = np.where(full, s - 1, l + ext - 1)
        return lo, hi, ing

    def count(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Cells of the mask in boxes [lo, hi] (inclusive, normalized). Boxes outside the
        table give meaningless counts (indices are clipped): mask them out."""
        terms = [(np.zeros(lo.shape[:-1], dtype=np.int32), 1)]
        for d in range(self.n):  # partial flat offsets, combined over the 2^n corners
            st = np.int32(self.tstrides[d])
            a = lo[..., d] * st
            b = (hi[..., d] + 1) * st
            terms = [(t + b, sg) for t, sg in terms] + [(t + a, -sg) for t, sg in terms]
        table = self.table
        out = np.zeros(lo.shape[:-1], dtype=self.dtype)
        for flat, sg in terms:
            v = table.take(flat, mode="clip")
            if sg > 0:
                out += v
            else:
                out -= v
        return out


# ---------------------------------------------------------------------------------------
# pair evaluation
# ---------------------------------------------------------------------------------------

class BoxFamily:
    """Per-(class, input) boxes relative to their cell, compiled for SAT lookups.

    The SAT flat index of corner ``c`` of box(cell, u) is ``base(cell) + corner[k(cell), u, c]``
    with ``base = mi . strides``. Periodic offsets are stored modulo n_d and extents capped at
    n_d, so with the SAT tiled 3 times along periodic dims no query needs wrapping: a box test
    is 2^n gathers and adds.
    """

    _PRECOMPUTE_BYTES = 16 << 20  # above this, corner offsets are computed per query

    def __init__(self, ab: Abstraction, off_lo: np.ndarray, off_hi: np.ndarray, counter: BoxCounter):
        g = ab.grid
        n = g.n
        self.ab, self.n, self.counter = ab, n, counter
        shape = np.array(g.shape, dtype=np.int64)
        pm = g.periodic_mask
        # int16 per (class, input, dim) when it fits (the generic path has one class per cell:
        # these tables, and their temporaries, are as large as the grid times the inputs)
        vmax = max([abs(int(f(a, initial=0))) for a in (off_lo, off_hi) for f in (np.min, np.max)])
        it = np.int16 if max(2 * vmax + 1, int(shape.max())) < 16000 else np.int32
        shape_it = shape.astype(it)
        ext = off_hi.astype(it)
        ext -= off_lo
        ext += 1
        np.maximum(ext, 0, out=ext)
        lo = off_lo.astype(it)
        for d in np.flatnonzero(pm):
            np.minimum(ext[..., d], shape_it[d], out=ext[..., d])
            lo[..., d] %= shape_it[d]
        self.lo = lo
        self.ext = ext
        self.vol = np.prod(ext, axis=-1, dtype=np.int32)
        self.tstr = counter.tstrides.astype(np.int64)
        self.shape = shape
        self.bounded = np.flatnonzero(~pm)
        del lo, ext
        self.signs = np.array([(-1) ** bin(c).count("1") for c in range(1 << n)], dtype=np.int32)
        K, M = off_lo.shape[:2]
        self.M = M
        self.corner = None
        if K * M * (1 << n) * 4 <= self._PRECOMPUTE_BYTES:
            self.corner = self._corners(self.lo.reshape(-1, n), self.ext.reshape(-1, n))
        self.vol_flat = self.vol.ravel()

    def _corners(self, lo: np.ndarray, ext: np.ndarray) -> np.ndarray:
        """(P, n) relative lo and extents -> (P, 2^n) relative flat corner offsets (int32)."""
        out = np.zeros((lo.shape[0], 1 << self.n), dtype=np.int32)
        for c in range(1 << self.n):  # bit d set: the lo side (index lo), else hi + 1
            for d in range(self.n):
                st = np.int32(self.tstr[d])
                l = lo[:, d].astype(np.int32)
                out[:, c] += (l if c >> d & 1 else l + ext[:, d]) * st
        return out

    def corners(self, q: np.ndarray) -> np.ndarray:
        """(P,) flat (class, input) indices -> (P, 2^n) corner offsets."""
        if self.corner is not None:
            return self.corner[q]
        n = self.n
        return self._corners(self.lo.reshape(-1, n)[q], self.ext.reshape(-1, n)[q])

    def count(self, table: np.ndarray, base: np.ndarray, q: np.ndarray, k=None) -> np.ndarray:
        """Cells of the SAT's mask in the boxes with cell bases ``base`` and pair indices ``q``
        (same shape; ``base`` broadcastable). With ``k`` (B,) classes, q is all inputs of the
        rows and the corner rows are taken per class (contiguous)."""
        qs = q.shape
        if k is not None and self.corner is not None:
            fl = self.corner.reshape(-1, self.M, 1 << self.n)[k]
        else:
            fl = self.corners(q.ravel()).reshape(qs + (1 << self.n,))
        fl += np.broadcast_to(base, qs)[..., None]
        # inclusion-exclusion as one small matrix product (faster than 2^n strided passes)
        return table.take(fl, mode="clip") @ self.signs


class PairEvaluator:
    """Successor-box tests for the pairs of a set of cells (all inputs, or listed pairs)."""

    def __init__(self, ab: Abstraction, blocked: np.ndarray, allowed: Optional[np.ndarray]):
        self.ab = ab
        g = ab.grid
        self.M = ab.n_inputs
        self.counter = BoxCounter(g.shape, g.periodic_mask)
        self.blocked = blocked
        self.fam = BoxFamily(ab, ab.off_lo, ab.off_hi, self.counter)
        self.vol = self.fam.vol
        self.mid = None
        if ab.mid_lo is not None and allowed is not None:
            self.allowed_counter = BoxCounter(g.shape, g.periodic_mask).set(allowed)
            self.mid = BoxFamily(ab, ab.mid_lo, ab.mid_hi, self.allowed_counter)
        # per-cell indices in int32 (the generic path has one class per cell: these are full size)
        self.mi_all = np.empty((g.size, g.n), dtype=np.int32)
        for d, c in enumerate(np.unravel_index(np.arange(g.size, dtype=np.int32), g.shape)):
            self.mi_all[:, d] = c
        self.cls_all = ab.cell_class(self.mi_all).astype(np.int32)
        it = np.int32 if ab.n_classes * self.M < 2 ** 31 else np.int64
        self.q0_all = self.cls_all.astype(it) * it(self.M)  # flat (class, input 0) index per cell
        self.base_all = np.zeros(g.size, dtype=np.int32)
        for d in range(g.n):
            self.base_all += self.mi_all[:, d] * np.int32(self.counter.tstrides[d])
        self.hull = None
        self.dist = DistinctBoxes.of(ab)
        self.dfam = None if self.dist is None else BoxFamily(ab, self.dist.lo, self.dist.hi, self.counter)

    def build_hulls(self, group: int = 8) -> BoxCounter:
        """Hull boxes of groups of ``group`` consecutive inputs (the bytes of the packed rows).

        Returns the (padded) counter to use with :meth:`groups_meeting`: a group whose hull
        misses the changed cells cannot change, so its pairs are not re-tested.
        """
        ab = self.ab
        g = ab.grid
        K, M, n = ab.off_lo.shape
        G = (M + group - 1) // group
        lo = np.full((K, G * group, n), np.iinfo(np.int16).max, dtype=np.int64)
        hi = np.full((K, G * group, n), np.iinfo(np.int16).min, dtype=np.int64)
        okm = ab.ok[..., None]
        lo[:, :M] = np.where(okm, ab.off_lo, lo[:, :M])
        hi[:, :M] = np.where(okm, ab.off_hi, hi[:, :M])
        lo = lo.reshape(K, G, group, n).min(axis=2)
        hi = hi.reshape(K, G, group, n).max(axis=2)
        empty = lo > hi
        lo = np.where(empty, 0, lo)
        hi = np.where(empty, -1, hi)  # empty hull: extent 0 (never meets anything)
        pad = np.maximum(np.abs(lo).max(axis=(0, 1)), np.abs(hi).max(axis=(0, 1))) + 1
        hc = BoxCounter(g.shape, g.periodic_mask, pad=pad)
        self.hull = BoxFamily(ab, lo, hi, hc)
        self.hull_base = ((self.mi_all.astype(np.int64) + hc.pad) @ hc.tstrides).astype(np.int32)
        self.hull_G = G
        self.group = group
        return hc

    def groups_meeting(self, ids: np.ndarray, hc: BoxCounter) -> np.ndarray:
        """(B, G) bool: the hull of input group g of cell ids[b] meets the counter's mask."""
        k = self.cls_all[ids]
        q = k[:, None] * self.hull_G + np.arange(self.hull_G)
        return self.hull.count(hc.table, self.hull_base[ids][:, None], q, k=k) > 0

    def test_rows(self, ids: np.ndarray, rows: np.ndarray, counter: BoxCounter) -> int:
        """rows (B, M) bool, the pairs of cells ``ids`` to test (assumed valid), is replaced in
        place by "box(c, u) lies in the counter's mask"; returns the number of pairs tested.

        When the block's pairs outnumber its (cell, distinct box) tests (:class:`DistinctBoxes`),
        each distinct box is tested once per cell and the results mapped to the inputs."""
        ci, uj = np.nonzero(rows)
        if self.dist is None or ci.size <= ids.size * self.dist.D:
            rows[ci, uj] = self.test_pairs(ids, ci, uj, counter)
            return ci.size
        k = self.cls_all[ids]
        D = self.dist.D
        q = k[:, None] * D + np.arange(D, dtype=k.dtype)
        ok_d = self.dfam.count(counter.table, self.base_all[ids][:, None], q, k=k) == self.dfam.vol_flat[q]
        rows &= np.take_along_axis(ok_d, self.dist.index[k], axis=1)
        return ci.size

    def test_pairs(self, ids: np.ndarray, ci: np.ndarray, uj: np.ndarray, counter: BoxCounter) -> np.ndarray:
        """(P,) bool: box(ids[ci], uj) lies in the counter's mask (pairs assumed valid)."""
        cells = ids[ci]
        q = self.q0_all[cells] + uj
        return self.fam.count(counter.table, self.base_all[cells], q) == self.fam.vol_flat[q]


class RowBoxes:
    """The normalized boxes of all pairs of the cells ``s:e`` (a range) or ``ids``, one (B, M)
    int32 array per dimension (no (B, M, n) arrays: numpy is slow along a short last axis).

    Periodic dimensions: lo modulo n_d, extent capped at n_d (a full circle); ``in_grid`` is
    False where a bounded dimension leaves the grid. ``lo_tab``/``hi_tab`` (K, M, n) are the
    relative successor boxes (default) or the hulls of the held periods; ``inputs`` a slice of them.
    """

    def __init__(self, ab: Abstraction, cells, lo_tab=None, hi_tab=None, inputs=slice(None), ok_tab=None):
        g = ab.grid
        lo_tab = ab.off_lo if lo_tab is None else lo_tab
        hi_tab = ab.off_hi if hi_tab is None else hi_tab
        ok_tab = ab.ok if ok_tab is None else ok_tab
        ids = np.arange(cells.start, cells.stop, dtype=np.int32) if isinstance(cells, slice) else \
            np.asarray(cells).astype(np.int32)
        mi = [(ids // np.int32(g.strides[d])) % np.int32(g.shape[d]) for d in range(g.n)]
        if len(ab.class_dims) == g.n:
            k = cells  # one class per cell: the class is the cell (a slice keeps views)
        else:
            k = np.zeros(ids.size, dtype=np.int32)
            cstride = 1
            for d in reversed(ab.class_dims):
                k += mi[d] * np.int32(cstride)
                cstride *= g.shape[d]
        self.k = k
        self.ok = ok_tab[k, inputs]
        self.lo, self.hi = [], []
        self.in_grid = np.ones(self.ok.shape, dtype=bool)
        self.vol = np.ones(self.ok.shape, dtype=np.int32)
        for d in range(g.n):
            lo = lo_tab[k, inputs, d] + mi[d][:, None]
            hi = hi_tab[k, inputs, d] + mi[d][:, None]
            nd = np.int32(g.shape[d])
            if g.periodic_mask[d]:
                ext = np.minimum(hi - lo + 1, nd)
                lo %= nd
                hi = lo + ext - 1
            else:
                self.in_grid &= (lo >= 0) & (hi < nd)
            self.vol *= hi - lo + 1
            self.lo.append(lo)
            self.hi.append(hi)

    def count(self, counter: "BoxCounter", sel=None) -> np.ndarray:
        """Cells of the counter's mask in the boxes (all, or those at index ``sel``); boxes that
        leave the grid give meaningless counts."""
        lo = self.lo if sel is None else [a[sel] for a in self.lo]
        hi = self.hi if sel is None else [a[sel] for a in self.hi]
        terms = [(0, 1)]
        for d in range(len(lo)):  # partial flat offsets, combined over the 2^n corners
            st = np.int32(counter.tstrides[d])
            a, b = lo[d] * st, (hi[d] + 1) * st
            terms = [(t + b, sg) for t, sg in terms] + [(t + a, -sg) for t, sg in terms]
        out = None
        for flat, sg in terms:
            v = counter.table.take(flat, mode="clip")
            out = v if out is None else (np.add(out, v, out=out) if sg > 0 else np.subtract(out, v, out=out))
        return out

    def inside(self, counter: "BoxCounter", sel=None) -> np.ndarray:
        """The boxes (all, or at ``sel``) lie in the counter's mask."""
        return self.count(counter, sel) == (self.vol if sel is None else self.vol[sel])

    def min_over(self, values: np.ndarray, shape, strides, sel) -> np.ndarray:
        """min of ``values`` (N,) over the cells of the boxes at ``sel`` (one entry per box)."""
        vol = self.vol[sel]
        rows, t = _expand(vol)
        cell = np.zeros(rows.size, dtype=np.int32)
        for d in range(len(self.lo) - 1, -1, -1):  # mixed-radix decode of the rank in the box
            lo = self.lo[d][sel]
            ext = (self.hi[d][sel] - lo + 1)[rows]
            cell += ((lo[rows] + t % ext) % np.int32(shape[d])) * np.int32(strides[d])
            t //= ext
        starts = np.cumsum(vol, dtype=np.int64) - vol
        return np.minimum.reduceat(values[cell], starts)


def pair_volumes(ab: Abstraction, dtype=np.int32, block: int = 1 << 18) -> np.ndarray:
    """(K, M) cells per box (extent capped at n_d in periodic dimensions), in ``dtype``.

    Computed over blocks of about ``block`` pairs, so that the temporaries stay small (the
    table itself can be 1 or 2 bytes a pair: :func:`volume_bound` says which dtype holds it)."""
    K, M, n = ab.off_lo.shape
    vol = np.empty((K, M), dtype=dtype)
    cb = max(1, block // max(M, 1))
    for s in range(0, K, cb):
        e = min(K, s + cb)
        v = np.ones((e - s, M), dtype=np.int64)
        for d in range(n):
            ext = ab.off_hi[s:e, :, d].astype(np.int32) - ab.off_lo[s:e, :, d] + 1
            if ab.grid.periodic_mask[d]:
                np.minimum(ext, ab.grid.shape[d], out=ext)
            v *= np.maximum(ext, 0)
        if v.size and v.max() > np.iinfo(dtype).max:
            raise OverflowError(f"pair_volumes: a box of {int(v.max())} cells does not fit {np.dtype(dtype).name}")
        vol[s:e] = v
    return vol


def volume_bound(ab: Abstraction, block: int = 1 << 20) -> int:
    """An upper bound on every pair's box volume: the product over the dimensions of the largest
    extent (capped at n_d in periodic dimensions), over blocks of about ``block`` pairs."""
    K, M, n = ab.off_lo.shape
    cb = max(1, block // max(M, 1))
    bound = 1
    for d in range(n):
        emax = 0
        for s in range(0, K, cb):
            diff = np.subtract(ab.off_hi[s:s + cb, :, d], ab.off_lo[s:s + cb, :, d], dtype=np.int32)
            emax = max(emax, int(diff.max(initial=-1)) + 1)
        if ab.grid.periodic_mask[d]:
            emax = min(emax, int(ab.grid.shape[d]))
        bound *= max(emax, 0)
    return bound


class DistinctBoxes:
    """Per class of shared boxes, the distinct successor boxes over the inputs.

    Inputs often share a box (on the TurtleBot at eta 0.08, hold 10: about 80 of 441 per
    heading), and every test of a pair depends on its box only (its ``ok`` flag, successor box
    and hull of the held periods). ``lo``/``hi``/``mid_lo``/``mid_hi`` (K, D, n), ``ok`` (K, D):
    the distinct boxes of each class, padded to D with ``ok`` False; ``index`` (K, M): the
    distinct box of each input; ``mult`` (K, D): how many inputs have it.
    """

    def __init__(self, ab: Abstraction, index, first, D):
        K, M, n = ab.off_lo.shape
        self.index, self.D = index, D
        k = np.arange(K)[:, None]
        self.lo, self.hi = ab.off_lo[k, first], ab.off_hi[k, first]
        self.ok = ab.ok[k, first]
        self.mid_lo = None if ab.mid_lo is None else ab.mid_lo[k, first]
        self.mid_hi = None if ab.mid_hi is None else ab.mid_hi[k, first]
        self.mult = np.zeros((K, D), dtype=np.int32)
        np.add.at(self.mult, (np.broadcast_to(k, index.shape), index), 1)

    @classmethod
    def of(cls, ab: Abstraction, worth: float = 0.75) -> Optional["DistinctBoxes"]:
        """The distinct boxes when there are shared classes and at most ``worth`` x M per class."""
        K, M, n = ab.off_lo.shape
        if len(ab.class_dims) == ab.grid.n or K * M > 1 << 22:  # one class per cell: not worth a pass
            return None
        parts = [ab.off_lo, ab.off_hi] + ([ab.mid_lo, ab.mid_hi] if ab.mid_lo is not None else [])
        rows = np.concatenate([p.astype(np.int64) for p in parts] + [ab.ok[..., None].astype(np.int64)], axis=2)
        index = np.empty((K, M), dtype=np.int64)
        firsts = []
        for k in range(K):  # K classes (headings): small
            _, first, inv = np.unique(rows[k], axis=0, return_index=True, return_inverse=True)
            index[k] = inv.ravel()
            firsts.append(first)
        D = max(f.size for f in firsts)
        if D > worth * M:
            return None
        first = np.full((K, D), M, dtype=np.int64)  # padding: ok False (index M is clipped below)
        for k, f in enumerate(firsts):
            first[k, :f.size] = f
        out = cls(ab, index, np.minimum(first, M - 1), D)
        out.ok &= first < M
        return out

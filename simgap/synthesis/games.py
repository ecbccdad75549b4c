"""Fixed-point games on an implicit abstraction: a worklist over predecessors, or summed-area tables.

Two algorithms with identical results (``method``; :func:`choose_method` picks one):

* worklist (SCOTS's algorithm, level-synchronous): a predecessor index inverts the box relation
  (:class:`Predecessors` for shared boxes; without them the abstraction's
  :class:`~simgap.synthesis.corner_index.CornerIndex`); reach keeps per-pair counters of box
  cells not yet won, invariance drops the pairs whose box meets a lost cell. The work of a
  level is the number of transitions into the cells changed in the level before.
* summed-area tables (SAT), described below: O(2^n) per pair test whatever the box volume, plus
  one table of all cells per level; better when boxes hold many cells.

Every successor set is an index box, so "all successors of (c, u) lie in Z" is the O(1) test
``count_Z(box) == volume(box)`` on a summed-area table of Z (2^n lookups). Periodic dimensions
are handled by a SAT of Z tiled three times along them, so a wrapped interval [lo, lo + len)
with 0 <= lo < 2 n_d and len <= n_d is one contiguous range.

Reach-avoid (least fixed point, level-synchronous so that the level is the steps-to-go)::

    W_0 = T                       (target cells; obstacle cells are never in W)
    W_{j+1} = W_j  u  Cpre(W_j),  Cpre(Z) = {c : exists valid u, box(c,u) subset Z}

Invariance / safety (greatest fixed point)::

    W_0 = S                       (safe cells)
    W_{j+1} = W_j  n  Cpre(W_j)

A pair (c, u) is *valid* when its box stays inside the grid in every bounded dimension (else it
may reach the losing "outside" state), the image is finite, and, when the input is held for
several periods, the hull of the intermediate boxes lies in the allowed cells.

Work per iteration is limited to a frontier: only cells within the offset range of the cells
that changed in the last iteration can change their status, so only their pairs are re-tested
(a worklist at cell granularity; SCOTS's worklist is per transition). With many inputs, groups
of inputs whose hull box misses the changed cells are skipped as well. Pairs that can never be
used are removed once, up front (:func:`live_pairs`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import SimgapError
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


def pair_volumes(ab: Abstraction) -> np.ndarray:
    """(K, M) int32 cells per box (extent capped at n_d in periodic dimensions)."""
    vol = np.ones(ab.off_lo.shape[:2], dtype=np.int32)
    for d in range(ab.grid.n):
        ext = ab.off_hi[..., d].astype(np.int32) - ab.off_lo[..., d] + 1
        if ab.grid.periodic_mask[d]:
            np.minimum(ext, ab.grid.shape[d], out=ext)
        vol *= np.maximum(ext, 0)
    return vol


def live_pairs(ab: Abstraction, blocked: np.ndarray, keep: np.ndarray, allowed=None, test_keep: bool = True):
    """One pass over all pairs: which can ever be used, and the SCOTS transition count.

    A pair (c, u) is *live* when it is valid (see module docstring) and its box lies in
    ``keep`` (reach: the unblocked cells; invariance: the safe cells); pairs that are not live
    can never be in the controller, so the games never test them again. With ``test_keep``
    False the pairs are only tested for validity (the reach worklist needs no more: a box that
    meets a blocked cell never gets all its cells won). Ranges of about 2^18 pairs, int32
    boxes, 2^n summed-area-table lookups per pair.

    Returns (live (N, ceil(M/8)) packed bits, number of valid boxes, sum of their volumes).
    """
    g = ab.grid
    N, M = g.size, ab.n_inputs
    kc = BoxCounter(g.shape, g.periodic_mask)
    if test_keep:
        kc.set(keep)
    ac = None
    if ab.mid_lo is not None and allowed is not None:
        ac = BoxCounter(g.shape, g.periodic_mask).set(allowed)
    packed = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
    dist = DistinctBoxes.of(ab)
    B = _block_size(ab)
    if dist is not None:  # blocks of as many (cell, distinct box) tests as (cell, input) pairs
        B = max(1, (1 << 18) // dist.D)
    boxes = trans = 0
    for s in range(0, N, B):
        rng = slice(s, min(N, s + B))
        if dist is not None:  # every test on the distinct boxes of the cell's class, then per input
            bx = RowBoxes(ab, rng, dist.lo, dist.hi, ok_tab=dist.ok)
            valid = bx.ok & bx.in_grid
            valid &= ~blocked[rng, None]
            if ac is not None:
                mid = RowBoxes(ab, rng, dist.mid_lo, dist.mid_hi, ok_tab=dist.ok)
                valid &= mid.in_grid
                valid &= mid.inside(ac)
            mult = dist.mult[bx.k]
            boxes += int((valid * mult).sum(dtype=np.int64))
            trans += int((valid * mult * bx.vol).sum(dtype=np.int64))
            if test_keep:
                valid &= bx.inside(kc)
            packed[rng] = pack_rows(np.take_along_axis(valid, dist.index[bx.k], axis=1))
            continue
        bx = RowBoxes(ab, rng)
        valid = bx.ok & bx.in_grid
        valid &= ~blocked[rng, None]  # blocked cells have no valid pairs
        if ac is not None:  # the hull of the held periods stays in the allowed cells
            mid = RowBoxes(ab, rng, ab.mid_lo, ab.mid_hi)
            valid &= mid.in_grid
            valid &= mid.inside(ac)
        boxes += int(np.count_nonzero(valid))
        trans += int(bx.vol[valid].sum(dtype=np.int64))
        if test_keep:
            valid &= bx.inside(kc)
        packed[rng] = pack_rows(valid)
    return packed, boxes, trans


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


@dataclass
class GameResult:
    """Outcome of a game.

    ``winning`` (N,) bool (for reach: includes the target cells); ``steps`` (N,) int32 steps to go
    (reach: 0 on target, -1 losing; invariance: 0 winning, -1 losing); ``valid`` (N, M) packed
    bits (np.packbits along axis 1) of the controller's valid inputs; ``iterations``, ``seconds``.
    """

    kind: str
    winning: np.ndarray
    steps: np.ndarray
    valid_packed: np.ndarray
    n_inputs: int
    target: np.ndarray
    chosen: Optional[np.ndarray] = None
    iterations: int = 0
    seconds: float = 0.0
    info: dict = field(default_factory=dict)


def _block_size(ab: Abstraction) -> int:
    # about 2^18 (cell, input) pairs per block keeps the temporaries small (cache friendly)
    return max(1, (1 << 18) // max(1, ab.n_inputs))


METHODS = ("auto", "worklist", "sat")
_WORKLIST_MAX_PAIRS = 1 << 26  # (cell, input) pairs: the worklist keeps 2 bytes or so per pair


def choose_method(method: str, ab: Abstraction) -> str:
    """``worklist`` or ``sat`` for ``auto``: the worklist touches every transition into the
    changed cells once (SCOTS's algorithm, cost ~ transitions), the SAT game tests 2^n table
    entries per candidate pair and rebuilds a table of all cells per level; the worklist wins
    unless the boxes are large (mean box volume above a few times 2^n, as with long held
    inputs; with a corner index, boxes small enough for it) or the pairs too many for its
    per-pair counters."""
    if method not in METHODS:
        raise SimgapError(f"game method must be one of {', '.join(METHODS)}, got {method!r}")
    if method != "auto":
        return method
    if ab.grid.size * ab.n_inputs > _WORKLIST_MAX_PAIRS:
        return "sat"
    if ab.corner_index is not None:  # one class per cell, small boxes: an index of one entry per pair
        return "worklist"
    vol = pair_volumes(ab)[ab.ok]
    # one class per cell: the worklist also builds the predecessor index (one entry per
    # transition), so it wins only for smaller boxes (measured: bench_synthesis_generic.py)
    limit = 1.25 if len(ab.class_dims) == ab.grid.n else 4
    return "worklist" if vol.size == 0 or vol.mean() <= limit * (1 << ab.grid.n) else "sat"


def _unpack(packed: np.ndarray, M: int) -> np.ndarray:
    """(N, ceil(M/8)) packed bits -> (N*M,) bool, pair id c * M + u."""
    return unpack_rows(packed, M).reshape(-1)


def unpack_rows(packed: np.ndarray, M: int) -> np.ndarray:
    """(N, ceil(M/8)) bits (np.packbits order) -> (N, M) bool; column by column for few inputs
    (np.unpackbits along a short axis is several times slower)."""
    if M > 16:
        return np.unpackbits(packed, axis=1, count=M).view(bool)
    out = np.empty((packed.shape[0], M), dtype=bool)
    for u in range(M):
        np.not_equal(packed[:, u >> 3] & np.uint8(0x80 >> (u & 7)), 0, out=out[:, u])
    return out


def pack_rows(rows: np.ndarray) -> np.ndarray:
    """(N, M) bool -> (N, ceil(M/8)) uint8, as np.packbits(rows, axis=1)."""
    N, M = rows.shape
    if M > 16:
        return np.packbits(rows, axis=1)
    out = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
    for u in range(M):
        out[:, u >> 3] |= rows[:, u].view(np.uint8) << np.uint8(7 - (u & 7))
    return out


def _predecessors(ab: Abstraction, live: np.ndarray):
    """The predecessor index: the abstraction's corner index when it has one (one class per
    cell, small boxes), else :class:`Predecessors` (its pairs() may return pairs that are not
    live; the games filter them)."""
    if ab.corner_index is not None:
        return ab.corner_index
    one_class_per_cell = len(ab.class_dims) == ab.grid.n
    return Predecessors(ab, live if one_class_per_cell else ab.ok.reshape(-1))


def _counter_dtype(vmax: int):
    for dt in (np.uint8, np.uint16, np.uint32):
        if vmax <= np.iinfo(dt).max:
            return dt
    return np.uint64


def solve_reach(ab: Abstraction, target: np.ndarray, blocked: np.ndarray,
                allowed: Optional[np.ndarray] = None, group_filter: Optional[bool] = None,
                method: str = "auto") -> GameResult:
    """Reach-avoid game: least fixed point W = T u Cpre(W) (module docstring).

    ``target`` and ``blocked`` (obstacles) are (N,) bool masks; ``allowed`` (N,) marks the cells
    where intermediate states may be when the input is held (default: not blocked).
    The valid inputs recorded for a cell won at level j are those whose box lies in W_{j-1};
    each of them guarantees at most j steps to go in the worst case. ``method``: ``worklist``
    (per-pair counters of box cells not yet won, decremented through the predecessors of the
    cells won in the last level, as SCOTS), ``sat`` (level-wise summed-area tables) or ``auto``
    (:func:`choose_method`); both give identical results.
    """
    t0 = time.perf_counter()
    M = ab.n_inputs
    target = target & ~blocked
    if allowed is None:
        allowed = ~blocked
    method = choose_method(method, ab)
    if method == "worklist" and ab.corner_index is not None and ab.hold == 1:
        live, n_boxes, n_trans = _usable_pairs(ab.corner_index, blocked)  # no pass over all pairs
    elif method == "worklist" and ab.mid_lo is None and len(ab.class_dims) < ab.grid.n:
        live, n_boxes, n_trans = _valid_shared(ab, blocked)
    else:
        live, n_boxes, n_trans = live_pairs(ab, blocked, ~blocked, allowed, test_keep=method == "sat")
    t1 = time.perf_counter()
    t_pre = 0.0
    if method == "worklist":
        live = _unpack(live, M)
        pre = _predecessors(ab, live)
        t_pre = time.perf_counter() - t1
        steps, packed, it, tested = _reach_worklist(ab, target, live, pre)
    else:
        ev = PairEvaluator(ab, blocked, allowed)
        steps, packed, it, tested = _reach_sat(ab, ev, target, blocked, live, group_filter)
    t2 = time.perf_counter()
    return GameResult(kind="reach_avoid", winning=steps >= 0, steps=steps, valid_packed=packed,
                      n_inputs=M, target=target, iterations=it,
                      seconds=time.perf_counter() - t0,
                      info={"pairs_tested": int(tested), "boxes": n_boxes, "transitions": n_trans,
                            "method": method, "seconds_parts": {
                                "live_pairs": t1 - t0, "predecessors": t_pre,
                                "fixed_point": t2 - t1 - t_pre, "controller": 0.0}})


def _reach_worklist(ab: Abstraction, target: np.ndarray, live: np.ndarray, pre):
    """SCOTS's reach game, level-synchronous: cnt[c, u] = cells of box(c, u) not yet won."""
    N, M = ab.grid.size, ab.n_inputs
    vol = pair_volumes(ab)
    vol = vol.astype(_counter_dtype(int(vol.max(initial=0)) + 1))
    if len(ab.class_dims) == ab.grid.n:
        cnt = vol.reshape(-1)
    else:
        cnt = np.broadcast_to(_per_class(ab, vol), tuple(ab.grid.shape) + (M,)).reshape(-1)  # a copy
    # a pair that is not live starts one above its box volume: it never completes, so the
    # decrements need no per-pair filter, only the (small, cached) per-cell one below
    cnt += ~live
    one = cnt.dtype.type(1)
    steps = np.full(N, -1, dtype=np.int32)
    steps[target] = 0
    won = target.copy()
    packed = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
    R = np.flatnonzero(target)
    it = tested = 0
    while R.size:
        p = pre.pairs(R)
        p = np.compress(~won.take(p // M), p)  # pairs of cells not yet won
        if p.size == 0:
            break
        it += 1
        tested += p.size
        np.subtract.at(cnt, p, one)  # one decrement per transition into a newly won cell
        done = np.unique(np.compress(cnt.take(p) == 0, p))
        if done.size == 0:
            break
        R, row = np.unique(done // M, return_inverse=True)
        rows = np.zeros((R.size, M), dtype=bool)
        rows[row, done % M] = True
        packed[R] = pack_rows(rows)
        won[R] = True
        steps[R] = it
    return steps, packed, it, tested


def _reach_sat(ab: Abstraction, ev: PairEvaluator, target, blocked, live, group_filter):
    """The level-wise game on summed-area tables of W (for large boxes)."""
    g = ab.grid
    N, M = g.size, ab.n_inputs
    W = target.copy()
    steps = np.full(N, -1, dtype=np.int32)
    steps[target] = 0
    open_ = ~W & ~blocked & live.any(axis=1)
    packed = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
    dlo, dhi = ab.offset_range()
    Wc = BoxCounter(g.shape, g.periodic_mask)
    # the input-group filter pays off with many inputs (its SAT costs one more build per level)
    hc = ev.build_hulls() if (group_filter if group_filter is not None else M >= 100) else None
    changed = np.flatnonzero(target)
    buf = np.zeros((3, N), dtype=bool)  # frontier buffers, reused every level
    it = 0
    B = _block_size(ab)  # ~2^18 pairs: block temporaries stay small enough for the heap to reuse
    tested = 0
    while True:
        # a cell can gain only when one of its boxes meets the cells won last round
        cand = _frontier(ab, changed, open_, dlo, dhi, buf)
        if cand.size == 0:
            break
        Wc.set(W)
        if hc is not None:
            buf[0] = False
            buf[0, changed] = True
            hc.set(buf[0])
        new_ids, new_rows = [], []
        for s in range(0, cand.size, B):
            ids = cand[s:s + B]
            # only input groups whose hull meets the new cells (and that have live pairs)
            lv = live[ids]
            if hc is not None:
                gm = ev.groups_meeting(ids, hc)
                if ev.group == 8:  # one group per byte of the packed rows
                    lv = lv & np.where(gm, 0xFF, 0).astype(np.uint8)
                else:
                    lv = lv & np.packbits(np.repeat(gm, ev.group, axis=1)[:, :M], axis=1)
            rows = np.unpackbits(lv, axis=1, count=M).view(bool)
            tested += ev.test_rows(ids, rows, Wc)
            win = rows.any(axis=1)
            if win.any():
                new_ids.append(ids[win])
                new_rows.append(np.packbits(rows[win], axis=1))
        it += 1
        if not new_ids:
            break
        new = np.concatenate(new_ids)
        packed[new] = np.concatenate(new_rows)
        W[new] = True
        open_[new] = False
        steps[new] = it
        changed = new
    return steps, packed, it, tested


def solve_invariance(ab: Abstraction, safe: np.ndarray, blocked: Optional[np.ndarray] = None,
                     max_margin: int = 3, method: str = "auto") -> GameResult:
    """Safety game: greatest fixed point W = S n Cpre(W) (module docstring).

    The valid inputs of a winning cell are all u with box(c, u) inside W. ``chosen`` (N,) is
    the valid input with the largest margin k <= max_margin (the box grown by k cells in every
    dimension still lies in W), ties by lowest index; -1 outside W. ``method`` as in
    :func:`solve_reach` (the worklist drops the pairs whose box meets a lost cell).
    """
    t0 = time.perf_counter()
    g = ab.grid
    N, M = g.size, ab.n_inputs
    if blocked is None:
        blocked = np.zeros(N, dtype=bool)
    S = safe & ~blocked
    method = choose_method(method, ab)
    ci = ab.corner_index if method == "worklist" and ab.hold == 1 else None
    alive = None
    if ci is not None and np.count_nonzero(~S) * ci.offsets.shape[0] <= N:
        # the abstraction's usable pairs of the safe cells, minus those whose box meets an unsafe
        # cell (their predecessors): no pass over all pairs
        live, n_boxes, n_trans = _usable_pairs(ci, ~S)
        alive = _unpack(live, M)
        alive[ci.pairs(np.flatnonzero(~S))] = False
    else:
        live, n_boxes, n_trans = live_pairs(ab, ~S, S, S)
    t1 = time.perf_counter()
    t_pre = 0.0
    if method == "worklist":
        alive = _unpack(live, M) if alive is None else alive
        pre = _predecessors(ab, alive)
        t_pre = time.perf_counter() - t1
        W, it, tested = _invariance_worklist(ab, S, alive, pre)  # alive: box in W, updated in place
    else:
        W, it, tested = _invariance_sat(ab, PairEvaluator(ab, ~S, S), S, live)
    t2 = time.perf_counter()
    packed, chosen = _safety_controller(ab, W, live, max_margin, alive=alive)
    steps = np.where(W, 0, -1).astype(np.int32)
    return GameResult(kind="invariance", winning=W, steps=steps, valid_packed=packed,
                      n_inputs=M, target=np.zeros(N, dtype=bool), chosen=chosen, iterations=it,
                      seconds=time.perf_counter() - t0,
                      info={"pairs_tested": int(tested), "boxes": n_boxes, "transitions": n_trans,
                            "method": method, "seconds_parts": {
                                "live_pairs": t1 - t0, "predecessors": t_pre, "fixed_point": t2 - t1 - t_pre,
                                "controller": time.perf_counter() - t2}})


def _invariance_worklist(ab: Abstraction, S: np.ndarray, alive: np.ndarray, pre):
    """Drop every pair whose box meets a lost cell; a cell with no pair left is lost next.

    ``alive`` (N*M,) bool, the live pairs, is updated in place: on return it marks the pairs
    whose box lies in W (every lost cell dropped the pairs that reach it)."""
    N, M = ab.grid.size, ab.n_inputs
    n_alive = _row_counts(alive, N, M)
    W = S & (n_alive > 0)
    R = np.flatnonzero(S & ~W)
    # scratch for removing duplicate pairs without sorting (at most 16 MB; else np.unique)
    owner = np.empty(alive.size, dtype=np.int32) if alive.size <= 1 << 22 else None
    it = tested = 0
    while True:
        it += 1
        p = pre.pairs(R)
        p = np.compress(alive.take(p), p)
        if p.size == 0:
            break
        p = _distinct(p, owner)
        tested += p.size
        alive[p] = False
        c = p // M
        np.subtract.at(n_alive, c, np.int32(1))
        R = _distinct(np.compress(n_alive.take(c) == 0, c), owner)
        if R.size == 0:
            break
        W[R] = False
    return W, it, tested


def _distinct(a: np.ndarray, owner: Optional[np.ndarray]) -> np.ndarray:
    """The distinct values of ``a`` (indices into ``owner``, a scratch int32 array), without
    sorting: every value keeps the one position whose index its owner entry holds."""
    if owner is None:
        return np.unique(a)
    pos = np.arange(a.size, dtype=np.int32)
    owner[a] = pos
    return np.compress(owner.take(a) == pos, a)


def _row_counts(flags: np.ndarray, N: int, M: int) -> np.ndarray:
    """(N,) int32 number of True per row of ``flags`` (N*M,) (column by column: a reduction
    along a short last axis is slow)."""
    rows = flags.reshape(N, M)
    out = np.zeros(N, dtype=np.int32)
    for u in range(M):
        out += rows[:, u]
    return out


def _per_class(ab: Abstraction, a: np.ndarray) -> np.ndarray:
    """(K, M) per (class, input) -> an n-D + 1 array broadcastable over grid.shape + (M,): the
    class dimensions at their positions, size 1 in the invariant ones."""
    a = a.reshape([ab.grid.shape[d] for d in ab.class_dims] + [a.shape[-1]])
    for d in range(ab.grid.n):
        if d not in ab.class_dims:
            a = np.expand_dims(a, d)
    return a


def _valid_shared(ab: Abstraction, blocked: np.ndarray):
    """:func:`live_pairs` without the keep test for shared boxes and no held input, by
    broadcasting: a pair is valid when ``ok``, its cell is not blocked and its box stays in the
    grid, which in an invariant dimension d is an index range per (class, input),
    -off_lo_d <= i_d <= n_d - 1 - off_hi_d. No pass over the pairs' boxes."""
    g = ab.grid
    N, M = g.size, ab.n_inputs
    K = ab.n_classes
    ok = ab.ok.copy()
    cmi = np.zeros((K, g.n), dtype=np.int64)
    if ab.class_dims:
        cmi[:, list(ab.class_dims)] = np.stack(np.unravel_index(
            np.arange(K), [g.shape[d] for d in ab.class_dims]), axis=1)
    valid = None
    for d in range(g.n):
        if g.periodic_mask[d]:
            continue
        lo, hi = ab.off_lo[..., d].astype(np.int64), ab.off_hi[..., d].astype(np.int64)
        if d in ab.class_dims:
            ok &= (cmi[:, d, None] + lo >= 0) & (cmi[:, d, None] + hi <= g.shape[d] - 1)
            continue
        i = np.arange(g.shape[d]).reshape([-1 if e == d else 1 for e in range(g.n)] + [1])
        v = (i + _per_class(ab, lo) >= 0) & (i + _per_class(ab, hi) <= g.shape[d] - 1)
        valid = v if valid is None else valid & v
    full = np.broadcast_to(_per_class(ab, ok), tuple(g.shape) + (M,))
    valid = full & (True if valid is None else valid)
    valid &= ~blocked.reshape(tuple(g.shape) + (1,))
    inv_axes = tuple(d for d in range(g.n) if d not in ab.class_dims)
    per_class = valid.sum(axis=inv_axes, dtype=np.int64).reshape(K, M)  # valid cells per (class, input)
    trans = int((per_class * pair_volumes(ab)).sum())
    return pack_rows(valid.reshape(N, M)), int(per_class.sum()), trans


def _usable_pairs(ci, blocked: np.ndarray):
    """The abstraction's usable pairs of the unblocked cells, as :func:`live_pairs` without
    the keep test (packed bits, boxes, transitions), from the corner index's per-cell tables."""
    free = ~blocked
    packed = ci.usable * free[:, None].view(np.uint8)
    return packed, int(ci.cell_boxes[free].sum()), int(ci.cell_transitions[free].sum())


def _invariance_sat(ab: Abstraction, ev: PairEvaluator, S: np.ndarray, live: np.ndarray):
    """The level-wise game on summed-area tables of W (for large boxes)."""
    g = ab.grid
    N, M = g.size, ab.n_inputs
    W = S & live.any(axis=1)
    dlo, dhi = ab.offset_range()
    Wc = BoxCounter(g.shape, g.periodic_mask)
    B = _block_size(ab)  # ~2^18 pairs: block temporaries stay small enough for the heap to reuse
    buf = np.zeros((3, N), dtype=bool)  # frontier buffers, reused every round
    changed = None
    it = 0
    tested = 0
    first = True
    while True:
        # a cell can lose only when one of its boxes meets the cells lost last round
        cand = np.flatnonzero(W) if first else _frontier(ab, changed, W, dlo, dhi, buf)
        first = False
        if cand.size == 0:
            break
        Wc.set(W)
        lose = []
        for s in range(0, cand.size, B):
            ids = cand[s:s + B]
            rows = np.unpackbits(live[ids], axis=1, count=M).view(bool)
            tested += ev.test_rows(ids, rows, Wc)
            bad = ~rows.any(axis=1)
            if bad.any():
                lose.append(ids[bad])
        it += 1
        if not lose:
            break
        changed = np.concatenate(lose)
        W[changed] = False
    return W, it, tested


def _safety_controller(ab: Abstraction, W: np.ndarray, live: np.ndarray, max_margin: int,
                       alive: Optional[np.ndarray] = None):
    """Valid inputs on the fixed point, and the input of largest margin k <= max_margin.

    The box grown by k cells lies in W exactly when the box lies in E_k, W eroded k times by
    the 3^n neighbourhood (outside the grid counts as not in W in bounded dimensions), so the
    margin of a valid pair is the min over its box of D, the number of erosions a cell
    survives. Valid means box(c, u) in W: ``alive`` (N*M,) from the worklist says so for the
    live pairs of W's cells, else one summed-area-table test. The inputs are taken in index
    order and a cell is settled by its first input of margin ``max_margin`` (one
    summed-area-table test against E_max), so most cells test one pair; the other pairs take
    the min of D over their box.
    """
    g = ab.grid
    N, M = g.size, ab.n_inputs
    E = W.reshape(g.shape)
    D = W.astype(np.int8) - np.int8(1)  # -1 outside W
    for _ in range(max_margin):
        E = _erode(E, g.periodic_mask)
        D += E.ravel()
    top = BoxCounter(g.shape, g.periodic_mask).set(E.ravel())
    del E
    if alive is None:
        wc = BoxCounter(g.shape, g.periodic_mask).set(W)
        valid = np.zeros((N, M), dtype=bool)
        B = _block_size(ab)
        for s in range(0, N, B):
            rng = slice(s, min(N, s + B))
            valid[rng] = unpack_rows(live[rng], M) & W[rng, None] & RowBoxes(ab, rng).inside(wc)
    else:
        valid = alive.reshape(N, M) & W[:, None]
    packed = pack_rows(valid)
    chosen = np.full(N, -1, dtype=np.int32)
    best = np.full(N, -1, dtype=np.int8)
    open_ = W.copy()  # cells without an input of margin max_margin yet
    B = 1 << 16  # cells per block: the block's temporaries stay small
    for u in range(M):
        ids_u = np.flatnonzero(open_ & valid[:, u])
        for s in range(0, ids_u.size, B):
            ids = ids_u[s:s + B]
            bx = RowBoxes(ab, ids, inputs=slice(u, u + 1))
            mg = np.where(bx.inside(top)[:, 0], np.int8(max_margin), np.int8(-1))
            rest = np.flatnonzero(mg < 0)
            if rest.size:
                mg[rest] = bx.min_over(D, g.shape, g.strides, (rest, np.zeros_like(rest)))
            better = mg > best[ids]  # strictly: ties keep the lowest input
            best[ids[better]] = mg[better]
            chosen[ids[better]] = u
        open_[ids_u[best[ids_u] == max_margin]] = False
    return packed, chosen


def _erode(E: np.ndarray, periodic_mask) -> np.ndarray:
    """E eroded by one cell in every dimension (Chebyshev), separable; the outside is empty."""
    for d in range(E.ndim):
        out = E.copy()
        if periodic_mask[d]:
            out &= np.roll(E, 1, axis=d)
            out &= np.roll(E, -1, axis=d)
        else:
            lo = [slice(None)] * E.ndim
            hi = [slice(None)] * E.ndim
            lo[d], hi[d] = slice(0, -1), slice(1, None)
            out[tuple(lo)] &= E[tuple(hi)]
            out[tuple(hi)] &= E[tuple(lo)]
            edge = [slice(None)] * E.ndim
            for i in (0, -1):
                edge[d] = i
                out[tuple(edge)] = False
        E = out
    return E

"""The previous release's games (level-wise summed-area tables), kept unchanged as the reference
path of ``bench/bench_synthesis_generic.py``: its vehicle timing is measured against this code in
the same run. Not used by the package.

Fixed-point games on an implicit abstraction, with summed-area tables (SAT).

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

from simgap.synthesis.abstraction import Abstraction


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

    def volume(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Number of cells in normalized boxes."""
        return np.prod(hi - lo + 1, axis=-1, dtype=np.int64)


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

    _PRECOMPUTE_BYTES = 64 << 20  # above this, corner offsets are computed per query

    def __init__(self, ab: Abstraction, off_lo: np.ndarray, off_hi: np.ndarray, counter: BoxCounter,
                 clamp: bool = True):
        g = ab.grid
        n = g.n
        self.ab, self.n, self.counter = ab, n, counter
        shape = np.array(g.shape, dtype=np.int64)
        pm = g.periodic_mask
        shape32 = shape.astype(np.int32)  # int32 temporaries: the generic path has K = N classes
        ext = off_hi.astype(np.int32) - off_lo + 1
        np.maximum(ext, 0, out=ext)
        lo = off_lo.astype(np.int32)
        if pm.any():
            ext = np.where(pm, np.minimum(ext, shape32), ext)
            lo = np.where(pm, np.mod(lo, shape32), lo)
        # int16 per (class, input, dim) when it fits: the generic path has one class per cell
        small = max(int(np.abs(lo).max(initial=0)), int(ext.max(initial=0)), int(shape.max())) < 16000
        it = np.int16 if small else np.int32
        self.lo = lo.astype(it)
        self.ext = ext.astype(it)
        self.vol = np.prod(ext, axis=-1, dtype=np.int32)
        self.tstr = counter.tstrides.astype(np.int64)
        self.shape = shape
        # in-domain test per bounded dimension: mi_d in [-off_lo_d, n_d - off_lo_d - ext_d]
        self.bounded = np.flatnonzero(~pm)
        self.rlo = (-lo).astype(it)
        self.rhi = (shape32 - lo - ext).astype(it)
        del lo, ext
        if not clamp:
            self.rlo = self.rhi = None
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

    def in_domain(self, mi: np.ndarray, k: np.ndarray) -> np.ndarray:
        """(B, M) bool: boxes of the rows (mi (B,n), class k (B,)) stay in the grid (bounded dims)."""
        ok = np.ones((mi.shape[0], self.M), dtype=bool)
        for d in self.bounded:
            ok &= (mi[:, d, None] >= self.rlo[k, :, d]) & (mi[:, d, None] <= self.rhi[k, :, d])
        return ok

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
        self.mi_all = g.ids_to_multi(np.arange(g.size)).astype(np.int32)
        self.cls_all = ab.cell_class(self.mi_all).astype(np.int64)
        self.q0_all = self.cls_all * self.M  # flat (class, input 0) index per cell
        self.base_all = (self.mi_all.astype(np.int64) @ self.counter.tstrides).astype(np.int32)
        self.hull = None

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
        self.hull = BoxFamily(ab, lo, hi, hc, clamp=False)
        self.hull_base = ((self.mi_all.astype(np.int64) + hc.pad) @ hc.tstrides).astype(np.int32)
        self.hull_G = G
        self.group = group
        return hc

    def groups_meeting(self, ids: np.ndarray, hc: BoxCounter) -> np.ndarray:
        """(B, G) bool: the hull of input group g of cell ids[b] meets the counter's mask."""
        k = self.cls_all[ids]
        q = k[:, None] * self.hull_G + np.arange(self.hull_G)
        return self.hull.count(hc.table, self.hull_base[ids][:, None], q, k=k) > 0

    def valid_rows(self, ids: np.ndarray):
        """(B,) cell ids -> valid (B, M) bool (in grid, finite, cell not blocked, intermediate
        hull allowed), and the flat pair indices q (B, M)."""
        ab = self.ab
        mi = self.mi_all[ids]
        k = self.cls_all[ids]
        q = self.q0_all[ids][:, None] + np.arange(self.M)
        valid = ab.ok[k] & self.fam.in_domain(mi, k)
        valid &= ~self.blocked[ids][:, None]
        if self.mid is not None:
            valid &= self.mid.in_domain(mi, k)
            valid &= self.mid.count(self.allowed_counter.table, self.base_all[ids][:, None], q, k=k) == \
                self.mid.vol[k]
        return valid, q

    def test_rows(self, ids: np.ndarray, q: np.ndarray, counter: BoxCounter) -> np.ndarray:
        """(B, M) bool: box(ids, u) lies in the counter's mask (meaningful for valid pairs)."""
        k = self.cls_all[ids]
        return self.fam.count(counter.table, self.base_all[ids][:, None], q, k=k) == self.fam.vol[k]

    def test_pairs(self, ids: np.ndarray, ci: np.ndarray, uj: np.ndarray, counter: BoxCounter) -> np.ndarray:
        """(P,) bool: box(ids[ci], uj) lies in the counter's mask (pairs assumed valid)."""
        cells = ids[ci]
        q = self.q0_all[cells] + uj
        return self.fam.count(counter.table, self.base_all[cells], q) == self.fam.vol_flat[q]

    def pair_boxes(self, ids: np.ndarray, ci: np.ndarray, uj: np.ndarray):
        """Explicit normalized boxes (lo, hi (P, n) int32) of the pairs (ids[ci], uj)."""
        ab = self.ab
        cells = ids[ci]
        k = self.cls_all[cells]
        mi = self.mi_all[cells]
        lo, hi, _ = self.counter.normalize(mi + ab.off_lo[k, uj], mi + ab.off_hi[k, uj])
        return lo, hi, self.vol[k, uj]


def live_pairs(ab: Abstraction, blocked: np.ndarray, keep: np.ndarray, allowed=None,
               ev: Optional["PairEvaluator"] = None):
    """One pass over all pairs: which can ever be used, and the SCOTS transition count.

    A pair (c, u) is *live* when it is valid (see module docstring) and its box lies in
    ``keep`` (reach: the unblocked cells; invariance: the safe cells); pairs that are not live
    can never be in the controller, so the games never test them again.

    Returns (live (N, ceil(M/8)) packed bits, number of valid boxes, sum of their volumes).
    """
    g = ab.grid
    N, M = g.size, ab.n_inputs
    if ev is None:
        ev = PairEvaluator(ab, blocked, allowed)
    kc = BoxCounter(g.shape, g.periodic_mask).set(keep)
    packed = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
    B = _block_size(ab)
    boxes = 0
    trans = 0
    free = np.flatnonzero(~blocked)  # blocked cells have no valid pairs
    for s in range(0, free.size, B):
        ids = free[s:s + B]
        valid, q = ev.valid_rows(ids)
        boxes += int(valid.sum())
        trans += int(ev.fam.vol_flat[q][valid].sum(dtype=np.int64))
        packed[ids] = np.packbits(valid & ev.test_rows(ids, q, kc), axis=1)
    return packed, boxes, trans


def _frontier(ab: Abstraction, changed: np.ndarray, candidates_mask: np.ndarray, dlo, dhi) -> np.ndarray:
    """Ids of cells c in ``candidates_mask`` with c + delta in ``changed`` for some delta in [dlo, dhi].

    Every box of c lies in c + [dlo, dhi], so only these cells can change status. Computed as
    a separable binary dilation of ``changed`` (one pass of shifted ORs per dimension).
    """
    g = ab.grid
    D = changed.reshape(g.shape)
    for d in range(g.n):
        src = D
        D = np.zeros_like(src)
        s = g.shape[d]
        for delta in range(int(dlo[d]), int(dhi[d]) + 1):  # a handful of shifts (offset range)
            if g.periodic_mask[d]:
                D |= np.roll(src, -delta, axis=d)
            else:
                if abs(delta) >= s:
                    continue
                dst = [slice(None)] * g.n
                sl = [slice(None)] * g.n
                if delta >= 0:  # D[i] |= src[i + delta]
                    dst[d], sl[d] = slice(0, s - delta), slice(delta, s)
                else:
                    dst[d], sl[d] = slice(-delta, s), slice(0, s + delta)
                D[tuple(dst)] |= src[tuple(sl)]
    return np.flatnonzero(D.ravel() & candidates_mask)


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


def solve_reach(ab: Abstraction, target: np.ndarray, blocked: np.ndarray,
                allowed: Optional[np.ndarray] = None, group_filter: Optional[bool] = None) -> GameResult:
    """Reach-avoid game: least fixed point W = T u Cpre(W) (module docstring).

    ``target`` and ``blocked`` (obstacles) are (N,) bool masks; ``allowed`` (N,) marks the cells
    where intermediate states may be when the input is held (default: not blocked).
    The valid inputs recorded for a cell won at level j are those whose box lies in W_{j-1};
    each of them guarantees at most j steps to go in the worst case.
    """
    t0 = time.perf_counter()
    g = ab.grid
    N, M = g.size, ab.n_inputs
    target = target & ~blocked
    if allowed is None:
        allowed = ~blocked
    ev = PairEvaluator(ab, blocked, allowed)
    live, n_boxes, n_trans = live_pairs(ab, blocked, ~blocked, allowed, ev=ev)
    t_live = time.perf_counter() - t0
    W = target.copy()
    steps = np.full(N, -1, dtype=np.int32)
    steps[target] = 0
    open_ = ~W & ~blocked & live.any(axis=1)
    packed = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
    dlo, dhi = ab.offset_range()
    Wc = BoxCounter(g.shape, g.periodic_mask)
    # the input-group filter pays off with many inputs (its SAT costs one more build per level)
    hc = ev.build_hulls() if (group_filter if group_filter is not None else M >= 100) else None
    changed = target.copy()
    it = 0
    B = _block_size(ab) * 4
    tested = 0
    while True:
        # a cell can gain only when one of its boxes meets the cells won last round
        cand = _frontier(ab, changed, open_, dlo, dhi)
        if cand.size == 0:
            break
        Wc.set(W)
        if hc is not None:
            hc.set(changed)
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
            ci, uj = np.nonzero(rows)
            tested += ci.size
            rows[ci, uj] = ev.test_pairs(ids, ci, uj, Wc)
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
        changed = np.zeros(N, dtype=bool)
        changed[new] = True
    return GameResult(kind="reach_avoid", winning=W, steps=steps, valid_packed=packed,
                      n_inputs=M, target=target, iterations=it,
                      seconds=time.perf_counter() - t0,
                      info={"pairs_tested": int(tested), "boxes": n_boxes, "transitions": n_trans,
                            "seconds_live": t_live})


def solve_invariance(ab: Abstraction, safe: np.ndarray, blocked: Optional[np.ndarray] = None,
                     max_margin: int = 3) -> GameResult:
    """Safety game: greatest fixed point W = S n Cpre(W) (module docstring).

    The valid inputs of a winning cell are all u with box(c, u) inside W. ``chosen`` (N,) is
    the valid input with the largest margin k <= max_margin (the box grown by k cells in every
    dimension still lies in W), ties by lowest index; -1 outside W.
    """
    t0 = time.perf_counter()
    g = ab.grid
    N, M = g.size, ab.n_inputs
    if blocked is None:
        blocked = np.zeros(N, dtype=bool)
    S = safe & ~blocked
    ev = PairEvaluator(ab, ~S, S)
    live, n_boxes, n_trans = live_pairs(ab, ~S, S, S, ev=ev)
    t_live = time.perf_counter() - t0
    W = S & live.any(axis=1)
    dlo, dhi = ab.offset_range()
    Wc = BoxCounter(g.shape, g.periodic_mask)
    B = _block_size(ab) * 4
    changed = ~W
    it = 0
    tested = 0
    first = True
    while True:
        # a cell can lose only when one of its boxes meets the cells lost last round
        cand = np.flatnonzero(W) if first else _frontier(ab, changed, W, dlo, dhi)
        first = False
        if cand.size == 0:
            break
        Wc.set(W)
        lose = []
        for s in range(0, cand.size, B):
            ids = cand[s:s + B]
            rows = np.unpackbits(live[ids], axis=1, count=M).view(bool)
            ci, uj = np.nonzero(rows)
            tested += ci.size
            rows[ci, uj] = ev.test_pairs(ids, ci, uj, Wc)
            bad = ~rows.any(axis=1)
            if bad.any():
                lose.append(ids[bad])
        it += 1
        if not lose:
            break
        lose = np.concatenate(lose)
        W[lose] = False
        changed = np.zeros(N, dtype=bool)
        changed[lose] = True
    # controller on the fixed point: valid inputs, and margins (grown boxes still in W)
    Wc = BoxCounter(g.shape, g.periodic_mask)
    Wc.set(W)
    packed = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
    chosen = np.full(N, -1, dtype=np.int32)
    ids_w = np.flatnonzero(W)
    for s in range(0, ids_w.size, B):
        ids = ids_w[s:s + B]
        rows = np.unpackbits(live[ids], axis=1, count=M).view(bool)
        ci, uj = np.nonzero(rows)
        lo, hi, vol = ev.pair_boxes(ids, ci, uj)
        ok = Wc.count(lo, hi) == vol
        rows[ci, uj] = ok
        packed[ids] = np.packbits(rows, axis=1)
        mg = np.where(ok, 0, -1).astype(np.int8)
        for k in range(1, max_margin + 1):  # grow the box by k cells and test again
            l2, h2, ing = Wc.normalize(lo - k, hi + k)
            okk = ok & ing & (Wc.count(l2, h2) == Wc.volume(l2, h2))
            mg[okk] = k
        grid_mg = np.full((ids.size, M), -1, dtype=np.int8)
        grid_mg[ci, uj] = mg
        # largest margin first, ties by lowest index (argmax returns the first maximum)
        chosen[ids] = np.where(grid_mg.max(axis=1) >= 0, grid_mg.argmax(axis=1), -1)
    steps = np.where(W, 0, -1).astype(np.int32)
    return GameResult(kind="invariance", winning=W, steps=steps, valid_packed=packed,
                      n_inputs=M, target=np.zeros(N, dtype=bool), chosen=chosen, iterations=it,
                      seconds=time.perf_counter() - t0,
                      info={"pairs_tested": int(tested), "boxes": n_boxes, "transitions": n_trans,
                            "seconds_live": t_live})

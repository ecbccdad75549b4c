"""Fixed-point games on an implicit abstraction, with summed-area tables (SAT).

Every successor set is an index box, so "all successors of (c, u) lie in Z" is the O(1) test
``count_Z(box) == volume(box)`` on a summed-area table of Z (2^n lookups). Periodic dimensions
are handled by a SAT of Z tiled twice along them, so a wrapped interval [lo, lo + len) with
0 <= lo < n_d is one contiguous range.

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
(a worklist at cell granularity; SCOTS's worklist is per transition).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import SimgapError
from .abstraction import Abstraction


# ---------------------------------------------------------------------------------------
# summed-area tables over index boxes
# ---------------------------------------------------------------------------------------

class BoxCounter:
    """Counts the cells of a boolean grid mask inside many index boxes at once."""

    def __init__(self, shape, periodic_mask, max_volume: Optional[int] = None):
        self.shape = np.array(shape, dtype=np.int64)
        # counts are exact modulo 2^16 when every queried box has fewer than 2^16 cells:
        # inclusion-exclusion in wrapping uint16 arithmetic then returns the true count
        self.dtype = np.uint16 if (max_volume is not None and max_volume < 65536) else np.int32
        self.pmask = np.asarray(periodic_mask, dtype=bool)
        self.n = len(shape)
        self.tshape = tuple(int(s * (2 if p else 1) + 1) for s, p in zip(self.shape, self.pmask))
        self.tstrides = np.array([int(np.prod(self.tshape[d + 1:])) for d in range(self.n)], dtype=np.int64)
        self.table = None

    def set(self, mask_flat: np.ndarray) -> "BoxCounter":
        """Build the SAT of ``mask_flat`` (N,) bool; cumulative sums per axis, int32."""
        Z = mask_flat.reshape(tuple(self.shape))
        for d in np.flatnonzero(self.pmask):
            Z = np.concatenate([Z, Z], axis=int(d))
        T = np.zeros(self.tshape, dtype=self.dtype)
        T[tuple(slice(1, None) for _ in range(self.n))] = Z
        for d in range(self.n):
            np.cumsum(T, axis=d, out=T, dtype=self.dtype)
        self.table = T.ravel()
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
        return out.astype(np.int32) if self.dtype != np.int32 else out

    def volume(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Number of cells in normalized boxes."""
        return np.prod(hi - lo + 1, axis=-1, dtype=np.int64)


# ---------------------------------------------------------------------------------------
# pair evaluation
# ---------------------------------------------------------------------------------------

class PairEvaluator:
    """Successor boxes and validity for all inputs of a batch of cells."""

    def __init__(self, ab: Abstraction, blocked: np.ndarray, allowed: Optional[np.ndarray]):
        self.ab = ab
        g = ab.grid
        self.counter = BoxCounter(g.shape, g.periodic_mask)
        self.blocked = blocked
        self.allowed_counter = None
        if ab.mid_lo is not None and allowed is not None:
            self.allowed_counter = BoxCounter(g.shape, g.periodic_mask).set(allowed)
        # box volumes depend on the class and input only (periodic extents capped at n_d)
        ext = ab.off_hi.astype(np.int64) - ab.off_lo + 1
        ext = np.where(g.periodic_mask, np.minimum(ext, np.array(g.shape)), ext)
        self.vol = np.prod(np.maximum(ext, 0), axis=-1).astype(np.int32)
        self.vol_flat = self.vol.ravel()
        # per-cell multi-index and class, and per-(class, input) offsets as one row of 2n
        self.mi_all = g.ids_to_multi(np.arange(g.size)).astype(np.int32)
        self.cls_all = ab.cell_class(self.mi_all).astype(np.int64) * ab.n_inputs
        self.off_flat = np.concatenate([ab.off_lo, ab.off_hi], axis=-1).reshape(-1, 2 * g.n)

    def boxes(self, ids: np.ndarray):
        """(B,) cell ids -> lo, hi (B, M, n) normalized int32, valid (B, M) bool, volume (B, M)."""
        ab = self.ab
        mi = ab.grid.ids_to_multi(ids).astype(np.int32)
        k = ab.cell_class(mi)
        c = self.counter
        lo, hi, ing = c.normalize(mi[:, None, :] + ab.off_lo[k], mi[:, None, :] + ab.off_hi[k])
        valid = ab.ok[k] & ing
        valid &= ~self.blocked[ids][:, None]
        if self.allowed_counter is not None:
            mlo, mhi, ming = c.normalize(mi[:, None, :] + ab.mid_lo[k], mi[:, None, :] + ab.mid_hi[k])
            valid &= ming
            valid &= self.allowed_counter.count(mlo, mhi) == c.volume(mlo, mhi)
        return lo, hi, valid, self.vol[k]

    def inside(self, ids: np.ndarray, counter: BoxCounter):
        """(B, M) bool: valid and the successor box lies in the counter's mask; plus lo, hi."""
        lo, hi, valid, vol = self.boxes(ids)
        return valid & (counter.count(lo, hi) == vol), lo, hi

    def pair_boxes(self, ids: np.ndarray, ci: np.ndarray, uj: np.ndarray):
        """Normalized boxes of the pairs (ids[ci], uj) (1-D lists), and their volumes."""
        n = self.ab.grid.n
        cells = ids[ci]
        p = self.cls_all[cells] + uj  # flat (class, input) index
        mi = self.mi_all[cells]
        off = self.off_flat[p]
        lo = mi + off[:, :n]
        hi = mi + off[:, n:]
        c = self.counter
        for d in np.flatnonzero(c.pmask):  # wrap periodic dims; full circle clamped
            sz = int(c.shape[d])
            ext = hi[:, d] - lo[:, d] + 1
            full = ext >= sz
            l = np.where(full, 0, lo[:, d] % sz)
            lo[:, d] = l
            hi[:, d] = np.where(full, sz - 1, l + ext - 1)
        return lo, hi, self.vol_flat[p]


def live_pairs(ab: Abstraction, blocked: np.ndarray, keep: np.ndarray, allowed=None):
    """One pass over all pairs: which can ever be used, and the SCOTS transition count.

    A pair (c, u) is *live* when it is valid (see module docstring) and its box lies in
    ``keep`` (reach: the unblocked cells; invariance: the safe cells); pairs that are not live
    can never be in the controller, so the games never test them again.

    Returns (live (N, ceil(M/8)) packed bits, number of valid boxes, sum of their volumes).
    """
    g = ab.grid
    N, M = g.size, ab.n_inputs
    ev = PairEvaluator(ab, blocked, allowed)
    kc = BoxCounter(g.shape, g.periodic_mask).set(keep)
    packed = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
    B = _block_size(ab) * 2
    boxes = 0
    trans = 0
    for s in range(0, N, B):
        ids = np.arange(s, min(N, s + B))
        lo, hi, valid, vol = ev.boxes(ids)
        boxes += int(valid.sum())
        trans += int(vol[valid].sum(dtype=np.int64))
        packed[ids] = np.packbits(valid & (kc.count(lo, hi) == vol), axis=1)
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
    # about 2^21 (cell, input) pairs per block keeps the temporaries near 100 MB at n = 3
    return max(1, (1 << 19) // max(1, ab.n_inputs))


def solve_reach(ab: Abstraction, target: np.ndarray, blocked: np.ndarray,
                allowed: Optional[np.ndarray] = None) -> GameResult:
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
    live, n_boxes, n_trans = live_pairs(ab, blocked, ~blocked, allowed)
    t_live = time.perf_counter() - t0
    W = target.copy()
    steps = np.full(N, -1, dtype=np.int32)
    steps[target] = 0
    open_ = ~W & ~blocked & live.any(axis=1)
    packed = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
    dlo, dhi = ab.offset_range()
    Wc = BoxCounter(g.shape, g.periodic_mask, max_volume=int(ev.vol.max(initial=0)))
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
        new_ids, new_rows = [], []
        for s in range(0, cand.size, B):
            ids = cand[s:s + B]
            rows = np.unpackbits(live[ids], axis=1, count=M).view(bool)
            ci, uj = np.nonzero(rows)
            lo, hi, vol = ev.pair_boxes(ids, ci, uj)
            tested += ci.size
            rows[ci, uj] = Wc.count(lo, hi) == vol
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
    live, n_boxes, n_trans = live_pairs(ab, ~S, S, S)
    t_live = time.perf_counter() - t0
    W = S & live.any(axis=1)
    dlo, dhi = ab.offset_range()
    Wc = BoxCounter(g.shape, g.periodic_mask, max_volume=int(ev.vol.max(initial=0)))
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
            lo, hi, vol = ev.pair_boxes(ids, ci, uj)
            tested += ci.size
            rows[ci, uj] = Wc.count(lo, hi) == vol
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


def count_transitions(ab: Abstraction, blocked: np.ndarray) -> tuple[int, int]:
    """(number of valid (cell, input) boxes, sum of their volumes) over unblocked cells.

    Pairs that leave the grid (out of domain) are not counted, as in SCOTS.
    """
    g = ab.grid
    N, M = g.size, ab.n_inputs
    ev = PairEvaluator(ab, blocked, None)
    B = _block_size(ab) * 4
    boxes = 0
    trans = 0
    for s in range(0, N, B):
        ids = np.arange(s, min(N, s + B))
        lo, hi, valid, vol = ev.boxes(ids)
        boxes += int(valid.sum())
        trans += int(vol[valid].sum(dtype=np.int64))
    return boxes, trans

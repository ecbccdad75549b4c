"""Reach-avoid game: the least fixed point, by a worklist or by summed-area tables.

Level-synchronous, so that the level is the steps-to-go::

    W_0 = T                       (target cells; obstacle cells are never in W)
    W_{j+1} = W_j  u  Cpre(W_j),  Cpre(Z) = {c : exists valid u, box(c,u) subset Z}

The worklist keeps per-pair counters of box cells not yet won (SCOTS); the summed-area-table
game re-tests the pairs of the frontier cells each level. Both give identical results.
"""

from __future__ import annotations

import time
from typing import Optional

import numpy as np

from .abstraction import Abstraction
from .boxes import BoxCounter, PairEvaluator, pair_volumes, volume_bound
from .corner_index import CornerIndex
from .fixed_point import GameResult, choose_method, tick
from .live import _per_class, _usable_pairs, _valid_shared, live_pairs
from .pair_rows import _block_size, _unpack, pack_rows
from .predecessors import _frontier, _predecessors


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
    # straight into the counter's dtype (1 or 2 bytes a pair; no int32 table and its temporaries)
    vol = pair_volumes(ab, dtype=_counter_dtype(volume_bound(ab) + 1))
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
    level = _compiled_level(pre, cnt)
    while R.size:
        if level is not None:  # the same level, compiled (kernels.reach_level): the same pairs
            done, n_p = level(R, won)
            if n_p == 0:
                break
            it += 1
            tested += n_p
            done = np.unique(done)
        else:
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
        tick(it, R.size)
        rows = np.zeros((R.size, M), dtype=bool)
        rows[row, done % M] = True
        packed[R] = pack_rows(rows)
        won[R] = True
        steps[R] = it
    return steps, packed, it, tested


def _compiled_level(pre, cnt):
    """``level(R, won) -> (pairs whose count reached 0, transitions visited)`` compiled
    (:func:`simgap.synthesis.game_kernels.reach_level`) when :mod:`.game_kernels` says so for this
    game's pairs and ``pre`` is a corner index; else None (the numpy level)."""
    if not isinstance(pre, CornerIndex):
        return None
    from . import game_kernels
    lib = game_kernels.library(cnt.size, np.int8, pre.q.dtype, cnt=cnt.dtype)
    if lib is None:
        return None
    args = (pre.indptr, pre.q, pre.code, np.ascontiguousarray(pre.offsets, dtype=np.int64),
            np.ascontiguousarray(pre.fits, dtype=np.uint8), np.array(pre.shape, dtype=np.int64),
            np.array(pre.strides, dtype=np.int64), np.asarray(pre.pmask, dtype=np.uint8), int(pre.M))
    return lambda R, won: game_kernels.reach_level(lib, R, *args, won, cnt)


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
        tick(it, new.size)
        packed[new] = np.concatenate(new_rows)
        W[new] = True
        open_[new] = False
        steps[new] = it
        changed = new
    return steps, packed, it, tested

"""Invariance (safety) game: the greatest fixed point, and its safety controller.

::

    W_0 = S                       (safe cells)
    W_{j+1} = W_j  n  Cpre(W_j)

The worklist drops the pairs whose box meets a lost cell; the summed-area-table game re-tests
the pairs of the frontier cells each round. Both give identical results. The controller picks,
per winning cell, the valid input of largest margin (its box grown by k cells stays in W),
from erosions of W.
"""

from __future__ import annotations

import time
from typing import Optional

import numpy as np

from .abstraction import Abstraction
from .boxes import BoxCounter, PairEvaluator, RowBoxes
from .fixed_point import GameResult, choose_method, tick
from .live import _usable_pairs, live_pairs
from .pair_rows import _block_size, _unpack, pack_rows, unpack_rows
from .predecessors import _frontier, _predecessors


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
    steps = np.full(N, -1, dtype=np.int32)  # no (N,) int64 temporary
    steps[W] = 0
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
    level = _compiled_level(pre, alive, n_alive)
    if level is not None:  # the same rounds in C (game_kernels.inv_level): the same W, alive and count
        it = tested = 0
        while True:
            it += 1
            R, n_p = level(R)
            if n_p == 0:
                break
            tested += n_p
            tick(it, R.size)
            if R.size == 0:
                break
            W[R] = False
        return W, it, tested
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
        tick(it, R.size)
        if R.size == 0:
            break
        W[R] = False
    return W, it, tested


def _compiled_level(pre, alive: np.ndarray, n_alive: np.ndarray):
    """``level(R) -> (cells left without an alive pair, pairs dropped)`` in C when
    :mod:`.game_kernels` says so and ``pre`` is a corner index; else None (the numpy rounds)."""
    from .corner_index import CornerIndex
    if not isinstance(pre, CornerIndex) or not alive.flags.c_contiguous:
        return None
    from . import game_kernels
    lib = game_kernels.library(alive.size, np.int8, pre.q.dtype)
    if lib is None:
        return None
    flags = alive.view(np.uint8)  # updated in place, as the numpy rounds update alive
    args = (pre.indptr, pre.q, pre.code, np.ascontiguousarray(pre.offsets, dtype=np.int64),
            np.ascontiguousarray(pre.fits, dtype=np.uint8), np.array(pre.shape, dtype=np.int64),
            np.array(pre.strides, dtype=np.int64), np.asarray(pre.pmask, dtype=np.uint8), int(pre.M))
    return lambda R: game_kernels.invariance_level(lib, R, *args, flags, n_alive)


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
        tick(it, changed.size)
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
    lib = None
    if alive is not None and len(ab.class_dims) == g.n:  # the same choice in C (game_kernels.safety_choose)
        from . import game_kernels
        lib = game_kernels.for_abstraction(ab)
    if lib is not None:
        valid = alive.reshape(N, M) & W[:, None]
        return pack_rows(valid), game_kernels.safety_choose(lib, ab, valid, D, max_margin)
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
        for s in range(0, N, B):  # the open cells of a block of cells: no (N,) index array
            ids = np.flatnonzero(open_[s:s + B] & valid[s:s + B, u])
            if ids.size == 0:
                continue
            ids += s
            bx = RowBoxes(ab, ids, inputs=slice(u, u + 1))
            mg = np.where(bx.inside(top)[:, 0], np.int8(max_margin), np.int8(-1))
            rest = np.flatnonzero(mg < 0)
            if rest.size:
                mg[rest] = bx.min_over(D, g.shape, g.strides, (rest, np.zeros_like(rest)))
            better = mg > best[ids]  # strictly: ties keep the lowest input
            best[ids[better]] = mg[better]
            chosen[ids[better]] = u
            open_[ids[best[ids] == max_margin]] = False  # these ids are not visited again for u
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

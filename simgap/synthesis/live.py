"""Live pairs: the (cell, input) pairs a game can ever use, found once before its fixed point.

A pair (c, u) is *valid* when its box stays inside the grid in every bounded dimension (else it
may reach the losing "outside" state), the image is finite, and, when the input is held for
several periods, the hull of the intermediate boxes lies in the allowed cells. Pairs that can
never be used are removed once, up front: :func:`live_pairs` (one pass over all pairs, with
summed-area-table tests), ``_valid_shared`` (shared boxes, no held input: by broadcasting) and
``_usable_pairs`` (from the corner index's per-cell tables).
"""

from __future__ import annotations

import numpy as np

from .abstraction import Abstraction
from .boxes import BoxCounter, DistinctBoxes, RowBoxes, pair_volumes
from .pair_rows import _block_size, pack_rows


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

"""Interval MDP of a translation-invariant simulator: sampled once per (heading cell, input), not per cell.

A robot on a uniform floor moves the same way wherever it starts: with ``invariant`` dimensions
I (the position (x, y) of the TurtleBot) the simulator satisfies, for every noise draw w,

    y_t(x + d, u, w) = y_t(x, u, w) + d        for every shift d along I, t = 1..k,    (ASSUMPTION)

the same declared invariance the collection uses (``[collect] invariant_dims``). Then the k-period
runs from one reference cell center per class of cells (same index along the other dimensions,
here the heading) are, shifted by whole cells, samples of the runs from every cell of the class.
The cost is classes x inputs x (N + N0) x k simulator steps instead of cells x inputs x ...: the
number of position cells is free, only the bookkeeping (numpy, BLAS) grows with it.

Per class h, input a and cell c of the class (center x_c = x_ref + d_c), with the runs' end
boxes touching the reference offsets o (cells x_ref + o):

* support T(c, a) = {c + o : o touched by a pilot run, c + o live or target} (the pilot runs are
  independent of the main runs; hits of unsafe pilot runs are kept too, which only enlarges T);
* a main run r is a sink run for c when one of its widened boxes, shifted by d_c, touches a
  blocked cell at some period (a cell, along I, that is not wholly allowed for some index of the
  other dimensions, or outside the grid: a summed-area table, no loop over cells; the touched
  cells cover the box, so this is a superset of the unsafe boxes, sound and at most a cell more
  conservative than the exact box test), or, at some period, its widened box leaves X or the
  grid along one of the other (non-angle) dimensions (the same for every cell of the class: the
  runs are not shifted there; within the grid, the blocked columns cover the safe set and the
  obstacles), or it touches an offset outside the pilot's, or c + o is not live/target for one
  of its offsets o;
* n_hit(c, c + o) = #runs touching o (the same for every c), n_in(c, c + o) = #runs touching o
  only and not a sink run for c, n_sink(c) = #sink runs for c;
* intervals and the union bound's split exactly as :func:`simgap.perrun.sampling.build_imdp` (each
  bound uses N i.i.d. runs of its own cell; Bonferroni needs no independence between bounds).

The widening constants: along an invariant dimension j the trajectory is shifted exactly, so
L[:, j] = e_j; the other columns are Wood-Zhang estimates from common-random-number slopes.
"""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from ..errors import SimgapError
from ..synthesis.grid import UniformGrid
from ..synthesis.spec import Spec
from .imdp import (IMDP, Allocation, IMDPOptions, assemble, box_unsafe, cell_labels, trajectories,
                   trajectory_lipschitz)


def build_imdp_translation(sim, spec: Spec, options: IMDPOptions, invariant: Sequence[int] = (0, 1),
                           lipschitz_pairs: int = 100, lipschitz_runs: int = 20, log=None, on_progress=None) -> IMDP:
    """Interval MDP of ``spec`` from runs at one reference cell per class (module docstring).

    ``on_progress(done, total)``: in steps of 2 k simulated periods (pilot, main) plus one per
    (class, input) pair counted."""
    t0 = time.perf_counter()
    s, o = sim.system, options
    o.validate(s.n)
    inv = sorted({int(d) for d in invariant})
    if not inv or any(d < 0 or d >= s.n or d in s.angle_dims for d in inv):
        raise SimgapError(f"invariant dimensions {list(invariant)} must be non-angle state dimensions of {s.name!r}")
    ad = tuple(s.angle_dims)
    grid = UniformGrid(s.x_lo, s.x_hi, o.eta, periodic=ad)
    k, N, N0, n = int(o.hold), int(o.n_runs), int(o.pilot_runs), s.n
    half = grid.eta / 2
    other = [d for d in range(n) if d not in inv]
    if o.lipschitz is None:
        L, how = trajectory_lipschitz(sim, k, half, np.random.default_rng([o.seed, 1]), lipschitz_pairs,
                                      lipschitz_runs, dims=other)
        L[:, inv] = np.eye(n)[:, inv]
        how["invariant_columns"] = [s.state_names[d] for d in inv]
    else:
        L, how = np.broadcast_to(np.asarray(o.lipschitz, float), (n, n)).copy(), "given"
    rho = L @ half
    t_lip = time.perf_counter() - t0

    live, target = cell_labels(grid, spec, s.x_lo, s.x_hi, ad)
    good = live | target
    C, M = grid.size, s.inputs.shape[0]
    shape = np.asarray(grid.shape)
    mi_all = grid.ids_to_multi(np.arange(C))
    # classes: the multi-index along the non-invariant dimensions; reference: the middle cell along I
    ref_mi = np.zeros((1, n), np.int64)
    ref_mi[0, inv] = shape[inv] // 2
    cls_shape = shape[other]
    n_cls = int(np.prod(cls_shape))
    cls_of = np.ravel_multi_index(mi_all[:, other].T, cls_shape)
    ref_mi = np.repeat(ref_mi, n_cls, axis=0)
    ref_mi[:, other] = np.stack(np.unravel_index(np.arange(n_cls), cls_shape), axis=1)
    x_ref = grid.multi_to_points(ref_mi)                                # (n_cls, n)

    # ----- simulate: every (class, input) pair, pilot and main runs, in two batches ----------------
    rng = np.random.default_rng([o.seed, 0])
    P = n_cls * M
    xs = x_ref[np.arange(P) // M]
    us = s.inputs[np.arange(P) % M]
    done = [0]

    def tick():
        done[0] += 1
        if on_progress:
            on_progress(done[0], 2 * k + P)

    pilot = trajectories(sim, np.repeat(xs, N0, axis=0), np.repeat(us, N0, axis=0), k, rng, tick)
    t_pilot = time.perf_counter() - t0 - t_lip
    main = trajectories(sim, np.repeat(xs, N, axis=0), np.repeat(us, N, axis=0), k, rng, tick)
    t_sim = time.perf_counter() - t0 - t_lip - t_pilot
    if log:
        log(f"imdp (translation): {n_cls} classes x {M} inputs x ({N} + {N0}) runs x {k} periods simulated in "
            f"{t_pilot + t_sim:.1f} s")

    inv_mask = np.zeros(n, bool)
    inv_mask[inv] = True
    per_mask = grid.periodic_mask
    # blocked cells along I (some cell of the column not allowed), padded by one blocked cell on each
    # side; a box is safe if every cell it touches along I is unblocked (the touched cells cover it)
    allowed = ~box_unsafe(spec, grid.points(np.arange(C)) - half, grid.points(np.arange(C)) + half, s.x_lo, s.x_hi, ad)
    blocked = ~np.all(allowed.reshape(grid.shape), axis=tuple(other))
    sat = np.pad(np.pad(blocked, 1, constant_values=True).astype(np.int64), (1, 0))
    for d in range(len(inv)):
        np.cumsum(sat, axis=d, out=sat)
    corners = [np.array(c) for c in np.ndindex(*(2,) * len(inv))]
    # along the other, non-angle dimensions a widened box must stay inside X and inside the grid
    # (whose columns the blocked test covers) at every period of the hold
    bounded = [d for d in other if not per_mask[d]]
    in_lo = np.maximum(s.x_lo, grid.first - half)[bounded]
    in_hi = np.minimum(s.x_hi, grid.first + (shape - 1) * grid.eta + half)[bounded]
    inv_shape = shape[inv]

    def blocked_in(lo, hi):
        """(...) bool: the index box [lo, hi] along I (... x |I|, inclusive) touches a blocked cell."""
        lo = np.clip(lo + 1, 0, inv_shape + 1)          # +1: the padding; clipped boxes keep a pad cell
        hi = np.clip(hi + 1, 0, inv_shape + 1) + 1
        tot = 0
        for c in corners:
            idx = np.where(c == 1, hi, lo)
            tot = tot + (-1) ** int(len(inv) - c.sum()) * sat[tuple(np.moveaxis(idx, -1, 0))]
        return tot > 0

    def index_box(y):
        """Multi-index range (lo, hi) of the cells the widened boxes y +- rho touch."""
        return (np.floor((y - rho - grid.first) / grid.eta + 0.5).astype(np.int64),
                np.floor((y + rho - grid.first) / grid.eta + 0.5).astype(np.int64))

    def offsets(traj, runs, p):
        """Cells touched by the end boxes of the runs of pair p: (run index, key (B, n), single (runs,)).

        key: the offset from the reference cell along I, the absolute index along the other dimensions."""
        lo_mi, hi_mi = index_box(traj[p * runs:(p + 1) * runs, -1])
        span = hi_mi - lo_mi + 1
        W = span.max(axis=0)
        offs = np.stack(np.meshgrid(*[np.arange(w) for w in W], indexing="ij"), axis=-1).reshape(-1, n)
        rb, pp = np.nonzero(np.all(offs[None] < span[:, None], axis=2))
        key = lo_mi[rb] + offs[pp]
        key[:, inv] -= ref_mi[p // M, inv]
        key[:, per_mask] %= shape[per_mask]
        return rb, key, np.prod(span, axis=1) == 1

    def targets(cells, keys):
        """(Cc, K) cell ids of the keys seen from each cell, -1 outside the grid."""
        tm = np.where(inv_mask, mi_all[cells][:, None, :] + keys[None], keys[None])
        inside = np.all((tm >= 0) & (tm < shape), axis=2)
        return np.where(inside, np.clip(tm, 0, shape - 1) @ grid.strides, -1)

    rows, cols, n_ins, n_hits, single_seen = [], [], [], [], False
    for p in range(P):  # pairs (class, input): a few hundred; the work inside is vectorized over cells x runs
        h, a = divmod(p, M)
        tick()
        cells = np.flatnonzero(live & (cls_of == h))
        if cells.size == 0:
            continue
        _, pkey, psingle = offsets(pilot, N0, p)
        single_seen |= bool(psingle.any())
        rb, mkey, single = offsets(main, N, p)
        keys, inv_k = np.unique(np.concatenate([pkey, mkey]), axis=0, return_inverse=True)
        inv_k = inv_k.ravel()
        in_pilot = np.zeros(len(keys), bool)
        in_pilot[inv_k[:len(pkey)]] = True
        km = inv_k[len(pkey):]                                               # key of each main hit
        tid = targets(cells, keys)                                           # (Cc, K)
        ok = (tid >= 0) & good[np.maximum(tid, 0)]
        # sink runs (N, Cc): a touched key outside the pilot's or not live/target from this cell, or
        # a widened box at some period touching a blocked cell (shifted to the cell)
        touch = np.zeros((N, len(keys)), np.float32)
        touch[rb, km] = 1.0
        bad_w = touch @ (~(ok & in_pilot[None])).T.astype(np.float32)
        lo_mi, hi_mi = index_box(main[p * N:(p + 1) * N].reshape(N * k, n))
        box = np.concatenate([lo_mi[:, inv], hi_mi[:, inv]], axis=1) - np.tile(ref_mi[h, inv], 2)
        ubox, inv_b = np.unique(box, axis=0, return_inverse=True)
        ci_ = mi_all[cells][:, inv]
        unsafe = blocked_in(ci_[:, None, :] + ubox[None, :, :len(inv)], ci_[:, None, :] + ubox[None, :, len(inv):])
        runs_box = np.zeros((N, len(ubox)), np.float32)
        runs_box[np.repeat(np.arange(N), k), inv_b.ravel()] = 1.0
        Yo = main[p * N:(p + 1) * N][:, :, bounded]                          # (N, k, |bounded|)
        out = np.any((Yo - rho[bounded] < in_lo) | (Yo + rho[bounded] > in_hi), axis=(1, 2))
        bad = ((bad_w + runs_box @ unsafe.T.astype(np.float32)) > 0) | out[:, None]   # (N, Cc)
        one = np.zeros((N, len(keys)), np.float32)
        one[rb[single[rb]], km[single[rb]]] = 1.0
        n_in = one.T @ (~bad).astype(np.float32)                             # (K, Cc)
        n_hit = touch.sum(axis=0)
        ci, ki = np.nonzero(ok & in_pilot[None])                             # the support T(c, a)
        rows += [cells[ci] * M + a, cells * M + a]
        cols += [tid[ci, ki], np.full(cells.size, C)]
        n_ins += [np.rint(n_in[ki, ci]).astype(np.int64), np.full(cells.size, -1)]
        n_hits += [np.rint(n_hit[ki]).astype(np.int64), bad.sum(axis=0)]
    cat = lambda parts: np.concatenate(parts) if parts else np.zeros(0, np.int64)  # noqa: E731
    # the split is fixed by the pilot (single-cell end boxes), before the main counts
    alloc = Allocation.of(o.split).after_pilot(single_seen)
    meta = {"pilot_runs": N0, "lipschitz": L.tolist(), "lipschitz_how": how, "rho": rho.tolist(),
            "live_cells": int(live.sum()), "seed": int(o.seed), "simulator": sim.config.to_dict(), "spec": spec.to_dict(),
            "assumption": "per realization: the k-period trajectory map is L-Lipschitz (common random numbers); "
                          f"translation invariance along {[s.state_names[d] for d in inv]}: runs shifted by whole "
                          "cells are runs of the shifted cell",
            "invariant": [s.state_names[d] for d in inv], "classes": n_cls,
            "seconds": {"lipschitz": t_lip, "pilot": t_pilot, "main": t_sim,
                        "intervals": time.perf_counter() - t0 - t_lip - t_pilot - t_sim},
            "samples": int(P * (N + N0) * k)}
    return assemble(grid, s.inputs, k, live, target, cat(rows), cat(cols), cat(n_ins), cat(n_hits), alloc, N, o.beta, meta)

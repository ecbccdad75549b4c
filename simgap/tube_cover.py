"""A cover along a tube: data where a box tube's proof reads gamma, not on a grid over X.

A box tube (:mod:`simgap.synthesis.box_tube`) reads gamma's sup over the boxes
B_t = x_nom(t) +- h_t, t = 0..T0, and over the terminal box x* +- H. A grid over X costs
prod_i ceil(L_i / h_i) points, exponential in the state dimension n; the tube needs gamma on the
union U = B_0 u ... u B_T only. This module covers U box by box:

    boxes      b_t = [x_nom(t) - h_t - margin, x_nom(t) + h_t + margin] clipped to X (and the terminal
               box x* +- (H + margin)), each with lo < hi in every covered dimension;
    points     per box the grid of :mod:`simgap.cover` over the box (cells of width w <= the spacing,
               points at the cell centers), the union over the boxes, exact duplicates removed.

Every x in U lies in some box b, so within 1/2 ||w_b|| <= epsilon of a center of b's grid: the
epsilon-cover property the certificate rests on (paper, Sec. III) holds on U. The number of points
is sum_b prod_i ceil(L_b,i / h_i): a box narrower than the spacing in every dimension costs ONE
point, so the collection grows with the horizon T0 (one or a few points per period), not
exponentially with n (``bench/bench_tube_cover.py`` measures it at 4, 6 and 14 states).

The certificate made from such data records the boxes (``Certificate.region_boxes``) with their hull
as ``region``: every consumer that takes gamma's sup over a set refuses a set that does not lie
inside ONE of the boxes (a set inside the hull but between the boxes is refused as well: gamma was
not certified there). A set straddling two overlapping boxes is refused too (sound, conservative):
the tube's boxes are the cover's own boxes, each inside its own b_t.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence

import numpy as np

from .errors import SimgapError


def tube_boxes(x_lo, x_hi, x_nom, radii=None, margin=0.0, terminal: Optional[tuple] = None,
               covered: Optional[Sequence[int]] = None) -> tuple:
    """(lo (B, n), hi (B, n)): the boxes x_nom(t) +- (h_t + margin), t = 0..T0, clipped to X = [x_lo, x_hi],
    then ``terminal`` = (x*, H) as x* +- (H + margin) (clipped likewise).

    ``radii``: h_t (T0 + 1, n) (default 0: the plan's points alone); ``margin``: one value or (n,), state
    units, >= 0: the room the tube under the gap needs beyond h_t. ``covered``: dimensions that need
    lo < hi (the others, declared invariant, are set to X's bounds). Boxes inside an earlier box are
    dropped (they add no point). Refused when a box leaves X entirely or has no width in a covered
    dimension (give a margin > 0)."""
    x_lo, x_hi = np.asarray(x_lo, float), np.asarray(x_hi, float)
    n = x_lo.size
    xn = np.atleast_2d(np.asarray(x_nom, float))
    if xn.shape[1] != n or not np.all(np.isfinite(xn)):
        raise SimgapError(f"tube cover: the plan needs finite states of {n} values, got shape {xn.shape}")
    h = np.zeros_like(xn) if radii is None else np.broadcast_to(np.asarray(radii, float), xn.shape)
    mg = np.broadcast_to(np.asarray(margin, float), (n,))
    if not (np.all(np.isfinite(h)) and np.all(h >= 0)):
        raise SimgapError("tube cover: the tube's half-widths must be finite and >= 0 (a tube that left X has "
                          "no cross-section to cover)")
    if not (np.all(np.isfinite(mg)) and np.all(mg >= 0)):
        raise SimgapError(f"tube cover: the margin must be finite and >= 0, got {np.asarray(margin).tolist()}")
    lo, hi = xn - h - mg, xn + h + mg
    if terminal is not None:
        xs, H = (np.asarray(a, float).ravel() for a in terminal)
        lo = np.concatenate([lo, (xs - H - mg)[None]])
        hi = np.concatenate([hi, (xs + H + mg)[None]])
    lo, hi = np.maximum(lo, x_lo), np.minimum(hi, x_hi)
    cov = list(range(n)) if covered is None else list(covered)
    inv = [i for i in range(n) if i not in cov]
    lo[:, inv], hi[:, inv] = x_lo[inv], x_hi[inv]
    flat = np.flatnonzero(np.any(hi[:, cov] <= lo[:, cov], axis=1))
    if flat.size:
        b = int(flat[0])
        raise SimgapError(f"tube cover: box {b} (period {b} of the plan) has no width inside X in some covered "
                          "dimension: the plan leaves X there, or the margin is 0 (give [collect] tube_margin > 0)")
    keep = np.ones(len(lo), dtype=bool)
    for b in range(1, len(lo)):  # consecutive periods: a box inside the previous kept one adds nothing
        prev = np.flatnonzero(keep[:b])[-1]
        if np.all(lo[b] >= lo[prev]) and np.all(hi[b] <= hi[prev]):
            keep[b] = False
    return lo[keep], hi[keep]


def check_boxes(system, boxes) -> tuple:
    """(lo (B, n), hi (B, n)) from ``boxes`` = [(lo, hi), ...] (or a pair of (B, n) arrays), refused unless
    every box has n finite bounds with lo < hi inside X."""
    try:
        if isinstance(boxes, tuple) and len(boxes) == 2 and np.ndim(boxes[0]) == 2:
            lo, hi = (np.asarray(b, float) for b in boxes)
        else:
            lo = np.array([np.asarray(b[0], float) for b in boxes])
            hi = np.array([np.asarray(b[1], float) for b in boxes])
    except (TypeError, ValueError, IndexError):
        raise SimgapError("cover boxes: need a list of [lo, hi] pairs of numbers") from None
    n = system.n
    if lo.ndim != 2 or lo.shape != hi.shape or lo.shape[1] != n or lo.shape[0] < 1:
        raise SimgapError(f"cover boxes: need one or more [lo, hi] pairs of {n} values each")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))) or np.any(lo >= hi):
        raise SimgapError("cover boxes: every box needs finite lo < hi in every state")
    tol = 1e-12 * np.maximum(1.0, np.abs(system.x_hi - system.x_lo))
    out = (lo < system.x_lo - tol) | (hi > system.x_hi + tol)
    if np.any(out):
        b, i = (int(v[0]) for v in np.nonzero(out))
        raise SimgapError(f"cover boxes: box {b} leaves X in {system.state_names[i]} ([{lo[b, i]:g}, {hi[b, i]:g}] "
                          f"not in [{system.x_lo[i]:g}, {system.x_hi[i]:g}])")
    return np.maximum(lo, system.x_lo), np.minimum(hi, system.x_hi)


def box_grid_points(lo, hi, covered: Sequence[int], h) -> tuple:
    """The union of the per-box grids: (points (N, n) over the covered dims (others 0), widths (B, d)).

    Box b, dimension i: c = ceil(L / h_i) cells of width L / c, points at the centers; the points of all
    boxes stacked, then exact duplicates removed (first occurrence kept, order preserved). When the grid
    over the boxes' hull has fewer points than the boxes' grids together (wide boxes overlapping from one
    period to the next), the hull's grid is taken instead: it covers the hull, so the union too."""
    cov = list(covered)
    L = (hi - lo)[:, cov]
    counts = np.maximum(1, np.ceil(L / h * (1 - 1e-12))).astype(np.int64)
    widths = L / counts
    total = int(counts.prod(axis=1).astype(float).sum())
    if len(lo) > 1 and grid_size(hi.max(axis=0)[cov] - lo.min(axis=0)[cov], h) < total:
        return box_grid_points(lo.min(axis=0)[None], hi.max(axis=0)[None], covered, h)
    if total > 2e8:
        raise SimgapError(f"tube cover: {total:.3g} points is too many; use a larger epsilon or a smaller margin")
    parts = []
    for b in range(len(lo)):
        axes = [lo[b, i] + (np.arange(c) + 0.5) * w for i, c, w in zip(cov, counts[b], widths[b])]
        mesh = np.meshgrid(*axes, indexing="ij")
        P = np.zeros((mesh[0].size, lo.shape[1]))
        for k, i in enumerate(cov):
            P[:, i] = mesh[k].ravel()
        parts.append(P)
    pts = np.concatenate(parts)
    _, first = np.unique(pts, axis=0, return_index=True)
    return pts[np.sort(first)], widths


def grid_size(L, h) -> int:
    """Points of a grid over a box of side lengths L at spacing h (the count :func:`simgap.cover.make_cover`
    builds): prod_i ceil(L_i / h_i) (a float: it may be astronomically large)."""
    return float(np.prod(np.maximum(1, np.ceil(np.asarray(L, float) / np.asarray(h, float) * (1 - 1e-12)))))


def default_spacing(epsilon: float, d: int) -> np.ndarray:
    """The cover's default spacing h_i = 2 epsilon / sqrt(d) (radius <= epsilon)."""
    return np.full(d, 2.0 * float(epsilon) / math.sqrt(d))

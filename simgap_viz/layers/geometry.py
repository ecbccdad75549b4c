"""Geometry of the state-space layers, in display coordinates.

Display convention: the first two state dimensions x1, x2 are mapped affinely from
X = [x_lo, x_hi] to the square [-1, 1]^2 (the plane z = 0), so the pendulum's
[-0.2, 0.2] x [-0.5, 0.5] and the TurtleBot's [0, 4]^2 arena look alike; a third state
dimension (TurtleBot heading) is projected away. Heights (z) show gap values scaled by
``zscale`` (display units per state unit), stated in the app's legend.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from simgap.errors import SimgapError
from simgap.systems import System

# colors (RGB 0-255)
BLUE = (60, 120, 220)
RUN_BLUE = (20, 50, 150)  # the thin rollouts: dark enough to read on the light green winning map
RED = (220, 50, 50)
GREEN = (40, 170, 80)
YELLOW = (250, 200, 20)
GREY = (150, 150, 150)
RUN_ALPHA = 0.12  # opacity of one drawn rollout (rollout_image): 100 and 1000 rollouts look different
DIM_COLORS = ((70, 130, 230), (230, 120, 40), (120, 180, 60), (170, 90, 200))
# viser draws an image's row 0 at the plane's -y (camera-image convention); this orientation
# (a half turn about x) puts row 0 at +x2, as the top-down maps here lay their images out
IMAGE_UP = (0.0, 1.0, 0.0, 0.0)


class Frame:
    """Affine map of two state dimensions ``dims`` (default the first two) to the display square
    [-1, 1]^2."""

    def __init__(self, system: System, dims=(0, 1)):
        self.system = system
        self.dims = [int(d) for d in dims] if system.n >= 2 else [0]
        self.lo = system.x_lo[self.dims].astype(float)
        self.hi = system.x_hi[self.dims].astype(float)
        if system.n == 1:  # pad a 1-D system with a flat second axis
            self.lo = np.array([self.lo[0], -1.0])
            self.hi = np.array([self.hi[0], 1.0])
        self.center = 0.5 * (self.lo + self.hi)
        self.half = 0.5 * (self.hi - self.lo)

    def xy(self, x: np.ndarray) -> np.ndarray:
        """States (..., n) -> display (..., 3) with z = 0."""
        x = np.asarray(x, dtype=float)
        xy = x[..., self.dims] if x.shape[-1] >= 2 else np.concatenate([x, np.zeros_like(x)], axis=-1)
        out = np.zeros(x.shape[:-1] + (3,))
        out[..., :2] = (xy - self.center) / self.half
        return out

    def scale_xy(self, widths: np.ndarray) -> np.ndarray:
        """State-space widths (..., 2) -> display widths."""
        return np.asarray(widths, dtype=float) / self.half


def variable_names(system: System) -> list[str]:
    """State then input variable names, the axes a gamma surface can be drawn over."""
    return list(system.state_names) + list(system.input_names)


def variable_ranges(system: System) -> np.ndarray:
    """(n+m, 2) ranges [lo, hi] of the state box X and of the finite input set U."""
    U = system.inputs
    return np.vstack([np.stack([system.x_lo, system.x_hi], axis=1),
                      np.stack([U.min(axis=0), U.max(axis=0)], axis=1)])


def colormap(t: np.ndarray) -> np.ndarray:
    """Values t in [0, 1] -> (.., 3) uint8 colors, blue (low) -> teal -> yellow (high)."""
    stops = np.array([[40, 60, 160], [30, 150, 170], [120, 200, 90], [250, 220, 40]], float)
    t = np.clip(np.nan_to_num(np.asarray(t, float)), 0.0, 1.0) * (len(stops) - 1)
    i = np.minimum(t.astype(int), len(stops) - 2)
    f = (t - i)[..., None]
    return ((1 - f) * stops[i] + f * stops[i + 1]).astype(np.uint8)


def margin_colors(margin: np.ndarray, scale: float) -> np.ndarray:
    """Colors of data points by their margin gamma - gap: red where negative (not covered),
    orange (margin 0, tight) -> grey-blue (margin >= ``scale``) otherwise."""
    m = np.asarray(margin, dtype=float)
    t = np.clip(m / max(scale, 1e-300), 0.0, 1.0)[:, None]
    tight, loose = np.array([245, 120, 0], float), np.array([150, 160, 185], float)
    col = ((1 - t) * tight + t * loose).astype(np.uint8)
    col[~(m >= 0)] = RED
    return col


def colorbar(width: int = 256, height: int = 14) -> np.ndarray:
    """(height, width, 3) uint8 image of :func:`colormap` from 0 (left) to 1 (right)."""
    return np.repeat(colormap(np.linspace(0.0, 1.0, width))[None], height, axis=0)


def nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    """About ``n`` round tick values in [lo, hi] (1, 2, 5 x 10^k steps)."""
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
        return np.array([lo])
    raw = (hi - lo) / max(n - 1, 1)
    mag = 10.0 ** np.floor(np.log10(raw))
    step = mag * min((m for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10)
    t = np.arange(np.ceil(lo / step - 1e-9), np.floor(hi / step + 1e-9) + 1) * step
    return t[(t >= lo - 1e-12 * abs(step)) & (t <= hi + 1e-12 * abs(step))] + 0.0  # no "-0"


# winning-domain map colors: reach-avoid dark (near the target) -> light (far); invariance one light
# green for a fully winning column, paler for a smaller share of winning cells over the other dimensions
WIN_NEAR, WIN_FAR = (15, 100, 45), (140, 210, 130)
WIN_ALL, WIN_SOME = (120, 200, 120), (200, 232, 180)
LOSING = (238, 232, 205)
UNSAFE = (150, 60, 60)
TARGET = (40, 110, 210)


def winning_map(controller, blocked: np.ndarray, allowed: np.ndarray, max_pixels: int = 1024) -> dict:
    """The winning domain as a top-down image over the first two state dimensions.

    Per (x1, x2) column of grid cells (other dimensions, e.g. the heading, reduced): *winning*
    (green) if any cell of the column is winning, shaded by the worst-case steps-to-go of its best
    cell for reach-avoid (dark: near the target, light: far) or by the winning share otherwise
    (light green: all, paler: some); *unsafe* (red-brown) if every cell is blocked (obstacle,
    outside X) or, for invariance, outside the safe set; *safe but losing* (beige) otherwise;
    target columns blue (reach-avoid only). ``blocked`` and ``allowed`` (N,) are the engine's cell
    labels (``label_cells``).

    Returns dict(image (H,W,3) uint8 with row 0 at the top (+x2), lo (2,), hi (2,) the image's
    extent in state units, counts, max_steps, reduced_dims). ``counts`` has ``winning_cells``
    (grid cells, target excluded: :func:`winning_cells_count`, the number the CLI table shows) and,
    in (x1, x2) columns as drawn, ``winning``, ``losing``, ``unsafe``, ``target`` and
    ``unsafe_inner`` (unsafe columns off the grid's outer ring, the ones a person can see: the ring
    of cells that straddle X's border lies under the safe-set outline).
    """
    g = controller.grid
    shape = tuple(g.shape) + ((1,) if g.n == 1 else ())
    cols = (shape[0], shape[1], -1)
    steps = np.asarray(controller.steps).reshape(cols)
    win = steps >= 0
    reach = controller.kind == "reach_avoid"
    unsafe_cell = np.asarray(blocked, bool).reshape(cols)
    if not reach:
        unsafe_cell = unsafe_cell | ~np.asarray(allowed, bool).reshape(cols)
    target = np.asarray(controller.target, bool).reshape(cols).any(axis=2) if reach \
        else np.zeros(shape[:2], bool)
    w_any = win.any(axis=2)
    unsafe = unsafe_cell.all(axis=2) & ~w_any
    img = np.empty(shape[:2] + (3,), np.uint8)
    img[:] = LOSING
    img[unsafe] = UNSAFE
    if reach:
        s = np.where(win, steps, np.iinfo(np.int32).max).min(axis=2).astype(float)
        smax = max(float(s[w_any].max()) if w_any.any() else 1.0, 1.0)
        t = np.where(w_any, s / smax, 0.0)
        near, far = np.array(WIN_NEAR, float), np.array(WIN_FAR, float)
    else:
        t = 1.0 - win.mean(axis=2)
        near, far = np.array(WIN_ALL, float), np.array(WIN_SOME, float)
    shade = ((1 - t)[..., None] * near + t[..., None] * far).astype(np.uint8)
    img[w_any] = shade[w_any]
    img[target] = TARGET
    k = max(1, min(8, max_pixels // max(shape[0], shape[1])))  # crisp cell edges under texture filtering
    image = np.repeat(np.repeat(img.transpose(1, 0, 2)[::-1], k, axis=0), k, axis=1)
    lo, hi = g.domain_lo[:2], g.domain_hi[:2]
    if g.n == 1:
        lo, hi = np.array([lo[0], -1.0]), np.array([hi[0], 1.0])
    inner = np.zeros(shape[:2], bool)
    inner[1:-1, 1:-1] = True
    return {"image": image, "lo": lo, "hi": hi,
            "counts": {"winning_cells": winning_cells_count(controller), "winning": int((w_any & ~target).sum()),
                       "losing": int((~w_any & ~unsafe).sum()), "unsafe": int(unsafe.sum()),
                       "unsafe_inner": int((unsafe & inner).sum()), "target": int(target.sum())},
            "max_steps": int(smax) if reach else None, "reduced_dims": max(g.n - 2, 0)}


WINNING_CELLS = ("winning cells: grid cells from which the controller keeps the state safe (invariance) or "
                 "brings it to the target (reach-avoid), the target's own cells not counted (SCOTS's count)")
"""The one definition of "winning cells" shown by the CLI table, the GUI, the recording and the summary."""


def winning_cells_count(controller) -> int:
    """The number of winning cells as :data:`WINNING_CELLS` defines it (``controller.size``)."""
    return int(controller.size)


def rollout_subset(failed: np.ndarray, n_draw: int, seed: int = 0) -> np.ndarray:
    """Indices of the rollouts to draw: every failure first (up to ``n_draw``), then an even
    (seeded) sample of the others; sorted."""
    failed = np.asarray(failed, bool)
    R = failed.size
    if n_draw >= R:
        return np.arange(R)
    f = np.flatnonzero(failed)[:n_draw]
    ok = np.flatnonzero(~failed)
    rest = np.random.default_rng(seed).choice(ok, min(n_draw - f.size, ok.size), replace=False)
    return np.sort(np.concatenate([f, rest]))


def grid_faces(na: int, nb: int) -> np.ndarray:
    """Triangle indices (2 (na-1)(nb-1), 3) of a regular na x nb vertex grid (row-major, b fastest)."""
    i, j = np.meshgrid(np.arange(na - 1), np.arange(nb - 1), indexing="ij")
    v00 = (i * nb + j).ravel()
    v01, v10, v11 = v00 + 1, v00 + nb, v00 + nb + 1
    return np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)]).astype(np.uint32)


def surface_points(system: System, a: int, b: int, fixed: Sequence[float], res: int = 41) -> tuple:
    """Query points for a gamma surface over variables ``a`` and ``b`` (indices into states+inputs).

    ``fixed`` holds a value for every variable (n+m); the ones for a and b are overwritten by a
    res x res grid over their ranges. Returns (x (res^2, n), u (res^2, m), A (res,), B (res,)).
    """
    nv = system.n + system.m
    if not (0 <= a < nv and 0 <= b < nv) or a == b:
        raise SimgapError(f"gamma surface: need two different variables among {variable_names(system)}")
    if len(fixed) != nv:
        raise SimgapError(f"gamma surface: need {nv} fixed values, got {len(fixed)}")
    rng = variable_ranges(system)
    A = np.linspace(rng[a, 0], rng[a, 1], res)
    B = np.linspace(rng[b, 0], rng[b, 1], res)
    P = np.tile(np.asarray(fixed, dtype=float), (res * res, 1))
    AA, BB = np.meshgrid(A, B, indexing="ij")
    P[:, a] = AA.ravel()
    P[:, b] = BB.ravel()
    return P[:, :system.n], P[:, system.n:], A, B


def gamma_surface(system: System, gamma: Callable, dim: int, a: int, b: int, fixed: Sequence[float],
                  res: int = 41, zscale: float = 1.0) -> dict:
    """Mesh of gamma_dim(x, u) over variables a, b (others at ``fixed``), in display coordinates.

    ``gamma(x (B,n), u (B,m)) -> (B,n)`` is the certificate's gap function [state units].
    The (a, b) plane is mapped to [-1, 1]^2; z = zscale * gamma_dim.
    Returns dict(vertices (res^2,3) float32, faces (2(res-1)^2,3) uint32, values (res^2,)).
    """
    x, u, A, B = surface_points(system, a, b, fixed, res)
    g = np.asarray(gamma(x, u), dtype=float)
    if g.ndim != 2 or g.shape[0] != x.shape[0] or not (0 <= dim < g.shape[1]):
        raise SimgapError(f"gamma surface: gamma returned shape {g.shape}, expected ({x.shape[0]}, n)")
    vals = g[:, dim]
    rng = variable_ranges(system)
    ua = 2 * (np.repeat(A, res) - rng[a].mean()) / max(np.ptp(rng[a]), 1e-12)
    ub = 2 * (np.tile(B, res) - rng[b].mean()) / max(np.ptp(rng[b]), 1e-12)
    verts = np.stack([ua, ub, zscale * vals], axis=1).astype(np.float32)
    return {"vertices": verts, "faces": grid_faces(res, res), "values": vals}


def data_slice(dataset, system: System, a: int, b: int, fixed: Sequence[float], max_points: int = 50000,
               seed: int = 0) -> np.ndarray:
    """Row indices of the dataset near the slice shown by a gamma surface.

    Rows whose variables other than a, b are within the cover spacing of the fixed values
    (state variables: |x_j - v_j| <= epsilon; input variables: the input value nearest to v_j).
    Subsampled (seeded) to at most ``max_points``.
    """
    P = np.hstack([dataset.x, dataset.u])
    keep = np.ones(P.shape[0], dtype=bool)
    for j in range(P.shape[1]):
        if j in (a, b):
            continue
        col = P[:, j]
        if j < system.n:
            keep &= np.abs(col - fixed[j]) <= max(dataset.epsilon, 1e-12)
        else:
            vals = np.unique(col)
            nearest = vals[np.argmin(np.abs(vals - fixed[j]))]
            keep &= col == nearest
    idx = np.flatnonzero(keep)
    if idx.size > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(idx, max_points, replace=False))
    return idx


def data_points(dataset, system: System, dim: int, a: int, b: int, fixed: Sequence[float],
                gamma: Callable | None = None, zscale: float = 1.0, max_points: int = 50000) -> dict:
    """Observed gaps g_dim(x_r, u) = |m - f| of the rows near the slice, as points above the (a, b) plane.

    Colored green where g <= gamma_dim(x_r, u) (the certificate covers the data point), red
    where it does not, grey without a certificate. Returns dict(points (P,3), colors (P,3) uint8,
    gap (P,), covered (P,) bool or None, margin (P,) gamma_dim - g or None, rows (P,)).
    """
    rows = data_slice(dataset, system, a, b, fixed, max_points)
    P = np.hstack([dataset.x[rows], dataset.u[rows]])
    g = dataset.gap()[rows, dim]
    rng = variable_ranges(system)
    pa = 2 * (P[:, a] - rng[a].mean()) / max(np.ptp(rng[a]), 1e-12)
    pb = 2 * (P[:, b] - rng[b].mean()) / max(np.ptp(rng[b]), 1e-12)
    pts = np.stack([pa, pb, zscale * g], axis=1).astype(np.float32)
    covered = margin = None
    colors = np.tile(np.array(GREY, np.uint8), (rows.size, 1))
    if gamma is not None and rows.size:
        gam = np.asarray(gamma(dataset.x[rows], dataset.u[rows]), dtype=float)[:, dim]
        margin = gam - g
        covered = margin >= -1e-12
        colors[covered] = GREEN
        colors[~covered] = RED
    return {"points": pts, "colors": colors, "gap": g, "covered": covered, "margin": margin, "rows": rows}


def rollout_segments(frame: Frame, traj: np.ndarray, failed: np.ndarray | None = None,
                     max_segments: int = 200000) -> dict:
    """All rollouts as one batch of line segments (display coordinates).

    ``traj`` (R, T+1, n) states; ``failed`` (R,) bool. Time is strided so that at most
    ``max_segments`` segments are drawn (endpoints kept). Failures red, the others blue.
    Returns dict(points (S,2,3) float32, colors (S,2,3) uint8, stride int).
    """
    traj = np.asarray(traj, dtype=float)
    if traj.ndim != 3:
        raise SimgapError(f"rollouts: expected trajectories of shape (R, T+1, n), got {traj.shape}")
    R, T1, _ = traj.shape
    stride = max(1, int(np.ceil(R * max(T1 - 1, 1) / max_segments)))
    t = np.arange(0, T1, stride)
    if t[-1] != T1 - 1:
        t = np.append(t, T1 - 1)
    P = frame.xy(traj[:, t])  # (R, T', 3)
    seg = np.stack([P[:, :-1], P[:, 1:]], axis=2).reshape(-1, 2, 3).astype(np.float32)
    col = np.empty((R, len(t) - 1, 2, 3), np.uint8)
    col[:] = BLUE
    if failed is not None:
        col[np.asarray(failed, bool)] = RED
    return {"points": seg, "colors": col.reshape(-1, 2, 3), "stride": stride}


def rollout_image(frame: Frame, traj: np.ndarray, failed: np.ndarray | None = None, px: int = 1024,
                  width: int = 2, max_samples: int = 20_000_000, alpha: float = RUN_ALPHA) -> np.ndarray:
    """The rollouts as an RGBA image of the display square [-1, 1]^2 (row 0 at +x2): every step
    of every trajectory rasterized as a ``width``-pixel line, dark blue, failures red on top; transparent
    elsewhere.

    Each rollout is translucent (opacity ``alpha``): a pixel crossed by k rollouts has opacity
    1 - (1 - alpha)^k, so the picture is a density -- 1000 rollouts look denser than 100, a lone
    run stays faint, and the bold mean/nominal lines above do not hide the spread. Drawn as one
    textured plane, 1000 rollouts cost a frame no more than the winning map does, while as
    geometry even 1-pixel GL lines cost several ms per 10k segments in software WebGL. Each
    segment is sampled one pixel apart (the ``width`` covers the gaps; fewer samples if the total
    would exceed ``max_samples``); k counts the visits of rollouts per pixel (the consecutive samples
    of one visit count once; a run that comes back counts again, as time spent there). Failures are drawn at opacity >= 0.6. Returns
    (px, px, 4) uint8.
    """
    traj = np.asarray(traj, dtype=float)
    R = traj.shape[0]
    failed = np.zeros(R, bool) if failed is None else np.asarray(failed, bool)
    img = np.zeros((px, px, 4), np.uint8)
    if R == 0 or traj.shape[1] < 2:
        return img
    P = ((frame.xy(traj)[..., :2] + 1.0) * (0.5 * px)).astype(np.float32)  # pixels, x right, y up
    for sel, rgb, a_run in ((~failed, RUN_BLUE, alpha), (failed, RED, max(alpha, 0.6))):
        if sel.any():
            layer = density_rgba(P[sel], px, px, rgb, a_run, width, max_samples)
            hit = layer[..., 3] > 0
            img[hit] = layer[hit]  # failures on top
    return img


def density_rgba(P: np.ndarray, W: int, H: int, rgb, alpha: float, width: int = 2,
                 max_samples: int = 20_000_000) -> np.ndarray:
    """Polylines P (R, T, 2) in pixel coordinates (x right, y up, [0, W) x [0, H)) rasterized into an
    RGBA image (H, W, 4) uint8 (row 0 at the top): every segment sampled one pixel apart and drawn
    ``width`` pixels wide in ``rgb``, a pixel visited by k lines at opacity 1 - (1 - alpha)^k (a
    density: each line translucent on its own), transparent elsewhere; the consecutive samples of
    one visit count once. Fewer samples per segment if the total would exceed ``max_samples``."""
    P = np.asarray(P, np.float32)
    img = np.zeros((H, W, 4), np.uint8)
    R = P.shape[0]
    if R == 0 or P.shape[1] < 2:
        return img
    d = P[:, 1:] - P[:, :-1]
    n = np.minimum(np.ceil(np.hypot(d[..., 0], d[..., 1])), 4 * max(W, H))  # (R, T - 1): 1 pixel apart
    n = np.where(np.isfinite(n), n, 0).astype(np.int64) + 1
    total = int(n.sum())
    if total > max_samples:
        n = np.maximum(1, (n * (max_samples / total)).astype(np.int64))
    k = np.zeros(W * H, np.int64)
    per = max(1, int(R * 500_000 // max(int(n.sum()), 1)))  # runs per chunk: about 5e5 samples (bounded memory)
    for r0 in range(0, R, per):
        nc = n[r0:r0 + per].ravel()
        a, dc = P[r0:r0 + per, :-1].reshape(-1, 2), d[r0:r0 + per].reshape(-1, 2)
        t = (np.arange(nc.sum(), dtype=np.float32) - np.repeat((np.cumsum(nc) - nc).astype(np.float32), nc)) \
            / np.repeat(nc.astype(np.float32), nc)
        ix = np.clip((np.repeat(a[:, 0], nc) + t * np.repeat(dc[:, 0], nc)).astype(np.int64), 0, W - 1)
        iy = np.clip(H - 1 - (np.repeat(a[:, 1], nc) + t * np.repeat(dc[:, 1], nc)).astype(np.int64), 0, H - 1)
        pix = iy * W + ix
        del t, ix, iy
        run = np.repeat(np.repeat(np.arange(min(per, R - r0)), P.shape[1] - 1), nc)
        keep = np.ones(pix.size, bool)
        keep[1:] = (pix[1:] != pix[:-1]) | (run[1:] != run[:-1])
        k += np.bincount(pix[keep], minlength=W * H)
    k = k.reshape(H, W)
    wide = k.copy()
    for j in range(1, width):  # thicken right and down (the densest neighbour counts)
        wide[:, j:] = np.maximum(wide[:, j:], k[:, :-j])
        wide[j:, :] = np.maximum(wide[j:, :], k[:-j, :])
    hit = wide > 0
    op = 1.0 - (1.0 - alpha) ** wide[hit]
    img[hit] = np.column_stack([np.broadcast_to(np.array(rgb, np.uint8), (int(hit.sum()), 3)),
                                np.round(255 * op).astype(np.uint8)])
    return img


def polyline_segments(frame: Frame, path: np.ndarray) -> np.ndarray:
    """One trajectory (T+1, n) as (T, 2, 3) display segments."""
    P = frame.xy(np.asarray(path, dtype=float))
    return np.stack([P[:-1], P[1:]], axis=1).astype(np.float32)


def dashed_segments(frame: Frame, path: np.ndarray, on: float, off: float, phase: float = 0.0) -> np.ndarray:
    """One trajectory (T+1, n) as a dashed line: (S, 2, 3) display segments covering arc lengths
    [phase + k (on + off), phase + k (on + off) + on) of the display path (units of the square).

    The bold lines are dashed so that the rollouts' density under them shows in the gaps."""
    P = frame.xy(np.asarray(path, dtype=float))
    if P.shape[0] < 2:
        return np.zeros((0, 2, 3), np.float32)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    if s[-1] <= 0:
        return np.zeros((0, 2, 3), np.float32)
    step = min(on, off) / 4
    t = np.arange(0.0, s[-1] + step, step)
    t[-1] = min(t[-1], s[-1])
    Q = np.stack([np.interp(t, s, P[:, k]) for k in range(3)], axis=1)
    keep = np.mod(t[:-1] - phase, on + off) < on
    return np.stack([Q[:-1][keep], Q[1:][keep]], axis=1).astype(np.float32)


def box_cells(frame: Frame, centers: np.ndarray, widths: np.ndarray, values: np.ndarray | None = None) -> dict:
    """Grid cells (first two dims) as batched box instances in display coordinates.

    Cells that share (x1, x2) (e.g. different headings) are merged; ``values`` in [0, 1]
    (fraction winning) colors them from red (0) to green (1). Returns dict(positions (C,3),
    scales (C,3), colors (C,3) uint8, fraction (C,)).
    """
    centers = np.asarray(centers, dtype=float)
    c2 = centers[:, :2] if centers.shape[1] >= 2 else np.hstack([centers, np.zeros_like(centers)])
    vals = np.ones(len(c2)) if values is None else np.asarray(values, dtype=float)
    keys, inv = np.unique(np.round(c2, 9), axis=0, return_inverse=True)
    inv = inv.ravel()
    frac = np.bincount(inv, weights=vals, minlength=len(keys)) / np.bincount(inv, minlength=len(keys))
    pos = frame.xy(keys)
    w = np.asarray(widths, dtype=float).ravel()
    w2 = w[:2] if w.size >= 2 else np.array([w[0], 2 * frame.half[1]])
    sc = np.empty((len(keys), 3))
    sc[:, :2] = frame.scale_xy(w2)
    sc[:, 2] = 0.01
    green, red = np.array(GREEN, float), np.array(RED, float)
    col = (red[None] + frac[:, None] * (green - red)[None]).astype(np.uint8)
    return {"positions": pos, "scales": sc, "colors": col, "fraction": frac}


def spec_outlines(frame: Frame, spec) -> tuple:
    """The spec's boxes (first two dims, clipped to X) as rectangle outlines in display
    coordinates: (segments (S, 2, 3) float32, colors (S, 2, 3) uint8); safe blue, target green,
    obstacles red."""
    boxes = [(ob, RED) for ob in (getattr(spec, "obstacles", ()) or ())]
    for attr, rgb in (("target", GREEN), ("safe", BLUE)):
        if getattr(spec, attr, None) is not None:
            boxes.append((getattr(spec, attr), rgb))
    segs, cols = [], []
    for box, rgb in boxes:
        lo = np.maximum(np.asarray(box.lo, float)[frame.dims], frame.lo)
        hi = np.minimum(np.asarray(box.hi, float)[frame.dims], frame.hi)
        c = frame.xy(np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]]))
        segs.append(np.stack([c, np.roll(c, -1, axis=0)], axis=1))
        cols.append(np.broadcast_to(np.array(rgb, np.uint8), (4, 2, 3)))
    if not segs:
        return np.zeros((0, 2, 3), np.float32), np.zeros((0, 2, 3), np.uint8)
    return np.concatenate(segs).astype(np.float32), np.concatenate(cols)


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB colors 0-255 -> linear-light values in [0, 1] (glTF vertex colors are linear)."""
    c = np.asarray(rgb, dtype=float) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 unit vertex normals: the area-weighted sum of the adjacent faces' normals."""
    V = np.asarray(vertices, float)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V)
    for k in range(3):
        np.add.at(N, F[:, k], fn)
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)
    return np.ascontiguousarray(N, dtype=np.float32)


def glb(positions: np.ndarray, colors: np.ndarray, faces: np.ndarray | None = None, unlit: bool = False,
        opacity: float = 1.0) -> bytes:
    """One glTF primitive as binary glTF (GLB) bytes, for viser's ``add_glb``.

    ``positions`` (V, 3) display coordinates and ``colors`` (V, 3) uint8 sRGB per vertex.
    With ``faces`` (F, 3): a double-sided triangle mesh (matte, or ``unlit``: flat vertex
    colors without lighting), translucent if ``opacity`` < 1; without: LINES, consecutive vertex
    pairs are segments, drawn by a glTF viewer (three.js) as native 1-pixel lines with an unlit
    material.
    """
    import json
    import struct
    P = np.ascontiguousarray(np.asarray(positions, np.float32).reshape(-1, 3))
    if P.shape[0] == 0:
        raise SimgapError("glb: no vertices")
    C = np.round(65535 * srgb_to_linear(np.asarray(colors).reshape(-1, 3))).astype(np.uint16)
    C = np.ascontiguousarray(np.concatenate([C, np.full((C.shape[0], 1), 65535, np.uint16)], axis=1))
    chunks = [P.tobytes(), C.tobytes()]
    n = P.shape[0]
    accessors = [{"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3",
                  "min": P.min(axis=0).tolist(), "max": P.max(axis=0).tolist()},
                 {"bufferView": 1, "componentType": 5123, "normalized": True, "count": n, "type": "VEC4"}]
    prim = {"attributes": {"POSITION": 0, "COLOR_0": 1}, "mode": 1}
    if faces is not None and not unlit:  # smooth shading (a glTF viewer shades a mesh without normals flat)
        N = vertex_normals(P, faces)
        chunks.append(N.tobytes())
        accessors.append({"bufferView": 2, "componentType": 5126, "count": n, "type": "VEC3"})
        prim["attributes"]["NORMAL"] = 2
    doc = {"asset": {"version": "2.0", "generator": "simgap"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0}], "meshes": [{"primitives": [prim]}]}
    if faces is not None:
        F = np.ascontiguousarray(np.asarray(faces, np.uint32).reshape(-1))
        chunks.append(F.tobytes())
        accessors.append({"bufferView": len(chunks) - 1, "componentType": 5125, "count": int(F.size), "type": "SCALAR"})
        prim.update(mode=4, indices=len(chunks) - 1, material=0)
        mat = {"pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, float(opacity)], "metallicFactor": 0.0,
                                        "roughnessFactor": 0.9}, "doubleSided": True}
        if opacity < 1.0:
            mat["alphaMode"] = "BLEND"
        if unlit:
            mat["extensions"] = {"KHR_materials_unlit": {}}
            doc["extensionsUsed"] = ["KHR_materials_unlit"]
        doc["materials"] = [mat]
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in chunks])]).tolist()  # each a multiple of 4
    doc["bufferViews"] = [{"buffer": 0, "byteOffset": offsets[k], "byteLength": len(c)} for k, c in enumerate(chunks)]
    doc["buffers"] = [{"byteLength": offsets[-1]}]
    doc["accessors"] = accessors
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * (-len(js) % 4)
    body = b"".join(chunks)
    total = 12 + 8 + len(js) + 8 + len(body)
    return (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(body), 0x004E4942) + body)

"""Epsilon-covers of the state set X and the cost of collecting data on them.

A cover is a finite set of points x_r in X such that every x in X lies within epsilon
(Euclidean norm, angle dimensions measured with wrapped differences) of some x_r (paper,
Sec. III: the data set D = {(x_r, u, f(x_r,u), fhat(x_r,u,w_k))}).

Grid construction (:func:`make_cover`): over the d *covered* dimensions, dimension i of
length L_i = x_hi_i - x_lo_i is split into c_i = ceil(L_i / h_i) equal cells of width
w_i = L_i / c_i <= h_i and the points sit at the cell centers x_lo_i + (k + 1/2) w_i. Every x
is then within w_i/2 of a center in each dimension, so within r = 1/2 sqrt(sum_i w_i^2) of one
point. The default spacing h_i = 2 epsilon / sqrt(d) gives r <= epsilon; a per-dimension
spacing may be given instead (then r, the achieved radius, must not exceed epsilon).

Angle dimensions spanning a full turn ([-pi, pi]) are periodic: the cells tile the circle and
the centers never sit on the seam, so x near +pi and near -pi are both within w/2 of a center.

A region (``CoverSpec.region``, ``[collect] region``): a sub-box of X, given per state name as
[lo, hi] (other dimensions keep X's bounds), covered instead of X. The data, and so the
certificate made from them, then speak of the region only: the certificate records it, and
every consumer that takes gamma's sup over a set refuses a set leaving it
(:meth:`simgap.certify.certificate.Certificate.require_inside`).

Declared invariances: if the gap is known not to depend on some dimensions (e.g. the
TurtleBot's position x1, x2 on a uniform floor), those dimensions are not covered; they are
fixed at a stated representative value (default: the center of X) and the claim is recorded
in the cover spec, the store manifest and the printed summary. Every x in X is then within
epsilon of a cover point *after* moving it along the invariant dimensions.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from .errors import SimgapError
from .systems import System

TWO_PI = 2.0 * np.pi


def _dim_index(system: System, d) -> int:
    """A state dimension given as 0-based int, state name (``theta``) or positional name (``x3``)."""
    if isinstance(d, (int, np.integer)) and not isinstance(d, bool):
        i = int(d)
    elif isinstance(d, str):
        if d in system.state_names:
            i = system.state_names.index(d)
        elif d.startswith("x") and d[1:].isdigit():
            i = int(d[1:]) - 1
        else:
            raise SimgapError(f"cover: unknown state dimension {d!r} for system {system.name!r}; "
                              f"names: {', '.join(system.state_names)} (or x1..x{system.n})")
    else:
        raise SimgapError(f"cover: a state dimension must be an index or a name, got {d!r}")
    if not 0 <= i < system.n:
        raise SimgapError(f"cover: state dimension {d!r} out of range for n={system.n}")
    return i


@dataclass(frozen=True)
class CoverSpec:
    """What to cover and how finely (JSON-able via :meth:`to_dict`).

    Attributes
    ----------
    epsilon : float
        Cover radius epsilon > 0 (state units; Euclidean over the covered dimensions).
    spacing : sequence of float, optional
        Requested grid spacing h_i per covered dimension (in the order of the covered
        dimensions) instead of the default 2 epsilon / sqrt(d).
    invariant_dims : sequence of int or str
        Dimensions along which the gap is declared invariant: not covered.
    fixed : dict, optional
        Representative value per invariant dimension (name or index -> value); default the
        center of X in that dimension.
    region : dict, optional
        A sub-box of X to cover instead of X: state name (or index) -> [lo, hi]; dimensions not
        named keep X's bounds (module docstring).
    boxes : tuple of ([lo], [hi]) pairs, optional
        A union of boxes in X to cover instead of X (a cover along a tube, :mod:`simgap.tube_cover`):
        each box gets its own grid (the spacing rules above); not together with ``region``.
    """

    epsilon: float
    spacing: Optional[tuple] = None
    invariant_dims: tuple = ()
    fixed: dict = field(default_factory=dict)
    region: dict = field(default_factory=dict)
    boxes: tuple = ()

    def to_dict(self) -> dict:
        out = {"epsilon": float(self.epsilon),
               "spacing": None if self.spacing is None else [float(h) for h in self.spacing],
               "invariant_dims": [d if isinstance(d, str) else int(d) for d in self.invariant_dims],
               "fixed": {str(k): float(v) for k, v in self.fixed.items()}}
        if self.region:  # only when given: the configuration hash of a collection over X is unchanged
            out["region"] = {str(k): [float(a) for a in v] for k, v in self.region.items()}
        if self.boxes:  # likewise
            out["boxes"] = [[[float(a) for a in b[0]], [float(a) for a in b[1]]] for b in self.boxes]
        return out


def region_box(system: System, region) -> tuple:
    """(lo, hi), (n,) each: X with the dimensions ``region`` names (name or index -> [lo, hi])
    narrowed to their [lo, hi]. Refused, naming the dimension, unless X_lo <= lo < hi <= X_hi."""
    lo, hi = system.x_lo.astype(float).copy(), system.x_hi.astype(float).copy()
    for k, v in (region or {}).items():
        i = _dim_index(system, k)
        try:
            a, b = (float(t) for t in v)
        except (TypeError, ValueError):
            raise SimgapError(f"region: {k!r} needs [lo, hi] (two numbers), got {v!r}") from None
        nm = system.state_names[i]
        if not (math.isfinite(a) and math.isfinite(b) and a < b):
            raise SimgapError(f"region: {nm} = [{a:g}, {b:g}] needs finite lo < hi")
        if a < system.x_lo[i] - 1e-12 or b > system.x_hi[i] + 1e-12:
            raise SimgapError(f"region: {nm} = [{a:g}, {b:g}] leaves X's [{system.x_lo[i]:g}, {system.x_hi[i]:g}]; "
                              "a region is a sub-box of X")
        lo[i], hi[i] = max(a, system.x_lo[i]), min(b, system.x_hi[i])
    return lo, hi


def restrict(system: System, region) -> System:
    """``system`` with X narrowed to :func:`region_box` (the same model; only the box changes)."""
    if not region:
        return system
    import dataclasses
    lo, hi = region_box(system, region)
    return dataclasses.replace(system, x_lo=lo, x_hi=hi)


@dataclass(frozen=True, eq=False)
class Cover:
    """A grid epsilon-cover of X (see module docstring).

    Attributes
    ----------
    points : (N, n) array
        The cover points x_r, C-order over the covered dimensions (first covered dimension
        varies slowest).
    epsilon : float
        The declared radius.
    radius : float
        The achieved radius r = 1/2 ||w|| <= epsilon.
    covered : tuple of int
        Covered dimensions (0-based).
    counts, widths : (d,) arrays
        Cells c_i and cell widths w_i per covered dimension.
    fixed : dict int -> float
        Representative values of the invariant dimensions.
    periodic : tuple of bool
        Per covered dimension: periodic (a full-turn angle dimension).
    spec : CoverSpec
    """

    system: System
    points: np.ndarray
    epsilon: float
    radius: float
    covered: tuple
    counts: np.ndarray
    widths: np.ndarray
    fixed: dict
    periodic: tuple
    spec: CoverSpec
    box_lo: Optional[np.ndarray] = None   # the covered box's lower corner (X's, or the region's)
    boxes: Optional[tuple] = None         # ((B, n), (B, n)) a cover along a tube: the union it covers

    @property
    def N(self) -> int:
        """Number of cover points."""
        return self.points.shape[0]

    def describe(self) -> dict:
        """JSON-ready record of the cover for manifests (spec plus what it produced). A cover along a
        tube records ``widths`` as the largest cell width per covered dimension over its boxes (the
        radius per dimension its certificate may use) and ``counts`` as the distinct values per one."""
        s = self.system
        return {
            **self.spec.to_dict(),
            "type": "grid" if self.boxes is None else "boxes",
            "covered_dims": [s.state_names[i] for i in self.covered],
            "invariant_dims": [s.state_names[i] for i in sorted(self.fixed)],
            "fixed": {s.state_names[i]: v for i, v in sorted(self.fixed.items())},
            "counts": self.counts.tolist(),
            "widths": self.widths.tolist(),
            "radius": float(self.radius),
            "n_points": int(self.N),
        }

    def summary(self) -> str:
        """One human-readable line, naming any declared invariance."""
        s = self.system
        dims = " x ".join(f"{s.state_names[i]}:{c}" for i, c in zip(self.covered, self.counts))
        out = f"cover: {self.N} points (epsilon={self.epsilon:g}, achieved radius {self.radius:.4g}; grid {dims})"
        if self.boxes is not None:
            out = (f"cover along a tube: {self.N} points in {len(self.boxes[0])} boxes (epsilon={self.epsilon:g}, "
                   f"achieved radius {self.radius:.4g}; distinct values {dims})\n  region (a local certificate: "
                   "gamma will hold in the union of the boxes only)")
        if self.spec.region:
            out += ("\n  region (a local certificate: gamma will hold there only): "
                    + " x ".join(f"{k} [{float(v[0]):g}, {float(v[1]):g}]" for k, v in self.spec.region.items()))
        if self.fixed:
            fx = ", ".join(f"{s.state_names[i]}={v:g}" for i, v in sorted(self.fixed.items()))
            out += (f"\n  declared invariance: the gap is assumed independent of "
                    f"{', '.join(s.state_names[i] for i in sorted(self.fixed))}; those are fixed at {fx}")
        return out

    def locate(self, x: np.ndarray) -> np.ndarray:
        """Index of the cover point whose cell contains x (B,n) -> (B,) (invariant dims ignored)."""
        if self.boxes is not None:
            raise SimgapError("cover.locate: a cover along a tube has no single grid; use its boxes")
        s = self.system
        x = np.atleast_2d(np.asarray(x, dtype=float))
        idx = np.zeros(x.shape[0], dtype=np.int64)
        for i, c, w, per in zip(self.covered, self.counts, self.widths, self.periodic):
            t = x[:, i] - (s.x_lo[i] if self.box_lo is None else self.box_lo[i])
            if per:
                t = np.mod(t, TWO_PI)
            k = np.clip(np.floor(t / w).astype(np.int64), 0, int(c) - 1)
            idx = idx * int(c) + k
        return idx

    def distance(self, x: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """Euclidean distance over the covered dims (angles wrapped) from x (B,n) to its cover point."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        idx = self.locate(x) if idx is None else idx
        d = self.system.diff(x, self.points[idx])[:, list(self.covered)]
        return np.sqrt((d ** 2).sum(axis=1))


def make_cover(system: System, spec: CoverSpec | float) -> Cover:
    """Grid epsilon-cover of X for ``system`` (see module docstring for the construction).

    Parameters
    ----------
    system : System
    spec : CoverSpec or float
        A float is taken as epsilon with the default spacing and no invariance.

    Raises
    ------
    SimgapError
        epsilon <= 0 or not finite, a bad spacing, an achieved radius above epsilon, an unknown
        invariant dimension, a fixed value outside X, or nothing left to cover.
    """
    if not isinstance(spec, CoverSpec):
        spec = CoverSpec(epsilon=spec)
    try:
        eps = float(spec.epsilon)
    except (TypeError, ValueError):
        raise SimgapError(f"cover: epsilon must be a number, got {spec.epsilon!r}") from None
    if not (math.isfinite(eps) and eps > 0):
        raise SimgapError(f"cover: epsilon must be > 0, got {spec.epsilon!r}")

    whole = system
    if spec.boxes and spec.region:
        raise SimgapError("cover: give a region or boxes (a cover along a tube), not both")
    system = restrict(system, spec.region)  # a region: cover it instead of X (its checks name the dimension)
    inv = sorted({_dim_index(system, d) for d in spec.invariant_dims})
    covered = tuple(i for i in range(system.n) if i not in inv)
    if not covered:
        raise SimgapError("cover: every state dimension is declared invariant; nothing left to cover")
    fixed = {}
    for k, v in spec.fixed.items():
        i = _dim_index(system, k)
        if i not in inv:
            raise SimgapError(f"cover: fixed value given for {k!r}, which is not an invariant dimension")
        fixed[i] = float(v)
    for i in inv:
        fixed.setdefault(i, float(0.5 * (system.x_lo[i] + system.x_hi[i])))
        v = fixed[i]
        if not (math.isfinite(v) and system.x_lo[i] <= v <= system.x_hi[i]):
            raise SimgapError(f"cover: fixed value {system.state_names[i]}={v!r} is outside "
                              f"{'the region' if spec.region else 'X'} "
                              f"[{system.x_lo[i]:g}, {system.x_hi[i]:g}]")

    d = len(covered)
    L = system.x_hi[list(covered)] - system.x_lo[list(covered)]
    if spec.boxes:  # the union of boxes along a tube: each box's own grid (simgap.tube_cover)
        return _box_cover(whole, spec, eps, covered, fixed)
    h = _spacing(spec, eps, d)
    # ceil with a relative slack so that L/h = 70.0000000001 from rounding does not add a cell
    counts = np.maximum(1, np.ceil(L / h * (1 - 1e-12))).astype(np.int64)
    widths = L / counts
    radius = 0.5 * float(np.sqrt((widths ** 2).sum()))
    if radius > eps * (1 + 1e-12):
        raise SimgapError(f"cover: spacing {h.tolist()} gives radius {radius:.6g} > epsilon {eps:g}")
    total = int(np.prod(counts.astype(float)))
    if total > 2e8:
        raise SimgapError(f"cover: {total:.3g} points is too many (epsilon={eps:g} over {d} dimensions); "
                          "use a larger epsilon or declare invariant dimensions")
    periodic = tuple(bool(i in system.angle_dims and abs(L[k] - TWO_PI) < 1e-9) for k, i in enumerate(covered))

    axes = [system.x_lo[i] + (np.arange(c) + 0.5) * w for i, c, w in zip(covered, counts, widths)]
    mesh = np.meshgrid(*axes, indexing="ij")
    pts = np.empty((total, system.n))
    for k, i in enumerate(covered):
        pts[:, i] = mesh[k].ravel()
    for i, v in fixed.items():
        pts[:, i] = v
    return Cover(system=whole, points=pts, epsilon=eps, radius=radius, covered=covered,
                 counts=counts, widths=widths, fixed=fixed, periodic=periodic, spec=spec,
                 box_lo=system.x_lo.copy())


def _spacing(spec: CoverSpec, eps: float, d: int) -> np.ndarray:
    if spec.spacing is None:
        return np.full(d, 2.0 * eps / math.sqrt(d))
    h = np.asarray(spec.spacing, dtype=float).ravel()
    if h.shape != (d,) or not np.all(np.isfinite(h)) or np.any(h <= 0):
        raise SimgapError(f"cover: spacing needs {d} positive values (one per covered dimension), "
                          f"got {spec.spacing!r}")
    return h


def _box_cover(system: System, spec: CoverSpec, eps: float, covered: tuple, fixed: dict) -> Cover:
    """The cover of a union of boxes (:mod:`simgap.tube_cover`): every box's grid at the spacing, the union."""
    from .tube_cover import box_grid_points, check_boxes
    lo, hi = check_boxes(system, spec.boxes)
    h = _spacing(spec, eps, len(covered))
    pts, widths = box_grid_points(lo, hi, covered, h)
    radius = 0.5 * float(np.sqrt((widths ** 2).sum(axis=1)).max())
    if radius > eps * (1 + 1e-12):
        raise SimgapError(f"cover: spacing {h.tolist()} gives radius {radius:.6g} > epsilon {eps:g}")
    for i, v in fixed.items():
        pts[:, i] = v
    inv = [i for i in range(system.n) if i not in covered]
    lo[:, inv], hi[:, inv] = system.x_lo[inv], system.x_hi[inv]  # gamma is declared independent of them
    counts = np.array([np.unique(pts[:, i]).size for i in covered], dtype=np.int64)
    return Cover(system=system, points=pts, epsilon=eps, radius=radius, covered=covered, counts=counts,
                 widths=widths.max(axis=0), fixed=fixed, periodic=tuple(False for _ in covered), spec=spec,
                 box_lo=None, boxes=(lo, hi))


# ----------------------------------------------------------------------------------------
# Cost estimate
# ----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CostEstimate:
    """Size and expected duration of a collection.

    n_points = N cover points; n_pairs = N * M; runs = n_pairs * N1hat simulator runs;
    sim_steps = runs * k physics periods (k = system steps); seconds = runs / (rate * workers).
    """

    n_points: int
    n_inputs: int
    n_pairs: int
    n_runs: int
    runs: int
    sim_steps: int
    rate_per_worker: Optional[float]
    workers: int
    seconds: Optional[float]
    rate_source: str = ""

    def summary(self) -> str:
        t = "unknown" if self.seconds is None else format_duration(self.seconds)
        rate = "" if self.rate_per_worker is None else \
            f" at {self.rate_per_worker:,.0f} runs/s per worker x {self.workers} ({self.rate_source})"
        return (f"{self.n_points:,} cover points x {self.n_inputs} inputs = {self.n_pairs:,} (x_r,u) pairs; "
                f"x {self.n_runs} runs = {self.sim_steps:,} simulator steps\n"
                f"estimated time: {t}{rate}")


def format_duration(s: float) -> str:
    s = float(s)
    if s < 60:
        return f"{s:.1f} s"
    if s < 3600:
        return f"{int(s // 60)} min {int(s % 60):02d} s"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"


CALIBRATION_SHARE = 0.05  # a rate's timing costs at most about this share of the work it prices
MIN_CALIBRATION_S = 0.05  # ... and at least this long (two timed batches in any case)


def timed_rate(batch: Callable[[int, bool], None], first: int, most: int, budget: float, grow: float = 0.25,
               work: Optional[float] = None) -> float:
    """Units (runs, pairs) per second of ``batch(k, timed)``, which computes k units.

    Batches grow from ``first`` units (x4) up to ``most`` until one takes ``grow`` x ``budget``
    (or 2 ``grow`` x ``budget`` has passed); none of these is timed for the rate: the first call
    at a new batch size may build per-row resources (MuJoCo's per-row model copies, a world's
    bodies), a one-off cost the priced work does not pay per batch. The rate is then measured on
    repeated batches of the size reached (``timed`` True: the caller takes other rows each time,
    so that a memoizing simulator is not timed on its memo), at least two, until ``budget``
    seconds have passed since the start: units / seconds over those batches (one short batch on
    a shared machine is noise).

    ``work``: the units the priced stage will compute. Each batch's time says roughly how long
    that takes, and the timed batches stop after ``CALIBRATION_SHARE`` of it (at least
    ``MIN_CALIBRATION_S``; two batches in any case): a small stage is not timed for longer than it
    runs. The growth keeps the whole budget: the batch timed is the stage's own size where it can be
    (a parallel simulator splits large batches over its helpers, small ones not: the rate differs)."""
    timed_budget = budget

    def shrink(units, seconds):
        nonlocal timed_budget
        if work is not None and units > 0:
            timed_budget = min(timed_budget, max(MIN_CALIBRATION_S, CALIBRATION_SHARE * float(work) * seconds / units))

    start = time.perf_counter()
    k = max(1, min(int(first), int(most)))
    batch(k, False)  # warm-up: the first call at this size builds what it needs
    while k < most:
        t0 = time.perf_counter()
        k = min(int(most), 4 * k)
        batch(k, False)  # the first call at a new size: not timed for the rate
        dt = time.perf_counter() - t0
        shrink(k, dt)
        if dt >= grow * budget or time.perf_counter() - start >= 2 * grow * budget:
            break
    units, spent = 0, 0.0
    while True:
        t0 = time.perf_counter()
        batch(k, True)
        spent += time.perf_counter() - t0
        units += k
        shrink(units, spent)
        if units >= 2 * k and (time.perf_counter() - start >= budget or spent >= timed_budget):
            return units / max(spent, 1e-9)  # two batches at least: one is noise


def calibrate_rate(simulator, n_runs: int = 4096, seed: int = 0, budget: float = 0.5, repeat: int = 1,
                   work: Optional[float] = None) -> float:
    """Simulator runs per second in this process: ``simulator.step`` timed on random states of X
    by :func:`timed_rate` (batches growing from 64 runs up to ``n_runs`` until one takes a quarter
    of ``budget``, untimed; then batches of that size until ``budget`` has passed, a shorter one
    for a small ``work``, the runs the priced stage makes). A slow simulator (a robot with many
    substeps) is thus measured within about twice its largest batch plus the budget. Each timed
    batch takes other rows (a random subset of ``n_runs`` random states), so that a simulator
    memoizing repeated batches is not timed on its memo.

    ``repeat``: every state-input row ``repeat`` times in a row, as the stage to be priced steps
    them (the Lipschitz runs per pair): a simulator that simulates identical noise-free rows once
    (the TurtleBot's) is timed as it will run.
    """
    s = simulator.system
    n_runs = max(1, int(n_runs))
    rep = max(1, min(int(repeat), n_runs))
    rng = np.random.default_rng(seed)
    k = -(-n_runs // rep)
    x = np.repeat(s.x_lo + rng.random((k, s.n)) * (s.x_hi - s.x_lo), rep, axis=0)[:n_runs]
    u = np.repeat(s.inputs[rng.integers(0, s.inputs.shape[0], k)], rep, axis=0)[:n_runs]

    def batch(b, timed):
        if not timed:
            rows = slice(0, b)
        elif rep == 1:  # other rows each time: a memo (ParallelSimulator's, identical noise-free draws)
            rows = rng.permutation(n_runs)[:b]
        else:  # whole blocks of repeated rows, in another order
            rows = (rng.permutation(-(-n_runs // rep))[:, None] * rep + np.arange(rep)).ravel()
            rows = rows[rows < n_runs][:b]
        simulator.step(x[rows], u[rows], rng)

    return timed_rate(batch, 64, n_runs, budget, grow=0.25, work=work)


def estimate_cost(cover: Cover, n_runs: int, rate_per_worker: Optional[float] = None,
                  workers: int = 1, rate_source: str = "") -> CostEstimate:
    """Cost of collecting N1hat = ``n_runs`` simulator runs for every (x_r, u) pair of ``cover``."""
    M = int(cover.system.inputs.shape[0])
    pairs = cover.N * M
    runs = pairs * int(n_runs)
    steps = runs * int(cover.system.steps)
    secs = None if not rate_per_worker else runs / (rate_per_worker * max(1, workers))
    return CostEstimate(n_points=cover.N, n_inputs=M, n_pairs=pairs, n_runs=int(n_runs), runs=runs,
                        sim_steps=steps, rate_per_worker=rate_per_worker, workers=int(workers),
                        seconds=secs, rate_source=rate_source)

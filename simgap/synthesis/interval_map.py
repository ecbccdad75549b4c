"""Sound enclosures of a system file's one-period map f and of its closed-loop Jacobian over a box.

For the invariant-set proof (:mod:`simgap.synthesis.invariant_set`) we need, for every x in a box
[x_lo, x_hi], a bound on the Jacobian of the closed loop g(x) = f(x, u* + K (x - x*)):

    J_g(x) = d f / d x (x, u(x)) + d f / d u (x, u(x)) K.

f is the model simgap uses everywhere else (``System.f``): for a continuous system file the
classical RK4 map with ``substeps`` steps per base period and u held (the same map the
certificate's gamma is measured against, so no enclosure of the exact flow is needed), for a
discrete one the file's map; ``steps`` base periods are composed. The enclosure is forward-mode
interval differentiation: every right-hand-side evaluation gets a value box and an interval
Jacobian from :meth:`simgap.certify.basis.Term.interval_grad` (the system file's expression trees,
definitions inlined, parameters folded), and every RK4 stage propagates (value box, interval
derivative d y / d x) with interval matrix products in midpoint-radius form:

    [Ac +- Ar] [Bc +- Br]  subset of  Ac Bc +- (|Ac| Br + Ar |Bc| + Ar Br).

Each quantity is enclosed for every x of the box at once, so the result contains J_g(x) for every
x in the box (and for every input in [u_lo, u_hi], the range u takes there). Rounding of the
floating-point operations is not directed; the radius is widened by a relative 1e-9 plus 1e-12 to
cover it (far above the accumulated rounding of the few dozen operations per entry).

The same enclosure is compiled from the expression trees by :mod:`simgap.compile` (one numba call
per batch of boxes for every period, substep and stage); :meth:`IntervalMap.closed_loop` uses it in
place of the numpy code here (the oracle and the fallback) as :meth:`IntervalMap.kernel` decides.

Refused (a clear message): models that are not system files, and formulas with functions that
have no interval derivative here (the non-smooth ones: abs, sign, min, max, clip, where,
comparisons; and sinh, cosh, log, arctan, arctan2) or non-integer powers.
"""

from __future__ import annotations

import time

import numpy as np

from ..certify.basis import FUNCS, Term
from ..errors import SimgapError
from ..expr import NONSMOOTH, walk
from ..system_file import model_trees
from ..systems import System

#: functions with interval derivatives (Term.interval_grad) that are smooth
SMOOTH_FUNCS = tuple(f for f in FUNCS if f not in NONSMOOTH)
#: relative and absolute widening of every enclosure radius (unrounded interval arithmetic)
REL_WIDEN, ABS_WIDEN = 1e-9, 1e-12


#: boxes evaluated by one IntervalMap in numpy from which it compiles its kernel in auto mode
#: (SIMGAP_JIT unset or auto): about the numpy path's cost of a first compile (seconds) on a
#: 4-state file; a loaded kernel (numba's start and the cached code) costs about 1 s
AUTO_BOXES = 20_000


def _imatmul(Ac, Ar, Bc, Br):
    """Enclosure of the interval product [Ac +- Ar] [Bc +- Br] (batched over the first axis)."""
    return Ac @ Bc, np.abs(Ac) @ Br + Ar @ np.abs(Bc) + Ar @ Br


class IntervalMap:
    """Interval enclosures of a system-file model's one-period map (module docstring)."""

    def __init__(self, system: System):
        t = model_trees(system)
        self.system = system
        self.n, self.m = system.n, system.m
        for i, tree in enumerate(t["trees"]):
            for node in walk(tree):
                if node[0] == "cmp" or (node[0] == "fn" and node[1] not in SMOOTH_FUNCS):
                    name = "a comparison" if node[0] == "cmp" else f"{node[1]}()"
                    raise SimgapError(f"system {system.name!r}: dynamics of {system.state_names[i]!r} use {name}, which "
                                      f"has no interval derivative here (supported: {', '.join(SMOOTH_FUNCS)}, "
                                      f"+ - * /, integer powers); the invariant-set proof needs one")
                if node[0] == "pow" and float(node[2]) != int(node[2]):
                    raise SimgapError(f"system {system.name!r}: dynamics of {system.state_names[i]!r} use the "
                                      f"non-integer power {node[2]}; write sqrt() for square roots")
        self.terms = [Term(f"d{s}", tree) for s, tree in zip(system.state_names, t["trees"])]
        self.terms_trees = list(t["trees"])
        self.continuous = t["continuous"]
        self.substeps = t["substeps"]
        self.base_tau = t["tau"]
        self.steps = int(system.steps)
        from ..compile import Twin, interval_source
        self.twin = Twin(interval_source, (self.terms_trees, self.n, self.m), "closed_loop", AUTO_BOXES)

    def kernel(self, boxes: int = 0):
        """The compiled closed loop (:func:`simgap.compile.interval_kernel`) if it pays for ``boxes``
        boxes now (:class:`simgap.compile.Twin`, auto mode from :data:`AUTO_BOXES`), else None."""
        return self.twin.get(boxes)

    def rhs(self, ylo, yhi, ulo, uhi):
        """Value box and interval Jacobian of the formulas over boxes y in [ylo, yhi], u in [ulo, uhi]
        (B, n) / (B, m): (vlo, vhi) (B, n) and (Gc, Gr) (B, n, n + m) midpoint and radius."""
        B = ylo.shape[0]
        dt = np.full((B, 1), self.base_tau)
        zlo = np.concatenate([ylo, ulo, dt], axis=1)
        zhi = np.concatenate([yhi, uhi, dt], axis=1)
        dims = range(self.n + self.m)
        vlo, vhi = np.empty((B, self.n)), np.empty((B, self.n))
        glo, ghi = np.empty((B, self.n, self.n + self.m)), np.empty((B, self.n, self.n + self.m))
        for i, term in enumerate(self.terms):
            vlo[:, i], vhi[:, i], glo[:, i], ghi[:, i] = term.interval_grad(zlo, zhi, dims)
        bad = ~(np.isfinite(vlo) & np.isfinite(vhi)).all(axis=1) | ~(np.isfinite(glo) & np.isfinite(ghi)).all(axis=(1, 2))
        if bad.any():  # unbounded (a denominator interval containing 0, ...): the proof cannot use it
            vlo[bad], vhi[bad], glo[bad], ghi[bad] = -np.inf, np.inf, -np.inf, np.inf
        return vlo, vhi, 0.5 * (glo + ghi), 0.5 * (ghi - glo)

    def closed_loop(self, x_lo, x_hi, u_lo, u_hi, K):
        """Enclosure over the boxes [x_lo, x_hi] (B, n) of f(x, u(x)) and of J_g(x) with
        u(x) = u* + K (x - x*) in [u_lo, u_hi] (B, m) and d u / d x = K (m, n).

        Returns (flo, fhi) (B, n) and (Jc, Jr) (B, n, n): J_g(x) in [Jc - Jr, Jc + Jr] for every x
        in its box. Infinite radii where the formulas are unbounded on the box.
        """
        x_lo, x_hi = np.atleast_2d(x_lo).astype(float), np.atleast_2d(x_hi).astype(float)
        u_lo, u_hi = np.atleast_2d(u_lo).astype(float), np.atleast_2d(u_hi).astype(float)
        B, n = x_lo.shape
        K = np.asarray(K, dtype=float)
        kern = self.kernel(B)
        if kern is not None:
            c = np.ascontiguousarray
            return kern(c(x_lo), c(x_hi), c(np.broadcast_to(u_lo, (B, self.m))), c(np.broadcast_to(u_hi, (B, self.m))),
                        c(K.reshape(self.m, n)), self.base_tau, self.substeps, self.steps, self.continuous,
                        REL_WIDEN, ABS_WIDEN)
        t0 = time.perf_counter()
        try:
            return self._closed_loop_numpy(x_lo, x_hi, u_lo, u_hi, K)
        finally:  # what the compiled twin would save (a long formula costs far more per box)
            self.twin.spent(time.perf_counter() - t0)

    def _closed_loop_numpy(self, x_lo, x_hi, u_lo, u_hi, K):
        """:meth:`closed_loop` in numpy (the oracle of the compiled kernel)."""
        B, n = x_lo.shape
        Kb = np.broadcast_to(K, (B,) + K.shape)
        zero_K = np.zeros_like(Kb)
        lo, hi = x_lo.copy(), x_hi.copy()
        Dc, Dr = np.broadcast_to(np.eye(n), (B, n, n)).copy(), np.zeros((B, n, n))

        def field(ylo, yhi, Yc, Yr):
            """(value box, derivative d/dx0) of F(y, u) for y with derivative [Yc +- Yr]."""
            vlo, vhi, Gc, Gr = self.rhs(ylo, yhi, u_lo, u_hi)
            c1, r1 = _imatmul(Gc[:, :, :n], Gr[:, :, :n], Yc, Yr)
            c2, r2 = _imatmul(Gc[:, :, n:], Gr[:, :, n:], Kb, zero_K)
            return vlo, vhi, c1 + c2, r1 + r2

        with np.errstate(invalid="ignore", over="ignore"):
            for _ in range(self.steps):
                if not self.continuous:
                    lo, hi, Dc, Dr = field(lo, hi, Dc, Dr)
                    continue
                h = self.base_tau / self.substeps
                for _ in range(self.substeps):
                    k = [field(lo, hi, Dc, Dr)]
                    for a in (h / 2, h / 2, h):
                        kl, kh, kc, kr = k[-1]
                        k.append(field(lo + a * kl, hi + a * kh, Dc + a * kc, Dr + a * kr))
                    w = (1.0, 2.0, 2.0, 1.0)
                    lo = lo + h / 6 * sum(wi * ki[0] for wi, ki in zip(w, k))
                    hi = hi + h / 6 * sum(wi * ki[1] for wi, ki in zip(w, k))
                    Dc = Dc + h / 6 * sum(wi * ki[2] for wi, ki in zip(w, k))
                    Dr = Dr + h / 6 * sum(wi * ki[3] for wi, ki in zip(w, k))
        Dr = Dr + REL_WIDEN * np.abs(Dc) + ABS_WIDEN
        Dr = np.where(np.isfinite(Dc) & np.isfinite(Dr), Dr, np.inf)
        Dc = np.where(np.isfinite(Dc), Dc, 0.0)
        span = REL_WIDEN * np.maximum(np.abs(lo), np.abs(hi)) + ABS_WIDEN
        return lo - span, hi + span, Dc, Dr

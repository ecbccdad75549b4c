"""Uniform grids of cells over a box, with the SCOTS v2 alignment convention.

Alignment (the convention parity checks rely on)
-------------------------------------------------
For a bounded (non-periodic) dimension d with bounds [lo_d, hi_d] and cell width eta_d, the
grid points are the integer multiples of eta_d inside the bounds::

    k_lo = ceil(lo_d / eta_d),  k_hi = floor(hi_d / eta_d)     (with a 1e-9 relative tolerance)
    p_d(i) = first_d + i * eta_d,   first_d = k_lo * eta_d,   i = 0 .. n_d - 1,  n_d = k_hi - k_lo + 1

Each grid point is the *center* of its cell ``[p - eta/2, p + eta/2]``, so the grid covers
``[first - eta/2, last + eta/2]``, which may stick out of [lo, hi] by up to eta/2 (SCOTS does
the same). Example: [0, 10] with eta = 0.2 gives 51 points 0, 0.2, ..., 10; [-3.5, 3.5] with
eta = 0.2 gives 35 points -3.4 ... 3.4.

A periodic dimension (an angle, period P = hi - lo) is split into n_d = ceil(P / eta_d) cells of
equal width P / n_d (<= the requested eta, so the circle is covered exactly once), with centers
``lo + i * eta_d``; indices wrap modulo n_d.

Cell ids are C-order flat indices of the multi-index (last dimension varies fastest).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..errors import SimgapError

_TOL = 1e-9


class UniformGrid:
    """A grid of cells, centers aligned as described in the module docstring.

    Parameters
    ----------
    lo, hi : (n,) array-like
        Bounds of the box to cover (state units).
    eta : float or (n,) array-like
        Cell width per dimension (state units), 0 < eta_d <= hi_d - lo_d.
    periodic : sequence of int
        Dimensions that wrap (period hi_d - lo_d).
    """

    def __init__(self, lo: Sequence[float], hi: Sequence[float], eta, periodic: Sequence[int] = (),
                 check_size: bool = True):
        lo = np.asarray(lo, dtype=float).ravel()
        hi = np.asarray(hi, dtype=float).ravel()
        n = lo.size
        if n == 0 or hi.size != n or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise SimgapError("grid: lo and hi must be finite, non-empty and of equal length")
        if np.any(hi <= lo):
            raise SimgapError(f"grid: need lo < hi in every dimension, got lo={lo.tolist()} hi={hi.tolist()}")
        eta = np.broadcast_to(np.asarray(eta, dtype=float).ravel(), (n,)).copy() \
            if np.asarray(eta).size in (1, n) else None
        if eta is None:
            raise SimgapError(f"grid: eta must be a scalar or have {n} components")
        if not np.all(np.isfinite(eta)) or np.any(eta <= 0):
            raise SimgapError(f"grid: eta must be > 0 in every dimension, got {eta.tolist()}")
        if np.any(eta > (hi - lo) * (1 + _TOL)):
            bad = int(np.flatnonzero(eta > (hi - lo) * (1 + _TOL))[0])
            raise SimgapError(f"grid: eta[{bad}] = {eta[bad]:g} is larger than the extent "
                              f"{hi[bad] - lo[bad]:g} of dimension {bad}")
        periodic = tuple(sorted(int(d) for d in periodic))
        if any(d < 0 or d >= n for d in periodic):
            raise SimgapError(f"grid: periodic dimensions {periodic} out of range for n={n}")
        pmask = np.zeros(n, dtype=bool)
        pmask[list(periodic)] = True

        first = np.empty(n)
        shape = np.empty(n, dtype=np.int64)
        for d in range(n):  # n is the state dimension (2-3): not a hot loop
            if pmask[d]:
                P = hi[d] - lo[d]
                k = int(np.ceil(P / eta[d] - _TOL))
                eta[d] = P / k
                first[d] = lo[d]
                shape[d] = k
            else:
                k_lo = int(np.ceil(lo[d] / eta[d] - _TOL))
                k_hi = int(np.floor(hi[d] / eta[d] + _TOL))
                if k_hi < k_lo:
                    raise SimgapError(f"grid: no multiple of eta[{d}] = {eta[d]:g} lies in "
                                      f"[{lo[d]:g}, {hi[d]:g}]; choose a smaller eta")
                first[d] = k_lo * eta[d]
                shape[d] = k_hi - k_lo + 1
        self.lo, self.hi, self.eta = lo, hi, eta
        self.first = first
        self.shape = tuple(int(s) for s in shape)
        self.periodic = periodic
        self.periodic_mask = pmask
        self.n = n
        self.size = int(np.prod(shape))
        if check_size:
            self.check_size()
        # C-order strides of the multi-index
        self.strides = np.array([int(np.prod(shape[d + 1:])) for d in range(n)], dtype=np.int64)

    def check_size(self) -> None:
        """Refuse a grid of 2^31 cells or more (cell ids are int32); ``check_size=False`` defers
        this, so that a cost estimate can name the numbers first."""
        if self.size >= 2 ** 31 - 1:
            raise SimgapError(f"grid: {self.size:,} cells is too many (limit 2^31); use a coarser eta")

    # ----- conversions ---------------------------------------------------------------------
    @property
    def last(self) -> np.ndarray:
        """Center of the last cell per dimension."""
        return self.first + (np.array(self.shape) - 1) * self.eta

    @property
    def domain_lo(self) -> np.ndarray:
        """Lower edge of the covered region, first - eta/2."""
        return self.first - self.eta / 2

    @property
    def domain_hi(self) -> np.ndarray:
        """Upper edge of the covered region, last + eta/2."""
        return self.last + self.eta / 2

    def ids_to_multi(self, ids: np.ndarray) -> np.ndarray:
        """(B,) flat ids -> (B, n) int64 multi-indices."""
        ids = np.asarray(ids, dtype=np.int64)
        return np.stack(np.unravel_index(ids, self.shape), axis=-1).astype(np.int64)

    def multi_to_ids(self, mi: np.ndarray) -> np.ndarray:
        """(B, n) multi-indices -> (B,) flat ids (periodic dims taken modulo their size)."""
        mi = np.asarray(mi, dtype=np.int64)
        if self.periodic:
            mi = mi.copy()
            for d in self.periodic:
                mi[..., d] %= self.shape[d]
        return mi @ self.strides

    def multi_to_points(self, mi: np.ndarray) -> np.ndarray:
        """(B, n) multi-indices -> (B, n) cell centers first + i * eta."""
        return self.first + np.asarray(mi, dtype=float) * self.eta

    def points(self, ids: np.ndarray) -> np.ndarray:
        """(B,) ids -> (B, n) cell centers."""
        return self.multi_to_points(self.ids_to_multi(ids))

    def axis_points(self, d: int) -> np.ndarray:
        """Centers along dimension d, (n_d,)."""
        return self.first[d] + np.arange(self.shape[d]) * self.eta[d]

    def x_to_multi(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, n) states -> ((B, n) multi-index of the cell containing x, (B,) inside mask).

        A state on a shared cell face goes to the cell with the larger index (round half up).
        Periodic dimensions wrap; a state outside [first - eta/2, last + eta/2] in a bounded
        dimension is reported as outside (its multi-index is clipped, do not use it).
        """
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.shape[-1] != self.n:
            raise SimgapError(f"grid: states must have {self.n} components, got {x.shape[-1]}")
        v = np.floor((x - self.first) / self.eta + 0.5)
        inside = np.all(np.isfinite(x), axis=-1)
        v = np.where(np.isfinite(v), v, 0)
        mi = v.astype(np.int64)
        shape = np.array(self.shape)
        for d in range(self.n):
            if self.periodic_mask[d]:
                mi[:, d] %= shape[d]
            else:
                inside &= (mi[:, d] >= 0) & (mi[:, d] < shape[d])
        mi = np.clip(mi, 0, shape - 1)
        return mi, inside

    def x_to_ids(self, x: np.ndarray) -> np.ndarray:
        """(B, n) states -> (B,) cell ids, -1 where x is outside the grid."""
        mi, inside = self.x_to_multi(x)
        return np.where(inside, self.multi_to_ids(mi), -1)

    # ----- labels --------------------------------------------------------------------------
    def cells_intersecting(self, lo, hi, slack: float = 1e-10) -> np.ndarray:
        """(N,) bool: cells whose closed extent meets the box [lo, hi] (with ``slack``).

        This is the SCOTS vehicle obstacle rule: center within [lo - eta/2, hi + eta/2].
        """
        return self._label(lo, hi, inside=False, slack=slack)

    def cells_inside(self, lo, hi, slack: float = 1e-10) -> np.ndarray:
        """(N,) bool: cells whose whole extent [c - eta/2, c + eta/2] lies in [lo, hi] (+ slack).

        This is the SCOTS vehicle target rule (slack absorbs rounding of first + i * eta).
        """
        return self._label(lo, hi, inside=True, slack=slack)

    def _label(self, lo, hi, inside: bool, slack: float) -> np.ndarray:
        lo = np.broadcast_to(np.asarray(lo, dtype=float).ravel(), (self.n,))
        hi = np.broadcast_to(np.asarray(hi, dtype=float).ravel(), (self.n,))
        mask = np.ones(self.shape, dtype=bool)
        for d in range(self.n):  # separable: one 1-D test per dimension
            c = self.axis_points(d)
            h = self.eta[d] / 2
            if self.periodic_mask[d] and (lo[d] <= self.lo[d] and hi[d] >= self.hi[d]):
                continue  # the whole circle
            if inside:
                ok = (c - h >= lo[d] - slack) & (c + h <= hi[d] + slack)
            else:
                ok = (c >= lo[d] - h - slack) & (c <= hi[d] + h + slack)
                if self.periodic_mask[d]:
                    P = self.hi[d] - self.lo[d]
                    ok |= (c + P >= lo[d] - h - slack) & (c + P <= hi[d] + h + slack)
                    ok |= (c - P >= lo[d] - h - slack) & (c - P <= hi[d] + h + slack)
            shp = [1] * self.n
            shp[d] = -1
            mask &= ok.reshape(shp)
        return mask.ravel()

    # ----- (de)serialization ---------------------------------------------------------------
    def describe(self) -> dict:
        return {"lo": self.lo.tolist(), "hi": self.hi.tolist(), "eta": self.eta.tolist(),
                "periodic": list(self.periodic), "first": self.first.tolist(),
                "shape": list(self.shape), "size": self.size}

    @classmethod
    def from_dict(cls, d: dict) -> "UniformGrid":
        g = cls(d["lo"], d["hi"], d["eta"], d.get("periodic", ()))
        if list(g.shape) != list(d.get("shape", g.shape)):
            raise SimgapError(f"grid: stored shape {d['shape']} does not match the rebuilt {list(g.shape)}")
        return g

    def __repr__(self) -> str:
        return f"UniformGrid(shape={self.shape}, eta={self.eta.tolist()}, periodic={self.periodic})"

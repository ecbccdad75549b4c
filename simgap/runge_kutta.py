"""Fixed-step Runge-Kutta for user systems and their growth bounds (SCOTS ``runge_kutta_fixed4``).

A continuous-time model x' = F(x, u) becomes a :class:`~simgap.systems.System` step with
:func:`rk4_step`, and its SCOTS-style growth bound (the radius of the image of the cell
[x - r, x + r] after tau) with :func:`rk4_growth`, which integrates the comparison system

    r' = L(u) r,     L_ii >= sup dF_i/dx_i,   L_ij >= sup |dF_i/dx_j| (i != j)

over tau (sup over the state set; Reissig, Weber & Rungger 2017, Thm. 1). Both use ``nint``
classical RK4 substeps of h = tau / nint, evaluated in SCOTS's operation order, and both take
tau as an argument, so they stay right for ``system.with_steps(k)`` (tau = k * base_tau)::

    import numpy as np
    from simgap.synthesis import rk4_growth, rk4_step
    from simgap.systems import System, input_grid

    def rhs(x, u):                      # damped pendulum, (B, 2) -> (B, 2)
        return np.stack([x[:, 1], -np.sin(x[:, 0]) - 0.5 * x[:, 1] + u[:, 0]], axis=1)

    L = np.array([[0.0, 1.0], [1.0, -0.5]])          # |cos| <= 1
    pend = System(name="pend", state_names=("a", "w"), input_names=("T",), x_lo=(-1, -2),
                  x_hi=(1, 2), inputs=input_grid([-1], [1], [5]), base_tau=0.1,
                  step=rk4_step(rhs, nint=5))
    growth = rk4_growth(L, nint=5)                   # growth(r, x, u, tau)

RK4 is not a rigorous enclosure: like SCOTS, the results are as accurate as the integration
(error O(h^4) per unit time); pick ``nint`` so that this is far below the cell width.
"""

from __future__ import annotations

from typing import Callable, Optional, Union

import numpy as np

from .errors import SimgapError
from .jit import AUTO_WORK, use_compiled

RhsFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _check_nint(nint) -> int:
    if int(nint) != nint or nint < 1:
        raise SimgapError(f"runge-kutta: nint must be an integer >= 1, got {nint}")
    return int(nint)


def rk4_integrate(rhs: RhsFn, x: np.ndarray, u: np.ndarray, tau: float, nint: int = 10,
                  prepare: Optional[Callable[[np.ndarray], object]] = None) -> np.ndarray:
    """x(tau) of x' = rhs(x, u), u held, with ``nint`` RK4 substeps. x (B, n), u (B, m).

    SCOTS's operation order, x + (h/6) (k0 + 2 k1 + 2 k2 + k3), in two reused buffers (no
    temporaries besides what ``rhs`` returns; bit-identical to the expression).

    ``prepare(u) -> p``, optional: the terms of the right-hand side that depend on the input
    only (u is held over tau), computed once per call instead of 4 * nint times; ``rhs`` is then
    called as ``rhs(x, p)``. The same operations on the same values give the same bits, so
    moving a u-only term (e.g. ``tan(u[:, 1])``) into ``prepare`` leaves the result unchanged.
    """
    nint = _check_nint(nint)
    h = tau / nint
    if prepare is not None:
        u = prepare(u)
    # column-major (B, n): the right-hand side's columns x[:, i] are contiguous (elementwise
    # operations give the same bits in any layout; the result is column-major too)
    x = np.array(x, dtype=float, copy=True, order="F" if np.ndim(x) == 2 else "K")
    acc, two, tmp = np.empty_like(x), np.empty_like(x), np.empty_like(x)
    for _ in range(nint):  # substeps, vectorized over the batch
        k = rhs(x, u)                                       # k0
        np.copyto(acc, k)
        np.multiply(k, h / 2, out=tmp)
        k = rhs(np.add(tmp, x, out=tmp), u)                 # k1 = rhs(x + h/2 k0)
        acc += np.add(k, k, out=two)                        # + 2 k1 (k + k is 2 k exactly)
        np.multiply(k, h / 2, out=tmp)                      # (k may be tmp itself: elementwise)
        k = rhs(np.add(tmp, x, out=tmp), u)                 # k2 = rhs(x + h/2 k1)
        acc += np.add(k, k, out=two)
        np.multiply(k, h, out=tmp)
        acc += rhs(np.add(tmp, x, out=tmp), u)              # k3 = rhs(x + h k2)
        acc *= h / 6
        x += acc
    return x


def rk4_step(rhs: RhsFn, nint: int = 10, prepare: Optional[Callable[[np.ndarray], object]] = None,
             compiled: Optional[Callable[[np.ndarray, np.ndarray, float], np.ndarray]] = None,
             numpy: Optional[Callable[[np.ndarray, np.ndarray, float], np.ndarray]] = None
             ) -> Callable[[np.ndarray, np.ndarray, float], np.ndarray]:
    """A :class:`~simgap.systems.System` ``step(x, u, tau)`` integrating x' = rhs(x, u) over tau
    (with ``prepare``: x' = rhs(x, prepare(u)), see :func:`rk4_integrate`).

    ``compiled(x (B, n), u (B, m), tau) -> (B, n)``, optional: a compiled twin giving the same
    bits (e.g. a numba kernel, :mod:`simgap.synthesis.kernels`), used instead of the numpy path
    when :func:`simgap.jit.use_compiled` says so (large jobs; ``SIMGAP_JIT``; an
    attribute ``compiled.min_rows`` sets its break-even in step rows). It should import its
    compiler inside, so that building the system costs nothing.

    ``numpy(x, u, tau) -> (B, n)``, optional: another numpy evaluation giving the same bits as
    ``rk4_integrate(rhs, x, u, tau, nint, prepare)`` (e.g. the rows grouped by input, each
    group with a right-hand side specialized to it), used instead of it when no compiled twin
    is used."""
    nint = _check_nint(nint)
    if prepare is not None and not callable(prepare):
        raise SimgapError("runge-kutta: prepare must be a callable prepare(u) -> terms of the right-hand side")
    if compiled is not None and not callable(compiled):
        raise SimgapError("runge-kutta: compiled must be a callable compiled(x, u, tau) -> next states")
    if numpy is not None and not callable(numpy):
        raise SimgapError("runge-kutta: numpy must be a callable numpy(x, u, tau) -> next states")

    def step(x, u, tau):
        if compiled is not None:
            xu = compiled_args(x, u)
            if xu is not None and use_compiled(getattr(compiled, "min_rows", AUTO_WORK)):
                return compiled(xu[0], xu[1], float(tau))
        if numpy is not None:
            return numpy(x, u, tau)
        return rk4_integrate(rhs, x, u, tau, nint, prepare)
    return step


def compiled_args(x, u):
    """(x, u) as C-contiguous float64 (B, n), (B, m) arrays for a compiled kernel, or None when
    they are not such a batch (then the numpy path handles broadcasting)."""
    if not (isinstance(x, np.ndarray) and isinstance(u, np.ndarray)) or x.ndim != 2 or u.ndim != 2 \
            or x.shape[0] != u.shape[0]:
        return None
    return np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(u, dtype=np.float64)


def rk4_growth(L: Union[np.ndarray, Callable[[np.ndarray], np.ndarray]], nint: int = 10):
    """A growth bound ``growth(r, x, u, tau)``: r(tau) of r' = L(u) r (module docstring).

    ``L`` is a constant (n, n) matrix or a callable ``L(u (B, m)) -> (B, n, n)``. Its
    off-diagonal entries must be >= 0 (a bound on |dF_i/dx_j|); this is checked. The growth
    does not depend on x (marked ``state_independent``), so the abstraction evaluates it once
    per input, not once per (cell, input).
    """
    nint = _check_nint(nint)
    const = None if callable(L) else np.asarray(L, dtype=float)
    if const is not None:
        if const.ndim != 2 or const.shape[0] != const.shape[1]:
            raise SimgapError(f"growth: L must be a square (n, n) matrix, got shape {const.shape}")
        _check_metzler(const)

    def growth(r, x, u, tau):
        r = np.atleast_2d(np.asarray(r, dtype=float))
        n = r.shape[1]
        # r(tau) = Phi(u) r(0) with Phi the RK4 propagator of r' = L(u) r (RK4 is linear in r):
        # integrated once per distinct input, not once per (cell, input)
        if const is not None:
            if const.shape[0] != n:
                raise SimgapError(f"growth: L is {const.shape[0]} x {const.shape[0]}, the state has {n} dimensions")
            A, inv = const[None], np.zeros(r.shape[0], dtype=np.int64)
        else:
            uu, inv = _input_rows(np.atleast_2d(np.asarray(u, dtype=float)))
            A = np.asarray(L(uu), dtype=float)
            if A.shape != (uu.shape[0], n, n):
                raise SimgapError(f"growth: L(u) returned shape {A.shape}, expected {(uu.shape[0], n, n)}")
            _check_metzler(A)
        phi = rk4_integrate(lambda P, _u: A @ P, np.broadcast_to(np.eye(n), A.shape), None, tau, nint)
        return _rowwise_matvec(phi[inv.ravel()], r)
    growth.state_independent = True  # L depends on u only: build_abstraction evaluates it per input
    return growth


def _check_metzler(A: np.ndarray) -> None:
    n = A.shape[-1]
    off = ~np.eye(n, dtype=bool)
    if np.any(A[..., off] < 0) or not np.all(np.isfinite(A)):
        raise SimgapError("growth: L must be finite with off-diagonal entries >= 0 (bounds on |dF_i/dx_j|)")


def _input_rows(u: np.ndarray):
    """(rows, index of each row of ``u`` among them): :func:`_unique_rows`, or, when the rows of
    ``u`` repeat with a period p (u[i] == u[i mod p], as in the abstraction's blocks of whole
    cells with all inputs each), (u[:p], i mod p) from two vectorized comparisons instead of a
    sort (the rows of u[:p] are then not necessarily distinct). Every row of ``u`` equals its
    representative exactly, so a function of the row gives the same bits either way."""
    B = u.shape[0]
    if B > 1 and u.ndim == 2 and u.shape[1]:
        same = u[1:, 0] == u[0, 0]  # column by column (a reduction along short rows is slow)
        for d in range(1, u.shape[1]):
            same &= u[1:, d] == u[0, d]
        rep = np.flatnonzero(same)
        if rep.size:
            p = int(rep[0]) + 1
            if np.array_equal(u[p:], u[:B - p]):
                return u[:p], np.tile(np.arange(p, dtype=np.intp), -(-B // p))[:B]
    return _unique_rows(u)


def _unique_rows(u: np.ndarray):
    """(distinct rows, index of each row's distinct row): a 1-D sort of a fixed projection of
    the rows (much faster than ``np.unique(axis=0)``), checked exactly afterwards."""
    key = u @ np.cos(np.arange(1, u.shape[1] + 1))  # a fixed direction, no two inputs alike in practice
    _, first, inv = np.unique(key, return_index=True, return_inverse=True)
    uu = u[first]
    if not np.array_equal(uu[inv], u):  # two distinct inputs projected alike: the exact way
        return np.unique(u, axis=0, return_inverse=True)
    return uu, inv


def _rowwise_matvec(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(B, n, n) @ (B, n) row by row; n^2 vector operations (n is small) beat einsum's loop."""
    out = np.empty_like(v)
    for i in range(v.shape[1]):
        acc = A[:, i, 0] * v[:, 0]
        for j in range(1, v.shape[1]):
            acc += A[:, i, j] * v[:, j]
        out[:, i] = acc
    return out

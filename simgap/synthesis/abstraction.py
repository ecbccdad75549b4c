"""Finite abstraction of x+ in f(x, u) + [-gamma(x, u), gamma(x, u)] on a uniform grid.

For every cell (center c, radius eta/2) and every input u the successor set is over-approximated
by a box, as in SCOTS v2's ``compute_gb``:

    r_0   = eta/2 + z,      z = guard * eta          (guard = 1e-10: SCOTS's rounding guard)
    r_j+1 = growth(r_j, c_j, u) + gamma_sup_j        (gamma_sup_j = sup of gamma over [c_j - r_j, c_j + r_j])
    c_j+1 = f(c_j, u)                                (the nominal image of the center)

for j = 0 .. hold-1 (``hold`` = number of sampling periods the input is held per abstract step;
default 1). The successor cells are the integer box

    lo_d = floor((c_d - r_d - z_d - first_d + eta_d/2) / eta_d),  hi_d = same with c + r + z

and the pair is *out of domain* (its only successor is the losing "outside" state) when
``c - r - z <= first - eta/2`` or ``c + r + z >= last + eta/2`` in a non-periodic dimension.
Periodic dimensions wrap. gamma_sup is taken over the *wrapped pieces* of the box in periodic
dimensions (:func:`gamma_upper_wrapped`): cells are centred at lo + i*eta, so the seam cell
holds theta in [pi - eta/2, pi) and [-pi, -pi + eta/2), and gamma, a polynomial in theta, is not
periodic: bounding it over the raw interval [-pi - eta/2, -pi + eta/2] was unsound. With ``hold > 1`` the hull of the intermediate boxes (j = 1..hold-1)
is also kept, so games can require the state to stay in the allowed cells *between* abstract
steps too (sound against obstacles passed through while the input is held).

Transitions are stored implicitly as per-(cell, input) index boxes, as offsets relative to the
cell's multi-index (``int8`` when they fit). When f(x, u) - x and the growth bound do not depend
on some dimensions (translation invariance, e.g. the planar position of a vehicle), pass them as
``invariant_dims``: the boxes are then computed and stored once per *class* of cells (cells that
agree in the other dimensions) and shared; the gap is then bounded over the whole grid extent in
those dimensions (sound, and exact for gaps that do not depend on them). This is checked
numerically on a sample.

Two ways to get an abstract step of k sampling periods
------------------------------------------------------
1. The default, and the only one the certificate covers: ``hold = 1`` with
   ``system.with_steps(k)`` and a gap certified at the k-step sampling time (data collected with
   the simulator run for k*tau, the input held). Theorem 1 then bounds |E fhat_k(x,u) - f_k(x,u)|
   for the whole abstract step.
2. ``hold = k`` with a one-step system and a one-step gap, only with ``compose_hold=True``: the
   per-step bounds are composed k times (the gap is added k times and grown by the dynamics each
   time). This is sound for a worst-case disturbance x+ in f(x,u) + [-gamma, gamma], but *not*
   for the certificate's first-moment statement: Theorem 1 bounds E fhat(x,u) for one
   deterministic x, and E fhat(fhat(x,u),u) is not fhat applied to a mean when f is nonlinear
   (fhat = (x1 + tau cos x3, x3 + w), w ~ N(0, s^2): the one-step gap is 0, the two-step mean
   differs from f(f(x)) by tau cos(x3)(exp(-s^2/2) - 1)). The controller records the choice
   (``hold_mode``). Without a gap, ``hold = k`` composes the nominal model and is exact.
"""


from __future__ import annotations

import inspect
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from ..errors import SimgapError
from ..systems import System
from .corner_index import CornerIndex
from .grid import UniformGrid
from ..jit import expected_work, use_compiled

GrowthFn = Callable[[np.ndarray, np.ndarray, np.ndarray, float], np.ndarray]

#: label of a composed hold (controller files, summaries): what it is and what it is not
COMPOSED_HOLD_LABEL = ("composed: a one-period gap composed over the held periods (worst-case disturbance "
                       "reading; not covered by the certificate's first-moment guarantee for a nonlinear f)")

_OFF_LIMIT = 32000  # offsets are clipped to +-_OFF_LIMIT (sound: grids are smaller than that)


# ---------------------------------------------------------------------------------------
# gap bounds
# ---------------------------------------------------------------------------------------

class ConstantGap:
    """A gap bound gamma(x, u) = const (per state dimension), for tests and simple designs."""

    def __init__(self, gamma):
        g = np.asarray(gamma, dtype=float).ravel()
        if g.size == 0 or not np.all(np.isfinite(g)) or np.any(g < 0):
            raise SimgapError(f"gap: constant gamma must be finite and >= 0, got {g.tolist()}")
        self.gamma = g

    def gamma_upper_box(self, lo: np.ndarray, hi: np.ndarray, u: np.ndarray) -> np.ndarray:
        """sup of gamma over the box [lo, hi] x {u}: the constant, (B, n)."""
        return np.broadcast_to(self.gamma, np.shape(lo)).copy()

    def describe(self) -> dict:
        return {"kind": "constant", "gamma": self.gamma.tolist()}


def as_gap(gap, system: System):
    """Normalize ``gap`` (None, a constant vector, or an object with ``gamma_upper_box``).

    Checks what can be checked against ``system``: state dimension, system name and sampling
    steps when the gap object exposes them (``n``, ``system_name``/``system``, ``steps``), and
    the shape, finiteness and sign of gamma on one box.
    """
    if gap is None:
        return None
    if not hasattr(gap, "gamma_upper_box"):
        g = np.asarray(gap, dtype=float).ravel()
        if g.size == 1:
            g = np.full(system.n, float(g[0]))
        if g.size != system.n:
            raise SimgapError(f"gap: constant gamma has {g.size} components, system {system.name!r} has {system.n} states")
        return ConstantGap(g)
    n = getattr(gap, "n", None)
    if n is not None and int(n) != system.n:
        raise SimgapError(f"gap: the certificate is for {int(n)} states, system {system.name!r} has {system.n}")
    name = getattr(gap, "system_name", None)
    if name is None:
        sysattr = getattr(gap, "system", None)
        name = sysattr.get("name") if isinstance(sysattr, dict) else (sysattr if isinstance(sysattr, str) else
                                                                      getattr(sysattr, "name", None))
    if name is not None and name != system.name:
        raise SimgapError(f"gap: the certificate is for system {name!r}, not {system.name!r}")
    steps = getattr(gap, "steps", None)
    if steps is not None and int(steps) != system.steps:
        raise SimgapError(f"gap: the certificate was certified at steps={int(steps)}, the system uses "
                          f"steps={system.steps}; pass --steps {int(steps)} or a matching certificate")
    lo = system.x_lo[None, :]
    hi = system.x_hi[None, :]
    region = getattr(gap, "region", None)
    if region is not None:  # a local certificate: the sample evaluation stays where gamma holds
        lo, hi = np.asarray(region[0], float)[None, :], np.asarray(region[1], float)[None, :]
        boxes = getattr(gap, "region_boxes", None)
        if boxes is not None:  # a cover along a tube: gamma holds in its boxes only (the hull is refused)
            lo, hi = np.asarray(boxes[0][:1], float), np.asarray(boxes[1][:1], float)
    try:
        g = np.asarray(gap.gamma_upper_box(lo, hi, system.inputs[:1]), dtype=float)
    except SimgapError:
        raise
    except Exception as e:  # a wrong-dimension certificate typically fails inside its own algebra
        raise SimgapError(f"gap: evaluating the certificate on system {system.name!r} failed ({e})") from e
    if g.shape != (1, system.n):
        raise SimgapError(f"gap: gamma_upper_box returned shape {g.shape}, expected (1, {system.n}) "
                          f"for system {system.name!r}")
    if not np.all(np.isfinite(g)) or np.any(g < 0):
        raise SimgapError(f"gap: gamma must be finite and >= 0, got {g.ravel().tolist()}")
    return gap


def check_hold(hold: int, gap, compose_hold: bool) -> None:
    """Refuse composing a one-period gap over ``hold > 1`` periods unless asked to explicitly."""
    if gap is not None and hold > 1 and not compose_hold:
        raise SimgapError(
            f"holding the input for {hold} periods would compose a one-period gap {hold} times, which the "
            f"certificate does not cover (Theorem 1 bounds the mean of one step from a known state); certify "
            f"at the abstraction step instead (collect with steps={hold} x the current steps and synthesize "
            f"with --steps and --hold 1), or pass compose_hold=True / --compose-hold to accept the composed "
            f"bound as a worst-case disturbance (labelled in the controller)")


def certified_input_mask(system: System, gap) -> np.ndarray:
    """(M,) bool: which rows of ``system.inputs`` the gap is certified for.

    A certificate bounds gamma only at the inputs its data covered (``gap.inputs``, (M', m));
    gamma at any other input is not certified (the Lipschitz terms cover x, not u). A gap
    without an input set (a constant or user-given bound) covers every input. A certificate
    (an object with ``check_system``) that records no input set is refused.
    """
    M = system.inputs.shape[0]
    if gap is None:
        return np.ones(M, dtype=bool)
    U_cert = getattr(gap, "inputs", None)
    if U_cert is None:
        if hasattr(gap, "check_system"):
            raise SimgapError("the certificate records no input set, so the inputs its gamma holds for are "
                              "unknown; re-certify the data set with this version")
        return np.ones(M, dtype=bool)
    U_cert = np.atleast_2d(np.asarray(U_cert, dtype=float))
    if U_cert.shape[1] != system.m:
        raise SimgapError(f"the certificate's inputs have {U_cert.shape[1]} components, system "
                          f"{system.name!r} has {system.m}")
    U = system.inputs
    keep = np.empty(M, dtype=bool)
    B = max(1, (1 << 20) // max(1, U_cert.size))
    for s in range(0, M, B):  # blocks of inputs bound the (B, M', m) comparison
        u = U[s:s + B, None, :]
        keep[s:s + B] = np.any(np.all(np.abs(u - U_cert[None]) <= 1e-9 * (1.0 + np.abs(u)), axis=2), axis=1)
    return keep


def uncertified_inputs_message(system: System, keep: np.ndarray, limit: int = 5) -> str:
    """Names the inputs of ``system`` outside the certified set (at most ``limit`` of them)."""
    bad = system.inputs[~keep]
    shown = ", ".join(str(np.round(u, 6).tolist()) for u in bad[:limit])
    more = f" and {len(bad) - limit} more" if len(bad) > limit else ""
    return (f"{len(bad)} of the {len(keep)} inputs of system {system.name!r} are not certified by the gap "
            f"({', '.join(system.input_names)} = {shown}{more}); gamma holds only at the inputs its data covered")


def wrapped_pieces(lo: np.ndarray, hi: np.ndarray, grid: UniformGrid):
    """Split boxes [lo, hi] (B, n) into boxes inside the canonical range of the periodic dims.

    gamma is a function of the canonical angle in [grid.lo_d, grid.hi_d) (the certificate's data
    lie there; a polynomial in theta is not periodic), so a box that sticks out of that range,
    e.g. the seam cell [-pi - eta/2, -pi + eta/2], must be bounded over its wrapped pieces
    [pi - eta/2, pi] and [-pi, -pi + eta/2], not over the raw interval. Returns
    ``(plo, phi, owner)``: the pieces (P, n) and the row of [lo, hi] each belongs to (the first B
    pieces are the rows themselves, shifted into range; boxes wider than a period become the
    whole range).
    """
    plo, phi = np.array(lo, dtype=float), np.array(hi, dtype=float)
    owner = np.arange(plo.shape[0])
    for d in grid.periodic:
        base, P = grid.lo[d], grid.hi[d] - grid.lo[d]
        width = phi[:, d] - plo[:, d]
        full = ~(width < P)  # also NaN widths: the whole range
        a = base + np.mod(plo[:, d] - base, P)
        b = a + width
        wraps = ~full & (b > base + P)
        lo2, hi2 = plo[wraps].copy(), phi[wraps].copy()
        lo2[:, d], hi2[:, d] = base, b[wraps] - P
        plo[:, d] = np.where(full, base, a)
        phi[:, d] = np.where(full, base + P, np.minimum(b, base + P))
        plo, phi = np.concatenate([plo, lo2]), np.concatenate([phi, hi2])
        owner = np.concatenate([owner, owner[wraps]])
    return plo, phi, owner


def gamma_upper_wrapped(gap, lo: np.ndarray, hi: np.ndarray, u: np.ndarray, grid: UniformGrid) -> np.ndarray:
    """Sound sup of gamma over the boxes [lo, hi] x {u} (B, n) on a grid with periodic dims.

    The sup over the union of the wrapped pieces (:func:`wrapped_pieces`) of each box: one
    ``gap.gamma_upper_box`` call over all pieces.
    """
    if not grid.periodic:
        return np.asarray(gap.gamma_upper_box(lo, hi, u), dtype=float)
    plo, phi, owner = wrapped_pieces(lo, hi, grid)
    g = np.asarray(gap.gamma_upper_box(plo, phi, np.asarray(u)[owner]), dtype=float)
    B = lo.shape[0]
    out = g[:B].copy()
    np.maximum.at(out, owner[B:], g[B:])
    return out


def describe_gap(gap) -> Optional[dict]:
    """Provenance of a gap object for controller metadata (JSON-ready)."""
    if gap is None:
        return None
    for attr in ("describe", "provenance", "to_dict"):
        fn = getattr(gap, attr, None)
        if callable(fn):
            try:
                d = fn()
                return {"type": type(gap).__name__, "info": _jsonable(d)}
            except Exception:  # provenance is best effort; the controller is still valid
                pass
    return {"type": type(gap).__name__}


def _jsonable(d):
    import json
    try:
        json.dumps(d)
        return d
    except TypeError:
        return json.loads(json.dumps(d, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


# ---------------------------------------------------------------------------------------
# the abstraction
# ---------------------------------------------------------------------------------------

@dataclass
class Abstraction:
    """Implicit transition relation: one index box per (cell class, input).

    Attributes
    ----------
    grid : UniformGrid
    inputs : (M, m) array
    class_dims : tuple of int
        Dimensions that distinguish cell classes (the complement of ``invariant_dims``).
    off_lo, off_hi : (K, M, n) int8/int16
        Successor box of cell c under input u: ``mi(c) + off_lo[k(c), u] .. mi(c) + off_hi[k(c), u]``
        (inclusive, multi-index units; may leave the grid in bounded dims = out of domain).
    ok : (K, M) bool
        False where the image is not finite or already out of domain in a class dimension.
    mid_lo, mid_hi : (K, M, n) or None
        Hull of the intermediate boxes when ``hold > 1``.
    corner_index : CornerIndex or None
        Predecessor index (one class per cell and small boxes only; built with the abstraction,
        as SCOTS builds its predecessor lists).
    """

    grid: UniformGrid
    inputs: np.ndarray
    class_dims: tuple
    off_lo: np.ndarray
    off_hi: np.ndarray
    ok: np.ndarray
    mid_lo: Optional[np.ndarray] = None
    mid_hi: Optional[np.ndarray] = None
    hold: int = 1
    seconds: float = 0.0
    info: dict = field(default_factory=dict)
    corner_index: Optional[CornerIndex] = None

    @property
    def n_classes(self) -> int:
        return self.off_lo.shape[0]

    @property
    def n_inputs(self) -> int:
        return self.inputs.shape[0]

    def cell_class(self, mi: np.ndarray) -> np.ndarray:
        """(B, n) multi-indices -> (B,) class ids."""
        if not self.class_dims:
            return np.zeros(mi.shape[0], dtype=np.int64)
        cd = list(self.class_dims)
        shape = [self.grid.shape[d] for d in cd]
        return np.ravel_multi_index(tuple(mi[:, d] for d in cd), shape)

    def offset_range(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-dimension min of off_lo and max of off_hi over usable pairs (for frontier search)."""
        if not self.ok.any():
            z = np.zeros(self.grid.n, dtype=np.int64)
            return z, z
        lo = self.off_lo[self.ok].min(axis=0).astype(np.int64)
        hi = self.off_hi[self.ok].max(axis=0).astype(np.int64)
        if self.mid_lo is not None:
            lo = np.minimum(lo, self.mid_lo[self.ok].min(axis=0))
            hi = np.maximum(hi, self.mid_hi[self.ok].max(axis=0))
        return lo, hi

    def successor_box(self, x: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Successor index box of the cells of states x (B, n) under inputs j (B,).

        Returns ``(lo, hi, ok)``: inclusive multi-index bounds (periodic dims not reduced modulo
        the grid size) and the usable-pair mask.
        """
        mi, _ = self.grid.x_to_multi(x)
        k = self.cell_class(mi)
        j = np.asarray(j, dtype=np.int64)
        return mi + self.off_lo[k, j], mi + self.off_hi[k, j], self.ok[k, j]

    def contains(self, x: np.ndarray, j: np.ndarray, x_next: np.ndarray) -> np.ndarray:
        """(B,) bool: x_next lies in a cell of the successor box of (cell of x, input j).

        The abstraction is sound for a successor x_next when this holds for every usable pair.
        """
        lo, hi, _ = self.successor_box(x, j)
        v = np.floor((np.asarray(x_next, dtype=float) - self.grid.first) / self.grid.eta + 0.5)
        shape = np.array(self.grid.shape)
        pm = self.grid.periodic_mask
        inside = (v >= lo) & (v <= hi)
        # periodic dims: compare modulo the number of cells (a box of >= n_d cells is the circle)
        wrapped = (np.mod(v - lo, shape) <= hi - lo) | (hi - lo + 1 >= shape)
        return np.all(np.where(pm, wrapped, inside), axis=1)

    def nbytes(self) -> int:
        b = self.off_lo.nbytes + self.off_hi.nbytes + self.ok.nbytes
        if self.mid_lo is not None:
            b += self.mid_lo.nbytes + self.mid_hi.nbytes
        if self.corner_index is not None:
            b += self.corner_index.nbytes()
        return b


def state_independent(growth: GrowthFn) -> GrowthFn:
    """Declare that ``growth(r, x, u, tau)`` does not depend on x (returns ``growth``, marked).

    :func:`build_abstraction` then evaluates it once per distinct (r, u) instead of once per
    (cell, input) pair: once per input when the radius is the same for every cell (no gap or a
    constant gap). :func:`~simgap.runge_kutta.rk4_growth` and the system's Jacobian
    bound are state-independent already. Declaring it for a growth that does depend on x is
    wrong (the boxes would be those of an arbitrary cell)."""
    try:
        growth.state_independent = True
    except AttributeError:  # a bound method or a builtin: marked through a wrapper
        inner = growth

        def growth(r, x, u, tau):
            return inner(r, x, u, tau)
        growth.state_independent = True
    return growth


def growth_function(system: System, growth: Optional[GrowthFn]) -> GrowthFn:
    """The growth bound to use: ``growth`` checked to take (r, x, u, tau), else the system's.

    A growth written for the earlier signature ``growth(r, x, u)`` (before tau was passed) is
    still accepted, with a DeprecationWarning, when tau is the system's base period (steps = 1,
    the only period such a function can have been written for); at other periods it is refused.
    """
    if growth is None:
        radius_post = getattr(system.step, "radius_post", None)  # a system file's bounds.growth
        if radius_post is not None:
            return radius_post(system.steps)
        if system.jacobian_bound is None:
            raise SimgapError(f"system {system.name!r} has no jacobian_bound; pass a growth function")
        return state_independent(lambda r, x, u, tau: system.growth_bound(r, u))  # uses system.tau
    if not callable(growth):
        raise SimgapError("growth must be a callable growth(r, x, u, tau)")
    try:
        inspect.signature(growth).bind(0, 0, 0, 0)
    except TypeError:
        try:
            inspect.signature(growth).bind(0, 0, 0)
        except TypeError:
            old = False
        else:
            old = system.steps == 1
        if not old:
            raise SimgapError("growth must accept (r, x, u, tau): it is called with the sampling period "
                              f"tau = system.tau ({system.tau:g} s for {system.name!r}), which changes with "
                              "with_steps(k)") from None
        import warnings
        warnings.warn("growth(r, x, u) without tau is deprecated: write growth(r, x, u, tau), tau the sampling "
                      "period system.tau (it changes with system.with_steps(k))", DeprecationWarning, stacklevel=3)
        wrapped = lambda r, x, u, tau: growth(r, x, u)  # noqa: E731
        wrapped.state_independent = getattr(growth, "state_independent", False)
        return wrapped
    except ValueError:  # builtins without a signature: trust the call
        pass
    return growth


def build_abstraction(system: System, grid: UniformGrid, *, growth: Optional[GrowthFn] = None,
                      gap=None, hold: int = 1, invariant_dims=(), guard: float = 1e-10,
                      block: int = 1 << 14, check_invariance: bool = True,
                      compose_hold: bool = False, on_progress=None) -> Abstraction:
    """Compute the successor boxes of all (cell, input) pairs (see the module docstring).

    Parameters
    ----------
    system : System
        Nominal model; ``system.f`` is one sampling period tau = steps * base_tau.
    grid : UniformGrid
        State grid (normally over system.x_lo .. x_hi).
    growth : callable, optional
        ``growth(r (B,n), x (B,n), u (B,m), tau) -> (B,n)``: radius of the image of the box
        [x - r, x + r] under f around f(x, u) after the sampling period tau = system.tau [s]
        (SCOTS ``radius_post``; see :func:`~simgap.runge_kutta.rk4_growth`).
        Default: the system's Jacobian-based ``growth_bound``.
    gap : None, constant vector, or object with ``gamma_upper_box(lo, hi, u) -> (B, n)``
        Bound on the simulation gap gamma (state units per sampling period).
    hold : int
        Sampling periods per abstract step with the input held (>= 1).
    invariant_dims : tuple of int
        Dimensions in which f(x, u) - x and the growth bound do not depend on x.
    guard : float
        Relative rounding guard z = guard * eta (SCOTS: 1e-10).
    compose_hold : bool
        Allow ``hold > 1`` with a gap (composes a one-period gap; module docstring, way 2).
    on_progress : callable, optional
        ``on_progress(classes_done, classes)`` after every block of classes.
    """
    t0 = time.perf_counter()
    if int(hold) != hold or hold < 1:
        raise SimgapError(f"hold must be an integer >= 1, got {hold}")
    hold = int(hold)
    n = grid.n
    if n != system.n:
        raise SimgapError(f"grid has {n} dimensions, system {system.name!r} has {system.n}")
    growth = growth_function(system, growth)
    gap = as_gap(gap, system)
    check_hold(hold, gap, compose_hold)
    keep = certified_input_mask(system, gap)
    if not keep.all():
        raise SimgapError(uncertified_inputs_message(system, keep) + "; restrict system.inputs (synthesize "
                          "does) or certify these inputs")
    inv = tuple(sorted(set(int(d) for d in invariant_dims)))
    if any(d < 0 or d >= n for d in inv):
        raise SimgapError(f"invariant_dims {inv} out of range for n={n}")
    class_dims = tuple(d for d in range(n) if d not in inv)
    U = system.inputs
    M = U.shape[0]
    eta = grid.eta
    z = guard * eta
    pmask = grid.periodic_mask

    # class representatives: invariant dims at index 0 (computed per block: with one class per
    # cell a (K, n) table would be as large as the grid)
    cshape = [grid.shape[d] for d in class_dims]
    K = int(np.prod(cshape)) if class_dims else 1

    def rep_mi(k: np.ndarray) -> np.ndarray:
        mi = np.zeros((k.size, n), dtype=np.int32)
        if class_dims:
            for d, c in zip(class_dims, np.unravel_index(k, cshape)):
                mi[:, d] = c
        return mi

    if inv and check_invariance:
        _check_invariance(system, grid, growth, U, rep_mi, K, inv, hold)

    # int8 until an offset does not fit, then int16 (one copy; no int16 table converted at the end)
    off = {"lo": np.empty((K, M, n), dtype=np.int8), "hi": np.empty((K, M, n), dtype=np.int8)}
    ok = np.empty((K, M), dtype=bool)
    mid_lo = np.empty((K, M, n), dtype=np.int16) if hold > 1 else None
    mid_hi = np.empty((K, M, n), dtype=np.int16) if hold > 1 else None
    inv_mask = np.zeros(n, dtype=bool)
    inv_mask[list(inv)] = True
    dom_lo, dom_hi = grid.domain_lo, grid.domain_hi

    # blocks of whole classes, all inputs each (pairs in (class, input) order, as stored)
    cb = max(1, block // M)
    j_full = np.tile(np.arange(M), cb)
    u_full = U[j_full]
    # radii r_0 .. r_hold per input, when they are the same for every cell: a growth declared
    # state-independent and a gap that does not depend on the box (one evaluation per input)
    radii = None
    if getattr(growth, "state_independent", False) and (gap is None or isinstance(gap, ConstantGap)):
        radii = [np.broadcast_to(eta / 2 + z, (M, n)).copy()]
        x_any = np.broadcast_to(grid.first, (M, n)).copy()  # not used by the growth (declared)
        with np.errstate(all="ignore"):
            for step in range(hold):
                g = gap.gamma_upper_box(x_any, x_any, U) if gap is not None else 0.0
                radii.append(np.asarray(growth(radii[-1], x_any, U, system.tau), dtype=float) + g)
        radii = [np.tile(rr, (cb, 1)) for rr in radii]

    disp_needed = bool(pmask.any()) or hold > 1
    kernel = None
    if radii is not None and gap is None and hold == 1 and not pmask.any():
        from .grid_kernel import grid_kernel  # a system file's boxes in one compiled pass
        kernel = grid_kernel(system, K * M * system.steps)
    if kernel is not None:
        kernel.boxes(system, grid, radii[1][:M], z, class_dims, off, ok, _OFF_LIMIT, on_progress)
    # the work declared, so that a system step with a compiled twin knows whether it pays (jit.py)
    with expected_work(K * M * hold * system.steps):
        for s in range(0, K if kernel is None else 0, cb):  # blocks bound the memory
            e = min(K, s + cb)
            P = (e - s) * M
            j, u = j_full[:P], u_full[:P]
            mi_c = rep_mi(np.arange(s, e))
            mi = np.repeat(mi_c, M, axis=0)
            x0 = np.repeat(grid.multi_to_points(mi_c), M, axis=0)  # per cell, then per pair (same values)
            x = x0
            r = radii[0][:P] if radii is not None else np.broadcast_to(eta / 2 + z, x.shape).copy()
            disp = np.zeros_like(x) if disp_needed else None
            if hold > 1:
                mlo = np.full(x.shape, np.inf)
                mhi = np.full(x.shape, -np.inf)
            with np.errstate(all="ignore"):
                for step in range(hold):
                    if radii is not None:
                        r_new = radii[step + 1][:P]
                    else:
                        if gap is not None:
                            blo, bhi = x - r, x + r
                            if inv:  # bound gamma over the whole extent of the shared dimensions (sound)
                                blo[:, inv_mask] = dom_lo[inv_mask]
                                bhi[:, inv_mask] = dom_hi[inv_mask]
                            g = gamma_upper_wrapped(gap, blo, bhi, u, grid)
                        else:
                            g = 0.0
                        r_new = np.asarray(growth(r, x, u, system.tau), dtype=float) + g
                    x_new = system.f(x, u)
                    if disp_needed:
                        disp = disp + system.diff(x_new, x) if pmask.any() else x_new - x0
                    x, r = x_new, r_new
                    if step < hold - 1:
                        mlo = np.minimum(mlo, disp - r)
                        mhi = np.maximum(mhi, disp + r)
                if not pmask.any() and use_compiled(1 << 62):  # numba already loaded (or forced)
                    _boxes_compiled(x, r, z, eta, grid, dom_lo, dom_hi, mi, inv_mask, off, ok, s, e)
                    x = r = None
                good = np.ones(P, dtype=bool)
                out = np.zeros(P, dtype=bool)
                for d in range(n if x is not None else 0):  # column by column, in place (n is 2-3)
                    xd, rd, zd, ed = x[:, d], r[:, d], z[d], eta[d]
                    good &= np.isfinite(xd)
                    good &= np.isfinite(rd)
                    if pmask[d]:  # relative displacement (the image may have wrapped)
                        _store(off, "lo", s, e, d, _cell_offset((disp[:, d] - rd - zd) / ed + 0.5, 0))
                        _store(off, "hi", s, e, d, _cell_offset((disp[:, d] + rd + zd) / ed + 0.5, 0))
                        continue
                    # SCOTS's formula in absolute coordinates (bit-for-bit parity)
                    left, right = xd - rd - zd, xd + rd + zd
                    if not inv_mask[d]:  # SCOTS's out-of-domain test, exact in the class dimensions
                        out |= left <= dom_lo[d]
                        out |= right >= dom_hi[d]
                    _store(off, "lo", s, e, d, _cell_offset((left - grid.first[d] + ed / 2) / ed, mi[:, d]))
                    _store(off, "hi", s, e, d, _cell_offset((right - grid.first[d] + ed / 2) / ed, mi[:, d]))
                if x is not None:
                    ok[s:e] = (good & ~out).reshape(e - s, M)
                if hold > 1:
                    ml = np.floor(np.nan_to_num((mlo - z) / eta + 0.5))
                    mh = np.floor(np.nan_to_num((mhi + z) / eta + 0.5))
                    mid_lo[s:e] = np.clip(ml, -_OFF_LIMIT, _OFF_LIMIT).reshape(e - s, M, n)
                    mid_hi[s:e] = np.clip(mh, -_OFF_LIMIT, _OFF_LIMIT).reshape(e - s, M, n)
            if on_progress is not None:
                on_progress(e, K)

    def small(a):
        if a is None:
            return None
        if a.size == 0 or (a.min() >= -128 and a.max() <= 127):
            return a.astype(np.int8)
        return a

    ab = Abstraction(grid=grid, inputs=U, class_dims=class_dims, off_lo=off["lo"],
                     off_hi=off["hi"], ok=ok, mid_lo=small(mid_lo), mid_hi=small(mid_hi),
                     hold=hold)
    t1 = time.perf_counter()
    if not inv and K * M <= CornerIndex.MAX_PAIRS:  # one class per cell: the predecessor index
        ab.corner_index = CornerIndex.build(ab)
    ab.seconds = time.perf_counter() - t0
    ab.info = {"invariant_dims": list(inv), "classes": K, "guard": guard, "hold": hold,
               "seconds_index": time.perf_counter() - t1}
    return ab


def _boxes_compiled(x, r, z, eta, grid, dom_lo, dom_hi, mi, inv_mask, off, ok, s, e) -> None:
    """The block's offsets and valid flags by :func:`simgap.synthesis.kernels.box_offsets` (the
    numpy loop's operations, per pair; no periodic dimension), written straight into the int8
    tables; when an offset does not fit, the tables become int16 (as :func:`_store` does) and
    the block is written again."""
    from .kernels import box_offsets
    P, n = x.shape
    good = np.empty(P, dtype=bool)
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    args = (f64(x), f64(r), f64(z), f64(eta), f64(grid.first), f64(dom_lo), f64(dom_hi),
            np.ascontiguousarray(mi), np.asarray(inv_mask, dtype=np.bool_), float(_OFF_LIMIT))
    for _ in range(2):
        lo, hi = off["lo"][s:e].reshape(P, n), off["hi"][s:e].reshape(P, n)  # views (contiguous)
        vmin, vmax = box_offsets(*args, lo, hi, good)
        info = np.iinfo(lo.dtype)
        if info.min <= vmin and vmax <= info.max:
            break
        for k in off:  # int8 -> int16 (+-_OFF_LIMIT fits); the block is written again
            off[k] = off[k].astype(np.int16)
    ok[s:e] = good.reshape(e - s, -1)


def _store(off: dict, side: str, s: int, e: int, d: int, v: np.ndarray) -> None:
    """Write the offsets ``v`` (float, integral, within +-_OFF_LIMIT) of classes s..e, dimension d,
    into ``off[side]``; an int8 table that cannot hold them becomes int16 (both sides alike)."""
    tab = off[side]
    if tab.dtype == np.int8 and v.size and (v.min() < -128 or v.max() > 127):
        for k in off:
            off[k] = off[k].astype(np.int16)
        tab = off[side]
    tab[s:e].reshape(-1, tab.shape[2])[:, d] = v  # tab[s:e] is contiguous: a view


def _cell_offset(v: np.ndarray, base) -> np.ndarray:
    """floor(v) - base, clipped to +-_OFF_LIMIT (NaN -> 0 - base), in place in ``v``."""
    np.floor(v, out=v)
    v[np.isnan(v)] = 0.0
    np.clip(v, -_OFF_LIMIT, _OFF_LIMIT, out=v)
    v -= base
    return np.clip(v, -_OFF_LIMIT, _OFF_LIMIT, out=v)


def _check_invariance(system, grid, growth, U, rep_mi, K, inv, hold, samples: int = 64):
    """Check on a seeded sample that f(x,u) - x and the growth bound ignore the invariant dims."""
    rng = np.random.default_rng(0)
    M = U.shape[0]
    k = rng.integers(0, K, samples)
    j = rng.integers(0, M, samples)
    mi = rep_mi(k)
    mi2 = mi.copy()
    for d in inv:
        mi2[:, d] = rng.integers(0, grid.shape[d], samples)
    x1, x2 = grid.multi_to_points(mi), grid.multi_to_points(mi2)
    u = U[j]
    r = np.broadcast_to(grid.eta / 2, x1.shape).copy()
    d1 = system.diff(system.f(x1, u), x1)
    d2 = system.diff(system.f(x2, u), x2)
    g1, g2 = growth(r, x1, u, system.tau), growth(r, x2, u, system.tau)
    scale = 1e-9 * (1 + np.abs(grid.domain_hi - grid.domain_lo))
    if np.any(np.abs(d1 - d2) > scale) or np.any(np.abs(np.asarray(g1) - np.asarray(g2)) > scale):
        raise SimgapError(f"invariant_dims {list(inv)}: f(x,u) - x or the growth bound of system "
                          f"{system.name!r} depends on these dimensions; do not declare them invariant")

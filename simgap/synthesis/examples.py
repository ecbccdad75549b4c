"""Reference problems: the SCOTS v2 vehicle example (reach-avoid, parity checks), and two systems
without translation invariance for the generic path (``bench/bench_synthesis_generic.py``).

Everything follows SCOTS v2 ``examples/vehicle/vehicle.cc`` (Reissig, Weber & Rungger, 2017)
operation by operation, so the abstraction agrees with SCOTS bit for bit where it matters:

* x = (x, y, theta), u = (v, steering), tau = 0.3, fixed-step RK4 with 10 intermediate steps;
* rhs: alpha = atan(tan(u2)/2); x' = u1 cos(alpha + theta)/cos(alpha),
  y' = u1 sin(alpha + theta)/cos(alpha), theta' = u1 tan(u2);
* growth bound (radius_post): c = |u1| sqrt(tan(u2)^2/4 + 1); r1 += c r3 tau; r2 += c r3 tau;
* state grid [0,10] x [0,10] x [-3.5,3.5], eta = 0.2 (51 x 51 x 35 points), no angle wrapping;
* input grid [-1,1]^2, eta = 0.3 (7 x 7 = 49 points);
* 15 obstacle boxes (cell rule: center within the box grown by eta/2 + 1e-10), target
  [9, 9.5] x [0, 0.5] (cells whose whole extent lies in it).
"""

from __future__ import annotations

import numpy as np

from pathlib import Path

from ..errors import SimgapError
from ..systems import System, input_grid
from .abstraction import state_independent
from .grid import UniformGrid
from .grid_kernel import file_step
from ..runge_kutta import compiled_args, rk4_growth, rk4_integrate, rk4_step
from .spec import Box, Spec

VEHICLE_TAU = 0.3
VEHICLE_NINT = 10
VEHICLE_ETA = (0.2, 0.2, 0.2)
VEHICLE_OBSTACLES = [
    [1, 1.2, 0, 9], [2.2, 2.4, 0, 5], [2.2, 2.4, 6, 10], [3.4, 3.6, 0, 9], [4.6, 4.8, 1, 10],
    [5.8, 6, 0, 6], [5.8, 6, 7, 10], [7, 7.2, 1, 10], [8.2, 8.4, 0, 8.5], [8.4, 9.3, 8.3, 8.5],
    [9.3, 10, 7.1, 7.3], [8.4, 9.3, 5.9, 6.1], [9.3, 10, 4.7, 4.9], [8.4, 9.3, 3.5, 3.7],
    [9.3, 10, 2.3, 2.5],
]
VEHICLE_TARGET = [9, 9.5, 0, 0.5]
#: SCOTS v2 results on this machine (see docs/synthesis.md)
SCOTS_VEHICLE_WINNING = 48018
SCOTS_VEHICLE_TRANSITIONS = 35_772_302


def _vehicle_rhs(x, u):
    """SCOTS's right-hand side as written there (every term evaluated per call)."""
    alpha = np.arctan(np.tan(u[:, 1]) / 2.0)
    ca = np.cos(alpha)
    dx = u[:, 0] * np.cos(alpha + x[:, 2]) / ca
    dy = u[:, 0] * np.sin(alpha + x[:, 2]) / ca
    dth = u[:, 0] * np.tan(u[:, 1])
    return np.stack([dx, dy, dth], axis=1)


def _vehicle_input_terms(u):
    """The terms of :func:`_vehicle_rhs` that depend on u only (held over tau): once per step."""
    alpha = np.arctan(np.tan(u[:, 1]) / 2.0)
    return alpha, np.cos(alpha), u[:, 0].copy(), u[:, 0] * np.tan(u[:, 1])


def _vehicle_rhs_prepared(x, p):
    """:func:`_vehicle_rhs` on the terms of :func:`_vehicle_input_terms`: the same operations on
    the same values (bit-identical), two transcendental functions per call instead of six."""
    alpha, ca, v, dth = p
    out = np.empty_like(x)
    a = alpha + x[:, 2]
    c = np.cos(a)
    c *= v
    c /= ca
    out[:, 0] = c
    s = np.sin(a, out=a)
    s *= v
    s /= ca
    out[:, 1] = s
    out[:, 2] = dth
    return out


#: SCOTS's examples as system files (package data): the built-in examples' compiled step is the C
#: kernel generated from them (:mod:`.grid_kernel`), the same bits as the numpy steps below
SCOTS_FILES = Path(__file__).with_name("scots")


def _vehicle_compiled(x, u, tau):
    """:func:`vehicle_step` by the kernel generated from ``scots/vehicle.toml`` (the same bits: the
    input terms by numpy once per distinct input, as the numpy path computes them)."""
    step = file_step(SCOTS_FILES / "vehicle.toml", force=True)
    if step is None:
        raise SimgapError("the vehicle's compiled step needs a C compiler ($CC, cc or gcc)")
    return step(x, u, tau)


def vehicle_step(x: np.ndarray, u: np.ndarray, tau: float) -> np.ndarray:
    """SCOTS ``runge_kutta_fixed4`` with 10 intermediate steps over tau, vectorized over rows
    (compiled when it pays: the kernel generated from ``scots/vehicle.toml``, the same bits)."""
    xu = compiled_args(x, u)
    step = file_step(SCOTS_FILES / "vehicle.toml", len(xu[0])) if xu is not None else None
    if step is not None:
        return step(xu[0], xu[1], float(tau))
    return rk4_integrate(_vehicle_rhs_prepared, x, u, tau, VEHICLE_NINT, prepare=_vehicle_input_terms)


@state_independent
def vehicle_growth(r: np.ndarray, x: np.ndarray, u: np.ndarray, tau: float = VEHICLE_TAU) -> np.ndarray:
    """SCOTS vehicle ``radius_post``: r (B,3) -> r+ over the sampling period tau (0.3 in SCOTS)."""
    c = np.abs(u[:, 0]) * np.sqrt(np.tan(u[:, 1]) * np.tan(u[:, 1]) / 4.0 + 1)
    r = np.array(r, dtype=float, copy=True)
    r[:, 0] = r[:, 0] + c * r[:, 2] * tau
    r[:, 1] = r[:, 1] + c * r[:, 2] * tau
    return r


def vehicle_inputs() -> np.ndarray:
    """The 49 SCOTS input grid points (multiples of 0.3 in [-1, 1]^2)."""
    ug = UniformGrid([-1.0, -1.0], [1.0, 1.0], 0.3)
    return ug.points(np.arange(ug.size))


def vehicle_system() -> System:
    """The SCOTS vehicle as a simgap System (no angle wrapping, as in SCOTS)."""
    return System(name="scots_vehicle", state_names=("x", "y", "theta"), input_names=("v", "steer"),
                  x_lo=(0.0, 0.0, -3.5), x_hi=(10.0, 10.0, 3.5), inputs=vehicle_inputs(),
                  base_tau=VEHICLE_TAU, step=vehicle_step, params={"nint": VEHICLE_NINT})


def vehicle_spec() -> Spec:
    """Reach the target box while avoiding the 15 obstacle boxes (theta unconstrained)."""
    inf = np.inf
    obs = tuple(Box([a, c, -inf], [b, d, inf]) for a, b, c, d in VEHICLE_OBSTACLES)
    a, b, c, d = VEHICLE_TARGET
    return Spec(kind="reach_avoid", target=Box([a, c, -inf], [b, d, inf]), obstacles=obs)


# ---------------------------------------------------------------------------------------
# systems without translation invariance (every cell has its own boxes)
# ---------------------------------------------------------------------------------------

#: boost DC-DC converter (SCOTS v2 ``examples/dcdc``): x = (i_l, v_c), two switch modes
DCDC_TAU = 0.5
DCDC_ETA = (2 / 4e3, 2 / 4e3)
_XC, _XL, _RC, _RL, _RO, _VS = 70.0, 3.0, 0.005, 0.05, 1.0, 1.0
_DCDC_A = np.array([
    [[-_RL / _XL, 0.0], [0.0, -1 / _XC / (_RO + _RC)]],
    [[-(_RL + _RO * _RC / (_RO + _RC)) / _XL, -_RO / (_RO + _RC) / _XL / 5],
     [5 * _RO / (_RO + _RC) / _XC, -1 / _XC / (_RO + _RC)]],
])
_DCDC_B = np.array([_VS / _XL, 0.0])


def _dcdc_mode(u: np.ndarray) -> np.ndarray:
    return (np.rint(u[:, 0]) == 2).astype(np.int64)


def _dcdc_rhs(x, u):
    m2 = u[:, 0] > 1.5  # the two modes written out (a per-row matrix product is slower)
    (a, _), (_, d) = _DCDC_A[0]
    (e, f), (g, h) = _DCDC_A[1]
    x0, x1 = x[:, 0], x[:, 1]
    out = np.empty_like(x)
    out[:, 0] = np.where(m2, e * x0 + f * x1, a * x0) + _DCDC_B[0]
    out[:, 1] = np.where(m2, g * x0 + h * x1, d * x1)
    return out


def _dcdc_rhs_mode(mode: int):
    """:func:`_dcdc_rhs` for the rows of one mode (1 or 2): the operations ``np.where`` keeps for
    them, in the same order (the same bits), without evaluating the other mode's."""
    if mode == 1:
        (a, _), (_, d) = _DCDC_A[0]

        def rhs(x, _u):
            out = np.empty_like(x)
            o0, o1 = out[:, 0], out[:, 1]
            np.multiply(x[:, 0], a, out=o0)
            o0 += _DCDC_B[0]
            np.multiply(x[:, 1], d, out=o1)
            return out
    else:
        (e, f), (g, h) = _DCDC_A[1]

        def rhs(x, _u):
            out = np.empty_like(x)
            o0, o1 = out[:, 0], out[:, 1]
            np.multiply(x[:, 0], e, out=o0)
            o0 += f * x[:, 1]
            o0 += _DCDC_B[0]
            np.multiply(x[:, 0], g, out=o1)
            o1 += h * x[:, 1]
            return out
    return rhs


_DCDC_RHS_MODE = {1: _dcdc_rhs_mode(1), 2: _dcdc_rhs_mode(2)}


def _dcdc_numpy(x, u, tau):
    """``rk4_integrate(_dcdc_rhs, x, u, tau, 5)`` with the rows grouped by mode (each group
    integrated by its own right-hand side, then put back in place): the same bits, about half
    the operations."""
    x = np.atleast_2d(np.asarray(x, dtype=float))
    u = np.atleast_2d(np.asarray(u, dtype=float))
    if x.ndim != 2 or u.ndim != 2 or x.shape[0] != u.shape[0] or x.shape[1] != 2:
        return rk4_integrate(_dcdc_rhs, x, u, tau, 5)  # broadcasting: the plain path
    m2 = u[:, 0] > 1.5
    out = np.empty(x.shape, order="F")
    for mode, rows in ((1, np.flatnonzero(~m2)), (2, np.flatnonzero(m2))):
        if rows.size:
            sel = _progression(rows)  # the abstraction's blocks alternate the modes: a strided slice
            out[sel] = rk4_integrate(_DCDC_RHS_MODE[mode], x[sel], None, tau, 5)
    return out


def _progression(rows: np.ndarray):
    """``rows`` (sorted, distinct) as a slice when they are evenly spaced, else themselves."""
    if rows.size == 1:
        return slice(int(rows[0]), int(rows[0]) + 1)
    step = int(rows[1] - rows[0])
    d = np.diff(rows)
    if (d == step).all():
        return slice(int(rows[0]), int(rows[-1]) + 1, step)
    return rows


def _dcdc_step(x, u, tau):
    """The converter's step: the kernel generated from ``scots/dcdc.toml`` when it pays (the same
    bits), else :func:`_dcdc_numpy`."""
    xu = compiled_args(x, u)
    step = file_step(SCOTS_FILES / "dcdc.toml", len(xu[0])) if xu is not None else None
    return step(xu[0], xu[1], float(tau)) if step is not None else _dcdc_numpy(x, u, tau)


def dcdc_system(x_lo=(1.15, 5.45), x_hi=(1.55, 5.85)) -> System:
    """Switched linear system x' = A_u x + b (u in {1, 2}), RK4 with 5 substeps over tau = 0.5.

    On [1.15, 1.55] x [5.45, 5.85] with eta = 2/4000 the grid has 801 x 801 = 641,601 cells.
    """
    return System(name="dcdc", state_names=("il", "vc"), input_names=("mode",), x_lo=x_lo, x_hi=x_hi,
                  inputs=np.array([[1.0], [2.0]]), base_tau=DCDC_TAU,
                  step=_dcdc_step,
                  params={"inputs": "categorical"})  # switch modes: nothing lies between 1 and 2


def dcdc_growth():
    """growth(r, x, u, tau): r' = L_u r with L_u = A_u, off-diagonals in absolute value."""
    L = np.abs(_DCDC_A) * (1 - np.eye(2)) + _DCDC_A * np.eye(2)
    return rk4_growth(lambda u: L[_dcdc_mode(u)], nint=5)


def dcdc_spec() -> Spec:
    """Stay in [1.15, 1.55] x [5.45, 5.85] forever."""
    return Spec(kind="invariance", safe=Box([1.15, 5.45], [1.55, 5.85]))


#: unicycle in a rotating current w(p) = a (-(y - 5), x - 5) around the arena's center
VORTEX_A = 0.1
VORTEX_TAU = 0.4
VORTEX_ETA = (0.2, 0.2, 2 * np.pi / 32)


def _vortex_rhs(x, u):
    v, w = u[:, 0], u[:, 1]
    return np.stack([v * np.cos(x[:, 2]) - VORTEX_A * (x[:, 1] - 5.0),
                     v * np.sin(x[:, 2]) + VORTEX_A * (x[:, 0] - 5.0), w], axis=1)


def vortex_system() -> System:
    """3-D nonlinear unicycle (x, y, heading) drifting in a vortex on [0, 10]^2: f(x, u) - x
    depends on the position, so no dimension is translation invariant. RK4, 5 substeps, tau 0.4."""
    inputs = np.array([[v, w] for v in (-0.5, 0.5, 1.0) for w in (-1.0, -0.5, 0.0, 0.5, 1.0)])
    return System(name="vortex", state_names=("x", "y", "theta"), input_names=("v", "omega"),
                  x_lo=(0.0, 0.0, -np.pi), x_hi=(10.0, 10.0, np.pi), inputs=inputs,
                  base_tau=VORTEX_TAU, step=rk4_step(_vortex_rhs, nint=5), angle_dims=(2,))


def vortex_growth():
    """growth(r, x, u, tau): |dF/dx| <= [[0, a, |v|], [a, 0, |v|], [0, 0, 0]]."""
    def L(u):
        B = u.shape[0]
        out = np.zeros((B, 3, 3))
        out[:, 0, 1] = out[:, 1, 0] = VORTEX_A
        out[:, 0, 2] = out[:, 1, 2] = np.abs(u[:, 0])
        return out
    return rk4_growth(L, nint=5)


def vortex_spec() -> Spec:
    """Reach [8, 9.5] x [8, 9.5] (any heading) avoiding two walls."""
    inf = np.inf
    return Spec(kind="reach_avoid", target=Box([8.0, 8.0, -inf], [9.5, 9.5, inf]),
                obstacles=(Box([3.0, 0.0, -inf], [3.6, 6.5, inf]), Box([6.4, 3.5, -inf], [7.0, 10.0, inf])))


def integrator_system(tau: float = 0.07, hi: float = 1.0) -> System:
    """x+ = x + tau u on [0, hi]^2 with 5 x 5 inputs in [-1, 1]^2 (a small system for tests)."""
    def step(x, u, dt):
        return x + dt * u

    def jac(u):
        return np.broadcast_to(np.eye(2), (u.shape[0], 2, 2))

    return System(name="integrator2", state_names=("p", "q"), input_names=("a", "b"),
                  x_lo=(0, 0), x_hi=(hi, hi), inputs=input_grid([-1, -1], [1, 1], [5, 5]),
                  base_tau=tau, step=step, jacobian_bound=jac)

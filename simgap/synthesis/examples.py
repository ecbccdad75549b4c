"""Reference problems for parity checks: the SCOTS v2 vehicle example (reach-avoid).

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

from ..systems import System
from .grid import UniformGrid
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
    alpha = np.arctan(np.tan(u[:, 1]) / 2.0)
    ca = np.cos(alpha)
    dx = u[:, 0] * np.cos(alpha + x[:, 2]) / ca
    dy = u[:, 0] * np.sin(alpha + x[:, 2]) / ca
    dth = u[:, 0] * np.tan(u[:, 1])
    return np.stack([dx, dy, dth], axis=1)


def vehicle_step(x: np.ndarray, u: np.ndarray, tau: float) -> np.ndarray:
    """SCOTS ``runge_kutta_fixed4`` with 10 intermediate steps over tau, vectorized over rows."""
    h = tau / VEHICLE_NINT
    x = np.array(x, dtype=float, copy=True)
    for _ in range(VEHICLE_NINT):
        k0 = _vehicle_rhs(x, u)
        k1 = _vehicle_rhs(x + h / 2 * k0, u)
        k2 = _vehicle_rhs(x + h / 2 * k1, u)
        k3 = _vehicle_rhs(x + h * k2, u)
        x = x + (h / 6) * (k0 + 2 * k1 + 2 * k2 + k3)
    return x


def vehicle_growth(r: np.ndarray, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """SCOTS vehicle ``radius_post``: r (B,3) -> r+ over one sampling period tau = 0.3."""
    c = np.abs(u[:, 0]) * np.sqrt(np.tan(u[:, 1]) * np.tan(u[:, 1]) / 4.0 + 1)
    r = np.array(r, dtype=float, copy=True)
    r[:, 0] = r[:, 0] + c * r[:, 2] * VEHICLE_TAU
    r[:, 1] = r[:, 1] + c * r[:, 2] * VEHICLE_TAU
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

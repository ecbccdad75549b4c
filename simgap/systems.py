"""Control systems: the nominal model x+ = f(x, u) that simgap certifies against a simulator.

A :class:`System` is a small, typed, immutable description:

* state set X = [x_lo, x_hi] (a box), state names, which dimensions are angles;
* a finite input set U, an (M, m) array of input vectors;
* a base sampling time ``base_tau`` and a one-step map ``step(x, u, tau) -> x_next``
  vectorized over a batch (x is (B, n), u is (B, m));
* ``steps`` = k: the system's sampling time is tau = k * base_tau with the input held for
  k base periods (``f`` applies ``step`` k times). Use :meth:`System.with_steps`.
* optionally ``jacobian_bound(u) -> (B, n, n)``: an elementwise bound |d step / dx| <= J(u)
  valid on all of X, for one base step. It gives the analytic Lipschitz constant L_f and
  the SCOTS-style growth bound used by synthesis.

Defining your own system takes a few lines::

    import numpy as np
    from simgap.systems import System, input_grid

    def step(x, u, tau):
        p, v = x[:, 0], x[:, 1]
        return np.stack([p + tau * v, v + tau * (u[:, 0] - 0.1 * v)], axis=1)

    mine = System(name="cart", state_names=("p", "v"), input_names=("F",),
                  x_lo=(-1, -1), x_hi=(1, 1), inputs=input_grid([-1], [1], [21]),
                  base_tau=0.01, step=step)

Angle-valued dimensions (``angle_dims``) are wrapped to [-pi, pi) by :meth:`System.wrap`,
and differences between states must use :meth:`System.diff`.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

from . import entry_points
from .errors import SimgapError

StepFn = Callable[[np.ndarray, np.ndarray, float], np.ndarray]
JacFn = Callable[[np.ndarray], np.ndarray]

TWO_PI = 2.0 * np.pi


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % TWO_PI - np.pi


def input_grid(lo: Sequence[float], hi: Sequence[float], counts: Sequence[int]) -> np.ndarray:
    """Cartesian grid of inputs: ``counts[j]`` evenly spaced values in [lo[j], hi[j]].

    Returns an (M, m) array, last input dimension varying fastest.
    """
    axes = [np.linspace(l, h, int(c)) for l, h, c in zip(lo, hi, counts)]
    return np.array(list(itertools.product(*axes)), dtype=float).reshape(-1, len(axes))


@dataclass(frozen=True, eq=False)
class System:
    """A discrete-time control system x+ = f(x, u) with sampling time tau = steps * base_tau.

    Attributes
    ----------
    name : str
        Identifier (built-ins: ``pendulum``, ``turtlebot``, ``emps``).
    state_names, input_names : tuple of str
        Variable names, used by basis terms (``x1``, ``u2``) and reports. Positional names
        ``x1..xn``/``u1..um`` always work as well.
    x_lo, x_hi : (n,) arrays
        The state set X = [x_lo, x_hi].
    inputs : (M, m) array
        The finite input set U.
    base_tau : float
        Sampling time of one ``step`` [s].
    step : callable
        ``step(x (B,n), u (B,m), tau) -> (B,n)``, one base sampling period.
    angle_dims : tuple of int
        0-based indices of angle-valued state dimensions (wrapped to [-pi, pi)).
    steps : int
        Number of base periods per sampling period (input held), k >= 1.
    jacobian_bound : callable, optional
        ``J(u (B,m)) -> (B,n,n)`` with |d step_i/d x_j| <= J_ij on X for one base step.
    params : dict
        Physical parameters, recorded in provenance.
    """

    name: str
    state_names: tuple
    input_names: tuple
    x_lo: np.ndarray
    x_hi: np.ndarray
    inputs: np.ndarray
    base_tau: float
    step: StepFn
    angle_dims: tuple = ()
    steps: int = 1
    jacobian_bound: Optional[JacFn] = None
    params: dict = field(default_factory=dict)

    def __post_init__(self):
        lo = np.asarray(self.x_lo, dtype=float).ravel()
        hi = np.asarray(self.x_hi, dtype=float).ravel()
        U = np.asarray(self.inputs, dtype=float)
        if U.ndim == 1:
            U = U[:, None]
        object.__setattr__(self, "x_lo", lo)
        object.__setattr__(self, "x_hi", hi)
        object.__setattr__(self, "inputs", U)
        object.__setattr__(self, "state_names", tuple(self.state_names))
        object.__setattr__(self, "input_names", tuple(self.input_names))
        object.__setattr__(self, "angle_dims", tuple(int(i) for i in self.angle_dims))
        n = lo.size
        if n == 0 or hi.size != n:
            raise SimgapError(f"system {self.name!r}: x_lo and x_hi must be non-empty and of equal length")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo < hi)):
            raise SimgapError(f"system {self.name!r}: need finite x_lo < x_hi in every dimension")
        if len(self.state_names) != n:
            raise SimgapError(f"system {self.name!r}: {len(self.state_names)} state names for {n} states")
        if U.ndim != 2 or U.shape[0] == 0 or U.shape[1] == 0:
            raise SimgapError(f"system {self.name!r}: the input set is empty or malformed (need an (M, m) array)")
        if not np.all(np.isfinite(U)):
            raise SimgapError(f"system {self.name!r}: the input set contains NaN or inf")
        if len(self.input_names) != U.shape[1]:
            raise SimgapError(f"system {self.name!r}: {len(self.input_names)} input names for {U.shape[1]} inputs")
        if any(i < 0 or i >= n for i in self.angle_dims):
            raise SimgapError(f"system {self.name!r}: angle_dims {self.angle_dims} out of range for n={n}")
        if not (self.base_tau > 0 and np.isfinite(self.base_tau)):
            raise SimgapError(f"system {self.name!r}: base_tau must be > 0, got {self.base_tau}")
        if int(self.steps) != self.steps or self.steps < 1:
            raise SimgapError(f"system {self.name!r}: steps must be an integer >= 1, got {self.steps}")
        if self.steps > MAX_STEPS:  # f applies the base step `steps` times per transition, for every row
            raise SimgapError(f"system {self.name!r}: steps = {int(self.steps):,} base periods per sampling period is "
                              f"more than the {MAX_STEPS:,} simgap accepts (every transition would evaluate the model "
                              f"{int(self.steps):,} times; refused before any work): give steps <= {MAX_STEPS:,} "
                              f"(tau = steps x base_tau = {self.base_tau:g} s x steps)")

    # ----- sizes and names -------------------------------------------------------------
    @property
    def n(self) -> int:
        """State dimension."""
        return self.x_lo.size

    @property
    def m(self) -> int:
        """Input dimension."""
        return self.inputs.shape[1]

    @property
    def tau(self) -> float:
        """Sampling time of f [s] (= steps * base_tau)."""
        return self.steps * self.base_tau

    @property
    def angle_mask(self) -> np.ndarray:
        mask = np.zeros(self.n, dtype=bool)
        mask[list(self.angle_dims)] = True
        return mask

    def with_steps(self, k: int) -> "System":
        """The same system sampled at k * base_tau, the input held for k base periods."""
        return dataclasses.replace(self, steps=int(k))

    # ----- the map -----------------------------------------------------------------------
    def f(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Nominal next state after tau = steps * base_tau with u held. x (B,n), u (B,m)."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        for _ in range(self.steps):
            x = self.step(x, u, self.base_tau)
        return self.wrap(x)

    def wrap(self, x: np.ndarray) -> np.ndarray:
        """Wrap angle dimensions of x (..., n) to [-pi, pi)."""
        if not self.angle_dims:
            return x
        x = np.array(x, dtype=float, copy=True)
        idx = list(self.angle_dims)
        x[..., idx] = wrap_angle(x[..., idx])
        return x

    def diff(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """a - b with angle dimensions wrapped to [-pi, pi)."""
        d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
        if self.angle_dims:
            idx = list(self.angle_dims)
            d[..., idx] = wrap_angle(d[..., idx])
        return d

    def jacobian_bound_f(self, u: np.ndarray) -> Optional[np.ndarray]:
        """Elementwise bound on |df/dx| over X for the whole sampling period: J^steps, (B,n,n)."""
        if self.jacobian_bound is None:
            return None
        J = np.asarray(self.jacobian_bound(np.atleast_2d(u)), dtype=float)
        out = J
        for _ in range(self.steps - 1):
            out = J @ out
        return out

    def growth_bound(self, r: np.ndarray, u: np.ndarray) -> np.ndarray:
        """SCOTS-style radius propagation over tau: r+ = J r per base step (r (B,n), u (B,m))."""
        if self.jacobian_bound is None:
            raise SimgapError(f"system {self.name!r} has no jacobian_bound; give a growth bound explicitly")
        J = np.asarray(self.jacobian_bound(np.atleast_2d(u)), dtype=float)
        r = np.atleast_2d(np.asarray(r, dtype=float))
        for _ in range(self.steps):
            r = np.einsum("bij,bj->bi", J, r)
        return r

    def lipschitz_f(self) -> Optional[np.ndarray]:
        """Analytic Lipschitz constants L_f^(i) of f_i in x (Euclidean norm), max over U.

        ``None`` when the system gives no Jacobian bound (then it must be estimated).
        """
        J = self.jacobian_bound_f(self.inputs)
        if J is None:
            return None
        return np.sqrt((J ** 2).sum(axis=2)).max(axis=0)

    def check_states(self, x: np.ndarray, what: str = "state") -> np.ndarray:
        """Validate that x (B,n) is finite and inside X; raise a ValueError naming the problem."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.shape[-1] != self.n:
            raise SimgapError(f"{what}: expected {self.n} components for system {self.name!r}, got {x.shape[-1]}")
        if not np.all(np.isfinite(x)):
            raise SimgapError(f"{what}: contains NaN or inf")
        tol = 1e-9 * np.maximum(1.0, np.abs(self.x_hi - self.x_lo))
        bad = np.any((x < self.x_lo - tol) | (x > self.x_hi + tol), axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise SimgapError(
                f"{what}: {int(bad.sum())} of {len(x)} outside X = {self._box_str()}, e.g. {x[i].tolist()}")
        return x

    def _box_str(self) -> str:
        return " x ".join(f"[{l:g}, {h:g}]" for l, h in zip(self.x_lo, self.x_hi))

    def describe(self) -> dict:
        """JSON-ready description for manifests and provenance."""
        return {
            "name": self.name,
            "state_names": list(self.state_names),
            "input_names": list(self.input_names),
            "x_lo": self.x_lo.tolist(),
            "x_hi": self.x_hi.tolist(),
            "n_inputs": int(self.inputs.shape[0]),
            "inputs_lo": self.inputs.min(axis=0).tolist(),
            "inputs_hi": self.inputs.max(axis=0).tolist(),
            "base_tau": self.base_tau,
            "steps": self.steps,
            "tau": self.tau,
            "angle_dims": list(self.angle_dims),
            "params": dict(self.params),
        }


# ---------------------------------------------------------------------------------------
# Built-in systems (the paper's parameters)
# ---------------------------------------------------------------------------------------

def pendulum(m: float = 1.0, l: float = 1.0, g: float = 9.81, tau: float = 0.005,
             inputs: Optional[np.ndarray] = None) -> System:
    """Pendulum (paper, Sec. V; theta = 0 hangs straight down, gravity restoring): x1 angle [rad], x2 angular velocity [rad/s], u torque [N m].

    x1+ = x1 + tau x2;  x2+ = -(3 g tau / 2 l) sin x1 + x2 + 3 tau u / (m l^2).
    X = [-0.2, 0.2] x [-0.5, 0.5], U = {-1, -0.9, ..., 1}.
    """
    a = 3.0 * g / (2.0 * l)
    b = 3.0 / (m * l * l)

    def step(x, u, dt):
        x1, x2 = x[:, 0], x[:, 1]
        return np.stack([x1 + dt * x2, -a * dt * np.sin(x1) + x2 + b * dt * u[:, 0]], axis=1)

    def jac(u):
        J = np.array([[1.0, tau], [a * tau, 1.0]])
        return np.broadcast_to(J, (u.shape[0], 2, 2))

    return System(
        name="pendulum", state_names=("theta", "omega"), input_names=("torque",),
        x_lo=(-0.2, -0.5), x_hi=(0.2, 0.5),
        inputs=input_grid([-1.0], [1.0], [21]) if inputs is None else inputs,
        base_tau=tau, step=step, jacobian_bound=jac,
        params={"m": m, "l": l, "g": g},
    )


def turtlebot(tau: float = 0.01, inputs: Optional[np.ndarray] = None) -> System:
    """Unicycle TurtleBot (paper, Sec. V): x1, x2 position [m], x3 heading [rad]; u1 speed [m/s],
    u2 turn rate [rad/s].

    x1+ = x1 + tau u1 cos x3;  x2+ = x2 + tau u1 sin x3;  x3+ = x3 + tau u2.
    X = [0, 4] x [0, 4] x [-pi, pi], U = {-1, -0.9, ..., 1}^2 (441 inputs).
    """

    def step(x, u, dt):
        th = x[:, 2]
        return np.stack([x[:, 0] + dt * u[:, 0] * np.cos(th),
                         x[:, 1] + dt * u[:, 0] * np.sin(th),
                         th + dt * u[:, 1]], axis=1)

    def jac(u):
        B = u.shape[0]
        J = np.zeros((B, 3, 3))
        J[:, 0, 0] = J[:, 1, 1] = J[:, 2, 2] = 1.0
        J[:, 0, 2] = J[:, 1, 2] = tau * np.abs(u[:, 0])
        return J

    return System(
        name="turtlebot", state_names=("x", "y", "theta"), input_names=("v", "omega"),
        x_lo=(0.0, 0.0, -np.pi), x_hi=(4.0, 4.0, np.pi),
        inputs=input_grid([-1.0, -1.0], [1.0, 1.0], [21, 21]) if inputs is None else inputs,
        base_tau=tau, step=step, angle_dims=(2,), jacobian_bound=jac,
        params={},
    )


def emps(M: float = 95.1, gtau: float = 35.15, tau: float = 0.001) -> System:
    """EMPS positioning axis, nominal double integrator: q [m], q' [m/s], input vir [V].

    q+ = q + tau q';  q'+ = q' + tau gtau vir / M.  Bounds cover the benchmark record
    (DATA_EMPS.mat: q in [-2.2e-5, 0.2464] m, |q'| <= 0.128 m/s after filtering at 10-200 Hz,
    vir in [-4.33, 4.14] V) with a margin: X = [-0.005, 0.255] x [-0.15, 0.15],
    U = {-4.5, -4.0, ..., 4.5} V.
    """
    k = gtau / M

    def step(x, u, dt):
        return np.stack([x[:, 0] + dt * x[:, 1], x[:, 1] + dt * k * u[:, 0]], axis=1)

    def jac(u):
        J = np.array([[1.0, tau], [0.0, 1.0]])
        return np.broadcast_to(J, (u.shape[0], 2, 2))

    return System(
        name="emps", state_names=("q", "qd"), input_names=("vir",),
        x_lo=(-0.005, -0.15), x_hi=(0.255, 0.15),
        inputs=input_grid([-4.5], [4.5], [19]),
        base_tau=tau, step=step, jacobian_bound=jac,
        params={"M": M, "gtau": gtau},
    )


BUILTIN = {"pendulum": pendulum, "turtlebot": turtlebot, "emps": emps}

# units of the built-ins' (states, inputs); plots, the app and recordings label axes with them
BUILTIN_UNITS = {
    "pendulum": (("rad", "rad/s"), ("N m",)),
    "turtlebot": (("m", "m", "rad"), ("m/s", "rad/s")),
    "emps": (("m", "m/s"), ("V",)),
}


def units(system: System) -> tuple:
    """(state units, input units) of ``system``, one string per variable ("" where unknown).

    From ``params["units"]`` (a table variable name -> unit, e.g. ``{"p": "m", "F": "N"}``),
    else the table a system file gives (``params["_system_file"]["units"]``), else the
    built-in's (:data:`BUILTIN_UNITS`, also for a refined built-in through ``base_system``).
    """
    p = system.params or {}
    table = p.get("units")
    if not isinstance(table, dict):
        spec = p.get("_system_file")
        table = spec.get("units") if isinstance(spec, dict) else None
    if isinstance(table, dict):
        return (tuple(str(table.get(n, "")) for n in system.state_names),
                tuple(str(table.get(n, "")) for n in system.input_names))
    su, iu = BUILTIN_UNITS.get(str(p.get("base_system", system.name)), ((), ()))
    if len(su) != system.n or len(iu) != system.m:
        return ("",) * system.n, ("",) * system.m
    return tuple(su), tuple(iu)


def labelled(name: str, unit: str) -> str:
    """``name [unit]`` (just the name when the unit is unknown)."""
    return f"{name} [{unit}]" if unit else name


#: most base periods per sampling period: a step count read from a file (a refined system, a data set's
#: embedded system, a system file) above it is refused before any work instead of running for hours
#: (10,000 evaluations of the model per transition; the simulators' own substeps stop at 10,000 too)
MAX_STEPS = 10_000


def get_system(name: str, steps: int = 1) -> System:
    """A built-in or plugin-registered system by name (:mod:`simgap.plugins`), optionally at
    k = ``steps`` base periods per sampling period."""
    factory = BUILTIN.get(name)
    if factory is not None:
        return factory().with_steps(steps)
    s = load_plugin_system(name) if isinstance(name, str) else None
    if s is None:
        raise SimgapError(f"unknown system {name!r}; built-in systems: {', '.join(sorted(BUILTIN))}"
                          + _plugins_note())
    return s.with_steps(steps)


def is_named(name) -> bool:
    """True for a built-in or an installed plugin system's name."""
    if not isinstance(name, str):
        return False
    if name in BUILTIN:
        return True
    return name in system_plugins()


def system_plugins() -> dict:
    """name -> :class:`simgap.entry_points.Plugin` of the installed system plugins (built-in names excluded)."""
    return entry_points.registered(entry_points.SYSTEM_GROUP, BUILTIN)


def _plugins_note() -> str:
    return entry_points.installed_note(entry_points.SYSTEM_GROUP, system_plugins())


def load_plugin_system(name: str):
    """The System registered as ``name`` (the entry point is a System or a factory () -> System),
    or None when no installed plugin registers it."""
    if name not in system_plugins():
        return None
    obj, plugin = entry_points.load(entry_points.SYSTEM_GROUP, name)
    if callable(obj) and not isinstance(obj, System):
        try:
            obj = obj()
        except SimgapError:
            raise
        except Exception as e:
            raise SimgapError(f"plugin system {name!r} ({plugin.origin()}) failed to build: "
                              f"{type(e).__name__}: {e}") from None
    if not isinstance(obj, System):
        raise SimgapError(f"plugin system {name!r} ({plugin.origin()}) is not a simgap System or a function "
                          f"returning one (got {type(obj).__name__})")
    if obj.name != name:
        raise SimgapError(f"plugin system {name!r} ({plugin.origin()}) builds a system named {obj.name!r}; "
                          f"the entry-point name and System.name must agree")
    return obj

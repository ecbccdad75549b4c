"""The library of physically named candidate effects a nominal model may lack.

Every effect is a term g(x, u) that enters ONE state's update scaled by the sampling time:

    x_i+ = f_i(x, u) + tau * c * g(x, u)

so the coefficient c is a rate (state unit per second per unit of g). Identifiers are stable
and appear in reports and saved refined systems:

============== =================================== ===========================================
name           g(x, u)                             coefficient c means
============== =================================== ===========================================
bias           1                                   constant rate offset [state unit / s]
viscous_frict. v (a velocity state)                c = -b/I for a viscous force -b v  [1/s]
coulomb_frict. sign(v)                             c = -F_c/I for a Coulomb force -F_c sign v
drag           v |v|                               c = -d/I for a quadratic drag -d v|v|
cubic_stiffn.  p^3, p the position integrating v   c = -k3/I for a cubic spring force -k3 p^3
                                                   (hardening: c < 0; softening: c > 0)
input_gain     B_ij(x) u_j ("as u_j enters f_i")   relative gain error: the input acts (1 + c) u_j
deadband       B_ij(x) sign(u_j)                   c = -w: a dead zone of width w [input unit]
                                                   (exact for |u_j| >= w)
input_coupl.   u_j, for a state x_i the model does c [state unit / s per input unit]: input j
               not drive by u_j (B_ij = 0 on X x U) acts on x_i where the model routes none
               and that integrates no velocity     (a differential drive's unequal wheels turn
                                                   the heading with the speed: theta' += c v)
input_cross    B_ij(x) u_j u_k, k != j              the gain of input j changes by c per unit of
input_cr._abs  B_ij(x) u_j |u_k|, k != j            input k (or of its size |u_k|): a turn rate lost
                                                   to slip that depends on the speed
gravity        the model's own drift of x_i,       relative error of the model's own gravity /
               (f_i(x, 0) - x_i) / tau             parameter term (x_i's drift at u = 0)
integration    a_j(x, u) = (f'_j(x, u) - x_j) / tau  for a position x_i integrating velocity x_j:
               the (refined) model's own velocity  the model's Euler update x_i+ = x_i + tau x_j
               update rate, entering x_i           misses tau * c * a_j within the step;
                                                   c [s] = tau for semi-implicit Euler (physics
                                                   engines), tau / 2 for exact integration
input_delay    B_ij(x) (u_j[k-d] - u_j[k]),        c = 1: input j acts d periods late (time-ordered
               d = 1 .. MAX_DELAY periods          data only; a model with memory, reported with its
                                                   length, not put into the memoryless f')
actuator_lag   B_ij(x) (a_j^L[k] - u_j[k]), a^L    c = 1: input j acts through a first-order lag of
               the input through a first-order     L periods (time constant T_a = -tau / ln(1 - 1/L));
               lag of L in LAG_PERIODS periods     time-ordered data only, not in the memoryless f')
<user name>    any expression in the variables     user-defined (lagged values name[k-1] on
                                                   time-ordered data)
============== =================================== ===========================================

B_ij(x, u) = (d f_i / d u_j) / tau is taken from the model itself by a central difference of
one base step, so "as the input enters the model" holds for any system (u1 cos x3 for the
TurtleBot's x1; 3 u / (m l^2) for the pendulum's omega).

Velocity states. Friction-type effects (viscous, Coulomb, drag) act on a velocity state and
enter that state's update. Which states are velocities is found, in this order, from
``system.params["velocity_dims"]``, from :data:`VELOCITY_DIMS` (built-ins: pendulum -> omega,
emps -> qd, turtlebot -> none: its speeds are inputs) which :func:`declare_velocity` extends,
or by inference: x_j is a velocity when some other state integrates it, i.e. one base step has
d f_i / d x_j = base_tau exactly (x_i+ = x_i + tau x_j + ...). ``gravity`` is a candidate for
velocity states (or, when a system declares none, for every state) whose drift is not zero.

Units. ``UNITS`` gives state/input units for the built-ins, and ``INERTIA`` an inertia I per
system (emps: M [kg], pendulum: m l^2 / 3 [kg m^2]) so that effects entering a velocity state
convert to physical forces / torques: F = I c g (e.g. N, N s/m).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, Iterable, Optional, Sequence

import numpy as np

from ..errors import SimgapError
from ..expr import VarSpace, parse
from ..systems import BUILTIN_UNITS, System

LIBRARY = ("bias", "viscous_friction", "coulomb_friction", "drag", "cubic_stiffness", "input_gain", "deadband",
           "input_coupling", "input_cross", "input_cross_abs", "gravity", "integration", "input_delay",
           "actuator_lag")
#: deepest history the library's delay candidates look at (periods), for time-ordered data
MAX_DELAY = 3
#: time constants (in periods L, 1 / L = 1 - exp(-tau / T_a)) of the first-order actuator-lag candidates
LAG_PERIODS = (2.0, 3.0, 5.0, 8.0, 13.0, 20.0)

#: built-in velocity-state declarations (0-based dims); extended by :func:`declare_velocity`
VELOCITY_DIMS: Dict[str, tuple] = {"pendulum": (1,), "emps": (1,), "turtlebot": ()}

#: (state units, input units) for reports
UNITS: Dict[str, tuple] = BUILTIN_UNITS


def _inertia(system: System) -> Optional[tuple]:
    """(I, force unit) converting a velocity-state rate into a physical force/torque."""
    name = _base_name(system)
    p = system.params
    if name == "emps" and "M" in p:
        return float(p["M"]), "N"
    if name == "pendulum" and "m" in p and "l" in p:
        return float(p["m"]) * float(p["l"]) ** 2 / 3.0, "N m"
    return None


def _base_name(system: System) -> str:
    return str(system.params.get("base_system", system.name))


def declare_velocity(system_name: str, dims: Sequence[int]) -> None:
    """Declare which 0-based state dims of a (user) system are velocities."""
    VELOCITY_DIMS[system_name] = tuple(int(d) for d in dims)


@dataclass(frozen=True, eq=False)
class Effect:
    """One candidate term g(x, u) entering state ``state``'s update as tau * c * g.

    ``variable`` names the state or input the term is built from (a velocity for friction,
    an input for input_gain/deadband), ``expr`` is a readable formula, ``smooth`` tells
    whether g is Lipschitz in x (sign terms are not), ``params`` holds what is needed to
    rebuild it (user expressions).
    """

    name: str
    state: int
    variable: Optional[str]
    expr: str
    term: Callable[..., np.ndarray]
    smooth: bool = True
    params: dict = field(default_factory=dict)
    lag: int = 0                    # periods of history the term reads (0: a function of (x_k, u_k))

    def key(self, system: System) -> str:
        s = f"{self.name}:{system.state_names[self.state]}"
        s += f":{self.variable}" if self.variable else ""
        return s + (f":{self.params['periods']}" if "periods" in self.params else "")

    def spec(self) -> dict:
        """JSON-able description; :func:`effect_from_spec` rebuilds the effect from it."""
        d = {"name": self.name, "state": int(self.state), "variable": self.variable}
        if self.params:
            d["params"] = dict(self.params)
        return d

    def __call__(self, x: np.ndarray, u: np.ndarray, hist: Optional[np.ndarray] = None) -> np.ndarray:
        """g on rows (x_k, u_k); ``hist`` (K, lag (n + m)) = [x_{k-1}, u_{k-1}, x_{k-2}, ...] for lag > 0."""
        val = self.term(x, u, hist) if self.lag else self.term(x, u)
        return np.asarray(val, dtype=float).reshape(x.shape[0])


# ---------------------------------------------------------------------------------------
# helpers derived from the model itself
# ---------------------------------------------------------------------------------------

def _input_rate(system: System, i: int, j: int) -> Callable:
    """B_ij(x, u) = (d step_i / d u_j) / base_tau by a central difference of one base step."""
    dt = system.base_tau
    span = float(np.ptp(system.inputs[:, j])) or 1.0
    h = 1e-4 * span

    def B(x, u):
        up, um = u.copy(), u.copy()
        up[:, j] += h
        um[:, j] -= h
        return (system.step(x, up, dt)[:, i] - system.step(x, um, dt)[:, i]) / (2 * h * dt)

    return B


def _drift(system: System, i: int) -> Callable:
    """The model's own drift rate of x_i at u = 0: (step_i(x, 0) - x_i) / base_tau."""
    dt = system.base_tau

    def g(x, u):
        return (system.step(x, np.zeros_like(u), dt)[:, i] - x[:, i]) / dt

    return g


def _rate(system: System, j: int) -> Callable:
    """The model's own update rate of x_j: (step_j(x, u) - x_j) / base_tau."""
    dt = system.base_tau

    def g(x, u):
        return (system.step(x, u, dt)[:, j] - x[:, j]) / dt

    return g


def integrator_pairs(system: System) -> list:
    """Pairs (i, j): state x_i integrates x_j, i.e. d step_i / d x_j = base_tau on X x U."""
    x, u = _sample_domain(system, 128)
    dt = system.base_tau
    out = []
    for j in range(system.n):
        h = 1e-6 * max(1.0, float(system.x_hi[j] - system.x_lo[j]))
        xp, xm = x.copy(), x.copy()
        xp[:, j] += h
        xm[:, j] -= h
        J = (system.step(xp, u, dt) - system.step(xm, u, dt)) / (2 * h)
        out += [(i, j) for i in range(system.n) if i != j and np.allclose(J[:, i], dt, rtol=1e-4, atol=0.0)]
    return out


def integration_effect(system: System, i: int, j: int) -> Effect:
    """The ``integration`` effect of x_i integrating x_j, built on ``system``'s own x_j update."""
    vn = system.state_names[j]
    return Effect("integration", i, vn, f"a_{vn}(x, u)", _rate(system, j))


def _sample_domain(system: System, count: int = 512, seed: int = 0) -> tuple:
    """Random states in X and inputs from U (fixed seed: applicability checks, bounds)."""
    rng = np.random.default_rng(seed)
    x = system.x_lo + rng.random((count, system.n)) * (system.x_hi - system.x_lo)
    u = system.inputs[rng.integers(0, system.inputs.shape[0], count)]
    return x, u


def velocity_dims(system: System) -> tuple:
    """0-based velocity states of ``system`` (see module docstring for the rules)."""
    if "velocity_dims" in system.params:
        return tuple(int(d) for d in system.params["velocity_dims"])
    name = _base_name(system)
    if name in VELOCITY_DIMS:
        return VELOCITY_DIMS[name]
    return tuple(sorted({j for _, j in integrator_pairs(system)}))


# ---------------------------------------------------------------------------------------
# building effects
# ---------------------------------------------------------------------------------------

def user_effect(system: System, name: str, state, expr: str, max_lag: int = 0) -> Effect:
    """A user-named term g = ``expr`` entering state ``state`` (index or name).

    ``expr`` is parsed by the shared allow-list parser :mod:`simgap.expr` (never evaluated as
    Python): numbers, the state and input names (``theta``, ``omega``), the positional names
    ``x1..xn``, ``u1..um``, ``pi``, ``+ - * / **``, comparisons for ``where`` and the functions of
    :data:`simgap.expr.FUNCTIONS` (sin, cos, tanh, exp, log, sqrt, abs, sign, clip, minimum,
    maximum, where, arctan, arctan2, ...). Example: ``"sin(2*pi*q/0.01)"``. With ``max_lag`` L > 0
    (time-ordered data) ``torque[k-1]`` .. ``torque[k-L]`` are the values 1..L periods earlier, and
    ``t`` is the row's time stamp [s] (e.g. ``"sin(2*pi*t/0.37)"``; the clock is the record's, read
    from the last column of the history). A term that reads lagged values or ``t`` is a history
    effect: reported, not put into the memoryless refined system.
    """
    if not isinstance(name, str) or not name or not name.replace("_", "").isalnum() or not name.isascii():
        raise SimgapError(f"user effect name {name!r}: use letters, digits and underscores")
    if name in LIBRARY:
        raise SimgapError(f"user effect name {name!r} clashes with the library effect of that name")
    i = _state_index(system, state)
    space = VarSpace.of_system(system, max_lag)
    w = system.n + system.m
    tcol = w * (1 + max_lag)                 # after every lag: [z_k, z_{k-1}, .., z_{k-L}, t_k]
    if max_lag > 0 and "t" not in space.columns:
        space = VarSpace({**space.columns, "t": tcol}, space.width, space.max_lag)
    try:
        parsed = parse(expr, space, what=f"user effect {name!r}:", comparisons=True)
    except SimgapError as e:
        if max_lag == 0 and "'t'" in str(e):
            raise SimgapError(f"{e} (the time t needs time-ordered data: transitions with time stamps)") from None
        raise
    uses_t = max_lag > 0 and tcol in parsed.columns
    lag = max((c // w for c in parsed.columns if c != tcol or not uses_t), default=0)

    def term(x, u, hist=None):
        z = np.concatenate([x, u], axis=1)
        if lag or uses_t:
            if hist is None:
                raise SimgapError(f"user effect {name!r} reads values {lag} period(s) back or the time t: "
                                  f"needs history")
            full = np.zeros((x.shape[0], tcol + 1))
            full[:, :w] = z
            full[:, w: w * (1 + lag)] = hist[:, : lag * w]
            if uses_t:
                full[:, tcol] = hist[:, -1]
            z = full
        return parsed.eval(z)

    x, u = _sample_domain(system, 8)
    try:
        term(x, u, np.zeros((8, max(lag, 1) * w + 1)))
    except Exception as e:  # report any evaluation failure as bad input
        raise SimgapError(f"user effect {name!r}: evaluating {expr!r} failed: {e}") from None
    return Effect(name=name, state=i, variable=None, expr=parsed.text, term=term, smooth=parsed.smooth,
                  params={"expr": parsed.text}, lag=max(lag, 1) if uses_t else lag)


def _state_index(system: System, state) -> int:
    if isinstance(state, (int, np.integer)) or (isinstance(state, str) and state.isdigit()):
        i = int(state)
    elif state in system.state_names:
        i = system.state_names.index(state)
    elif isinstance(state, str) and state[:1] == "x" and state[1:].isdigit():
        i = int(state[1:]) - 1
    else:
        raise SimgapError(f"unknown state {state!r}; states of {system.name!r}: {', '.join(system.state_names)}")
    if not 0 <= i < system.n:
        raise SimgapError(f"state index {i} out of range for n = {system.n}")
    return i


def effect_from_spec(system: System, spec: dict) -> Effect:
    """Rebuild an effect from :meth:`Effect.spec` (used when loading refined systems)."""
    try:
        name, state = spec["name"], int(spec["state"])
    except (KeyError, TypeError, ValueError):
        raise SimgapError(f"effect spec {spec!r} needs 'name' and an integer 'state'") from None
    if name not in LIBRARY:
        expr = (spec.get("params") or {}).get("expr")
        if expr is None:
            raise SimgapError(f"unknown effect {name!r}: not in the library ({', '.join(LIBRARY)}) "
                              f"and no user expression given")
        return user_effect(system, name, state, expr)
    periods = (spec.get("params") or {}).get("periods")
    for e in library_candidates(system, [name], check_applicable=False, max_lag=MAX_DELAY):
        if e.state == state and e.variable == spec.get("variable") and e.params.get("periods") == periods:
            return e
    raise SimgapError(f"effect {name!r} on state {state} with variable {spec.get('variable')!r} "
                      f"does not apply to system {system.name!r}")


def library_candidates(system: System, names: Optional[Iterable[str]] = None,
                       check_applicable: bool = True, max_lag: int = 0) -> list:
    """All library effects (optionally only those named) that apply to ``system``.

    An effect applies when its term is not identically zero on random samples of X x U (e.g.
    ``gravity`` does not apply to the EMPS double integrator, which has no drift term).
    ``input_delay`` candidates (d = 1 .. ``max_lag`` periods) need time-ordered data: none when
    ``max_lag`` is 0.
    """
    names = list(LIBRARY) if names is None else list(names)
    unknown = [nm for nm in names if nm not in LIBRARY]
    if unknown:
        raise SimgapError(f"unknown effect name(s) {unknown}; the library has: {', '.join(LIBRARY)} "
                          f"(add your own with a user term NAME:STATE:EXPR), and affine_ct on its own (affine "
                          f"continuous-time terms of a system file's velocity states, simgap.refine.affine_ct)")
    s = system
    vdims = velocity_dims(s)
    out = []
    for nm in names:
        if nm == "bias":
            out += [Effect("bias", i, None, "1", lambda x, u: np.ones(x.shape[0])) for i in range(s.n)]
        elif nm in ("viscous_friction", "coulomb_friction", "drag"):
            for v in vdims:
                vn = s.state_names[v]
                if nm == "viscous_friction":
                    out.append(Effect(nm, v, vn, vn, lambda x, u, v=v: x[:, v]))
                elif nm == "coulomb_friction":
                    out.append(Effect(nm, v, vn, f"sign({vn})", lambda x, u, v=v: np.sign(x[:, v]),
                                      smooth=False))
                else:
                    out.append(Effect(nm, v, vn, f"{vn}|{vn}|", lambda x, u, v=v: x[:, v] * np.abs(x[:, v])))
        elif nm == "cubic_stiffness":
            for v in vdims:
                for p in positions_of(s, v):
                    pn = s.state_names[p]
                    out.append(Effect(nm, v, pn, f"{pn}^3", lambda x, u, p=p: x[:, p] ** 3))
        elif nm in ("input_gain", "deadband"):
            for i in range(s.n):
                for j in range(s.m):
                    B = _input_rate(s, i, j)
                    un = s.input_names[j]
                    if nm == "input_gain":
                        out.append(Effect(nm, i, un, f"B_{i + 1}{j + 1}(x) {un}",
                                          lambda x, u, B=B, j=j: B(x, u) * u[:, j]))
                    else:
                        out.append(Effect(nm, i, un, f"B_{i + 1}{j + 1}(x) sign({un})",
                                          lambda x, u, B=B, j=j: B(x, u) * np.sign(u[:, j])))
        elif nm == "input_coupling":
            # an input acting where the model routes none; not on a position integrating a velocity
            # (within the step the velocity's input reaches it: that is ``integration``)
            x, u = _sample_domain(s)
            integrating = {i for i, _ in integrator_pairs(s)}
            for i in range(s.n):
                for j in range(s.m):
                    if i in integrating or np.any(_input_rate(s, i, j)(x, u) != 0):
                        continue
                    un = s.input_names[j]
                    out.append(Effect(nm, i, un, un, lambda x, u, j=j: u[:, j]))
        elif nm in ("input_cross", "input_cross_abs"):
            # the gain of input j varying with another input k (or its size)
            for i in range(s.n):
                for j in range(s.m):
                    B = _input_rate(s, i, j)
                    un = s.input_names[j]
                    for k in range(s.m):
                        if k == j:
                            continue
                        kn = s.input_names[k] if nm == "input_cross" else f"|{s.input_names[k]}|"
                        size = (lambda a: a) if nm == "input_cross" else np.abs
                        out.append(Effect(nm, i, f"{un}*{kn}", f"B_{i + 1}{j + 1}(x) {un} {kn}",
                                          lambda x, u, B=B, j=j, k=k, size=size: B(x, u) * u[:, j] * size(u[:, k])))
        elif nm == "input_delay":
            # the input acting d periods late: f(x, u[k-d]) - f(x, u[k]) = tau B (u[k-d] - u[k]) for
            # an input entering affinely; c = 1 is the whole input delayed by d periods
            w = s.n + s.m
            for i in range(s.n):
                for j in range(s.m):
                    B = _input_rate(s, i, j)
                    un = s.input_names[j]
                    for d in range(1, max_lag + 1):
                        col = (d - 1) * w + s.n + j
                        out.append(Effect(nm, i, un, f"B_{i + 1}{j + 1}(x) ({un}[k-{d}] - {un})",
                                          lambda x, u, h, B=B, j=j, col=col: B(x, u) * (h[:, col] - u[:, j]),
                                          lag=d, params={"periods": d}))
        elif nm == "actuator_lag" and max_lag > 0:
            # the history holds, after the lagged [x, u], the inputs through each lag of LAG_PERIODS
            for i in range(s.n):
                for j in range(s.m):
                    B = _input_rate(s, i, j)
                    un = s.input_names[j]
                    for g, L in enumerate(LAG_PERIODS):
                        col = max_lag * (s.n + s.m) + g * s.m + j
                        out.append(Effect(nm, i, un, f"B_{i + 1}{j + 1}(x) (lag{L:g}({un}) - {un})",
                                          lambda x, u, h, B=B, j=j, col=col: B(x, u) * (h[:, col] - u[:, j]),
                                          lag=1, params={"periods": L}))
        elif nm == "integration":
            out += [integration_effect(s, i, j) for i, j in integrator_pairs(s)]
        elif nm == "gravity":
            dims = vdims if vdims else tuple(range(s.n))
            out += [Effect(nm, i, None, f"drift_{i + 1}(x)", _drift(s, i)) for i in dims]
    if check_applicable:
        x, u = _sample_domain(s)
        xh, uh = _sample_domain(s, seed=1)
        hist = np.tile(np.concatenate([xh, uh], axis=1), (1, max(max_lag, 1)))
        hist = np.concatenate([hist, np.tile(uh, (1, len(LAG_PERIODS))), np.ones((xh.shape[0], 1))], axis=1)
        keep = []
        for e in out:
            g = e(x, u, hist)
            if np.any(np.abs(g) > 1e-12 * max(1.0, float(np.abs(g).max(initial=0.0)))) and np.any(g != 0):
                keep.append(e)
        out = keep
    return out


def parse_user_terms(system: System, items: Iterable[str], max_lag: int = 0) -> list:
    """User terms from ``NAME:STATE:EXPR`` strings (CLI ``--term``); lags up to ``max_lag``."""
    out = []
    for it in items:
        parts = it.split(":", 2)
        if len(parts) != 3:
            raise SimgapError(f"--term {it!r}: expected NAME:STATE:EXPR, e.g. cogging:qd:sin(2*pi*q/0.01)")
        out.append(user_effect(system, parts[0].strip(), parts[1].strip(), parts[2].strip(), max_lag))
    return out


def candidate_effects(system: System, names: Optional[Iterable[str]] = None,
                      user_terms: Sequence[Effect] = (), max_lag: int = 0) -> list:
    """Library candidates (all, or the named ones) plus user terms; names are checked."""
    cands = library_candidates(system, names, max_lag=max_lag)
    keys = set()
    for e in list(cands) + list(user_terms):
        k = e.key(system)
        if k in keys:
            raise SimgapError(f"duplicate candidate effect {k}")
        keys.add(k)
    return list(cands) + list(user_terms)


def coefficient_units(system: System, e: Effect) -> str:
    """Unit of the coefficient c in model units (c g has the unit of x_i per second)."""
    units = UNITS.get(_base_name(system))
    if units is None:
        return ""
    su, iu = units
    rate = f"{su[e.state]}/s"
    if e.name in ("bias", "coulomb_friction"):
        return rate
    if e.name == "input_coupling":
        return f"{rate} per ({iu[system.input_names.index(e.variable)]})"
    if e.name in ("input_cross", "input_cross_abs"):
        k = e.variable.split("*")[1].strip("|")
        return f"1 (relative) per ({iu[system.input_names.index(k)]})"
    if e.name == "viscous_friction":
        return "1/s"
    if e.name == "drag":
        vu = su[system.state_names.index(e.variable)]
        return f"{rate} per ({vu})^2"
    if e.name == "cubic_stiffness":
        return f"{rate} per ({su[system.state_names.index(e.variable)]})^3"
    if e.name in ("input_gain", "gravity"):
        return "1 (relative)"
    if e.name == "integration":
        return "s"
    if e.name == "input_delay":
        return "1 (fraction delayed)"
    if e.name == "actuator_lag":
        return "1 (fraction lagged)"
    if e.name == "deadband":
        return iu[system.input_names.index(e.variable)]
    return ""


def physical(system: System, e: Effect, coef: float, stderr: float) -> Optional[dict]:
    """The coefficient in physical units where the library knows how, else None.

    Effects entering a velocity state of a system with a known inertia I become forces
    (torques) F = I c g: bias -> N, viscous -> N s/m (F = value * v), Coulomb -> N
    (F = value * sign v), drag -> N s^2/m^2. A deadband gives its width w = -c in input units,
    an input gain the effective gain factor 1 + c.
    """
    if e.name == "deadband":
        return {"quantity": "deadband width w", "value": -coef, "stderr": stderr,
                "unit": coefficient_units(system, e)}
    if e.name == "integration":
        return None
    if e.name == "input_delay":
        d = int(e.params["periods"])
        return {"quantity": f"input delay ({d} period{'s' if d > 1 else ''})", "value": d * system.tau,
                "stderr": None, "unit": "s"}
    if e.name == "actuator_lag":
        L = float(e.params["periods"])
        return {"quantity": f"actuator lag time constant ({L:g} periods)",
                "value": -system.tau / np.log(1.0 - 1.0 / L), "stderr": None, "unit": "s"}
    if e.name in ("input_gain", "gravity"):
        return {"quantity": "effective gain factor 1 + c", "value": 1.0 + coef, "stderr": stderr, "unit": ""}
    inert = _inertia(system)
    if inert is None or e.state not in velocity_dims(system):
        return None
    I, fu = inert
    units = UNITS.get(_base_name(system), ((), ()))[0]
    vu = units[e.state] if units else ""
    table = {"bias": ("constant force", fu),
             "viscous_friction": ("viscous force per velocity (F = value * v)", f"{fu} s/{vu.split('/')[0]}"),
             "coulomb_friction": ("Coulomb force (F = value * sign v)", fu),
             "drag": ("drag force per v|v| (F = value * v|v|)", f"{fu} s^2/{vu.split('/')[0]}^2")}
    if e.name not in table:
        return None
    q, unit = table[e.name]
    return {"quantity": q, "value": I * coef, "stderr": I * stderr, "unit": unit}


# ---------------------------------------------------------------------------------------
# physical signs
# ---------------------------------------------------------------------------------------

FRICTION = ("viscous_friction", "coulomb_friction", "drag")
#: bounds on a coefficient (lo, hi, what it means) where the truth may sit at the bound itself:
#: refused only beyond two standard errors
SOFT_BOUNDS = {"input_gain": (-1.0, np.inf, "an effective input gain 1 + c <= 0 (the input would act backwards)"),
               "gravity": (-1.0, np.inf, "a drift term reversed (1 + c < 0)"),
               "input_delay": (-np.inf, 1.0, "more than the whole input delayed (fraction > 1)"),
               "actuator_lag": (-np.inf, 1.0, "more than the whole input lagged (fraction > 1)")}


def _nominal_friction(system: System, v: int, count: int = 512) -> np.ndarray:
    """The model's own friction in the library's shapes: (a_visc, a_coul, a_drag) of velocity x_v.

    Least squares of the velocity-dependent part of its update rate, rate_v(x, u) - rate_v(x|v=0, u),
    on (v, sign v, v|v|) over random samples of X x U (zero for a model without friction).
    """
    x, u = _sample_domain(system, count, seed=2)
    x0 = x.copy()
    x0[:, v] = 0.0
    g = _rate(system, v)
    d = g(x, u) - g(x0, u)
    w = x[:, v]
    A = np.stack([w, np.sign(w), w * np.abs(w)], axis=1)
    a = np.linalg.lstsq(A, d, rcond=None)[0]
    scale = np.sqrt(np.mean(d ** 2)) + np.sqrt(np.mean(g(x, u) ** 2))
    return np.where(np.abs(a) * np.sqrt(np.mean(A ** 2, axis=0)) > 1e-9 * max(scale, 1e-300), a, 0.0)


def sign_check(system: System, effects: Sequence[Effect], x: np.ndarray) -> Callable:
    """A check of physical signs for the candidates ``effects`` of one state on data states ``x``.

    Returns ``check(keys, coef, se) -> None | (key, reason, beyond)``: the first selected term
    whose coefficient is impossible, why, and whether it is impossible beyond two standard
    errors (``beyond``: the state is then flagged; a term merely on the wrong side of zero is
    refused without a flag). Rules:

    * friction (viscous, Coulomb, drag on velocity v, together with the model's own friction in
      those shapes, :func:`_nominal_friction`) must dissipate: phi(v) v <= 0 for every v in the
      data's range, phi = total friction rate; otherwise the term adding most power at the worst
      v is refused ("would inject energy");
    * deadband: width w = -c >= 0;
    * input_delay: fraction c >= 0 (and <= 1 within two standard errors);
    * input_gain: 1 + c > 0, gravity: 1 + c >= 0 (within two standard errors).
    """
    by_key = {e.key(system): e for e in effects}
    vgrid = {}
    nominal = {}
    for e in effects:
        if e.name in FRICTION and e.state not in vgrid:
            v = system.state_names.index(e.variable)
            vmax = float(np.max(np.abs(x[:, v]))) if x.size else 0.0
            vgrid[e.state] = np.linspace(-vmax, vmax, 401)
            nominal[e.state] = _nominal_friction(system, v)

    def shapes(w):
        return {"viscous_friction": w, "coulomb_friction": np.sign(w), "drag": w * np.abs(w)}

    def check(keys, coef, se):
        se = np.where(np.isfinite(se), se, 0.0)
        for k, c, s in zip(keys, coef, se):
            e = by_key.get(k)
            if e is None:
                continue
            if e.name == "deadband" and c > 0:
                return k, (f"a dead zone of negative width w = {-c:.4g} {coefficient_units(system, e)} "
                           f"(a saturation or a gain that falls with the input reads this way)"), bool(c > 2 * s)
            if e.name in ("input_delay", "actuator_lag") and c < 0:
                what = "delayed" if e.name == "input_delay" else "lagged"
                return k, f"a negative fraction {what} ({c:.4g})", bool(c < -2 * s)
            if e.name in SOFT_BOUNDS:
                lo, hi, what = SOFT_BOUNDS[e.name]
                if c < lo - 2 * s or c > hi + 2 * s:
                    return k, f"{what}: c = {c:.4g} +- {s:.2g}", True
        for st, w in vgrid.items():
            terms = [(k, c, s) for k, c, s in zip(keys, coef, se)
                     if k in by_key and by_key[k].name in FRICTION and by_key[k].state == st]
            if not terms:
                continue
            shp = shapes(w)
            a = nominal[st]
            phi = a[0] * shp["viscous_friction"] + a[1] * shp["coulomb_friction"] + a[2] * shp["drag"]
            contrib = {k: c * shp[by_key[k].name] for k, c, _ in terms}
            power = (phi + sum(contrib.values())) * w
            scale = float(np.max(np.abs(phi * w)) + sum(np.max(np.abs(g * w)) for g in contrib.values()))
            if np.max(power) <= 1e-9 * scale:
                continue
            at = int(np.argmax(power))
            k = max(contrib, key=lambda k: contrib[k][at] * w[at])
            c, s = [(c, s) for kk, c, s in terms if kk == k][0]
            # still injecting energy with this term 2 standard errors towards zero?
            shrunk = c - np.sign(c) * min(abs(c), 2 * s)
            power2 = power - (c - shrunk) * shp[by_key[k].name] * w
            return k, (f"{k} = {c:.4g} would inject energy: the total friction force pushes along the "
                       f"motion at v = {w[at]:.4g} (phi(v) v = {power[at]:.3g} > 0)"), bool(np.max(power2) > 1e-9 * scale)
        return None

    return check


# ---------------------------------------------------------------------------------------
# corrections carried into the states that integrate a velocity
# ---------------------------------------------------------------------------------------

def positions_of(system: System, v: int) -> list:
    """States x_p that integrate velocity x_v: d step_p / d x_v within 50 % of the base period on X x U
    (explicit, semi-implicit and exact discretisations alike)."""
    x, u = _sample_domain(system, 128, seed=3)
    dt = system.base_tau
    h = 1e-6 * max(1.0, float(system.x_hi[v] - system.x_lo[v]))
    xp, xm = x.copy(), x.copy()
    xp[:, v] += h
    xm[:, v] -= h
    Jv = (system.step(xp, u, dt) - system.step(xm, u, dt)) / (2 * h)
    return [p for p in range(system.n) if p != v and np.all(np.abs(Jv[:, p] - dt) < 0.5 * dt)]


def carry_matrix(system: System) -> np.ndarray:
    """K (n, n): a correction delta of velocity x_v's update moves position x_p's update by K[p, v] delta.

    A force-like correction acts in the model as an input does. For every velocity v
    (:func:`velocity_dims`) and input j that enters it, K[p, v] = (d step_p / d u_j) /
    (d step_v / d u_j) over random samples of X x U, for the positions p that integrate v
    (d step_p / d x_v within 50 % of the base period): 0 for explicit Euler (x_p+ = x_p + dt x_v), dt
    for semi-implicit Euler (x_p+ = x_p + dt x_v+, physics engines), dt / 2 for an exact
    (zero-order-hold) discretisation. Without an input entering v, K[:, v] = 0.
    """
    n = system.n
    K = np.zeros((n, n))
    vd = velocity_dims(system)
    if not vd:
        return K
    x, u = _sample_domain(system, 128, seed=3)
    dt = system.base_tau
    for v in vd:
        for j in range(system.m):
            Bv = _input_rate(system, v, j)(x, u)
            if not np.all(np.abs(Bv) > 1e-12 * max(1.0, float(np.abs(Bv).max()))):
                continue
            for p in positions_of(system, v):
                kappa = float(np.median(_input_rate(system, p, j)(x, u) / Bv))
                K[p, v] = kappa if abs(kappa) > 1e-9 * dt else 0.0
            break
    return K

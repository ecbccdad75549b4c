"""Generated refinement cases with a known truth: what an honest refinement must report.

Each case is a built-in nominal model f plus a planted truth (an effect in the library, an effect
outside it, an input delay, or nothing but noise), sampled either as independent rows (uniform
states in X, random inputs from U) or as time series (trajectories from random states with
random inputs held for a random number of periods). Every draw comes from a seeded generator.

``expect`` says what a correct report contains:

* ``{"effects": [(name, state_name), ...]}``: exactly these effects, no flag;
* ``{"flag": state_name}``: that state flagged unexplained (a residual the library cannot explain);
* ``{"delay": periods}``: an ``input_delay`` effect of that length;
* ``{"lag": state_name}``: on that state only ``actuator_lag`` effects (any of the library's time
  constants), or the state flagged;
* ``{"effects": []}``: nothing (noise only), no flag.

``truth`` holds the planted numbers (e.g. the dead-zone width) for error-bar checks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..systems import get_system
from .data import Transitions, make_transitions


@dataclass
class Case:
    name: str
    system: str
    data: Transitions
    expect: dict
    truth: dict = field(default_factory=dict)
    shape: str = ""


def _rows(sysname: str, K: int, rng, extra: Callable, noise: Callable) -> Transitions:
    """Independent rows: x uniform in X, u uniform from the input set, x+ = f + tau extra + noise."""
    s = get_system(sysname)
    x = s.x_lo + rng.random((K, s.n)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, len(s.inputs), K)]
    xn = s.f(x, u) + s.tau * extra(x, u) + noise(x, u, rng)
    return make_transitions(x, u, xn, s.tau, system=s, source=f"generated:{sysname}")


def _series(sysname: str, K: int, rng, extra: Callable, noise: Callable, delay: int = 0,
            runs: int = 40, lag: float = 0.0, timed: Callable = None, memory: Callable = None) -> Transitions:
    """``runs`` trajectories of K / runs transitions with random held inputs.

    The truth applies the input ``delay`` periods late: x+ = f(x, u[k - delay]) + tau extra + noise,
    and, with ``lag`` = T_a / tau > 0, through a first-order actuator a+ = a + (u - a) / lag (the
    acting input a starts at the first command). ``timed(x, u, t, p)`` adds a time-dependent rate
    (t the record's clock [s], p in [0, 1) the position in the record). ``memory(x, u, m)`` returns
    (rate, m'): a rate that depends on the past through its own state m (None at the start; hysteresis,
    a delayed coupling). Time stamps continue across runs with a gap, so runs are separate segments of
    one record.
    """
    s = get_system(sysname)
    T = K // runs
    U = s.inputs
    idx = rng.integers(0, len(U), (runs, T + delay))
    hold = rng.random((runs, T + delay)) < 0.5            # keep the previous input half of the time
    for k in range(1, T + delay):
        idx[:, k] = np.where(hold[:, k], idx[:, k - 1], idx[:, k])
    useq = U[idx]                                          # (runs, T + delay, m)
    if lag > 0:
        act = useq.copy()
        for k in range(1, T + delay):
            act[:, k] = act[:, k - 1] + (useq[:, k - 1] - act[:, k - 1]) / lag
    else:
        act = useq
    x = s.x_lo + (0.25 + 0.5 * rng.random((runs, s.n))) * (s.x_hi - s.x_lo)
    X, Uk, XN = [], [], []
    tt = (np.arange(runs)[:, None] * (T + 10) + np.arange(T)[None, :]) * s.tau
    pos = (np.arange(runs)[:, None] * T + np.arange(T)[None, :]) / (runs * T)
    mem = None
    for k in range(T):
        u_now, u_act = useq[:, k + delay], act[:, k]
        xn = s.f(x, u_act) + s.tau * extra(x, u_now) + noise(x, u_now, rng)
        if memory is not None:
            rate, mem = memory(x, u_now, mem)
            xn = xn + s.tau * rate
        if timed is not None:
            xn = xn + s.tau * timed(x, u_now, tt[:, k], pos[:, k])
        X.append(x), Uk.append(u_now), XN.append(xn)
        x = xn
    X, Uk, XN = (np.stack(a, axis=1).reshape(runs * T, -1) for a in (X, Uk, XN))
    t = tt.reshape(-1)
    return make_transitions(X, Uk, XN, s.tau, t, system=s, source=f"generated:{sysname}:series")


def _white(std):
    def noise(x, u, rng):
        return std * rng.standard_normal(x.shape)
    return noise


def _zero(x, u):
    return np.zeros_like(x)


def _on(dim, fn):
    def extra(x, u):
        out = np.zeros_like(x)
        out[:, dim] = fn(x, u)
        return out
    return extra


def _deadzone(x, u):
    """Pendulum torque through a dead zone of width 0.2: the model's input term minus what is lost."""
    w = 0.2
    lost = u[:, 0] - np.sign(u[:, 0]) * np.maximum(np.abs(u[:, 0]) - w, 0.0)
    return -_pend_B() * lost


def _friction_dead_zone(x, u):
    """Viscous friction that acts only beyond |omega| = 0.25 rad/s: -0.8 (omega - clip(omega))."""
    w = x[:, 1]
    return -0.8 * (w - np.clip(w, -0.25, 0.25))


def _backlash(x, u, a):
    """Pendulum torque through a backlash (play) of half-width 0.3: the acting input a follows u only
    when u pulls it beyond 0.3; the model's input term minus what the play holds back (hysteresis)."""
    a = u[:, 0].copy() if a is None else np.clip(a, u[:, 0] - 0.3, u[:, 0] + 0.3)
    out = np.zeros_like(x)
    out[:, 1] = _pend_B() * (a - u[:, 0])
    return out, a


def _delayed_coupling(x, u, past):
    """omega pulled towards where theta was 5 periods ago: -3 (theta[k-5] - theta[k])."""
    past = [x[:, 0].copy()] * 6 if past is None else past[1:] + [x[:, 0].copy()]
    out = np.zeros_like(x)
    out[:, 1] = -3.0 * (past[0] - x[:, 0])
    return out, past


def _pend_B():
    s = get_system("pendulum")
    return 3.0 / (float(s.params["m"]) * float(s.params["l"]) ** 2)


CASES = {
    # in the library
    "viscous": dict(system="pendulum", kind="rows", extra=_on(1, lambda x, u: -0.5 * x[:, 1]), std=1e-4,
                    expect={"effects": [("viscous_friction", "omega")]}, shape="in library"),
    "input_gain": dict(system="pendulum", kind="rows", extra=_on(1, lambda x, u: -0.2 * _pend_B() * u[:, 0]),
                       std=1e-4, expect={"effects": [("input_gain", "omega")]}, shape="in library"),
    "coulomb_viscous": dict(system="pendulum", kind="rows",
                            extra=_on(1, lambda x, u: -0.3 * x[:, 1] - 0.1 * np.sign(x[:, 1])), std=1e-4,
                            expect={"effects": [("coulomb_friction", "omega"), ("viscous_friction", "omega")]},
                            shape="in library"),
    "heading_bias": dict(system="turtlebot", kind="rows", extra=_on(2, lambda x, u: 0.05 + 0 * x[:, 2]),
                         std=1e-4, expect={"effects": [("bias", "theta")]}, shape="in library"),
    # unequal wheels: the heading turns with the speed, a path the unicycle model lacks (input_coupling)
    "heading_speed": dict(system="turtlebot", kind="rows", extra=_on(2, lambda x, u: 0.06 * u[:, 0]),
                          std=1e-4, expect={"effects": [("input_coupling", "theta")]}, truth={"coupling": 0.06},
                          shape="in library: heading turned by the speed"),
    # in the library only approximately: the dead zone's error bar must carry the misfit
    "dead_zone": dict(system="pendulum", kind="rows", extra=_on(1, _deadzone), std=1e-4,
                      expect={"effects": [("deadband", "omega")]}, truth={"width": 0.2},
                      shape="approximately in library"),
    # outside the library: three shapes
    "slip": dict(system="turtlebot", kind="rows",
                 extra=lambda x, u: np.stack([
                     -0.3 * (np.abs(u[:, 1]) > 0.5) * u[:, 0] * np.cos(x[:, 2]),
                     -0.3 * (np.abs(u[:, 1]) > 0.5) * u[:, 0] * np.sin(x[:, 2]),
                     0 * x[:, 2]], axis=1),
                 std=1e-4, expect={"flag": "x"}, shape="outside: wheel slip when |omega| > 0.5"),
    "ripple": dict(system="pendulum", kind="rows",
                   extra=_on(1, lambda x, u: 0.02 / 0.005 * np.sin(40 * x[:, 0]) * np.cos(12 * x[:, 1])),
                   std=2e-4, expect={"flag": "omega"}, shape="outside: smooth ripple (100 x noise)"),
    "terrain": dict(system="turtlebot", kind="rows", extra=_on(0, lambda x, u: 0.3 * np.sin(3 * x[:, 1])),
                    std=1e-4, expect={"flag": "x"}, shape="outside: position-dependent push"),
    # history
    "delay1": dict(system="pendulum", kind="series", delay=1, extra=_zero, std=1e-4,
                   expect={"delay": 1}, shape="input delay 1 period"),
    "delay2": dict(system="pendulum", kind="series", delay=2, extra=_zero, std=1e-4,
                   expect={"delay": 2}, shape="input delay 2 periods"),
    "delay7": dict(system="pendulum", kind="series", delay=7, extra=_zero, std=1e-4,
                   expect={"delay": 7}, shape="input delay 7 periods (deeper than the default 3)"),
    # a small effect next to a large one: Coulomb friction 2x the noise, 20x below an input-gain error
    "small_coulomb": dict(system="pendulum", kind="rows",
                          extra=_on(1, lambda x, u: -0.3 * _pend_B() * u[:, 0] - 0.027 * np.sign(x[:, 1])),
                          std=6.75e-5, expect={"effects": [("coulomb_friction", "omega"), ("input_gain", "omega")]},
                          truth={"coulomb": -0.027}, shape="in library: small Coulomb next to a large gain error"),
    # outside the library, issue 57: a friction dead zone (viscous + Coulomb outside it, zero inside),
    # friction that depends on the position, hysteresis (backlash) and a delayed state coupling
    "friction_dead_zone": dict(system="pendulum", kind="rows", extra=_on(1, _friction_dead_zone), std=1e-4,
                               expect={"flag": "omega"}, shape="outside: viscous friction only beyond |omega| 0.25"),
    "position_friction": dict(system="pendulum", kind="rows",
                              extra=_on(1, lambda x, u: -0.8 * x[:, 1] * (1 + 0.9 * np.sin(15 * x[:, 0]))),
                              std=1e-4, expect={"flag": "omega"}, shape="outside: friction varying with the angle"),
    "backlash": dict(system="pendulum", kind="series", extra=_zero, memory=_backlash, std=1e-4,
                     expect={"flag": "omega"}, shape="outside: backlash (hysteresis) of 0.3 on the torque"),
    "delayed_coupling": dict(system="pendulum", kind="series", extra=_zero, memory=_delayed_coupling, std=1e-4,
                             expect={"flag": "omega"}, shape="outside: omega coupled to theta 5 periods ago"),
    # time: a periodic disturbance (period 0.37 s, 99.7 % of the residual) and an actuator gain
    # drifting from 1.0 to 0.6 over the record
    "periodic": dict(system="pendulum", kind="series", extra=_zero, std=1e-4,
                     timed=lambda x, u, t, p: np.stack([0 * t, 0.5 * np.sin(2 * np.pi * t / 0.37)], 1),
                     expect={"flag": "omega"}, truth={"period": 0.37}, shape="outside: periodic disturbance in time"),
    "drift": dict(system="pendulum", kind="series", extra=_zero, std=1e-4,
                  timed=lambda x, u, t, p: np.stack([0 * t, -0.4 * p * _pend_B() * u[:, 0]], 1),
                  expect={"flag": "omega"}, shape="outside: input gain drifting 1.0 -> 0.6 over the record"),
    # memory: a first-order actuator lag of 5 periods (a library time constant) and of 6.5 (between two)
    "actuator_lag": dict(system="pendulum", kind="series", lag=5.0, extra=_zero, std=1e-4,
                         expect={"effects": [("actuator_lag", "omega")]}, truth={"lag_periods": 5.0},
                         shape="memory: first-order actuator lag (5 periods)"),
    "actuator_lag_offgrid": dict(system="pendulum", kind="series", lag=6.5, extra=_zero, std=1e-4,
                                 expect={"lag": "omega"}, truth={"lag_periods": 6.5},
                                 shape="memory: first-order actuator lag (6.5 periods, between library values)"),
    "actuator_lag_long": dict(system="pendulum", kind="series", lag=40.0, extra=_zero, std=1e-4,
                              expect={"lag": "omega"}, truth={"lag_periods": 40.0},
                              shape="memory: first-order actuator lag (40 periods, beyond the library's 20)"),
    # an input saturation at |u| = 0.6: a dead zone would need a negative width
    "saturation": dict(system="pendulum", kind="rows",
                       extra=_on(1, lambda x, u: -_pend_B() * (u[:, 0] - np.clip(u[:, 0], -0.6, 0.6))),
                       std=1e-4, expect={"flag": "omega"}, shape="outside: input saturation at |u| = 0.6"),
    # noise only
    "noise": dict(system="pendulum", kind="rows", extra=_zero, std=1e-3, expect={"effects": []},
                  shape="pure noise"),
    "hetero_noise": dict(system="turtlebot", kind="rows", extra=_zero,
                         noise=lambda x, u, rng: 1e-3 * (0.1 + 3 * np.abs(u[:, [0]]) + np.abs(x[:, [2]]))
                         * rng.standard_normal(x.shape),
                         expect={"effects": []}, shape="heteroscedastic noise"),
    "noise_series": dict(system="pendulum", kind="series", extra=_zero, std=1e-4, expect={"effects": []},
                         shape="pure noise, time series"),
}


def make_case(name: str, K: int = 20000, seed: int = 0) -> Case:
    """The generated case ``name`` (see :data:`CASES`) with K transitions."""
    c = CASES[name]
    rng = np.random.default_rng(seed)
    noise = c.get("noise") or _white(c["std"])
    if c["kind"] == "rows":
        data = _rows(c["system"], K, rng, c["extra"], noise)
    else:
        data = _series(c["system"], K, rng, c["extra"], noise, delay=c.get("delay", 0), lag=c.get("lag", 0.0),
                       timed=c.get("timed"), memory=c.get("memory"))
    return Case(name=name, system=c["system"], data=data, expect=c["expect"], truth=c.get("truth", {}),
                shape=c.get("shape", ""))


def verdict(case: Case, report: dict) -> tuple:
    """(ok, what was found) of a refine report against the case's expectation."""
    found = sorted((e["name"], e["state_name"]) for e in report["effects"])
    flagged = sorted(s["state_name"] for s in report["states"] if s["unexplained"])
    desc = ", ".join(f"{n}:{s}" for n, s in found) or "no effect"
    if flagged:
        desc += "; flagged " + ",".join(flagged)
    ex = case.expect
    if "width" in case.truth:
        # a wrong-shaped term: right name, and an error bar that covers the truth (or a flag)
        d = [e for e in report["effects"] if e["name"] == "deadband"]
        covers = bool(d) and abs(-d[0]["coefficient"] - case.truth["width"]) <= 2 * d[0]["stderr"]
        return bool(d) and (covers or bool(flagged)), desc
    if "flag" in ex:
        return ex["flag"] in flagged, desc
    if "lag" in ex:
        on = [e["name"] for e in report["effects"] if e["state_name"] == ex["lag"]]
        return (bool(on) and set(on) == {"actuator_lag"}) or ex["lag"] in flagged, desc
    if "delay" in ex:
        d = [e for e in report["effects"] if e["name"] == "input_delay"]
        ok = bool(d) and all(e.get("periods") == ex["delay"] for e in d) and not flagged
        return ok, desc
    return found == sorted(ex["effects"]) and not flagged, desc


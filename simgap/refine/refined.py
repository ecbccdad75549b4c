"""The refined model f'(x, u) = f(x, u) + tau * sum_k c_k g_k(x, u) as a first-class System.

A refined system is an ordinary :class:`simgap.systems.System` (same X, U, base_tau, names,
angle dims) whose one-base-step map is

    step'(x, u, dt) = step(x, u, dt) + (I + K) dt * sum_k c_k g_k(x, u) e_{i_k}

(effect k enters state i_k; K = :func:`simgap.refine.effects.carry_matrix` carries a correction of a
velocity's update into the positions that integrate it as the model's own discretisation does:
zero for the explicit-Euler built-ins, dt for a semi-implicit model). With ``steps`` = k > 1 the effects act in every base step, so
f' is the k-fold composition as for any system. Its ``params`` carry ``base_system`` (the
built-in it started from) and ``refinement`` (the effects with coefficients), so reports and
manifests show what was added.

Saved as JSON (``format: simgap-refined-system``)::

    {"format": "simgap-refined-system", "version": 1, "name": "pendulum_refined",
     "base": "pendulum", "steps": 1,
     "effects": [{"name": "viscous_friction", "state": 1, "variable": "omega",
                  "coefficient": -0.4987, "stderr": 0.003}]}

``base`` is a built-in or plugin name, an embedded system file (``format: simgap-system``,
:mod:`simgap.system_file`) or, for a refinement of a refinement, the nested JSON object.
:func:`load_system` accepts a built-in name or the path of such a file wherever a system is
expected.

Jacobian bound: the base bound plus dt |c_k| max |d g_k / d x| estimated by central differences
on 256 random states of X (times 1.05); exact for terms linear in x (bias, viscous friction,
input gains of the built-ins). A discontinuous term (Coulomb friction, deadband with a
state-dependent gain, user terms with sign/abs) has no Lipschitz bound: the refined system then
has ``jacobian_bound = None`` and its Lipschitz constant must be estimated from data.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import SimgapError
from ..systems import BUILTIN, System, get_system, is_named
from ..system_ref import resolve_system
from .effects import Effect, carry_matrix, effect_from_spec, integration_effect

FORMAT = "simgap-refined-system"


def refined_system(base: System, effects: Sequence[Effect], coefficients: Sequence[float],
                   stderrs: Optional[Sequence[float]] = None, name: Optional[str] = None) -> System:
    """f' = f + tau * sum_k c_k g_k as a new System (see module docstring)."""
    effects = list(effects)
    c = np.asarray(coefficients, dtype=float).reshape(-1)
    if c.size != len(effects):
        raise SimgapError(f"refined system: {len(effects)} effects but {c.size} coefficients")
    if not np.all(np.isfinite(c)):
        raise SimgapError("refined system: coefficients must be finite")
    se = np.full(c.size, np.nan) if stderrs is None else np.asarray(stderrs, dtype=float).reshape(-1)
    base_step = base.step
    if any(e.name == "integration" for e in effects):
        # the integration term uses the refined velocity update (all other effects included)
        other = [(e, ck) for e, ck in zip(effects, c) if e.name != "integration"]
        inner = refined_system(base, [e for e, _ in other], [ck for _, ck in other])
        effects = [integration_effect(inner, e.state, inner.state_names.index(e.variable))
                   if e.name == "integration" else e for e in effects]

    # a correction of a velocity's update also moves the positions that integrate it, as the
    # model's own discretisation does (carry_matrix: 0 for explicit Euler, dt semi-implicit)
    K = carry_matrix(base) if effects else np.zeros((base.n, base.n))
    carried = bool(np.any(K))

    def step(x, u, dt):
        out = np.array(base_step(x, u, dt), dtype=float, copy=True)
        add = np.zeros_like(out)
        for e, ck in zip(effects, c):
            add[:, e.state] += dt * ck * e(x, u)
        if carried:
            add += (dt / base.base_tau) * add @ K.T
        return out + add

    jac = None
    if base.jacobian_bound is not None and all(e.smooth for e in effects):
        rng = np.random.default_rng(0)
        xs = base.x_lo + rng.random((256, base.n)) * (base.x_hi - base.x_lo)
        dt0 = base.base_tau

        def effect_bound(uu):
            """max over the sample states of |d/dx sum_k c_k g_k(x, u)|, (B, n, n) for unique inputs."""
            B, S, n = uu.shape[0], xs.shape[0], base.n
            X = np.repeat(xs[None], B, axis=0).reshape(B * S, n)
            U = np.repeat(uu, S, axis=0)
            D = np.zeros((B, n, n))
            for j in range(n):
                h = 1e-6 * max(1.0, float(base.x_hi[j] - base.x_lo[j]))
                Xp, Xm = X.copy(), X.copy()
                Xp[:, j] += h
                Xm[:, j] -= h
                dsum = np.zeros((B * S, n))
                for e, ck in zip(effects, c):
                    dsum[:, e.state] += ck * (e(Xp, U) - e(Xm, U)) / (2 * h)
                if carried:
                    dsum += dsum @ K.T
                D[:, :, j] = np.abs(dsum).reshape(B, S, n).max(axis=1)
            return D

        def jac(u):
            u = np.atleast_2d(np.asarray(u, dtype=float))
            J = np.array(base.jacobian_bound(u), dtype=float, copy=True)
            if not effects:
                return J
            # the bound depends on u only: evaluate once per distinct input (synthesis asks for
            # millions of rows drawn from the finite input set)
            uniq, inv = np.unique(u, axis=0, return_inverse=True)
            return J + 1.05 * dt0 * effect_bound(uniq)[inv.reshape(-1)]

    refinement = [dict(e.spec(), coefficient=float(ck), stderr=float(sk) if np.isfinite(sk) else None)
                  for e, ck, sk in zip(effects, c, se)]
    params = dict(base.params)
    params["base_system"] = str(base.params.get("base_system", base.name))
    params["refinement"] = list(base.params.get("refinement", [])) + refinement
    return System(name=name or f"{base.name}_refined", state_names=base.state_names,
                  input_names=base.input_names, x_lo=base.x_lo, x_hi=base.x_hi, inputs=base.inputs,
                  base_tau=base.base_tau, step=step, angle_dims=base.angle_dims, steps=base.steps,
                  jacobian_bound=jac, params=params)


def refined_to_dict(system: System, base_spec, effects: Sequence[Effect], coefficients, stderrs) -> dict:
    """The JSON object of a refined system built on ``base_spec`` (a name or a nested dict)."""
    return {"format": FORMAT, "version": 1, "name": system.name, "base": base_spec,
            "steps": int(system.steps),
            "effects": [dict(e.spec(), coefficient=float(c),
                             stderr=float(s) if np.isfinite(s) else None)
                        for e, c, s in zip(effects, coefficients, stderrs)]}


def save_refined(system: System, path: str | Path) -> Path:
    """Write a refined system (made by :func:`refined_system` / :func:`system_from_dict`) as JSON.

    Written atomically (temp file + rename).
    """
    d = system.params.get("_refined_json")
    if d is None:
        raise SimgapError(f"system {system.name!r} is not a refined system built by simgap.refine")
    base = d["base"]
    if not (isinstance(base, dict) or is_named(base)):
        raise SimgapError(f"cannot save refined system: its base {base!r} is a system defined in Python only; "
                          f"write it as a system file (docs/system-files.md) or register it as a plugin, or "
                          f"rebuild it in Python with refined_system()")
    d = dict(d, steps=int(system.steps), name=system.name)
    from .. import fileio
    return fileio.write_text(Path(path), json.dumps(d, indent=2, allow_nan=False))


def build_refined(base: System, base_spec, effects: Sequence[Effect], coefficients,
                  stderrs=None, name: Optional[str] = None) -> System:
    """:func:`refined_system` that also remembers its JSON form (for :func:`save_refined`)."""
    stderrs = np.full(len(effects), np.nan) if stderrs is None else stderrs
    sysobj = refined_system(base, effects, coefficients, stderrs, name=name)
    sysobj.params["_refined_json"] = refined_to_dict(sysobj, base_spec, effects, coefficients, stderrs)
    return sysobj


MAX_NESTING = 16  # refinements of refinements a file may hold


def system_from_dict(d: dict, _depth: int = 0) -> System:
    """Rebuild a refined system from its JSON object (see module docstring)."""
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise SimgapError(f"not a simgap refined-system file (need \"format\": \"{FORMAT}\")")
    if _depth > MAX_NESTING:
        raise SimgapError(f"refined system: more than {MAX_NESTING} nested refinements")
    from ..file_guard import printable
    missing = [k for k in ("base", "effects") if k not in d]
    if missing:
        raise SimgapError(f"refined system: needs 'base' and 'effects' (missing {', '.join(missing)})")
    base_spec, effs, steps = d["base"], d["effects"], d.get("steps", 1)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise SimgapError(f"refined system: \"steps\" must be a whole number of base steps >= 1, got "
                          f"{printable(repr(steps))[:80]}")
    from ..systems import MAX_STEPS
    if steps > MAX_STEPS:  # checked before the model is built: every transition would take `steps` evaluations
        raise SimgapError(f"refined system: \"steps\": {steps:,} base steps per sampling period is more than the "
                          f"{MAX_STEPS:,} simgap accepts (refused before any work); give \"steps\" <= {MAX_STEPS:,}")
    name = d.get("name")
    if name is not None and (not isinstance(name, str) or is_named(name)):
        raise SimgapError(f"refined system: name {printable(repr(name))[:80]} must be a string other than a built-in's "
                          "or plugin's")
    if name is not None and printable(name) != name:
        raise SimgapError(f"refined system: name {printable(repr(name))[:80]} holds control characters (terminal "
                          "escape codes); give a plain name")
    from ..system_file import is_spec, system_from_spec
    if is_spec(base_spec):
        base = system_from_spec(base_spec, "refined system: its base system file").with_steps(1)
    elif isinstance(base_spec, dict):
        base = system_from_dict(base_spec, _depth + 1).with_steps(1)
    elif is_named(base_spec):
        base = get_system(base_spec)
    else:
        raise SimgapError(f"refined system: base {base_spec!r} is not a built-in system "
                          f"({', '.join(sorted(BUILTIN))}), an installed plugin system, an embedded system file "
                          f"or a nested refined system")
    if not isinstance(effs, list):
        raise SimgapError("refined system: 'effects' must be a list")
    effects, coefs, ses = [], [], []
    for spec in effs:
        if not isinstance(spec, dict) or "coefficient" not in spec:
            raise SimgapError(f"refined system: effect {spec!r} has no coefficient")
        effects.append(effect_from_spec(base, spec))
        try:
            coefs.append(float(spec["coefficient"]))
            se = spec.get("stderr")
            ses.append(float("nan") if se is None else float(se))
        except (TypeError, ValueError):
            raise SimgapError(f"refined system: effect {printable(repr(spec.get('name')))} has a coefficient or "
                              f"stderr that is not a number") from None
    _check_terms(base, effects, coefs)
    sysobj = build_refined(base, base_spec, effects, coefs, ses, name=name).with_steps(steps)
    check_values(sysobj, "refined system")
    return sysobj


#: largest |term| an effect may add in one base step: its square (residual variances, R^2) stays finite
MAX_TERM = 1e150


def _check_terms(base: System, effects, coefs) -> None:
    """Refuse, by the effect's name, state and coefficient, a coefficient whose term base_tau c g(x, u)
    is not finite or so large that its square overflows, at the corners and seeded states of X with
    each input (up to 16): the model may stay finite on X while every report of it holds inf."""
    from ..file_guard import printable
    from ..system_file import _check_states
    X = _check_states(base.x_lo, base.x_hi)
    U = base.inputs[:16]
    Xr, Ur = np.repeat(X, len(U), axis=0), np.tile(U, (len(X), 1))
    for e, ck in zip(effects, coefs):
        if e.name == "integration":  # built from the other effects' terms, which are checked
            continue
        with np.errstate(all="ignore"):
            big = float(np.max(np.abs(base.base_tau * ck * np.asarray(e(Xr, Ur), dtype=float)), initial=0.0))
        if not np.isfinite(ck) or not np.isfinite(big) or big > MAX_TERM:
            what = "is not finite" if not np.isfinite(ck) else (
                f"makes its term base_tau c g(x, u) reach {big:.3g} at a state of X" if np.isfinite(big)
                else "makes its term overflow to inf at a state of X")
            raise SimgapError(f"refined system: effect {printable(e.name)!r} on state "
                              f"{base.state_names[e.state]!r}: \"coefficient\": {ck:g} {what} (its square overflows; "
                              f"at most {MAX_TERM:g} per base step): not a fitted value; fit it again with "
                              "simgap refine --save-system, or correct it")


def check_values(system: System, where: str) -> None:
    """Refuse a model that is not finite on X: evaluated once per input at the corners and seeded
    states of X (:mod:`simgap.system_file`'s check), so inf or NaN is named on load, not in a report."""
    from ..system_file import _check_finite, _check_states
    xs = _check_states(system.x_lo, system.x_hi)
    _check_finite(lambda x, u, dt: system.f(x, u), xs, system.inputs, 0.0, list(system.state_names), where,
                  "the refined model")


def load_refined(path: str | Path) -> System:
    """Load a refined system JSON file."""
    from ..file_guard import read_json
    d = read_json(path, "refined system")
    return system_from_dict(d)


def load_system(name_or_path, steps: Optional[int] = None) -> System:
    """A system by built-in name, refined-system JSON (path or object) or System:
    :func:`simgap.system_ref.resolve_system`."""
    return resolve_system(name_or_path, steps)

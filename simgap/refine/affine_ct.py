"""Affine continuous-time terms on the velocity states: the damping a model lacks, found from
one-step transitions and written back as a system file (library entry ``affine_ct``).

A rigid-body model M(q) qdd = tau - C(q, qd) - g(q) that leaves out joint damping D qd misses
qdd += -M(q)^-1 D qd: through the mass matrix, one joint's damper also acts on the other joints'
accelerations (the cart-pole's hinge damper moves the cart: v' <- omega, and the slider's moves the
pole: omega' <- v). Near a working region M(q)^-1 is nearly constant, so the missing terms are
close to affine. This entry adds, to the continuous-time right-hand side F_i of every velocity
state i (or, for a discrete map, to its update as dt * (...)),

    dx_i/dt = F_i(x, u) + c_i0 + sum_j c_ij x_j + sum_k d_ik u_k,

over the states that are not translation invariant and over the inputs, and fits the
coefficients to one-step transitions (x, u, x_next) by Gauss-Newton **on the model that is saved**:
the refined system file integrated with the base file's own RK4 substeps (so positions pick up
the velocity terms the way the integrator carries them; no first-order approximation remains in
what is reported). The start is the linear least-squares fit of the velocity residual / tau on
(1, x, u) (the first-order reading).

Confidence: every coefficient carries a heteroskedasticity-robust (sandwich, HC0) standard error
from the final Jacobian of the velocity residuals in the coefficients, and a 95 % interval
+- 1.96 stderr (a normal approximation: with noise-free data the spread is the misfit of the
affine form, not noise). The before/after errors are on held-out rows (a seeded 30 % split).

The output is a system-file table (:func:`refined_spec`) with the coefficients as parameters
``ct_<state>_<variable>``, one definition ``ct_<state>`` per velocity state and the formulas
``(<base formula>) + ct_<state>``; every formula goes through the expression allow-list of
:mod:`simgap.expr` when it is read. A ``growth`` bound of the base file is carried over soundly
(|c_ij| added off the diagonal, c_ii on it: the added term's derivative is that constant); a
``jacobian`` bound is dropped (the refined file's bound is then estimated) and the report says so.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import SimgapError
from ..systems import System

NAME = "affine_ct"
Z95 = 1.959963984540054


def base_spec(system: System) -> dict:
    """The system-file table ``system`` was built from (a system file's own, embedded), else refused."""
    spec = (system.params or {}).get("_system_file")
    if not isinstance(spec, dict):
        raise SimgapError(f"--effects {NAME}: system {system.name!r} is not a system file (a built-in, plugin or "
                          "refined-system JSON); the affine terms are written into a system file's formulas, so give "
                          "--system FILE.toml")
    return copy.deepcopy(spec)


def _variables(spec: dict) -> list:
    """The terms' variables: "1", the states not declared translation invariant, the inputs."""
    inv = set(spec.get("translation_invariant") or [])
    return ["1"] + [s for s in spec["states"] if s not in inv] + list(spec["inputs"])


def _velocities(spec: dict, system: System) -> list:
    vel = list(spec.get("velocities") or [])
    if not vel:
        vel = [system.state_names[i] for i in (system.params or {}).get("velocity_dims", [])]
    if not vel:
        raise SimgapError(f"--effects {NAME}: system {system.name!r} declares no velocity states; add "
                          "velocities = [...] to its system file (the affine terms act on velocity states)")
    return vel


def _param(state: str, var: str) -> str:
    return f"ct_{state}_{'const' if var == '1' else var}"


def refined_spec(spec: dict, coef: dict, name: Optional[str] = None) -> dict:
    """The system-file table of ``spec`` with the affine terms ``coef`` {state: {variable: c}} added
    (module docstring). Parameter and definition names are refused if the base file already uses them."""
    out = copy.deepcopy(spec)
    params = dict(out.get("params") or {})
    defs = dict(out.get("definitions") or {})
    dyn = dict(out["dynamics"])
    taken = set(params) | set(defs) | set(out["states"]) | set(out["inputs"])
    discrete = dyn.get("kind") == "discrete"
    for st, cs in coef.items():
        dname = f"ct_{st}"
        terms = []
        for var, c in cs.items():
            p = _param(st, var)
            if p in taken or dname in taken:
                raise SimgapError(f"--effects {NAME}: the system file already uses the name {p if p in taken else dname!r}")
            params[p] = float(c)
            terms.append(p if var == "1" else f"{p}*{var}")
        defs[dname] = " + ".join(terms) if terms else "0"
        dyn[st] = f"({dyn[st]}) + {'dt*' if discrete else ''}{dname}"
    out["params"], out["definitions"], out["dynamics"] = params, defs, dyn
    bounds = out.get("bounds")
    if bounds and "growth" in bounds:
        G = [list(r) for r in bounds["growth"]]
        idx = {s: i for i, s in enumerate(out["states"])}
        for st, cs in coef.items():
            i = idx[st]
            for var, c in cs.items():
                if var in idx:
                    j = idx[var]
                    add = float(c) if i == j else abs(float(c))
                    G[i][j] = f"({G[i][j]}) + ({add!r})" if isinstance(G[i][j], str) else float(G[i][j]) + add
                    if i != j and not isinstance(G[i][j], str):
                        G[i][j] = max(G[i][j], 0.0)
        out["bounds"] = dict(bounds, growth=G)
    elif bounds and "jacobian" in bounds:
        out.pop("bounds")
    out["name"] = name or f"{spec['name']}_{NAME}"
    out["description"] = (f"{spec.get('description', spec['name'])}; plus affine continuous-time terms on "
                          f"{', '.join(coef)} fitted by simgap refine ({NAME})")
    return out


@dataclass
class AffineFit:
    """What :func:`fit_affine_ct` found (``report`` is JSON-ready)."""

    spec: dict                  # the refined system-file table
    system: System              # built from ``spec`` at the data's steps
    base: System                # the base model at the data's steps
    report: dict = field(default_factory=dict)


def _build(spec: dict, steps: int) -> System:
    from ..system_file import system_from_spec
    s = system_from_spec(spec, where=f"refined system file ({NAME})")
    return s if steps == s.steps else s.with_steps(steps)


def fit_affine_ct(system: System, data, *, holdout: float = 0.3, seed: int = 0, iterations: int = 4,
                  name: Optional[str] = None) -> AffineFit:
    """Fit the affine continuous-time terms of the module docstring to the transitions ``data``
    (:class:`simgap.refine.data.Transitions`) of the system file ``system``; see :class:`AffineFit`."""
    from .residual import match_tau
    spec = base_spec(system)
    base = match_tau(system, data.tau)
    steps = base.steps
    states = list(spec["states"])
    vel = _velocities(spec, system)
    vidx = [states.index(v) for v in vel]
    variables = _variables(spec)
    K = data.K
    P = len(vel) * len(variables)
    if K < 10 * P:
        raise SimgapError(f"--effects {NAME}: {K} transitions for {P} coefficients; need at least {10 * P}")
    if not 0.0 < holdout < 1.0:
        raise SimgapError(f"--holdout must be in (0, 1), got {holdout}")
    rng = np.random.default_rng(seed)
    held = np.zeros(K, dtype=bool)
    held[rng.permutation(K)[:int(round(holdout * K))]] = True
    train = ~held
    X, U, Y = data.x, data.u, data.x_next
    cols = {"1": np.ones(K)}
    cols.update({s: X[:, i] for i, s in enumerate(states)})
    cols.update({s: U[:, j] for j, s in enumerate(spec["inputs"])})
    Phi = np.stack([cols[v] for v in variables], axis=1)          # (K, p) features
    tau = base.tau

    def coef_of(theta):
        th = theta.reshape(len(vel), len(variables))
        return {v: {var: float(c) for var, c in zip(variables, row)} for v, row in zip(vel, th)}

    def predict(theta, rows):
        s = _build(refined_spec(spec, coef_of(theta), name), steps)
        return s.f(X[rows], U[rows])

    r0 = base.diff(Y, base.f(X, U))                                 # residual of the base model
    # start: first-order reading, velocity residual / tau regressed on the features
    theta = np.concatenate([np.linalg.lstsq(Phi[train], r0[train, i] / tau, rcond=None)[0] for i in vidx])
    scale = np.maximum(np.abs(Phi[train]).max(axis=0), 1e-12)     # finite-difference steps per feature
    rows = np.flatnonzero(train)
    for _ in range(int(iterations)):
        base_pred = predict(theta, rows)
        e = base.diff(Y[rows], base_pred)[:, vidx].ravel(order="F")  # velocity residuals, state-major
        J = np.empty((e.size, P))
        for k in range(P):                                          # the map is affine in theta up to O(tau^2)
            h = 1e-3 / scale[k % len(variables)]
            t2 = theta.copy()
            t2[k] += h
            J[:, k] = (base.diff(predict(t2, rows), base_pred)[:, vidx].ravel(order="F")) / h
        step = np.linalg.lstsq(J, e, rcond=None)[0]
        theta = theta + step
        if np.all(np.abs(step) <= 1e-10 + 1e-8 * np.abs(theta)):
            break
    # sandwich (HC0) standard errors at the final point
    pred = predict(theta, rows)
    e = base.diff(Y[rows], pred)[:, vidx].ravel(order="F")
    JtJ_inv = np.linalg.pinv(J.T @ J)
    cov = JtJ_inv @ (J.T * e ** 2) @ J @ JtJ_inv
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    refined = _build(refined_spec(spec, coef_of(theta), name), steps)
    hx = np.flatnonzero(held)
    before = np.abs(base.diff(Y[hx], base.f(X[hx], U[hx])))
    after = np.abs(base.diff(Y[hx], refined.f(X[hx], U[hx])))
    effects = []
    for k in range(P):
        st, var = vel[k // len(variables)], variables[k % len(variables)]
        effects.append({"name": NAME, "state": states.index(st), "state_name": st, "variable": var,
                        "parameter": _param(st, var), "coefficient": float(theta[k]), "stderr": float(se[k]),
                        "ci95": [float(theta[k] - Z95 * se[k]), float(theta[k] + Z95 * se[k])],
                        "in_refined_system": True})
    notes = []
    if (spec.get("bounds") or {}).get("jacobian") is not None:
        notes.append("the base file's [bounds] jacobian does not hold for the refined formulas: dropped (the refined "
                     "file's Jacobian bound is estimated)")
    if (spec.get("bounds") or {}).get("growth") is not None:
        notes.append("[bounds] growth carried over: |c_ij| added off the diagonal, c_ii on it (the added term's "
                     "derivative is that constant, so the bound stays sound)")
    report = {
        "method": NAME, "system": system.name, "refined_system": refined.name, "tau": float(tau),
        "samples": int(K), "train": int(train.sum()), "heldout": int(held.sum()), "holdout_kind": "random rows",
        "variables": variables, "velocity_states": vel, "effects": effects,
        "rms_before": np.sqrt((before ** 2).mean(axis=0)).tolist(), "rms_after": np.sqrt((after ** 2).mean(axis=0)).tolist(),
        "max_before": before.max(axis=0).tolist(), "max_after": after.max(axis=0).tolist(),
        "confidence": "95 % intervals coefficient +- 1.96 stderr, stderr heteroskedasticity-robust (sandwich, HC0) "
                      "from the Gauss-Newton Jacobian on the training rows",
        "notes": notes, "data": data.source,
    }
    return AffineFit(spec=refined_spec(spec, coef_of(theta), name), system=refined, base=base, report=report)


def format_affine_table(report: dict, state_names) -> str:
    """The terminal table of an ``affine_ct`` report: coefficients with intervals, then held-out errors."""
    lines = [f"{NAME}: affine continuous-time terms on {', '.join(report['velocity_states'])} over "
             f"{', '.join(report['variables'])} ({report['train']} train / {report['heldout']} held-out transitions)",
             f"{'state':<10}{'variable':<12}{'coefficient':>14}{'stderr':>12}   95 % interval"]
    for e in report["effects"]:
        lines.append(f"{e['state_name']:<10}{e['variable']:<12}{e['coefficient']:>14.6g}{e['stderr']:>12.3g}   "
                     f"[{e['ci95'][0]:.6g}, {e['ci95'][1]:.6g}]")
    lines.append(f"{'held-out':<10}{'rms before':>14}{'rms after':>14}{'max before':>14}{'max after':>14}")
    for i, nm in enumerate(state_names):
        lines.append(f"{nm:<10}{report['rms_before'][i]:>14.4g}{report['rms_after'][i]:>14.4g}"
                     f"{report['max_before'][i]:>14.4g}{report['max_after'][i]:>14.4g}")
    lines += [f"note: {n}" for n in report.get("notes", [])]
    return "\n".join(lines)


def save_system_file(fit: AffineFit, path) -> None:
    """Write the refined system file (TOML, read back and checked before the file is replaced)."""
    from .. import fileio
    from ..system_split import toml_text
    header = (f"{fit.spec['name']}: written by simgap refine --effects {NAME} from {fit.report.get('data') or 'data'}.\n"
              f"The base model {fit.report['system']!r} plus affine continuous-time terms (definitions ct_*, "
              "parameters ct_*_*);\nsee docs/refine.md, \"Affine continuous-time terms\".")
    fileio.write_text(path, toml_text(fit.spec, header))

"""System files: a user's nominal model x+ = f(x, u) as a TOML file, parsed, never executed.

A system file (reference: docs/system-files.md) names the state and input variables, the box
X, the input set U, the base period tau and either a discrete-time one-step map or a
continuous-time right-hand side x' = F(x, u) that is integrated with classical RK4
(:func:`simgap.runge_kutta.rk4_integrate`, ``substeps`` per base period)::

    format = "simgap-system"
    name = "duffing"
    states = ["x", "v"]
    inputs = ["F"]
    units = {x = "m", v = "m/s", F = "N"}
    x_lo = [-1.5, -2.0]
    x_hi = [1.5, 2.0]
    tau = 0.05
    input_grid = {lo = [-1.0], hi = [1.0], counts = [11]}

    [params]
    d = 0.3
    k = 1.0
    k3 = 0.5

    [dynamics]
    kind = "continuous"
    substeps = 10
    x = "v"
    v = "-k*x - k3*x^3 - d*v + F"

Every formula goes through :mod:`simgap.expr`'s allow-list (numbers, the variables, ``pi``,
``e``, + - * / ^, the listed functions); parameters are folded in as constants, and
``[definitions]`` (named intermediate formulas) are computed first, in dependency order. A file that
refers to an unknown name, has the wrong number of entries, empty or non-finite bounds, or a
map that is not finite on X (checked on the corners of X and seeded random states, with every
input) is refused with a message naming the problem.

``velocities`` names the velocity states (the refinement library's friction and drag act on
them; :func:`simgap.refine.effects.velocity_dims`), ``angles`` the states wrapped to [-pi, pi),
``translation_invariant`` the states f(x, u) - x does not depend on (synthesis uses this and
checks it numerically).

Optional bounds (``[bounds]``): ``jacobian`` (n x n, |d step_i / d x_j| <= J_ij on X for one base
step; formulas of the inputs, parameters and ``dt``), or, for a continuous model, ``growth``
(n x n Metzler matrix L of SCOTS's growth bound: L_ii >= sup dF_i/dx_i, L_ij >= sup |dF_i/dx_j|),
which gives the one-step bound exp(L tau). Without them the bound is estimated as for refined
systems: central differences of the step on 256 seeded states of X per input, plus 5 % of the
largest |d step / dx - I| (not a proof; the description says ``jacobian: estimated``); a model with sign/abs/where/...
gets none (certify then estimates L_f from data, synthesize needs a bound).

The parsed table travels as a JSON object (``"format": "simgap-system"``) embedded in data
manifests, certificates and controllers (``System.params["_system_file"]``), so every later
command rebuilds the model without the file; its :func:`spec_digest` identifies the model.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Optional

import numpy as np

from . import expr
from .errors import SimgapError
from .fileio import content_digest
from .systems import System, input_grid

FORMAT = "simgap-system"
VERSION = 1
#: keys of the top level and of the sub-tables (anything else is an error naming the nearest)
KEYS = ("format", "version", "name", "description", "states", "inputs", "units", "x_lo", "x_hi", "tau",
        "steps", "angles", "velocities", "translation_invariant", "input_grid", "input_set", "params", "definitions", "dynamics", "bounds")
DYNAMICS_KINDS = ("discrete", "continuous")
BOUND_KEYS = ("jacobian", "growth")
#: names a variable or parameter may not take (the expression language's own words)
RESERVED = frozenset(expr.FUNCTIONS) | frozenset(expr.CONSTANTS) | {"dt", "t"}
MAX_SUBSTEPS = 10_000
#: sizes a file may ask for (a file is data: it must not make simgap allocate without bound)
MAX_STATES, MAX_INPUT_DIMS, MAX_INPUTS = 32, 16, 100_000
#: rows per block when the model is checked on X x U and its Jacobian estimated
BLOCK_ROWS = 200_000
#: states of X per input on which the map is checked finite and its Jacobian estimated
CHECK_STATES = 256


def load_system_file(path: str | Path) -> System:
    """Read, check and build the system of a TOML system file (module docstring)."""
    path = Path(path)
    where = f"system file {str(path)!r}"
    from .file_guard import read_text
    try:
        raw = tomllib.loads(read_text(path, "system file"))
    except tomllib.TOMLDecodeError as e:
        raise SimgapError(f"{where} is not valid TOML: {e}") from None
    return system_from_spec(dict(raw, format=raw.get("format", FORMAT)), where)


def is_spec(obj) -> bool:
    """True for an embedded system-file object (``"format": "simgap-system"``)."""
    return isinstance(obj, dict) and obj.get("format") == FORMAT


def spec_digest(spec: dict) -> str:
    """sha256 of what the model computes: the spec without its name, description and steps."""
    core = {k: v for k, v in spec.items() if k not in ("name", "description", "steps")}
    return content_digest({"system-file": core})


def system_from_spec(spec: dict, where: str = "embedded system file") -> System:
    """The :class:`~simgap.systems.System` of a system-file table (as read or as embedded)."""
    _check_keys(spec, KEYS, where, "top level")
    if spec.get("format", FORMAT) != FORMAT:
        raise SimgapError(f"{where}: format {spec.get('format')!r} is not {FORMAT!r}")
    if spec.get("version", VERSION) != VERSION:
        raise SimgapError(f"{where}: version {spec.get('version')!r} is not supported (this simgap reads {VERSION})")
    name = _string(spec, "name", where)
    from .systems import BUILTIN
    if name in BUILTIN:
        raise SimgapError(f"{where}: name {name!r} is a built-in system's; choose another")
    states = _names(spec, "states", where)
    inputs = _names(spec, "inputs", where)
    params = _params(spec.get("params", {}), where)
    clash = (set(states) & set(inputs)) | ((set(states) | set(inputs)) & set(params))
    if clash:
        raise SimgapError(f"{where}: {sorted(clash)} used for more than one of states, inputs and params")
    n, m = len(states), len(inputs)
    x_lo = _vector(spec, "x_lo", n, where)
    x_hi = _vector(spec, "x_hi", n, where)
    bad = np.flatnonzero(~(x_lo < x_hi))
    if bad.size:
        i = int(bad[0])
        raise SimgapError(f"{where}: X is empty in {states[i]!r}: x_lo = {x_lo[i]:g} is not below x_hi = {x_hi[i]:g}")
    tau = spec.get("tau")
    if isinstance(tau, bool) or not isinstance(tau, (int, float)) or not (np.isfinite(tau) and tau > 0):
        raise SimgapError(f"{where}: tau (the base period [s]) must be a finite number > 0, got {tau!r}")
    steps = spec.get("steps", 1)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise SimgapError(f"{where}: steps must be an integer >= 1, got {steps!r}")
    from .systems import MAX_STEPS
    if steps > MAX_STEPS:
        raise SimgapError(f"{where}: steps = {steps:,} base periods per sampling period is more than the {MAX_STEPS:,} "
                          f"simgap accepts (refused before any work); give steps <= {MAX_STEPS:,}")
    U = _input_set(spec, m, where)
    _units(spec.get("units", {}), states + inputs, where)
    angles = _dims(spec, "angles", states, where)
    _dims(spec, "translation_invariant", states, where)
    velocities = _dims(spec, "velocities", states, where)
    if "description" in spec and not isinstance(spec["description"], str):
        raise SimgapError(f"{where}: description must be a string")

    defs = spec.get("definitions", {})
    if not isinstance(defs, dict):
        raise SimgapError(f"{where}: [definitions] must be a table name = \"formula\"")
    for d in defs:
        _name_ok(d, "definition", where)
        if d in states or d in inputs or d in params:
            raise SimgapError(f"{where}: definition {d!r} has the name of a state, input or parameter")
    K = len(defs)
    wz = n + m + 1 + K
    variables, consts = _variable_space(states, inputs, list(defs), params)
    dyn = spec.get("dynamics")
    if not isinstance(dyn, dict):
        raise SimgapError(f"{where}: needs a [dynamics] table with kind and one formula per state")
    kind = dyn.get("kind")
    if kind not in DYNAMICS_KINDS:
        raise SimgapError(f"{where}: dynamics.kind must be one of {', '.join(DYNAMICS_KINDS)}, got {kind!r}")
    continuous = kind == "continuous"
    allowed = ("kind",) + (("substeps",) if continuous else ()) + tuple(states)
    extra = [k for k in dyn if k not in allowed]
    missing = [s for s in states if s not in dyn]
    if extra or missing:
        raise SimgapError(f"{where}: [dynamics] needs one formula per state ({', '.join(states)})"
                          + (f"; missing {missing}" if missing else "") + (f"; unknown {extra}" if extra else "")
                          + (" (substeps belongs to a continuous model)" if "substeps" in extra else ""))
    substeps = dyn.get("substeps", 10) if continuous else 1
    if isinstance(substeps, bool) or not isinstance(substeps, int) or not 1 <= substeps <= MAX_SUBSTEPS:
        raise SimgapError(f"{where}: dynamics.substeps must be an integer in 1..{MAX_SUBSTEPS}, got {substeps!r}")
    # a right-hand side does not depend on the step length; a discrete map may use dt
    def_forms = {n + m + 1 + k: _formula(text, variables, consts, f"{where}: definitions.{d}",
                                         allow_dt=not continuous, uses=range(wz))
                 for k, (d, text) in enumerate(defs.items())}
    order = _evaluation_order(def_forms, list(defs), n + m + 1, where)
    forms = [_formula(dyn[s], variables, consts, f"{where}: dynamics.{s}", allow_dt=not continuous,
                      uses=range(wz)) for s in states]
    rhs_or_map = _vector_field(forms, [(c, def_forms[c]) for c in order], n, m, wz)
    compiled = _CompiledStep(spec, n, m, substeps, continuous)
    if continuous:
        from .runge_kutta import rk4_integrate

        def step(x, u, dt, _F=rhs_or_map, _k=substeps):
            out = compiled(x, u, dt)
            return out if out is not None else rk4_integrate(lambda xx, uu: _F(xx, uu, dt), x, u, dt, _k)
    else:
        def step(x, u, dt, _f=rhs_or_map):
            out = compiled(x, u, dt)
            return out if out is not None else _f(np.asarray(x, dtype=float), np.asarray(u, dtype=float), dt)

    xs = _check_states(x_lo, x_hi)
    _check_finite(step, xs, U, float(tau), states, where, "the model")
    smooth = all(f.smooth for f in forms) and all(f.smooth for f in def_forms.values())
    jac, how = _jacobian(spec.get("bounds", {}), variables, consts, continuous, float(tau), n, m, where,
                         step, xs, smooth)
    if hasattr(jac, "growth_matrix"):  # the grid synthesis' growth bound (abstraction.growth_function)
        step.radius_post = _radius_post(jac.growth_matrix, substeps)
    # embedded without steps: the System carries them (system_ref adds them back)
    embedded = {k: v for k, v in dict(spec, format=FORMAT, version=VERSION).items() if k != "steps"}
    sysparams = dict(params)
    sysparams["_system_file"] = embedded
    sysparams["_jacobian"] = how
    if "velocities" in spec:  # what the refinement library's friction effects act on
        sysparams["velocity_dims"] = list(velocities)
    s = System(name=name, state_names=tuple(states), input_names=tuple(inputs), x_lo=x_lo, x_hi=x_hi,
               inputs=U, base_tau=float(tau), step=step, angle_dims=angles, steps=int(steps),
               jacobian_bound=jac, params=sysparams)
    if hasattr(jac, "growth_matrix"):  # finite and Metzler on U (then exp(L tau) is finite and >= 0)
        jac.growth_matrix(U)
    elif jac is not None:
        J = np.asarray(jac(U), dtype=float)
        if J.shape != (U.shape[0], n, n) or not np.all(np.isfinite(J)) or np.any(J < 0):
            raise SimgapError(f"{where}: the Jacobian bound must be finite and >= 0 for every input of U")
    return s


class _CompiledStep:
    """The step's compiled twin (:func:`simgap.compile.point_kernel`: the same bits as the numpy
    step) when it pays (:class:`simgap.compile.Twin`: SIMGAP_JIT=1, or in auto mode a declared job
    or the rows stepped so far reaching :data:`simgap.jit.AUTO_WORK`) and the formulas
    have a bit-identical kernel (:func:`simgap.compile.point_exact`); otherwise the call returns
    None (the numpy step)."""

    def __init__(self, spec, n, m, substeps, continuous):
        self.spec, self.n, self.m, self.substeps, self.continuous = spec, n, m, substeps, continuous
        self.twin, self.exact = None, None

    def __call__(self, x, u, dt):
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if self.exact is False or x.ndim != 2 or x.shape[1] != self.n:
            return None  # the numpy step (it names a wrong shape)
        if self.exact is None:
            from .compile import point_exact
            from .jit import mode
            if mode() == "0":
                return None
            trees = _spec_trees(self.spec)["trees"]
            self.exact = not point_exact(trees)
            if not self.exact:
                return None
            from .compile import Twin, point_source
            from .jit import AUTO_WORK
            # no early load from the cache: numba's ~100 MB pay only on large grids (measured: SCOTS's
            # dcdc as a file, 1.3 M rows, 1.9 s CPU either way; docs/synthesis.md "Speed")
            self.twin = Twin(point_source, (trees, self.n, self.m), "step", AUTO_WORK, early=AUTO_WORK)
        kern = self.twin.get(x.shape[0])
        if kern is None:
            return None
        u = np.ascontiguousarray(np.broadcast_to(np.atleast_2d(np.asarray(u, dtype=float)), (x.shape[0], self.m)))
        return kern(np.ascontiguousarray(x), u, float(dt), self.substeps, self.continuous)


def translation_invariant_dims(system: System) -> tuple:
    """0-based state dimensions the system file declares translation-invariant (f(x, u) - x and
    the Jacobian bound independent of them; synthesis checks this numerically)."""
    spec = system.params.get("_system_file")
    if not is_spec(spec) or "_refined_json" in system.params:  # effects may depend on any state
        return ()
    names = spec.get("translation_invariant", [])
    return tuple(system.state_names.index(s) for s in names if s in system.state_names)


def units(system: System) -> dict:
    """Units the system file gives per variable name ({} if none)."""
    spec = system.params.get("_system_file")
    return dict(spec.get("units", {})) if is_spec(spec) else {}


def _variable_space(states, inputs, defs, params):
    """Columns of z: x (n), u (m), dt, definitions (K); parameters get columns after z and are
    folded into constants. Returns (VarSpace, {column: parameter value})."""
    n, m, wz = len(states), len(inputs), len(states) + len(inputs) + 1 + len(defs)
    variables = expr.VarSpace(dict({s: i for i, s in enumerate(states)},
                                   **{s: n + j for j, s in enumerate(inputs)}, dt=n + m,
                                   **{d: n + m + 1 + k for k, d in enumerate(defs)},
                                   **{p: wz + j for j, p in enumerate(params)}), wz)
    return variables, {wz + j: v for j, v in enumerate(params.values())}


def model_trees(system: System) -> dict:
    """The expression trees of a system-file model, for interval analysis of its map.

    Returns {"trees": one tree per state over z = [x (n), u (m), dt] (parameters folded in,
    ``[definitions]`` substituted), "continuous": bool, "substeps": int, "tau": base period}.
    The model was checked when it was built; a system that is not a plain system file (a
    built-in, or a refined system whose effects are not expressions of this table) is refused.
    """
    spec = system.params.get("_system_file")
    if not is_spec(spec) or "_refined_json" in system.params:
        raise SimgapError(f"system {system.name!r} is not a system file (a built-in, a plugin or a refined system): "
                          f"its formulas are not available for interval analysis")
    return _spec_trees(spec)


def _spec_trees(spec: dict) -> dict:
    """:func:`model_trees` of a checked system-file table."""
    states, inputs = list(spec["states"]), list(spec["inputs"])
    defs = dict(spec.get("definitions", {}))
    params = _params(spec.get("params", {}), "system file")
    variables, consts = _variable_space(states, inputs, list(defs), params)
    n, m = len(states), len(inputs)
    dyn = spec["dynamics"]
    continuous = dyn["kind"] == "continuous"
    parse = lambda text, what: _formula(text, variables, consts, what, allow_dt=not continuous,
                                        uses=range(n + m + 1 + len(defs))).tree
    first = n + m + 1
    def_trees = {first + k: parse(t, f"definitions.{d}") for k, (d, t) in enumerate(defs.items())}

    def inline(t):
        if t[0] == "var":
            return inline(def_trees[t[1]]) if t[1] in def_trees else t
        return (t[0],) + tuple(inline(c) if isinstance(c, tuple) else c for c in t[1:])
    trees = [inline(parse(dyn[s], f"dynamics.{s}")) for s in states]
    return {"trees": trees, "continuous": continuous, "substeps": int(dyn.get("substeps", 10)) if continuous else 1,
            "tau": float(spec["tau"])}


# ----- checks of the table --------------------------------------------------------------------
def _check_keys(d: dict, allowed, where: str, table: str) -> None:
    if not isinstance(d, dict):
        raise SimgapError(f"{where}: {table} must be a table")
    import difflib
    for k in d:
        if k not in allowed:
            near = difflib.get_close_matches(k, allowed, n=1, cutoff=0.6)
            raise SimgapError(f"{where}: unknown key {k!r} at {table}" + (f"; did you mean {near[0]!r}?" if near else "")
                              + f" (keys: {', '.join(allowed)})")


def _string(spec, key, where) -> str:
    v = spec.get(key)
    if not isinstance(v, str) or not v.isidentifier():
        raise SimgapError(f"{where}: {key} must be a name (letters, digits, _), got {v!r}")
    return v


def _names(spec, key, where) -> list:
    v = spec.get(key)
    if not isinstance(v, list) or not v:
        raise SimgapError(f"{where}: {key} must be a non-empty list of names, got {v!r}")
    cap = MAX_STATES if key == "states" else MAX_INPUT_DIMS
    if len(v) > cap:
        raise SimgapError(f"{where}: {len(v)} {key}; at most {cap}")
    for s in v:
        _name_ok(s, f"{key} entry", where)
    if len(set(v)) != len(v):
        raise SimgapError(f"{where}: {key} has a repeated name: {v}")
    return list(v)


def _name_ok(s, what, where) -> None:
    import re
    if not isinstance(s, str) or not s.isidentifier() or s.startswith("_"):
        raise SimgapError(f"{where}: {what} {s!r} is not a name (letters, digits, _, not starting with _)")
    if s in RESERVED or re.fullmatch(r"[xu]\d+", s):
        raise SimgapError(f"{where}: {what} {s!r} is reserved (function names, pi, e, dt, t, x1.., u1..)")


def _params(p, where) -> dict:
    if not isinstance(p, dict):
        raise SimgapError(f"{where}: [params] must be a table of numbers")
    out = {}
    for k, v in p.items():
        _name_ok(k, "parameter", where)
        if k in ("velocity_dims", "base_system", "refinement"):
            raise SimgapError(f"{where}: parameter name {k!r} is used by simgap itself; choose another")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise SimgapError(f"{where}: parameter {k!r} must be a finite number, got {v!r}")
        out[k] = float(v)
    return out


def _vector(spec, key, n, where) -> np.ndarray:
    v = spec.get(key)
    if not isinstance(v, list) or any(isinstance(a, bool) or not isinstance(a, (int, float)) for a in v):
        raise SimgapError(f"{where}: {key} must be a list of {n} numbers, got {v!r}")
    if len(v) != n:
        raise SimgapError(f"{where}: {key} has {len(v)} entries for {n} states")
    a = np.asarray(v, dtype=float)
    if not np.all(np.isfinite(a)):
        raise SimgapError(f"{where}: {key} must be finite, got {v}")
    return a


def _input_set(spec, m, where) -> np.ndarray:
    grid, sset = spec.get("input_grid"), spec.get("input_set")
    if (grid is None) == (sset is None):
        raise SimgapError(f"{where}: give the input set U as input_grid = {{lo, hi, counts}} or input_set = "
                          f"[[...], ...], exactly one of them")
    if grid is not None:
        _check_keys(grid, ("lo", "hi", "counts"), where, "input_grid")
        lo, hi, counts = grid.get("lo"), grid.get("hi"), grid.get("counts")
        for key, val in (("lo", lo), ("hi", hi), ("counts", counts)):
            if not isinstance(val, list) or len(val) != m or \
                    any(isinstance(a, bool) or not isinstance(a, (int, float)) for a in val):
                raise SimgapError(f"{where}: input_grid.{key} must be a list of {m} numbers (one per input), "
                                  f"got {val!r}")
        if not np.all(np.isfinite(lo + hi)) or any(not (isinstance(c, int) and c >= 1) for c in counts) \
                or any(h < l for l, h in zip(lo, hi)):
            raise SimgapError(f"{where}: input_grid needs finite lo <= hi and integer counts >= 1")
        if np.prod([float(c) for c in counts]) > MAX_INPUTS:
            raise SimgapError(f"{where}: input_grid has {np.prod([float(c) for c in counts]):.3g} inputs; at most "
                              f"{MAX_INPUTS:,}")
        return input_grid(lo, hi, counts)
    if isinstance(sset, list) and len(sset) > MAX_INPUTS:
        raise SimgapError(f"{where}: input_set has {len(sset):,} inputs; at most {MAX_INPUTS:,}")
    rows = [r if isinstance(r, list) else [r] for r in sset] if isinstance(sset, list) else None
    if not rows or any(len(r) != m or any(isinstance(a, bool) or not isinstance(a, (int, float)) for a in r)
                       for r in rows):
        raise SimgapError(f"{where}: input_set must be a non-empty list of {m}-vectors, got {sset!r}")
    U = np.asarray(rows, dtype=float)
    if not np.all(np.isfinite(U)):
        raise SimgapError(f"{where}: input_set must be finite")
    return U


def _units(u, names, where) -> None:
    if not isinstance(u, dict):
        raise SimgapError(f"{where}: units must be a table name = \"unit\"")
    for k, v in u.items():
        if k not in names:
            raise SimgapError(f"{where}: units names {k!r}, which is not a state or input ({', '.join(names)})")
        if not isinstance(v, str):
            raise SimgapError(f"{where}: the unit of {k!r} must be a string, got {v!r}")


def _dims(spec, key, states, where) -> tuple:
    v = spec.get(key, [])
    if not isinstance(v, list) or any(s not in states for s in v):
        raise SimgapError(f"{where}: {key} must list state names ({', '.join(states)}), got {v!r}")
    return tuple(states.index(s) for s in v)


# ----- formulas ------------------------------------------------------------------------------
def _formula(text, variables, consts, what, allow_dt, uses) -> expr.Expr:
    if isinstance(text, bool) or not isinstance(text, (str, int, float)):
        raise SimgapError(f"{what}: must be a formula (a string) or a number, got {text!r}")
    e = expr.parse(str(text), variables, what=what, comparisons=True)
    dt_col = variables.columns["dt"]
    if not allow_dt and dt_col in e.columns:
        raise SimgapError(f"{what} {text!r}: dt (the step length) is not available here")
    cols = e.columns - set(consts) - {dt_col}
    if not cols <= set(uses):
        raise SimgapError(f"{what} {text!r}: may use only the inputs, parameters and dt here")
    return expr.Expr(e.text, _fold(e.tree, consts))


def _fold(tree: tuple, consts: dict) -> tuple:
    """The tree with parameter columns replaced by their values."""
    if tree[0] == "var":
        return ("const", consts[tree[1]]) if tree[1] in consts else tree
    return (tree[0],) + tuple(_fold(c, consts) if isinstance(c, tuple) else c for c in tree[1:])


def _columns(x, u, dt, width) -> np.ndarray:
    z = np.zeros((x.shape[0], width))
    n, m = x.shape[1], u.shape[1]
    z[:, :n], z[:, n:n + m], z[:, n + m] = x, u, dt
    return z


def _evaluation_order(def_forms: dict, names: list, first: int, where: str) -> list:
    """Columns of the definitions in an order where each comes after those it uses (a cycle is
    an error naming it); independent of the table's key order, which JSON does not keep."""
    deps = {c: {d for d in e.columns if d in def_forms and d != c} for c, e in def_forms.items()}
    for c, e in def_forms.items():
        if c in e.columns:
            raise SimgapError(f"{where}: definition {names[c - first]!r} uses itself")
    order, done = [], set()
    while len(order) < len(def_forms):
        ready = sorted(c for c in def_forms if c not in done and deps[c] <= done)
        if not ready:
            cyc = sorted(names[c - first] for c in def_forms if c not in done)
            raise SimgapError(f"{where}: definitions {cyc} use each other in a cycle")
        order += ready
        done.update(ready)
    return order


def _vector_field(forms, defs, n, m, width):
    """(x (B,n), u (B,m), dt) -> (B,n): the definitions (column, Expr) in order, then the formulas,
    evaluated row-wise (vectorized over B)."""
    def field(x, u, dt):
        x = np.atleast_2d(x)
        u = np.broadcast_to(np.atleast_2d(u), (x.shape[0], m))
        z = _columns(x, u, dt, width)
        for col, e in defs:
            z[:, col] = e.eval(z)
        return np.stack([f.eval(z) for f in forms], axis=1)
    return field


def _check_states(lo, hi) -> np.ndarray:
    """Corners of X (up to 2^10) and CHECK_STATES seeded random states."""
    n = lo.size
    rng = np.random.default_rng(0)
    pts = [lo + rng.random((CHECK_STATES, n)) * (hi - lo), 0.5 * (lo + hi)[None]]
    if n <= 10:
        corners = np.array(np.meshgrid(*[[a, b] for a, b in zip(lo, hi)], indexing="ij")).reshape(n, -1).T
        pts.append(corners)
    return np.concatenate(pts)


def _check_finite(step, xs, U, tau, states, where, what) -> None:
    per = max(1, BLOCK_ROWS // xs.shape[0])  # inputs per block: every state of xs with each
    for j in range(0, U.shape[0], per):
        Ub = U[j:j + per]
        X = np.repeat(xs, Ub.shape[0], axis=0)
        Uu = np.tile(Ub, (xs.shape[0], 1))
        with np.errstate(all="ignore"):
            out = step(X, Uu, tau)
        bad = ~np.isfinite(out)
        if bad.any():
            r, c = np.argwhere(bad)[0]
            raise SimgapError(f"{where}: {what} is not finite on X: {states[c]} is {out[r, c]} after one period "
                              f"from x = {X[r].tolist()}, u = {Uu[r].tolist()} ({int(bad.any(axis=1).sum())} of "
                              f"{len(out)} checked (x, u) pairs)")


def _jacobian(bounds, variables, consts, continuous, tau, n, m, where, step, xs, smooth):
    """(J(u) -> (B,n,n) or None, how it was obtained) for one base step of length tau."""
    _check_keys(bounds, BOUND_KEYS, where, "[bounds]")
    if "growth" in bounds and not continuous:
        raise SimgapError(f"{where}: bounds.growth (the matrix L of x' = F(x, u)) needs dynamics.kind = "
                          f"\"continuous\"; give bounds.jacobian for a discrete map")
    if "growth" in bounds and "jacobian" in bounds:
        raise SimgapError(f"{where}: give bounds.jacobian or bounds.growth, not both")
    key = "jacobian" if "jacobian" in bounds else "growth" if "growth" in bounds else None
    if key is not None:
        rows = bounds[key]
        if not isinstance(rows, list) or len(rows) != n or any(not isinstance(r, list) or len(r) != n for r in rows):
            raise SimgapError(f"{where}: bounds.{key} must be an {n} x {n} matrix (a list of {n} lists of {n})")
        cells = [[_formula(c, variables, consts, f"{where}: bounds.{key}[{i}][{j}]", allow_dt=key == "jacobian",
                           uses=range(n, n + m)) for j, c in enumerate(r)] for i, r in enumerate(rows)]

        def matrix(u, dt):
            u = np.atleast_2d(np.asarray(u, dtype=float))
            z = _columns(np.zeros((u.shape[0], n)), u, dt, n + m + 1)
            return np.stack([np.stack([c.eval(z) for c in r], axis=1) for r in cells], axis=1)

        if key == "jacobian":
            return (lambda u: matrix(u, tau)), "given"

        def metzler(u):
            L = matrix(u, tau)
            off = ~np.eye(n, dtype=bool)
            if np.any(L[:, off] < 0) or not np.all(np.isfinite(L)):
                raise SimgapError(f"{where}: bounds.growth must be finite with off-diagonal entries >= 0 "
                                  f"(bounds on |dF_i/dx_j|)")
            return L

        def jac(u):
            from scipy.linalg import expm  # imported on use: 0.3 s of a grid synthesis' start
            u = np.atleast_2d(np.asarray(u, dtype=float))
            uu, inv = np.unique(u, axis=0, return_inverse=True)
            # |d phi_tau / dx| <= exp(L tau) elementwise for a Metzler bound L of dF/dx
            return np.stack([expm(Li * tau) for Li in metzler(uu)])[inv.reshape(-1)]
        jac.growth_matrix = metzler  # L(u) (B, n, n): SCOTS's radius_post integrates r' = L r
        return jac, "given (growth)"
    if not smooth:
        return None, "none (non-smooth model: sign, abs, where, ... )"
    return _estimated_jacobian(step, xs[:CHECK_STATES], tau, n), "estimated"


def _radius_post(L, substeps: int):
    """SCOTS's radius_post for ``bounds.growth``: ``steps -> growth(r, x, u, tau)``, r' = L(u) r
    integrated by RK4 over the sampling period with the model's substeps per base period
    (:func:`~simgap.runge_kutta.rk4_growth`), as SCOTS integrates its growth bound alongside its RK4
    model (exp(L tau), the bound of the exact flow, stays the certificate's Jacobian bound)."""
    def for_steps(steps: int):
        from .runge_kutta import rk4_growth
        return rk4_growth(L, nint=substeps * int(steps))
    return for_steps


def _estimated_jacobian(step, xs, tau, n):
    """max over the sample states of |d step / dx| by central differences plus 5 % of max |d step / dx - I|
    (the margin scales with what the step changes, not with the identity part), per input."""
    span = np.ptp(xs, axis=0)
    cache: dict = {}

    def bound_for(uu):
        S = xs.shape[0]
        X = np.repeat(xs[None], uu.shape[0], axis=0).reshape(-1, n)
        Ur = np.repeat(uu, S, axis=0)
        D = np.zeros((uu.shape[0], n, n))
        E = np.zeros((uu.shape[0], n, n))
        eye = np.eye(n)
        for j in range(n):
            h = 1e-6 * max(1.0, float(span[j]))
            Xp, Xm = X.copy(), X.copy()
            Xp[:, j] += h
            Xm[:, j] -= h
            d = (step(Xp, Ur, tau) - step(Xm, Ur, tau)) / (2 * h)
            D[:, :, j] = np.abs(d).reshape(uu.shape[0], S, n).max(axis=1)
            E[:, :, j] = np.abs(d - eye[:, j]).reshape(uu.shape[0], S, n).max(axis=1)
        return D + 0.05 * E

    def jac(u):
        u = np.atleast_2d(np.asarray(u, dtype=float))
        uu, inv = np.unique(u, axis=0, return_inverse=True)
        new = [r for r in map(tuple, uu) if r not in cache]
        per = max(1, BLOCK_ROWS // xs.shape[0])
        for j in range(0, len(new), per):  # blocks bound the memory for large input sets
            for r, D in zip(new[j:j + per], bound_for(np.array(new[j:j + per], dtype=float))):
                cache[r] = D
        return np.stack([cache[r] for r in map(tuple, uu)])[inv.reshape(-1)]
    return jac

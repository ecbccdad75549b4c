"""Fit named parameters of a system file to noise-free simulator transitions.

A system file's ``[params]`` are constants of its formulas (:mod:`simgap.system_file`). Given
transitions (x_r, u_r) -> y_r of the simulator with its noise and parameter randomization off,
:func:`fit_params` chooses the named parameters theta to minimise

    sum_r sum_i ( diff_i(y_r, f_theta(x_r, u_r)) / s_i )^2

(nonlinear least squares, :func:`scipy.optimize.least_squares`, trust-region reflective with
finite-difference Jacobians), where diff wraps angle dimensions to [-pi, pi) and s_i is the RMS
of the observed increments diff_i(y_r, x_r) (so a dimension that moves little per period weighs
as much as one that moves a lot; 1 where a dimension does not move). The model f_theta is the
system file's own, rebuilt through the expression allow-list for every theta
(:func:`with_params`): nothing is executed, nothing pickled.

:func:`fitted_text` writes the result back into the file's text: only the ``name = value`` lines
of the fitted names in its ``[params]`` table change (comments and everything else stay), and the
new text is parsed again and refused unless it reads back as the original with the new values.

``simgap fit`` (:mod:`simgap.cli.fit`) is the command; examples/husky/fit_gains.py uses it.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np

from .errors import SimgapError
from .systems import System


def system_file_spec(system: System) -> dict:
    """The system-file table a System was built from; SimgapError for any other system."""
    spec = system.params.get("_system_file")
    if spec is None:
        raise SimgapError(f"system {system.name!r} is not from a system file: only a system file's [params] can be "
                          "fitted (docs/system-files.md)")
    return spec


def with_params(system: System, values: Dict[str, float]) -> System:
    """The system file's model with some of its ``[params]`` replaced (same steps).

    Every name must be one of the file's parameters; the formulas are parsed again with the
    values folded in (:func:`simgap.system_file.system_from_spec`)."""
    from .system_file import system_from_spec
    spec = system_file_spec(system)
    params = dict(spec.get("params", {}))
    unknown = [k for k in values if k not in params]
    if unknown:
        raise SimgapError(f"parameter(s) {', '.join(map(repr, unknown))} not in the system file's [params] "
                          f"({', '.join(params) or 'none'})")
    params.update({k: float(v) for k, v in values.items()})
    return system_from_spec({**spec, "params": params}).with_steps(int(system.steps))


def sample_states(system: System, points: int, rng: np.random.Generator, fix: Optional[Dict[str, float]] = None,
                  grid: bool = False) -> np.ndarray:
    """States to simulate from: ``points`` seeded uniform draws in X, or (``grid``) ``points`` evenly
    spaced values per free dimension (cell centres; a full-turn angle without repeating its seam),
    every combination. ``fix``: state name -> value held at that value (in X)."""
    fix = dict(fix or {})
    for k, v in fix.items():
        if k not in system.state_names:
            raise SimgapError(f"--fix {k}: not a state of {system.name!r} ({', '.join(system.state_names)})")
        j = system.state_names.index(k)
        if not system.x_lo[j] <= v <= system.x_hi[j]:
            raise SimgapError(f"--fix {k}={v:g}: outside X [{system.x_lo[j]:g}, {system.x_hi[j]:g}]")
    free = [j for j, nm in enumerate(system.state_names) if nm not in fix]
    if grid:
        axes = [system.x_lo[j] + (np.arange(points) + 0.5) / points * (system.x_hi[j] - system.x_lo[j]) for j in free]
        mesh = np.meshgrid(*axes, indexing="ij") if axes else []
        B = int(points) ** len(free)  # a Python int: no overflow (priced by check_fit_size)
        x = np.empty((B, system.n))
        for a, j in enumerate(free):
            x[:, j] = mesh[a].ravel()
    else:
        x = system.x_lo + rng.random((points, system.n)) * (system.x_hi - system.x_lo)
    for k, v in fix.items():
        x[:, system.state_names.index(k)] = v
    return x


def check_fit_size(system: System, points: int, grid: bool, fix: Optional[Dict[str, float]], n_params: int,
                   what: str) -> int:
    """The fit's transitions R (states x inputs), refused before any state is drawn when they cannot
    fit in memory: B = points (or points^d on a grid of the d free states) states, R = B |U| rows; per
    row the states, inputs and next states with the simulator's and the formulas' temporaries
    (6 (2n + m) floats) and the least-squares fit's residuals and finite-difference Jacobian
    (n (2p + 8) floats, p parameters)."""
    from .checks import check_memory
    free = sum(1 for nm in system.state_names if nm not in (fix or {}))
    states = int(points) ** free if grid else int(points)
    rows = states * len(system.inputs)
    # measured: 254 bytes per row for n = m = 1, p = 3 (peak RSS at 1e6 and 5e6 rows); the formulas'
    # temporaries are the rest
    need = 8.0 * rows * (6 * (2 * system.n + system.m) + system.n * (2 * n_params + 8))
    check_memory(need, f"{what}: {states:,} states x {len(system.inputs)} inputs = {rows:,} transitions "
                 "(states, next states and the fit's Jacobian)",
                 "use fewer --points or a coarser --grid" + (" (or --fix some states)" if grid else ""))
    return rows


def seconds_per_evaluation(system: System, x: np.ndarray, rows: int, sample: int = 65536) -> float:
    """Seconds of one evaluation of the fit's residual over ``rows`` transitions: the model rebuilt
    (:func:`with_params`) and evaluated on ``sample`` rows from the states ``x`` (the second of two
    timings, the first warms up), scaled to ``rows``."""
    import time
    k = max(1, min(int(sample), len(x) * len(system.inputs)))
    X = np.repeat(x[: -(-k // len(system.inputs))], len(system.inputs), axis=0)[:k]
    U = np.tile(system.inputs, (-(-k // len(system.inputs)), 1))[:k]
    for _ in range(2):
        t = time.perf_counter()
        system.diff(X, with_params(system, {}).f(X, U))
        dt = time.perf_counter() - t
    return dt * rows / k


def transitions(simulator, x: np.ndarray, inputs: np.ndarray, rng: np.random.Generator):
    """(x, u, y): every state of ``x`` with every input row of ``inputs``, stepped once by ``simulator``
    (built noise-free by the caller)."""
    X = np.repeat(x, len(inputs), axis=0)
    U = np.tile(inputs, (len(x), 1))
    Y = np.asarray(simulator.step(X, U, rng), dtype=float)
    if not np.all(np.isfinite(Y)):
        raise SimgapError("the simulator returned NaN/inf on the fit's states")
    return X, U, Y


@dataclass
class FitResult:
    """The fitted parameters and how well the model matches the transitions before and after.

    ``rms_*`` and ``max_*`` per state dimension in its units (angles wrapped); ``scale`` the
    residual weights' denominators s_i; ``rows`` the transitions used."""

    names: List[str]
    initial: np.ndarray
    fitted: np.ndarray
    rms_before: np.ndarray
    rms_after: np.ndarray
    max_before: np.ndarray
    max_after: np.ndarray
    scale: np.ndarray
    rows: int
    evaluations: int
    message: str
    extra: dict = field(default_factory=dict)

    def values(self) -> Dict[str, float]:
        return {k: float(v) for k, v in zip(self.names, self.fitted)}

    def to_dict(self) -> dict:
        return {"names": self.names, "initial": self.initial.tolist(), "fitted": self.fitted.tolist(),
                "rms_before": self.rms_before.tolist(), "rms_after": self.rms_after.tolist(),
                "max_before": self.max_before.tolist(), "max_after": self.max_after.tolist(),
                "scale": self.scale.tolist(), "rows": self.rows, "evaluations": self.evaluations,
                "message": self.message, **self.extra}


def _gap(system: System, x, u, y) -> np.ndarray:
    return system.diff(y, system.f(x, u))


def fit_params(system: System, names: Sequence[str], x: np.ndarray, u: np.ndarray, y: np.ndarray,
               bounds: Optional[Dict[str, tuple]] = None) -> FitResult:
    """Least-squares fit of the system file's parameters ``names`` to transitions (x, u) -> y (module
    docstring). ``bounds``: name -> (lo, hi), default unbounded. The start is the file's values."""
    from scipy.optimize import least_squares

    spec = system_file_spec(system)
    params = spec.get("params", {})
    names = list(names)
    if not names:
        raise SimgapError("--params: name at least one parameter to fit")
    missing = [k for k in names if k not in params]
    if missing:
        raise SimgapError(f"--params {', '.join(missing)}: not in the system file's [params] "
                          f"({', '.join(params) or 'none'})")
    if len(set(names)) != len(names):
        raise SimgapError("--params: a name appears twice")
    if len(x) * system.n < len(names):
        raise SimgapError(f"{len(x)} transitions x {system.n} states cannot determine {len(names)} parameters")
    theta0 = np.array([float(params[k]) for k in names])
    bounds = dict(bounds or {})
    lo = np.array([bounds.get(k, (-np.inf, np.inf))[0] for k in names], dtype=float)
    hi = np.array([bounds.get(k, (-np.inf, np.inf))[1] for k in names], dtype=float)
    theta0 = np.clip(theta0, np.nextafter(lo, np.inf), np.nextafter(hi, -np.inf))
    inc = system.diff(y, x)
    scale = np.sqrt((inc ** 2).mean(axis=0))
    scale = np.where(scale > 0, scale, 1.0)

    def residual(theta):
        try:
            model = with_params(system, dict(zip(names, theta)))
        except SimgapError as e:
            raise SimgapError(f"the model is not valid at {dict(zip(names, np.round(theta, 6)))} ({e}); bound the "
                              "parameters (--bounds name=lo:hi)") from None
        r = _gap(model, x, u, y) / scale
        if not np.all(np.isfinite(r)):
            raise SimgapError(f"the model is not finite at {dict(zip(names, np.round(theta, 6)))}; bound the "
                              "parameters (--bounds name=lo:hi)")
        return r.ravel()

    res = least_squares(residual, theta0, bounds=(lo, hi), x_scale="jac", method="trf")
    before = np.abs(_gap(system, x, u, y))
    after = np.abs(_gap(with_params(system, dict(zip(names, res.x))), x, u, y))
    return FitResult(names=names, initial=theta0, fitted=np.asarray(res.x, dtype=float),
                     rms_before=np.sqrt((before ** 2).mean(axis=0)), rms_after=np.sqrt((after ** 2).mean(axis=0)),
                     max_before=before.max(axis=0), max_after=after.max(axis=0), scale=scale, rows=len(x),
                     evaluations=int(res.nfev), message=str(res.message))


_TABLE = re.compile(r"^\s*\[\s*([^\]]+?)\s*\]\s*(#.*)?$")


def fitted_text(text: str, values: Dict[str, float], digits: int = 6) -> str:
    """The system file's text with the ``[params]`` lines of ``values`` set to them (``digits``
    significant digits); refused unless the new text parses to the old table with those values."""
    lines = text.splitlines(keepends=True)
    start = next((i for i, ln in enumerate(lines) if _TABLE.match(ln) and _TABLE.match(ln).group(1) == "params"), None)
    if start is None:
        raise SimgapError("the system file has no [params] table of name = value lines to write the fit into")
    end = next((i for i in range(start + 1, len(lines)) if _TABLE.match(lines[i])), len(lines))
    rounded = {k: float(f"{float(v):.{digits}g}") for k, v in values.items()}
    done = set()
    for i in range(start + 1, end):
        for k, v in rounded.items():
            m = re.match(rf"^(\s*{re.escape(k)}\s*=\s*)([^#\r\n]*?)(\s*(#[^\r\n]*)?)(\r?\n)?$", lines[i])
            if m:
                lines[i] = f"{m.group(1)}{v!r}{m.group(3)}{m.group(5) or ''}"
                done.add(k)
    if done != set(rounded):
        raise SimgapError(f"parameter(s) {', '.join(sorted(set(rounded) - done))} are not name = value lines of the "
                          "file's [params] table; edit them by hand")
    new = "".join(lines)
    old_t, new_t = tomllib.loads(text), tomllib.loads(new)
    want = dict(old_t, params={**old_t.get("params", {}), **rounded})
    if new_t != want:
        raise SimgapError("writing the fitted values changed more than those parameters; edit the file by hand")
    return new

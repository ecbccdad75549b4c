"""Audit a run-level certificate: empirical coverage of gamma^alpha at fresh points.

For B fresh (x, u) (x uniform in X, off the cover; u from the certificate's inputs; seeded)
R independent runs each give the exceedance count k_i = #{|wrap(fhat_i - f_i)| > gamma^alpha_i}.
The claim is P(exceed) <= alpha at every point, so a point is

* ``violated`` if the one-sided Clopper-Pearson LOWER bound of its exceedance probability at
  level ``level`` / B (Bonferroni over the points) is above alpha: evidence beyond audit noise;
* otherwise it holds (or is inconclusive, if its empirical rate is above alpha).

The audit passes when no point is violated in any dimension.
"""

from __future__ import annotations

import numpy as np

from ..certify.audit import _chunk_progress, draw_points
from ..errors import SimgapError
from ..simulators.base import Simulator, make_simulator
from .orderstats import cp_lower
from .realization import run_alpha


def audit_run(cert, simulator, points: int = 100, runs: int = 2000, seed: int = 0, level: float = 0.001,
              chunk_samples: int = 1_000_000, system=None, on_progress=None) -> dict:
    """Coverage audit of the run-level certificate ``cert`` (see module docstring); returns a report dict.

    ``system``: the nominal model when it is not the simulator's own (as in :func:`simgap.certify.audit.audit`);
    ``on_progress(runs_done, points x runs)`` as there."""
    alpha = run_alpha(cert)
    if int(points) < 1 or int(runs) < 10:
        raise SimgapError(f"run audit: need points >= 1 and runs >= 10, got points={points}, runs={runs}")
    sim = simulator if isinstance(simulator, Simulator) else make_simulator(simulator)
    s = sim.system if system is None else system.with_steps(sim.system.steps)
    cert.check_system(s)
    B, R = int(points), int(runs)
    x, u = draw_points(s, B, np.random.default_rng([seed, 0]), inputs=cert.inputs)
    gam = cert.gamma(x, u)
    fnom = s.f(x, u)
    rng = np.random.default_rng([seed, 1])
    exceed = np.zeros((B, s.n), dtype=np.int64)
    per = max(1, chunk_samples // R)
    for a in range(0, B, per):  # bounded memory; vectorized over points x runs
        b = min(B, a + per)
        nxt = sim.step(np.repeat(x[a:b], R, axis=0), np.repeat(u[a:b], R, axis=0), rng,
                       on_rows=_chunk_progress(on_progress, a, R, B)).reshape(b - a, R, s.n)
        d = np.abs(s.diff(nxt, fnom[a:b, None, :]))
        exceed[a:b] = (d > gam[a:b, None, :]).sum(axis=1)
    lower = cp_lower(exceed, R, level / B)
    violated = lower > alpha
    rate = exceed / R
    per_dim = {name: {"coverage_mean": float(1 - rate[:, i].mean()), "coverage_min": float(1 - rate[:, i].max()),
                      "points_violated": int(violated[:, i].sum()),
                      "points_above_alpha": int((rate[:, i] > alpha).sum())}
               for i, name in enumerate(s.state_names)}
    return {"alpha": alpha, "points": B, "runs": R, "seed": int(seed), "level": level,
            "test": f"one-sided Clopper-Pearson lower bound of the exceedance rate > alpha at level {level}/B",
            "per_dim": per_dim, "passed": bool(not violated.any()), "n_violated": int(violated.any(axis=1).sum()),
            "simulator": sim.config.to_dict(),
            "x": x.tolist(), "u": u.tolist(), "exceed": exceed.tolist()}


def report_table(rep: dict) -> str:
    """Text table of :func:`audit_run`."""
    lines = [f"run-level audit: alpha = {rep['alpha']:g}, {rep['points']} fresh points x {rep['runs']} runs",
             f"{'dim':<10}{'coverage mean':>15}{'coverage min':>14}{'above alpha':>13}{'violated':>10}"]
    for name, d in rep["per_dim"].items():
        lines.append(f"{name:<10}{d['coverage_mean']:>15.4f}{d['coverage_min']:>14.4f}{d['points_above_alpha']:>13}"
                     f"{d['points_violated']:>10}")
    lines.append(("PASSED" if rep["passed"] else "FAILED") + f": coverage >= 1 - alpha = {1 - rep['alpha']:g} "
                 f"({rep['test']})")
    return "\n".join(lines)

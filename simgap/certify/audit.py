"""Audit a certificate against ground truth: fresh (x, u) points, many simulator runs each.

For B fresh points (x uniform in X, NOT on the cover; u uniform from U; seeded) the true mean
next state E fhat(x, u, w) is estimated with R independent runs each, and the certificate's
claim |E fhat_i - f_i| <= gamma_i(x, u) is checked per dimension and jointly.

Monte-Carlo error of the audit itself: the estimated gap has standard error
SE_i = s_i / sqrt(R) (s_i the sample std of the R runs). A point counts as

Inputs are drawn from the certificate's input set (the inputs its data covered).

* ``holds``       if gamma_i - |mean_i - f_i| >= 0,
* ``violated``    if |mean_i - f_i| - gamma_i > 3 SE_i (a violation beyond audit noise),
* ``inconclusive`` otherwise (within 3 SE of the boundary).

The audit passes when no point is violated beyond 3 SE in any dimension. When the simulator
offers an exact mean (numpy backend, ``mean_next``; exact when actuation noise is 0), the exact
gap is checked as well.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import fileio
from ..errors import SimgapError
from ..simulators.base import Simulator, make_simulator

QUANTILES = (0.0, 0.01, 0.05, 0.5, 0.95, 1.0)


def draw_points(system, B: int, rng: np.random.Generator, cover=None, cov_dims=None, inputs=None):
    """B fresh states uniform in X (not on the cover points) and inputs uniform from ``inputs`` (default U).

    ``cover`` holds the cover points' coordinates in the covered dimensions ``cov_dims``.
    """
    x = system.x_lo + rng.random((B, system.n)) * (system.x_hi - system.x_lo)
    cov_dims = list(range(system.n)) if cov_dims is None else list(cov_dims)
    if cover is not None and len(cover):
        from scipy.spatial import cKDTree
        tree = cKDTree(cover)
        d, _ = tree.query(x[:, cov_dims])
        hit = d < 1e-9
        while hit.any():  # measure-zero event, redraw those (seeded)
            x[hit] = system.x_lo + rng.random((int(hit.sum()), system.n)) * (system.x_hi - system.x_lo)
            d, _ = tree.query(x[:, cov_dims])
            hit = d < 1e-9
    U = system.inputs if inputs is None else inputs
    u = U[rng.integers(0, len(U), size=B)]
    return x, u


def audit(cert, simulator, points: int = 200, runs: int = 2000, seed: int = 0, dataset=None,
          chunk_samples: int = 1_000_000) -> dict:
    """Audit ``cert`` with ``simulator`` (a Simulator, SimulatorConfig or its dict). Returns the report dict."""
    if int(points) < 1 or int(runs) < 2:
        raise SimgapError(f"audit: need points >= 1 and runs >= 2, got points={points}, runs={runs}")
    sim = simulator if isinstance(simulator, Simulator) else make_simulator(simulator)
    s = sim.system
    cert.check_system(s)
    rng = np.random.default_rng(seed)
    cover, cov_dims = None, list(range(s.n))
    if dataset is not None:
        from .pipeline import invariant_dims
        inv = invariant_dims(dataset)  # declared-invariant dims are not covered: distances over the others
        cov_dims = [j for j in range(s.n) if j not in inv]
        cover = np.unique(dataset.x[:, cov_dims], axis=0)
    x, u = draw_points(s, int(points), rng, cover, cov_dims, cert.inputs)
    B, R, n = len(x), int(runs), s.n
    fx = s.f(x, u)
    mean_dev = np.empty((B, n))
    sd = np.empty((B, n))
    per = max(1, chunk_samples // R)
    for a in range(0, B, per):  # chunks of points; runs vectorized
        b = min(B, a + per)
        nxt = sim.step(np.repeat(x[a:b], R, axis=0), np.repeat(u[a:b], R, axis=0), rng).reshape(b - a, R, n)
        d = s.diff(nxt, fx[a:b, None, :])
        mean_dev[a:b] = d.mean(axis=1)
        sd[a:b] = d.std(axis=1, ddof=1)
    gap = np.abs(mean_dev)
    se = sd / np.sqrt(R)
    gam = cert.gamma(x, u)
    margin = gam - gap
    holds = margin >= 0
    violated = -margin > 3.0 * se
    inconclusive = ~holds & ~violated
    names = list(s.state_names)
    rep = {
        "system": s.name, "steps": s.steps, "points": B, "runs": R, "seed": int(seed),
        "simulator": sim.config.to_dict(), "certificate_method": cert.method,
        "certificate_dataset_hash": cert.provenance.get("dataset_hash"),
        "stated_confidence": cert.per_dim_confidence, "stated_joint_confidence": cert.joint_confidence,
        "per_dim": {},
        "joint": {"fraction_holds": float(holds.all(axis=1).mean()),
                  "fraction_violated": float(violated.any(axis=1).mean()),
                  "fraction_inconclusive": float((inconclusive.any(axis=1) & ~violated.any(axis=1)).mean())},
    }
    for i, nm in enumerate(names):
        worst = int(np.argmin(margin[:, i]))
        rep["per_dim"][nm] = {
            "fraction_holds": float(holds[:, i].mean()),
            "fraction_violated": float(violated[:, i].mean()),
            "fraction_inconclusive": float(inconclusive[:, i].mean()),
            "worst_violation": float(max(0.0, -margin[worst, i])),
            "worst_point": {"x": x[worst].tolist(), "u": u[worst].tolist(), "gap": float(gap[worst, i]),
                            "gamma": float(gam[worst, i]), "se": float(se[worst, i])},
            "margin_quantiles": {str(q): float(v) for q, v in zip(QUANTILES, np.quantile(margin[:, i], QUANTILES))},
            "gap_max": float(gap[:, i].max()), "gamma_min": float(gam[:, i].min()),
            "mc_standard_error": {"median": float(np.median(se[:, i])), "max": float(se[:, i].max())},
        }
    if hasattr(sim, "mean_next"):
        ex = np.abs(s.diff(sim.mean_next(x, u), fx))
        em = gam - ex
        exact_ok = sim.config.noise.get("actuation_std", 0) in (0, 0.0, None)
        rep["exact"] = {"available": True, "exact_mean": bool(exact_ok),
                        "fraction_holds": {nm: float((em[:, i] >= 0).mean()) for i, nm in enumerate(names)},
                        "joint_fraction_holds": float((em >= 0).all(axis=1).mean()),
                        "worst_violation": {nm: float(max(0.0, -em[:, i].min())) for i, nm in enumerate(names)}}
    if cover is not None:
        from scipy.spatial import cKDTree
        d, _ = cKDTree(cover).query(x[:, cov_dims])
        rep["distance_to_cover"] = {"dims": [s.state_names[j] for j in cov_dims], "min": float(d.min()), "median": float(np.median(d)), "max": float(d.max()),
                                    "epsilon": float(dataset.epsilon)}
    rep["passed"] = bool(not violated.any())
    return rep


def save_report(rep: dict, path) -> Path:
    """Write the audit report JSON atomically."""
    return fileio.write_json(path, rep)


def report_table(rep: dict) -> str:
    """Readable table of an audit report."""
    lines = [f"audit: system {rep['system']} (steps={rep['steps']}), {rep['points']} fresh points x {rep['runs']} runs, "
             f"certificate method {rep['certificate_method']}"]
    hdr = f"{'dim':<10}{'holds':>8}{'violated':>10}{'inconcl.':>10}{'worst viol.':>13}{'margin min':>12}" \
          f"{'margin p5':>12}{'margin med':>12}{'MC SE med':>12}{'stated conf':>13}"
    lines += [hdr, "-" * len(hdr)]
    conf = rep.get("stated_confidence") or []
    for k, (nm, d) in enumerate(rep["per_dim"].items()):
        c = conf[k] if k < len(conf) else None
        q = d["margin_quantiles"]
        lines.append(f"{nm:<10}{d['fraction_holds']:>8.3f}{d['fraction_violated']:>10.3f}"
                     f"{d['fraction_inconclusive']:>10.3f}{d['worst_violation']:>13.4g}{q['0.0']:>12.4g}"
                     f"{q['0.05']:>12.4g}{q['0.5']:>12.4g}{d['mc_standard_error']['median']:>12.3g}"
                     f"{'-' if c is None else format(c, '.4f'):>13}")
    j = rep["joint"]
    lines.append(f"{'joint':<10}{j['fraction_holds']:>8.3f}{j['fraction_violated']:>10.3f}"
                 f"{j['fraction_inconclusive']:>10.3f}")
    if "exact" in rep:
        e = rep["exact"]
        lines.append("exact mean (simulator.mean_next" + ("" if e["exact_mean"] else ", approximate") + "): "
                     + ", ".join(f"{k} holds {v:.3f}" for k, v in e["fraction_holds"].items())
                     + f", joint {e['joint_fraction_holds']:.3f}")
    lines.append("PASSED: no violation beyond 3 Monte-Carlo standard errors" if rep["passed"]
                 else "FAILED: gamma is violated beyond 3 Monte-Carlo standard errors")
    return "\n".join(lines)

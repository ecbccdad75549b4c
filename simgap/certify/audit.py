"""Audit a certificate against ground truth: fresh (x, u) points, many simulator runs each.

For B fresh points (x uniform in X, NOT on the cover; u uniform from the certificate's input
set, the inputs its data covered; seeded) the true mean next state E fhat(x, u, w) is estimated
with R independent runs each, and the claim |E fhat_i - f_i| <= gamma_i(x, u) is tested per
point and dimension.

What is tested. Null hypothesis per (point, dimension): |E fhat_i - f_i| <= gamma_i(x, u).
Statistic z = (|mean_i - f_i| - gamma_i) / SE_i with SE_i = s_i / sqrt(R) (s_i the sample std
of the R runs). Its p-value under the composite null (worst case E fhat_i - f_i = +-gamma_i)
is P(T > z) + P(T > z + 2 gamma_i / SE_i), T Student's t with R - 1 degrees of freedom (SE is
estimated: at R = 100 the normal tail at z ~ 4 is half the t tail and doubled the false-alarm
rate); the second term matters where gamma is within a few SE of 0 (|mean - f| is then folded). The m = B n tests are corrected
for multiplicity with Holm's step-down procedure at family-wise false-alarm rate ``alpha``
(default 0.05): the chance that a certificate which holds everywhere fails the audit is at
most alpha. (Without correction, 400 tests at the boundary at 3 SE give about a 42 % false
alarm.) A point and dimension is

* ``holds``        if gamma_i - |mean_i - f_i| >= 0,
* ``violated``     if Holm rejects its null (beyond the corrected critical value),
* ``inconclusive`` otherwise.

The audit passes when nothing is violated. Power: if a fraction rho of the (x, u) the audit
draws from violates gamma by at least the detectable size (z_B + t_0.95) SE (z_B the Bonferroni
critical value; each such point is then detected with probability >= 0.95), the audit fails
with probability >= 1 - (1 - 0.95 rho)^B. Smaller violated fractions or smaller violations can
pass unnoticed; the report states both numbers.

NOT tested: the certificate's confidence. It is a probability over the data draw (which cover
data the certificate was computed from); one audit of one certificate checks that certificate's
realized gamma and cannot estimate that probability.

When the simulator offers an exact mean (numpy backend, ``mean_next``; exact when actuation
noise is 0), the exact gap is checked as well.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import fileio
from ..dataset import invariant_dims
from ..errors import SimgapError
from ..simulators import Simulator, make_simulator
from .lipschitz import load_fitting_modules

QUANTILES = (0.0, 0.01, 0.05, 0.5, 0.95, 1.0)
#: simulator rows (point x run) stepped at once: bounds the audit's memory
CHUNK_SAMPLES = 1_000_000


def audit_cost(points: int, runs: int, system, rate_per_worker=None, workers: int = 1,
               chunk_samples: int = CHUNK_SAMPLES) -> dict:
    """Work, peak memory and time of an audit of ``points`` x ``runs`` (before any of it runs).

    ``rows`` = points x runs simulator periods (each ``system.steps`` base periods); the points go
    in chunks of ``chunk_samples`` rows, all of a point's runs at once, so a chunk of
    max(runs, ...) rows holds states, inputs, noise and next states (float64, a factor 4 for the
    simulator's work arrays). ``seconds`` = rows / (rate x workers) when a rate [runs/s of one
    worker] was measured (:func:`simgap.cover.calibrate_rate`)."""
    n, m = system.n, system.m
    rows = float(points) * float(runs)
    chunk = float(min(int(points), max(1, chunk_samples // int(runs)))) * float(runs)
    memory = chunk * (3 * n + m) * 8 * 4 + float(points) * n * 8 * 6
    secs = rows / (rate_per_worker * max(1, workers)) if rate_per_worker else None
    return {"points": int(points), "runs": int(runs), "rows": rows, "sim_steps": rows * system.steps,
            "memory": memory, "seconds": secs, "rate": rate_per_worker, "workers": int(workers)}


def audit_rate(simulator, points: int, runs: int, chunk_samples: int = CHUNK_SAMPLES, budget: float = 0.5) -> float:
    """Runs per second of the audit's own ``simulator`` (all its processes: a
    :class:`~simgap.simulators.parallel.ParallelSimulator` spreads each batch over its helpers),
    timed at the audit's batch size: a chunk of min(points, chunk_samples // runs) points x runs
    rows per call, capped at 65,536 rows for the calibration (:func:`simgap.cover.calibrate_rate`).
    With this rate :func:`audit_cost` takes ``workers=1``: the simulator's processes are in it."""
    from ..cover import calibrate_rate
    load_fitting_modules()
    rows = min(int(points), max(1, int(chunk_samples) // max(1, int(runs)))) * int(runs)
    return calibrate_rate(simulator, n_runs=max(64, min(rows, 65536)), budget=budget, work=float(points) * float(runs))


def audit_cost_text(c: dict) -> str:
    """:func:`audit_cost` as the line a command prints before the audit starts."""
    from ..checks import available_memory, human_bytes
    from ..cover import format_duration
    t = ("time unknown" if c["seconds"] is None else
         f"about {format_duration(c['seconds'])} at {c['rate']:,.0f} runs/s per worker x {c['workers']} "
         "(calibrated here)")
    return (f"estimate: audit of {c['points']:,} points x {c['runs']:,} runs = {c['rows']:,.0f} simulator runs; "
            f"{t}; peak memory about {human_bytes(c['memory'])} ({human_bytes(available_memory())} available)")


def check_audit_cost(c: dict) -> None:
    """Refuse an audit over the machine's memory (or over :data:`simgap.checks.MAX_COMMAND_SECONDS`)."""
    from ..checks import check_sim_work
    check_sim_work(c["rows"], c["memory"], f"auditing {c['points']:,} points x {c['runs']:,} runs",
                   "use fewer --points or --runs (or the experiment's [audit] points / runs)", c["rate"], c["workers"])


def _chunk_progress(on_progress, a: int, R: int, B: int):
    """``on_rows`` for :meth:`Simulator.step` of the chunk starting at point ``a``: runs done of B x R."""
    if on_progress is None:
        return None
    return lambda rows: on_progress(a * R + rows, B * R)


def draw_points(system, B: int, rng: np.random.Generator, cover=None, cov_dims=None, inputs=None, input_box=None,
                boxes=None):
    """B fresh states uniform in X (not on the cover points) and inputs uniform from ``inputs`` (default U),
    or uniform in ``input_box`` = (lo, hi) when given (a certificate for continuous inputs).

    ``cover`` holds the cover points' coordinates in the covered dimensions ``cov_dims``. ``boxes`` =
    ((K, n), (K, n)): the states are drawn in their union instead (a box at random, then uniform in it:
    a certificate whose data covered a tube is audited where it speaks).
    """
    def uniform(k):
        if boxes is None:
            return system.x_lo + rng.random((k, system.n)) * (system.x_hi - system.x_lo)
        b = rng.integers(0, len(boxes[0]), size=k)
        return boxes[0][b] + rng.random((k, system.n)) * (boxes[1][b] - boxes[0][b])

    x = uniform(B)
    cov_dims = list(range(system.n)) if cov_dims is None else list(cov_dims)
    if cover is not None and len(cover):
        from scipy.spatial import cKDTree
        tree = cKDTree(cover)
        d, _ = tree.query(x[:, cov_dims])
        hit = d < 1e-9
        while hit.any():  # measure-zero event, redraw those (seeded)
            x[hit] = uniform(int(hit.sum()))
            d, _ = tree.query(x[:, cov_dims])
            hit = d < 1e-9
    if input_box is not None:
        lo, hi = (np.asarray(b, float) for b in input_box)
        return x, lo + rng.random((B, lo.size)) * (hi - lo)
    U = system.inputs if inputs is None else inputs
    u = U[rng.integers(0, len(U), size=B)]
    return x, u


def holm(p: np.ndarray, alpha: float) -> np.ndarray:
    """Holm's step-down rejections (same shape as ``p``) at family-wise error rate ``alpha``.

    Sorted p_(1) <= ... <= p_(m): reject p_(k) while p_(k) <= alpha / (m - k + 1) for all earlier k.
    """
    flat = np.asarray(p, float).ravel()
    m = flat.size
    order = np.argsort(flat, kind="stable")
    ok = flat[order] <= alpha / (m - np.arange(m))
    k = m if ok.all() else int(np.argmin(ok))  # first step that fails stops the procedure
    rej = np.zeros(m, dtype=bool)
    rej[order[:k]] = True
    return rej.reshape(np.shape(p))


def power(points: int, fraction: float) -> float:
    """P(audit fails) >= 1 - (1 - 0.95 rho)^B when a fraction rho of draws violates by the detectable size."""
    return float(1.0 - (1.0 - 0.95 * float(fraction)) ** int(points))


def audit(cert, simulator, points: int = 200, runs: int = 2000, seed: int = 0, dataset=None,
          chunk_samples: int = CHUNK_SAMPLES, alpha: float = 0.05, power_fraction: float = 0.01,
          system=None, on_progress=None) -> dict:
    """Audit ``cert`` with ``simulator`` (a Simulator, SimulatorConfig or its dict). Returns the report dict.

    ``system``: the nominal model f the certificate is for when it is not the simulator's own
    (a refined model certified on the simulator's data, ``simgap certify --system``).

    ``alpha``: family-wise false-alarm rate of the Holm-corrected tests; ``power_fraction``: the
    violated fraction of (x, u) the reported power refers to (see module docstring).
    ``on_progress(runs_done, points x runs)``: called while the runs go (the same numbers either way).
    """
    if int(points) < 1 or int(runs) < 2:
        raise SimgapError(f"audit: need points >= 1 and runs >= 2, got points={points}, runs={runs}")
    if not (0 < alpha < 1) or not (0 < power_fraction <= 1):
        raise SimgapError(f"audit: need 0 < alpha < 1 and 0 < power fraction <= 1, got alpha={alpha}, "
                          f"power fraction={power_fraction}")
    sim = simulator if isinstance(simulator, Simulator) else make_simulator(simulator)
    s = sim.system if system is None else system.with_steps(sim.system.steps)
    cert.check_system(s)
    rng = np.random.default_rng(seed)
    cover, cov_dims = None, list(range(s.n))
    if dataset is not None:
        inv = invariant_dims(dataset)  # declared-invariant dims are not covered: distances over the others
        cov_dims = [j for j in range(s.n) if j not in inv]
        cover = np.unique(dataset.x[:, cov_dims], axis=0)
    # a certificate for continuous inputs is audited between the grid's values too
    cont = bool(getattr(cert, "continuous", False))
    # a local certificate is audited where it speaks: fresh points in its region
    x, u = draw_points(cert.restrict(s) if hasattr(cert, "restrict") else s, int(points), rng, cover, cov_dims,
                       cert.inputs, cert.input_box if cont else None, getattr(cert, "region_boxes", None))
    B, R, n = len(x), int(runs), s.n
    fx = s.f(x, u)
    mean_dev = np.empty((B, n))
    sd = np.empty((B, n))
    per = max(1, chunk_samples // R)
    for a in range(0, B, per):  # chunks of points; runs vectorized
        b = min(B, a + per)
        nxt = sim.step(np.repeat(x[a:b], R, axis=0), np.repeat(u[a:b], R, axis=0), rng,
                       on_rows=_chunk_progress(on_progress, a, R, B)).reshape(b - a, R, n)
        d = s.diff(nxt, fx[a:b, None, :])
        mean_dev[a:b] = d.mean(axis=1)
        sd[a:b] = d.std(axis=1, ddof=1)
    gap = np.abs(mean_dev)
    se = sd / np.sqrt(R)
    gam = cert.gamma(x, u, continuous=True) if cont else cert.gamma(x, u)
    margin = gam - gap
    holds = margin >= 0
    from scipy.stats import t as student
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(se > 0, -margin / se, np.where(margin < 0, np.inf, -np.inf))  # SE 0: no noise, exact
        # p-value of the composite null |mu| <= gamma: the worst case mu = +-gamma gives
        # P(|N(gamma, SE)| - gamma > z SE) = P(Z > z) + P(Z > z + 2 gamma / SE)
        # (Student t with runs - 1 degrees of freedom: SE is estimated; the normal tail is 2x too light at z ~ 4)
        pval = student.sf(z, R - 1) + np.where(se > 0, student.sf(z + 2.0 * np.maximum(gam, 0.0) / se, R - 1), 0.0)
    violated = holm(np.minimum(pval, 1.0), alpha)
    inconclusive = ~holds & ~violated
    m_tests = violated.size
    z_bonf = float(student.isf(alpha / m_tests, R - 1))
    names = list(s.state_names)
    rep = {
        "system": s.name, "steps": s.steps, "points": B, "runs": R, "seed": int(seed),
        "simulator": sim.config.to_dict(), "certificate_method": cert.method,
        "lipschitz_term": getattr(cert, "lipschitz_term", "paper"), "inputs": "uniform in the input box" if cont else
        "uniform from the certificate's input set",
        "certificate_dataset_hash": cert.provenance.get("dataset_hash"),
        "certificate_digest": cert.digest,
        "test": {"null": "|E fhat_i(x,u) - f_i(x,u)| <= gamma_i(x,u) at each audited (x,u) and dimension i",
                 "statistic": "z = (|mean - f| - gamma) / SE, SE = sample std / sqrt(runs); "
                              "p = P(T > z) + P(T > z + 2 gamma / SE), T Student t with runs - 1 dof",
                 "correction": "Holm step-down", "tests": int(m_tests), "family_wise_alpha": float(alpha),
                 "z_first_step": z_bonf,
                 "not_tested": "the certificate's confidence (a probability over the data draw): one audit checks "
                               "this certificate's realized gamma only"},
        "power": {"violation_fraction": float(power_fraction), "probability": power(B, power_fraction),
                  "detectable_violation": {nm: float((z_bonf + student.isf(0.05, R - 1)) * np.median(se[:, i]))
                                           for i, nm in enumerate(s.state_names)},
                  "fraction_detected_at_95": float((1.0 - 0.05 ** (1.0 / B)) / 0.95),
                  "meaning": "if this fraction of the audited (x,u) distribution violates gamma by at least the "
                             "detectable violation, the audit fails with at least this probability"},
        "certificate_statement": cert.statement(),
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
            "margins": margin[:, i].tolist(),  # per audit point, for histograms (the app's audit plot)
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
    """Readable table of an audit report: what was tested, the results, and the audit's power."""
    t, pw = rep["test"], rep["power"]
    lines = [f"audit: system {rep['system']} (steps={rep['steps']}), {rep['points']} fresh points x {rep['runs']} runs, "
             f"certificate method {rep['certificate_method']}",
             f"tested: {t['null']}; violated when Holm rejects at family-wise false-alarm rate "
             f"{t['family_wise_alpha']:g} over {t['tests']} tests (first step z > {t['z_first_step']:.2f})"]
    hdr = f"{'dim':<10}{'holds':>8}{'violated':>10}{'inconcl.':>10}{'worst viol.':>13}{'margin min':>12}" \
          f"{'margin p5':>12}{'margin med':>12}{'MC SE med':>12}{'detectable':>12}"
    lines += [hdr, "-" * len(hdr)]
    for nm, d in rep["per_dim"].items():
        q = d["margin_quantiles"]
        lines.append(f"{nm:<10}{d['fraction_holds']:>8.3f}{d['fraction_violated']:>10.3f}"
                     f"{d['fraction_inconclusive']:>10.3f}{d['worst_violation']:>13.4g}{q['0.0']:>12.4g}"
                     f"{q['0.05']:>12.4g}{q['0.5']:>12.4g}{d['mc_standard_error']['median']:>12.3g}"
                     f"{pw['detectable_violation'][nm]:>12.3g}")
    j = rep["joint"]
    lines.append(f"{'joint':<10}{j['fraction_holds']:>8.3f}{j['fraction_violated']:>10.3f}"
                 f"{j['fraction_inconclusive']:>10.3f}")
    if "exact" in rep:
        e = rep["exact"]
        lines.append("exact mean (simulator.mean_next" + ("" if e["exact_mean"] else ", approximate") + "): "
                     + ", ".join(f"{k} holds {v:.3f}" for k, v in e["fraction_holds"].items())
                     + f", joint {e['joint_fraction_holds']:.3f}")
    lines.append(f"power: if a fraction {pw['violation_fraction']:g} of (x,u) violated gamma by at least the "
                 f"'detectable' size, this audit would fail with probability >= {pw['probability']:.3f} "
                 f"(95 % at a fraction {pw['fraction_detected_at_95']:.3g})")
    lines.append(f"not tested: {t['not_tested']}")
    lines.append("PASSED: no violation after the multiplicity correction" if rep["passed"]
                 else "FAILED: gamma is violated beyond the audit's Monte-Carlo error (Holm-corrected)")
    return "\n".join(lines)

"""The realization-level gap gamma^alpha: a bound on one run's deviation, not on the mean's.

Claim (at confidence 1 - beta over the data): for every (x, u) in X x U and every dimension i,

    P_w( |fhat_i(x, u, w) - f_i(x, u)| <= gamma^alpha_i(x, u) ) >= 1 - alpha.

Construction from the same N1hat runs per cover pair (x_r, u) the paper uses:

1. Order statistic. D = |wrap(fhat_i(x_r,u,w) - f_i(x_r,u))|; the (N1hat - j)-th order statistic
   of the N1hat runs bounds D's (1 - alpha)-quantile with confidence 1 - beta' when
   P(Bin(N1hat, alpha) <= j) <= beta' (:mod:`.orderstats`). beta' = beta / (n K): a union
   (Bonferroni) bound over all K pairs and n dimensions, so the bounds hold for all pairs at
   once with probability >= 1 - beta. The collection keeps the 32 largest deviations, so j is
   capped at 31 (the bound stays valid, only more conservative, for large alpha).
2. Scenario LP (the paper's SCP-N1hat with delta_1 = 0): q_i with q_i^T p_i(x_r,u) >= qhat_i(x_r,u)
   at every pair, minimizing the maximum.
3. Lipschitz extension. ASSUMPTION (per realization): for every fixed w (common random numbers:
   the same noise draw at x and x_r) the increment x -> fhat(x,u,w) - x is Lhat-Lipschitz in
   every dimension, and f - x is L_f-Lipschitz. Then for ||x - x_r|| <= eps,
   |fhat_i(x,u,w) - f_i(x,u)| <= |fhat_i(x_r,u,w) - f_i(x_r,u)| + (L_f + Lhat) eps, and
   q^T p(x_r,u) <= q^T p(x,u) + L_2 eps, so

       gamma^alpha_i(x, u) = q_i^T p_i(x, u) + (L_f + Lhat + L_2) eps (+ solver repair).

   Lhat is a Wood-Zhang estimate from per-run slopes with common random numbers (simulator),
   L_2 the sound interval bound of the fitted polynomial's gradient. The Lipschitz constants are
   estimates, as in the paper: the statement is conditional on them.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import asdict, dataclass
from typing import Optional

import numpy as np

from ..certify.certificate import Certificate, DimCertificate
from ..certify.lipschitz import l2_analytic, neighbour_pairs, slopes_of, wood_zhang
from ..certify.pipeline import _versions, bases_for, check_dataset, dataset_region
from ..certify.scp import solve_scp
from ..dataset import invariant_dims
from ..errors import SimgapError
from ..system_ref import embedded_ref, system_digest
from .orderstats import alpha_min, order_index

ASSUMPTION = ("per realization: for every noise draw w, x -> fhat(x,u,w) - x is Lhat-Lipschitz (common random "
              "numbers) and f - x is L_f-Lipschitz; Lipschitz constants are Wood-Zhang estimates")


@dataclass
class RunCertifyOptions:
    """Options of :func:`certify_run`.

    alpha : per-dimension miss probability of one run, in (0, 1).
    beta : failure probability of the whole certificate (all pairs, all dimensions).
    degree, terms : the basis (as in :class:`simgap.certify.CertifyOptions`).
    lhat_pairs, lhat_runs : random pairs ||x - x'|| = eps and runs per pair for Lhat (simulator).
    """

    alpha: float = 0.05
    beta: float = 0.01
    degree: int = 2
    terms: dict = None
    lhat_pairs: int = 1000
    lhat_runs: int = 20
    solver: str = "CLARABEL"
    seed: int = 0

    def validate(self):
        if not (isinstance(self.alpha, (int, float)) and 0.0 < float(self.alpha) < 1.0):
            raise SimgapError(f"alpha must be in (0, 1), got {self.alpha!r}")
        if not (isinstance(self.beta, (int, float)) and 0.0 < float(self.beta) < 1.0):
            raise SimgapError(f"beta must be in (0, 1), got {self.beta!r}")
        if int(self.lhat_pairs) < 10 or int(self.lhat_runs) < 1:
            raise SimgapError("lhat_pairs must be >= 10 and lhat_runs >= 1")


def per_pair_beta(beta: float, K: int, n: int) -> float:
    """beta' = beta / (n K): the Bonferroni share of each (pair, dimension) order-statistic bound."""
    return float(beta) / (int(K) * int(n))


def smallest_alpha(dataset, beta: float = 0.01) -> float:
    """The smallest alpha the data set's N1hat supports at certificate confidence 1 - beta."""
    return alpha_min(int(dataset.n_runs), per_pair_beta(beta, dataset.K, dataset.system.n))


def quantile_bounds(dataset, alpha: float, beta: float):
    """(qhat (K, n), j, j_used): per-pair upper bounds on the (1-alpha)-quantile of |fhat_i - f_i|."""
    if dataset.absdev_top is None:
        raise SimgapError("the data set has no per-run order statistics (collected before they were kept); "
                          "collect it again with this version to certify at the run level")
    check_deviations(dataset)
    N = int(dataset.n_runs)
    j = order_index(N, alpha, per_pair_beta(beta, dataset.K, dataset.system.n))
    j_used = min(j, dataset.absdev_top.shape[1] - 1)
    return dataset.absdev_top[:, j_used, :], j, j_used


def check_deviations(dataset) -> None:
    """Refuse per-run deviations that cannot come from the data's own runs (forged or corrupt
    with a recomputed digest): each pair's top |d| must be finite, >= 0 and descending; the
    largest must equal max(hi - f_nom, f_nom - lo) (the runs' own extremes, kept beside them);
    and their squares cannot add up to more than all N1hat squared deviations,
    (N1hat - 1) var + N1hat (mean - f_nom)^2. A plausibility check, not a proof (docs/deviations.md)."""
    top = np.asarray(dataset.absdev_top, dtype=float)
    where = "the data set's per-run deviations (absdev_top)"
    if not np.all(np.isfinite(top)):
        raise SimgapError(f"{where} contain NaN or inf: refused")
    if np.any(top < 0):
        raise SimgapError(f"{where} contain negative absolute deviations: refused")
    if np.any(np.diff(top, axis=1) > 0):
        raise SimgapError(f"{where} are not sorted largest first: refused")
    f = dataset.f_nom
    ext = np.maximum(dataset.hi - f, f - dataset.lo)
    tol = 1e-9 * (1.0 + np.abs(f) + np.abs(dataset.hi) + np.abs(dataset.lo))
    bad = np.abs(top[:, 0, :] - ext) > tol
    if np.any(bad):
        k, i = np.argwhere(bad)[0]
        raise SimgapError(f"{where}: pair {k}, dimension {i}: the largest deviation {top[k, 0, i]:.6g} is not the runs' "
                          f"own extreme max(hi - f_nom, f_nom - lo) = {ext[k, i]:.6g}: refused")
    N = int(dataset.n_runs)
    d_mean = dataset.system.diff(dataset.mean, f)  # wrapped for angles, as the deviations are
    total = (N - 1) * dataset.var + N * d_mean ** 2
    if np.any((top ** 2).sum(axis=1) > total * (1 + 1e-6) + tol):
        raise SimgapError(f"{where} add up to more than the runs' own variance and mean allow: refused")


def per_run_slopes(sim, rng: np.random.Generator, h: float, n_pairs: int, runs: int) -> np.ndarray:
    """Slopes |d_i(x,w) - d_i(x',w)| / h of single runs with common random numbers, (n_pairs*runs, n).

    d = fhat(.,u,w) - . is the increment; x' = x + h*direction, u uniform from U, the same w at both ends.
    """
    s = sim.system
    from ..certify.lipschitz import check_pair_distance
    check_pair_distance(s, h)
    lo, hi = s.x_lo + h, s.x_hi - h
    x = lo + rng.random((n_pairs, s.n)) * (hi - lo)
    d = rng.standard_normal((n_pairs, s.n))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    u = s.inputs[rng.integers(0, len(s.inputs), n_pairs)]
    X = np.repeat(np.concatenate([x, x + h * d]), runs, axis=0)
    U = np.repeat(np.concatenate([u, u]), runs, axis=0)
    noise = {k: np.concatenate([v, v]) for k, v in sim.draw_noise(n_pairs * runs, rng).items()}
    inc = s.diff(sim.step_with_noise(X, U, noise), X).reshape(2, n_pairs * runs, s.n)
    return np.abs(s.diff(inc[0], inc[1])) / h


def certify_run(dataset, options: Optional[RunCertifyOptions] = None, simulator=None, **kw) -> Certificate:
    """The realization-level certificate gamma^alpha of ``dataset`` (see module docstring).

    Returns a :class:`Certificate` with ``method = "run"``; its ``gamma`` is gamma^alpha and
    ``options`` hold alpha, beta, the order-statistic index and the assumption. ``simulator``
    (a Simulator) is used for Lhat; by default it is rebuilt from the data manifest.
    """
    t0 = time.perf_counter()
    o = options or RunCertifyOptions(**kw)
    o.validate()
    ds, s = dataset, dataset.system
    X_lo, X_hi = s.x_lo.copy(), s.x_hi.copy()
    region = dataset_region(ds)
    if region is not None:  # a local data set: estimates over the region, gamma^alpha stated there only
        ds = dataclasses.replace(ds, system=dataclasses.replace(s, x_lo=region[0], x_hi=region[1]))
        s = ds.system
    check_dataset(ds)
    qhat, j, j_used = quantile_bounds(ds, float(o.alpha), float(o.beta))
    K, N, n = ds.K, int(ds.n_runs), s.n
    inv = invariant_dims(ds)
    bases = bases_for(s, o.degree, {int(k): list(v) for k, v in (o.terms or {}).items()}, inv)

    # Lipschitz constants: nominal increments over neighbouring cover points, fhat per run (CRN)
    pairs = neighbour_pairs(ds)
    sl_f = slopes_of(s.diff(ds.f_nom, ds.x), pairs, s)
    if simulator is None:
        from ..simulators.base import make_simulator
        cfg = ds.manifest.get("simulator")
        if not cfg:
            raise SimgapError("run-level certificate: the data manifest names no simulator (needed for Lhat)")
        with make_simulator(cfg, system=s) as sim:
            sl_fhat = per_run_slopes(sim, np.random.default_rng([o.seed, 11]), ds.epsilon, o.lhat_pairs, o.lhat_runs)
    else:
        sl_fhat = per_run_slopes(simulator, np.random.default_rng([o.seed, 11]), ds.epsilon, o.lhat_pairs,
                                 o.lhat_runs)
    U_data = np.unique(ds.u, axis=0)
    bi = float(o.beta) / n
    dims = []
    for i in range(n):
        P = bases[i].design(ds.x, ds.u)
        res = solve_scp(P, qhat[:, i], 0.0, solver=o.solver, seed=o.seed)
        wf = wood_zhang(sl_f[:, i], np.random.default_rng([o.seed, 2, i]))
        wh = wood_zhang(sl_fhat[:, i], np.random.default_rng([o.seed, 3, i]))
        L_2 = l2_analytic(bases[i], res.q, s, inputs=U_data)
        if not np.isfinite(L_2):
            raise SimgapError(f"L_2 of dimension {s.state_names[i]} is unbounded on X; change the basis terms")
        fit = P @ res.q
        const = (wf.estimate + wh.estimate + L_2) * ds.epsilon + res.repair
        scp = res.to_dict()
        scp["gamma_range_on_data"] = [float(fit.min() + const), float(fit.max() + const)]
        how = {"L_f": {"how": "Wood-Zhang estimate on slopes of f - x over neighbouring cover points", **wf.to_dict()},
               "L_fhat": {"how": f"Wood-Zhang estimate on per-run slopes of fhat - x, common random numbers, "
                                 f"{o.lhat_pairs} pairs x {o.lhat_runs} runs at distance eps", **wh.to_dict()},
               "L_2": "analytic: interval bound of ||grad_x q^T p||_2 over sub-boxes of X, all u in U (sound)"}
        dims.append(DimCertificate(terms=bases[i].names, q=res.q, delta1=0.0, delta2=0.0, beta1=bi, beta2=0.0,
                                   beta_v=0.0, Mhat=None, L_f=wf.estimate, L_fhat=wh.estimate, L_2=L_2,
                                   lipschitz_how=how, repair=res.repair, eta=res.eta,
                                   gap_max=float(qhat[:, i].max()), scp=scp, basis=bases[i]))
    opts = asdict(o)
    opts.update({"level": "run", "order_index": j, "order_index_used": j_used,
                 "order_statistic": f"D_(N1hat - {j_used}) of N1hat = {N}",
                 "per_pair_beta": per_pair_beta(o.beta, K, n), "alpha_min": smallest_alpha(ds, o.beta),
                 "union_bound": f"Bonferroni over K = {K} pairs and n = {n} dimensions",
                 "assumption": ASSUMPTION, "beyond_paper": ["realization-level gap (run level)"],
                 "notes": ([f"order statistic capped at the {j_used + 1} largest kept deviations "
                            f"(alpha supports j = {j})"] if j_used < j else [])})
    prov = {"dataset_hash": ds.hash, "versions": _versions(), "seed": o.seed, "dataset_seed": ds.manifest.get("seed"),
            "simulator": ds.manifest.get("simulator"), "created_unix": time.time(),
            "seconds": time.perf_counter() - t0}
    return Certificate(system_name=s.name, steps=int(s.steps), state_names=tuple(s.state_names),
                       input_names=tuple(s.input_names), x_lo=X_lo, x_hi=X_hi, region=region,
                       angle_dims=tuple(s.angle_dims), epsilon=float(ds.epsilon), n_runs=N, K=K, method="run",
                       options=opts, dims=dims, provenance=prov, inputs=U_data,
                       system_digest=system_digest(s), system_ref=embedded_ref(s))


def run_alpha(cert: Certificate) -> float:
    """alpha of a run-level certificate (SimgapError for other certificates)."""
    if cert.method != "run":
        raise SimgapError(f"need a run-level certificate (simgap certify --level run), got method {cert.method!r}")
    return float(cert.options["alpha"])

"""The case-study pipeline: deterministic gap versus stochastic gap, end to end.

``run_experiment`` runs every stage of the paper's comparison for one experiment profile:

1. collect the stochastic data set (resumable store) with the experiment's simulator;
2. collect the deterministic baseline's data set: the same simulator with its noise and parameter
   randomization switched off (the predecessor work assumes a deterministic simulator, so one
   run per pair is all it has; the store keeps two identical runs because it needs N1hat >= 2);
   the undeclared effects stay, since they are part of the simulator, not of its noise;
3. certify both: the paper's stochastic method on (1), the deterministic method on (2);
4. audit both certificates against the *stochastic* simulator at fresh points;
5. synthesize a controller with each gap (same grid, hold, specification);
6. roll each controller out R times (default 1000) in the stochastic simulator from x0;
7. write ``summary.json`` (configuration, provenance, every number of the comparison table).

The experiment TOML's sections ``[certify]``, ``[audit]``, ``[synthesis]`` and ``[rollout]``
hold the stage options (see ``assets/experiments/pendulum.toml``).
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from . import fileio, results_folder
from .collect import check_collection, collect, load_store, printed_collection_estimate
from .store import check_fillable
from .config import ExperimentConfig
from .errors import SimgapError
# the specification of an experiment lives in simgap.experiment_spec (the per-run stage needs it too);
# re-exported here, its old home
from .experiment_spec import experiment_spec  # noqa: F401
from .synthesis import set_synthesis
from .synthesis.statement import METHOD_NAMES, statement_of
from .simulators import make_simulator

METHODS = ("deterministic", "stochastic")
#: every result file a run may write into its folder (a foreign file under one of these names is refused)
RESULT_NAMES = tuple(f"{kind}_{m}.{ext}" for m in METHODS for kind, ext in
                     (("cert", "json"), ("audit", "json"), ("controller", "npz"), ("rollouts", "npz"))) + (
    "summary.json", "run.rrd", "perrun.rrd", "cert_run.json", "controller_run_baseline.npz", "controller_perrun.npz",
    "controller_nominal.npz", "rollouts_nominal.npz")  # the invariant-set run's nominal-model set

def baseline_experiment(exp: ExperimentConfig) -> ExperimentConfig:
    """The deterministic baseline's collection: noise and randomization off, N1hat = 2 identical runs."""
    sim = dataclasses.replace(exp.simulator, noise={}, randomize={})
    col = dataclasses.replace(exp.collect, n_runs=2, out=None)
    return dataclasses.replace(exp, simulator=sim, collect=col)


def certify_options(section: dict, method: str, system=None):
    """CertifyOptions from an experiment's ``[certify]`` section (``terms`` keys: state names, ``all``,
    or 0-based numbers with -1 = all; names need ``system``)."""
    from .certify.bounds import BoundOptions
    from .certify.pipeline import CertifyOptions

    s = dict(section)  # keys and types checked by simgap.schema when the experiment was loaded
    bkw = {k: s.pop(k) for k in ("concentration", "uniform", "lemma2_factor") if k in s}
    if "terms" in s:
        if system is not None:
            from .certify.basis import terms_by_dimension
            s["terms"] = terms_by_dimension(s["terms"], system)
        else:
            s["terms"] = {int(k): list(v) for k, v in s["terms"].items()}
    if method == "deterministic":
        for k in ("delta1", "delta2", "beta1", "beta2", "confidence", "variance", "safety", "value_range"):
            s.pop(k, None)
    return CertifyOptions(method=method, bounds=BoundOptions(**bkw), **s)


def check_experiment(exp: ExperimentConfig, out: Optional[str | Path] = None, *, n_rollouts: Optional[int] = None,
                     workers: Optional[int] = None) -> dict:
    """Check everything :func:`run_experiment` will need before any stage runs.

    The file's keys and types were checked when it was loaded (:mod:`simgap.schema`); here the
    values are checked against the system and each other: eta, the safe box, x0 and the
    per-dimension margins have the system's dimension, x0 lies in X, the certify options build
    (basis terms parse, the basis fits the data set's size), the simulator can be made, and the
    collection and the rollouts fit in memory and on disk. Returns ``spec``, ``x0``, ``eta``,
    ``hold`` and ``n_rollouts``; SimgapError naming the section and key otherwise.
    """
    from . import checks
    from .certify.pipeline import bases_for

    s = exp.system
    n = s.n
    syn, ro, cert = exp.section("synthesis"), exp.section("rollout"), exp.section("certify")
    if n_rollouts is not None and (int(n_rollouts) != n_rollouts or n_rollouts < 1):
        raise SimgapError(f"rollouts per controller must be an integer >= 1, got {n_rollouts!r}")
    R = int(n_rollouts or ro.get("n", 1000))

    def per_dim(section, key, value):
        if np.ndim(value) and np.size(value) not in (1, n):
            raise SimgapError(f"[{section}] {key}: need one value or {n} (one per state {', '.join(s.state_names)}), "
                              f"got {value!r}")

    grid = set_synthesis.method_of(syn) == "grid"
    if grid and "eta" not in syn:
        raise SimgapError("[synthesis] eta (grid cell widths) is required")
    if "eta" in syn:
        per_dim("synthesis", "eta", syn["eta"])
    for k in ("safe_lo", "safe_hi"):
        if k in syn and len(syn[k]) != n:
            raise SimgapError(f"[synthesis] {k}: need {n} values, got {syn[k]!r}")
    set_synthesis.check_method(syn)  # before the spec: a reach-avoid map is not read for it
    spec, map_x0, _ = experiment_spec(exp)
    if not grid:
        set_synthesis.check_section(s, syn, spec)
    if exp.collect.region:  # a local certificate: the set synthesis takes gamma over must lie in the region
        from .cover import region_box
        rlo, rhi = region_box(s, exp.collect.region)
        what, lo, hi = (("the grid synthesis's domain X", s.x_lo, s.x_hi) if grid else
                        ("[synthesis] safe set", np.maximum(spec.safe.lo, s.x_lo), np.minimum(spec.safe.hi, s.x_hi)))
        out_dims = [s.state_names[i] for i in range(n) if lo[i] < rlo[i] - 1e-12 or hi[i] > rhi[i] + 1e-12]
        if out_dims:
            raise SimgapError(f"{what} leaves [collect] region in {', '.join(out_dims)} ("
                              + "; ".join(f"{s.state_names[i]}: set [{lo[i]:g}, {hi[i]:g}], region [{rlo[i]:g}, "
                                          f"{rhi[i]:g}]" for i in range(n) if s.state_names[i] in out_dims)
                              + "): gamma holds on the region only; "
                              + ("narrow safe_lo / safe_hi to it" if not grid else
                                 "use method = \"invariant_set\" with a safe set inside it, or no region"))
    x0 = np.asarray(ro["x0"], dtype=float) if "x0" in ro else map_x0
    if x0 is None:
        raise SimgapError("[rollout] x0 is required (no map gives an initial state)")
    if x0.shape != (n,):
        raise SimgapError(f"[rollout] x0: need {n} values, got {ro.get('x0')!r}")
    s.check_states(x0[None, :], "[rollout] x0")
    if "horizon" in ro:
        checks.check_memory(R * (ro["horizon"] + 1) * (2 * n * 8 + 4),
                            f"{R:,} rollouts x horizon {ro['horizon']:,}", "use fewer rollouts or a shorter horizon")
        if set_synthesis.method_of(syn) == "box_tube" and syn.get("per_run", True):
            from .synthesis.noise_tube import check_horizon
            check_horizon(ro["horizon"], n, "[rollout] horizon")  # the box tube's per-run statement

    for k in ("delta1", "delta2", "beta1", "beta2", "degree"):
        if k in cert:
            per_dim("certify", k, cert[k])
    plan = exp.plan()
    inv = [d if isinstance(d, int) else s.state_names.index(d) for d in exp.collect.invariant_dims
           if isinstance(d, int) or d in s.state_names]
    for method in METHODS:
        opts = certify_options(cert, method, exp.system)
        degs = list(opts.degree) if np.ndim(opts.degree) else [opts.degree] * n
        n_terms = max(len(opts.terms.get(-1, [])) + len(opts.terms.get(i, [])) for i in range(n))
        checks.check_basis(plan.n_pairs, n + s.m - len(inv), degs, n_terms, what="[certify] degree")
        bases_for(s, opts.degree, opts.terms, inv)  # every term parses
        check_against_cover(s, plan.cover, opts)

    c = exp.collect
    wk = workers if workers is not None else c.workers
    check_collection(plan.n_pairs, plan.n_runs, n, s.m, s.steps, plan.batch_runs, wk or os.cpu_count() or 1,
                            plan.keep_samples, Path(out) if out is not None else Path("."))
    with make_simulator(exp.simulator, s):
        pass  # the simulator's kind, noise, effects and options are valid
    return {"spec": spec, "x0": x0, "eta": syn.get("eta"), "hold": int(syn.get("hold", 1)), "n_rollouts": R,
            "method": set_synthesis.method_of(syn)}


def check_against_cover(system, cover, opts, where: str = "[certify]") -> None:
    """The certify options' refusals that the cover and the input set decide, before any collection.

    - the basis degree against the values each variable will take on the data
      (:func:`simgap.checks.check_degree_values`);
    - lhat = "simulator": its pair distance h = the cover's epsilon fits inside X along every covered
      dimension (:func:`simgap.certify.lipschitz.check_pair_distance`);
    - the gap's own Lipschitz term (lipschitz_term = "gap" or continuous inputs): at least two cover
      values along every covered dimension (and input, for continuous inputs): it needs neighbours.
    Each message names the setting to change."""
    from . import checks
    from .certify.lipschitz import check_pair_distance

    cov = list(cover.covered)
    counts = {system.state_names[j]: int(c) for j, c in zip(cov, cover.counts)}
    inputs = {nm: len(np.unique(system.inputs[:, k])) for k, nm in enumerate(system.input_names)}
    remedy = {nm: f"a finer cover along {nm} ([collect] epsilon or spacing, --epsilon)" for nm in counts}
    remedy.update({nm: f"more values of {nm} in the system's input set" for nm in inputs})
    degs = list(opts.degree) if np.ndim(opts.degree) else [opts.degree] * system.n
    checks.check_degree_values([d if d is not None else -1 for d in degs], {**counts, **inputs},
                               system.state_names, f"{where} degree", remedy)
    if opts.lhat == "simulator":
        check_pair_distance(system, float(cover.epsilon), cov)
    if opts.lipschitz_term == "gap" or opts.continuous_inputs:
        # a cover along a tube with the simulator's slopes needs no neighbours along the states (its radii are
        # its cells', its slopes the simulator's pairs: certify's own rule); the inputs' grid still counts
        tube_sim = getattr(cover, "boxes", None) is not None and opts.lhat == "simulator"
        need = dict({} if tube_sim else counts, **(inputs if opts.continuous_inputs else {}))
        for nm, v in need.items():
            if v < 2:
                raise SimgapError(f"{where} the gap's own Lipschitz term (lipschitz_term = \"gap\" or continuous "
                                  f"inputs) needs cover points with neighbours along every covered dimension, but "
                                  f"the data will have {v} value of {nm}: use "
                                  f"{remedy[nm]} (at least 2 values), or lipschitz_term = \"paper\"")


def closest_approach(arena, rr) -> dict:
    """Closest approach [m] of the robot centre to the grown obstacles (signed, negative inside;
    :meth:`simgap.maps.ArenaMap.clearance`): per rollout the minimum over its trajectory, then
    the minimum, 5 % quantile and median over the rollouts, and the mean-map trajectory's."""
    per_run = arena.clearance(rr.trajectories).min(axis=1)  # padding repeats real states
    out = {"min": float(per_run.min()), "q05": float(np.quantile(per_run, 0.05)),
           "median": float(np.median(per_run))}
    if rr.mean_map_trajectory is not None:
        out["mean_map"] = float(arena.clearance(np.asarray(rr.mean_map_trajectory)).min())
    return out


#: why the case study's controllers carry no p_cert (summary.json and the table say it)
NO_P_CERT = ("the deterministic-gap controller states no probability and the stochastic-gap controller's guarantee "
             "is about the mean map (the expected state), not single runs: neither has a per-run p_cert; the per-run "
             "stage ([perrun] section, docs/per-run.md) synthesizes its own controller with one")


def per_run_empirical(rr, controller=None) -> dict:
    """p_emp(x0) of one controller from the case study's R rollouts: the success fraction k / R (a run
    succeeds by the spec's verdict within the horizon), its standard error sqrt(p (1 - p) / R) and
    two-sided 95 % Clopper-Pearson interval; ``p_cert`` the box tube's per-run statement for the
    rollouts' horizon T (:mod:`simgap.synthesis.noise_tube`) with the runs inside its tube, else None
    with the reason (:data:`NO_P_CERT`)."""
    from .perrun.validation import empirical
    R = int(rr.n_rollouts)
    k = R - int(rr.n_failures)
    e = empirical(np.array([k]), R)
    out = {"p_emp": e["p_emp"][0], "se": e["se"][0], "ci95": e["ci95"][0], "successes": k, "n_rollouts": R,
           "horizon": int(rr.horizon), "p_cert": None, "p_cert_note": NO_P_CERT}
    nt = getattr(controller, "noise_tube", None)
    why = ((getattr(controller, "meta", None) or {}).get("stats", {}).get("noise_tube") or {}).get("none")
    if nt is None and why:  # a box tube whose certificate does not support the per-run statement
        out["p_cert_note"] = f"the box tube states no per-run probability: {why}"
    if nt is not None:
        T = int(rr.horizon)
        inside = int(controller.inside(rr.trajectories, noise=True).sum())
        ei = empirical(np.array([inside]), R)
        out.update(p_cert=nt.p_run(T), p_cert_note=(
            f"box tube's noise tube: P(a run stays in it for T = {T} periods, then in its terminal box inside the "
            f"target) >= 1 - beta_noise - beta_cert = 1 - {nt.beta_noise(T):.3g} - {nt.beta_cert:.3g}, the noise's "
            f"response bounded by {nt.lam:.3g} x its sub-Gaussian proxy; assumes {nt.assumption}"),
            in_noise_tube=inside, p_emp_in_noise_tube=ei["p_emp"][0], se_in_noise_tube=ei["se"][0])
    return out


def per_run_note(summary: dict) -> Optional[str]:
    """What the table's per-run rows mean (printed under it by ``simgap run``); None without them."""
    if not any("per_run_empirical" in summary["methods"][m] for m in METHODS):
        return None
    notes = {m: summary["methods"][m]["per_run_empirical"] for m in METHODS
             if summary["methods"][m].get("per_run_empirical", {}).get("p_cert_note", NO_P_CERT) != NO_P_CERT}
    p_cert = "; ".join(f"{m}: {e['p_cert_note']}" for m, e in notes.items()) if notes else NO_P_CERT
    return (f"p_emp(x0): successes out of the rollouts from x0 (95 % Clopper-Pearson intervals in summary.json); "
            f"p_cert: {p_cert}")


def _gamma_stats(cert, ds) -> dict:
    """gamma's max and mean over the data rows; with the gap's own Lipschitz term also the max with
    the paper's term, for the side-by-side rows of the table."""
    fit = cert.fit(ds.x, ds.u)
    g = fit + cert.constant()
    out = {"max": g.max(axis=0).tolist(), "mean": g.mean(axis=0).tolist(), "lipschitz_term": cert.lipschitz_term}
    if cert.lipschitz_term == "gap":
        out["max_paper_term"] = (g - cert.lipschitz_terms() + cert.paper_terms()).max(axis=0).tolist()
    return out


def run_experiment(exp: ExperimentConfig, out: str | Path, *, executor: Optional[str] = None,
                   workers: Optional[int] = None, address: Optional[str] = None, n_rollouts: Optional[int] = None,
                   log: Callable[[str], None] = print, progress: Optional[Callable] = None,
                   stores_from: Optional[str | Path] = None, force: bool = False) -> dict:
    """Run the deterministic-vs-stochastic comparison of ``exp`` into ``out``; return the summary.

    Writes ``out/data`` and ``out/data_deterministic`` (resumable stores), ``cert_<method>.json``,
    ``audit_<method>.json``, ``controller_<method>.npz``, ``rollouts_<method>.npz`` and
    ``summary.json`` (written last, atomically). ``progress(stage_name, unit)``, if given, returns an
    ``on_progress(done, total)`` callback for that stage: each collection ("pairs") and the long
    parts of the per-run stage (:func:`simgap.perrun.stage.run_stage`). ``executor``, ``workers`` and
    ``address`` (default: the experiment's ``[collect]``) say where the collections' chunks and the
    per-run stage's interval-MDP sampling run; ``address`` is a Ray cluster's. A folder holding the
    finished run of another experiment or profile is refused unless ``force`` (its files are named).
    """
    from .certify.audit import audit, audit_cost, audit_rate, audit_cost_text, check_audit_cost
    from .certify.lipschitz import crn_cost_text
    from .certify.pipeline import certify, lhat_cost
    from .cover import calibrate_rate, estimate_cost
    from .synthesis.controller import synthesize
    from .rollout import rollout

    t_start = time.perf_counter()
    out = Path(out)
    if exp.collect.tube_margin is not None:  # the cover along the nominal tube, fixed before any data
        from .tube_collect import along_tube
        exp = along_tube(exp, log)
    from .rounds import Budget
    budget = Budget(exp.collect.budget_runs, exp.collect.budget_minutes)
    if budget.active and set_synthesis.method_of(exp.section("synthesis")) not in set_synthesis.SET_METHODS:
        raise SimgapError("[collect] budget_runs / budget_minutes: the rounds re-prove a set synthesis (method = "
                          "\"box_tube\" or \"invariant_set\"), whose proof reports the factor of gamma it tolerates")
    per_run = exp.section("perrun")
    if per_run:  # validated before any work: bad input writes nothing
        from .perrun.stage import check_section
        per_run = check_section(per_run, exp.system, exp.plan().n_pairs, exp.collect.n_runs,
                                exp.section("rollout").get("horizon"))
        from .executors import make_executor
        from .perrun.stage import project_cost
        # the per-run sampling runs on the collection's executor (a local pool unless told otherwise)
        perrun_ex = make_executor(executor or exp.collect.executor,
                                  workers if workers is not None else exp.collect.workers,
                                  address or exp.collect.address)
        project_cost(per_run, exp, perrun_ex, log)
    checked = check_experiment(exp, out, n_rollouts=n_rollouts, workers=workers)
    syn, ro, au = exp.section("synthesis"), exp.section("rollout"), exp.section("audit")
    cert_section = exp.section("certify")
    spec, x0, hold, R = checked["spec"], checked["x0"], checked["hold"], checked["n_rollouts"]
    arena = experiment_spec(exp)[2]
    if per_run:  # a reach-avoid horizon shorter than one hold certifies nothing: refused before any work
        from .perrun.value_iteration import check_horizon
        check_horizon(spec.kind, int(per_run["horizon"]), int(per_run["hold"]))
    if stores_from is not None and not Path(stores_from).is_dir():
        raise SimgapError(f"stores_from: {str(stores_from)!r} is not a folder (it should hold the data/ and "
                          "data_deterministic/ stores of an earlier run)")
    store_root = out if stores_from is None else Path(stores_from)
    # the stores must be resumable and the folder's files ours to replace before anything is removed:
    # a refused run leaves an earlier run's results and the user's own files as they were
    for e, sub in ((exp, "data"), (baseline_experiment(exp), "data_deterministic")):
        check_fillable(store_root / sub, e.plan().config())
    results_folder.check_same_run(out, exp.name, exp.profile, force)  # another run's results: only with force
    results_folder.claim(out, RESULT_NAMES)
    out.mkdir(parents=True, exist_ok=True)  # after validation: bad input leaves no folder behind
    run_id = results_folder.new_run_id()
    try:  # embedded: the folder opens without the file, from anywhere (simgap gui RESULTS)
        toml_text = exp.path.read_text()
    except OSError:
        toml_text = None
    with results_folder.run_lock(out):
        # again under the lock (the folder may have changed since), then the earlier run's files go
        import shlex
        resume = "simgap run " + " ".join(shlex.quote(a) for a in (str(exp.path.resolve()), "--profile",
                                                                    exp.profile or "base", "--out", str(out.resolve())))
        results_folder.claim(out, RESULT_NAMES).release(run_id, log, resume=resume)

        def wrote(*names):
            results_folder.record(out, names)
        ex = executor or exp.collect.executor
        wk = workers if workers is not None else exp.collect.workers
        times: dict = {}
        estimates: dict = {}  # stage -> the seconds its printed estimate said (bench/bench_estimates.py)
        summary: dict = {"experiment": exp.name, "profile": exp.profile, "description": exp.description,
                         "run_id": run_id, "config_file": str(exp.path.resolve()), "experiment_toml": toml_text,
                         "sections": {k: exp.section(k) for k in ("certify", "audit", "synthesis", "rollout")},
                         "simulator": exp.simulator.to_dict(), "system": exp.system.describe(),
                         "x0": x0.tolist(), "n_rollouts": R,
                         "collect": {"epsilon": exp.collect.epsilon, "n_runs": exp.collect.n_runs,
                                     "seed": exp.collect.seed},
                         "stores_from": None if stores_from is None else str(Path(stores_from).resolve()),
                         "collected_runs": {}, "statements": SUMMARY_STATEMENTS, "methods": {}}

        def stage(name, fn):
            log(f"[{name}] ...")
            t0 = time.perf_counter()
            r = fn()
            times[name] = round(time.perf_counter() - t0, 3)
            log(f"[{name}] done in {times[name]:.1f} s")
            return r

        data = {}
        with make_simulator(exp.simulator.to_dict(), exp.system) as one:  # one worker's rate, for the estimates
            rate = calibrate_rate(one, budget=0.3, work=exp.plan().n_pairs * float(exp.collect.n_runs)
                                  + float(au.get("points", 200)) * float(au.get("runs", 2000)))
        n_workers = wk or os.cpu_count() or 1
        # the audits' size is known now: an audit over the limits is refused before the collections
        acost = audit_cost(int(au.get("points", 200)), int(au.get("runs", 2000)), exp.system, rate, workers=n_workers)
        check_audit_cost(acost)
        for method, e, sub in (("stochastic", exp, "data"), ("deterministic", baseline_experiment(exp),
                                                              "data_deterministic")):
            plan = e.plan()
            est = printed_collection_estimate(plan, store_root / sub, ex, wk, address or exp.collect.address, rate, n_workers)
            estimates[f"collect/{method}"] = est.seconds
            log(f"[collect/{method}] " + est.summary().replace("\n", "; "))
            res = stage(f"collect/{method}", lambda: collect(plan, store_root / sub, executor=ex, workers=wk or None,
                                                             address=address or exp.collect.address,
                                                             on_progress=progress and progress(f"collect/{method}", "pairs")))
            if not res.complete:
                raise SimgapError(f"collection of {store_root / sub} did not finish (cancelled); run again to resume")
            summary["collected_runs"][method] = int(res.runs)  # new this call (a resumed store's earlier chunks not)
            data[method] = load_store(store_root / sub, system=e.system)

        # one simulator per data set for the stages that call it directly (Lhat_fhat, audit, rollouts),
        # each batch spread over the collection's cores (the same results as in one process)
        sims = {m: make_simulator(e.simulator.to_dict(), e.system, workers=wk or 0)
                for m, e in (("stochastic", exp), ("deterministic", baseline_experiment(exp)))}
        sim = sims["stochastic"]  # audits and rollouts run against the stochastic simulator
        controllers = {}
        invariant = checked["method"] in set_synthesis.SET_METHODS  # a proved set (ellipsoid or box tube)
        tube = checked["method"] == "box_tube"

        def roll_out(method, sres, entry):
            """R rollouts from x0 (and, for an invariant set, from states drawn in E) into ``entry``."""
            if sres.empty or not bool(sres.controller.winning(x0[None, :])[0]):
                st = statement_of(checked["method"], None if sres.empty else sres.controller, sres.stats)
                why = (sres.stats.get("diagnosis") or f"{st.name}: nothing proved") if sres.empty else \
                    f"x0 is outside {st.set_name}"
                entry["rollouts"] = {"skipped": why}
                log(f"[rollout/{method}] skipped: {why}")
            else:
                bar = progress and progress(f"rollout/{method}", "steps")
                rr = stage(f"rollout/{method}", lambda: rollout(sres.controller, sim, x0, n_rollouts=R,
                                                                horizon=ro.get("horizon"), seed=int(ro.get("seed", 11)),
                                                                on_exit=ro.get("on_exit", "hold"),
                                                                on_estimate=lambda t: log(f"[rollout/{method}] {t}"),
                                                                on_progress=bar))
                _close(bar)
                estimates[f"rollout/{method}"] = rr.timing.get("estimate_s")
                rr.save_npz(out / f"rollouts_{method}.npz")
                wrote(f"rollouts_{method}.npz")
                entry["rollouts"] = rr.to_dict(per_rollout=False)
                entry["failures"] = int(rr.n_failures)
                entry["n_rollouts"] = int(rr.n_rollouts)
                entry["mean_map_satisfies"] = None if rr.mean_map is None else rr.mean_map["satisfied"]
                entry["rollout_average_satisfies"] = rr.rollout_average_verdict["satisfied"]
                entry["per_run_empirical"] = per_run_empirical(rr, sres.controller)
                if arena is not None:
                    entry["closest_approach"] = closest_approach(arena, rr)
                if tube:  # reach and stay: in the terminal box at every period from T0 on
                    c = sres.controller
                    stay = c.reached_and_stayed(rr.trajectories)
                    mm = rr.mean_map_trajectory
                    entry["reach_and_stay"] = {"T0": c.T0, "held": int(stay.sum()), "of": int(stay.size),
                                               "runs_in_tube": int(c.inside(rr.trajectories).sum()),
                                               "mean_map_in_tube": None if mm is None else
                                               bool(c.inside(np.asarray(mm)[None])[0])}
            k = int(syn.get("set_states", 20))
            if invariant and not tube and not sres.empty and k:  # a tube is proved from x0 only
                entry["rollouts_in_set"] = stage(f"rollout-in-E/{method}", lambda: set_synthesis.rollouts_in_set(
                    rollout, sres.controller, sim, k, R, ro.get("horizon"), int(ro.get("seed", 11)) + 1000,
                    ro.get("on_exit", "hold"), log))
        def certify_prove(method, ds, opts, tag=""):
            """Certify ``ds`` and synthesize with the certificate: (cert, sres)."""
            cost = lhat_cost(ds, opts, sims[method])  # the simulator's Lipschitz runs, if any: priced first
            if cost is not None:
                estimates[f"certify/{method}{tag}"] = cost["seconds"]
                log(f"[certify/{method}{tag}] {crn_cost_text(cost)}")
            bar = progress and cost is not None and progress(f"certify/{method}: Lipschitz (simulator)", "runs")
            cert = stage(f"certify/{method}{tag}", lambda: certify(ds, opts, simulator=sims[method],
                                                                   on_progress=bar or None))
            _close(bar)
            if invariant:
                sres = stage(f"synthesize/{method}{tag}", lambda: set_synthesis.synthesize(
                    exp.system, spec, cert, syn, x0=x0, horizon=ro.get("horizon"),
                    log=lambda t: log(f"[synthesize/{method}{tag}] {t}")))
            else:
                bar = progress and progress(f"synthesize/{method}: abstraction", "classes")
                sres = stage(f"synthesize/{method}{tag}", lambda: synthesize(exp.system, spec, syn["eta"], gap=cert,
                                                                             hold=hold, x0=x0, log=log,
                                                                             on_progress=bar))
                _close(bar)
            return cert, sres

        def in_rounds(opts):
            """The stochastic certificate and proof in anytime-valid rounds (simgap.rounds): round 1 on the
            collected data, round k >= 2 on a fresh store data_round<k> with N1hat doubled each round."""
            from .rounds import Attempt, run_rounds
            got = {}

            def attempt(k, n_k):
                runs, secs = 0, 0.0
                sub = "data"
                if k == 1:
                    ds = data["stochastic"]
                else:
                    e = dataclasses.replace(exp, collect=dataclasses.replace(exp.collect, n_runs=n_k,
                                                                             seed=exp.collect.seed + k - 1))
                    plan, sub = e.plan(), f"data_round{k}"
                    check_fillable(store_root / sub, plan.config())
                    check_collection(plan.n_pairs, plan.n_runs, exp.system.n, exp.system.m, exp.system.steps,
                                     plan.batch_runs, n_workers, plan.keep_samples, store_root / sub)
                    est = printed_collection_estimate(plan, store_root / sub, ex, wk, address or exp.collect.address,
                                                      rate, n_workers)
                    log(f"[collect/round {k}] " + est.summary().replace("\n", "; "))
                    res = stage(f"collect/round {k}", lambda: collect(
                        plan, store_root / sub, executor=ex, workers=wk or None, address=address or exp.collect.address,
                        on_progress=progress and progress(f"collect/round {k}", "pairs")))
                    if not res.complete:
                        raise SimgapError(f"collection of {store_root / sub} did not finish (cancelled); run again "
                                          "to resume")
                    runs, secs = int(res.runs), float(res.seconds)
                    summary["collected_runs"][f"stochastic round {k}"] = runs
                    ds = load_store(store_root / sub, system=exp.system)
                cert, sres = certify_prove("stochastic", ds, dataclasses.replace(opts, round=k),
                                           "" if k == 1 else f" round {k}")
                got.update(cert=cert, sres=sres, ds=ds, sub=sub)
                scale = sres.stats.get("gap_scale") if invariant else None
                if invariant and sres.stats.get("gap_scale_text", "").startswith("any"):
                    scale = float("inf")
                return Attempt(proved=not sres.empty, scale=scale, cert=cert, runs=runs, seconds=secs)

            rr = run_rounds(exp.collect.n_runs, exp.plan().n_pairs, budget, attempt, log)
            log(f"[rounds] {rr.stopped}")
            summary["rounds"] = rr.to_dict()
            return got["cert"], got["sres"], got["ds"], got["sub"]

        for method in METHODS:
            ds = data[method]
            opts = certify_options(cert_section, method, exp.system)
            data_dir = {"stochastic": "data", "deterministic": "data_deterministic"}[method]
            if method == "stochastic" and budget.active:
                cert, sres, ds, data_dir = in_rounds(opts)
            else:
                cert, sres = certify_prove(method, ds, opts)
            cert.save(out / f"cert_{method}.json")
            wrote(f"cert_{method}.json")
            # the audit's own simulator timed at its batch size, at the start of each audit (a shared
            # machine's load changes within a minute: one rate for both audits was off by 3x)
            acost = audit_cost(int(au.get("points", 200)), int(au.get("runs", 2000)), exp.system,
                               audit_rate(sim, int(au.get("points", 200)), int(au.get("runs", 2000))), workers=1)
            estimates[f"audit/{method}"] = acost["seconds"]
            log(f"[audit/{method}] {audit_cost_text(acost)}")
            bar = progress and progress(f"audit/{method}", "runs")
            rep = stage(f"audit/{method}", lambda: audit(cert, sim, points=int(au.get("points", 200)),
                                                         runs=int(au.get("runs", 2000)), seed=int(au.get("seed", 7)),
                                                         dataset=data["stochastic"], on_progress=bar))
            _close(bar)
            fileio.write_json(out / f"audit_{method}.json", rep)
            wrote(f"audit_{method}.json")
            if not (invariant and sres.empty):  # no set proved: nothing written (the summary says why)
                sres.controller.save(out / f"controller_{method}.npz")
                wrote(f"controller_{method}.npz")
            if not sres.empty:
                controllers[method] = sres.controller
            entry = {
                "gamma": _gamma_stats(cert, data["stochastic"]),
                "confidence_per_dim": cert.per_dim_confidence, "confidence_joint": cert.joint_confidence,
                "confidence_scope": cert.scope, "confidence_joint_pointwise": cert.scope_confidences()["pointwise"],
                "confidence_joint_simultaneous": cert.scope_confidences()["simultaneous"],
                # what the synthesis's proof (gamma's sup over its cells / set) rests on: the all-rows
                # reading; None = deterministic baseline or vacuous (never the pointwise number)
                "confidence_proof": cert.sup_confidence(),
                # the all-rows reading over every round's certificate (the all-rows reading itself without rounds)
                "confidence_all_rounds": cert.all_rounds_confidence(),
                "region": None if cert.region is None else [np.asarray(b).tolist() for b in cert.region],
                "audit_pass_rate_per_dim": {k: v["fraction_holds"] for k, v in rep["per_dim"].items()},
                "audit_pass_rate_joint": rep["joint"]["fraction_holds"],
                "audit_violated_joint": rep["joint"]["fraction_violated"],
                "winning_cells": int(not sres.empty) if invariant else int(sres.stats["winning"]),
                "synthesis": sres.stats,
                "dataset_hash": ds.hash, "data_dir": data_dir, "warnings": list(cert.options.get("warnings") or []),
                # the gap's Lipschitz entries whose estimate is mostly noise, worst first (one warning names
                # their count and the worst; this lists them all)
                "noisy_gap_entries": list(cert.options.get("noisy_gap_entries") or []),
            }
            summary["methods"][method] = entry
            roll_out(method, sres, entry)
            entry["statement"] = statement_of(checked["method"], sres.controller, sres.stats, entry).to_json()
        if invariant and syn.get("nominal", True):
            # the nominal model without any gap: what the set and the rollouts look like when the proof
            # ignores the simulation gap (no guarantee about the simulator)
            sres = stage("synthesize/nominal", lambda: set_synthesis.synthesize(
                exp.system, spec, None, syn, x0=x0, log=lambda t: log(f"[synthesize/nominal] {t}")))
            if not sres.empty:
                sres.controller.save(out / "controller_nominal.npz")
                wrote("controller_nominal.npz")
            entry = {"gap": "none (nominal model; no statement about the simulator)", "synthesis": sres.stats,
                     "winning_cells": int(not sres.empty)}
            summary["methods"]["nominal"] = entry
            roll_out("nominal", sres, entry)
            entry["statement"] = statement_of(checked["method"], sres.controller, sres.stats, entry).to_json()
        if per_run:
            from .perrun.stage import run_stage
            summary["per_run"] = stage("perrun", lambda: run_stage(exp, out, data["stochastic"], controllers, spec, x0,
                                                                   per_run, sim=sim, log=log, progress=progress,
                                                                   executor=perrun_ex, wrote=wrote))
        for each in sims.values():
            each.close()
        summary["seconds"] = times
        summary["estimated_seconds"] = estimates
        summary["wall_seconds"] = round(time.perf_counter() - t_start, 3)  # everything, between the stages too
        summary["files"] = results_folder.list_files(out, run_id)
        results_folder.seal(summary)
        fileio.write_json(out / "summary.json", summary, default=_json_default)
        return summary


def _close(bar) -> None:
    """Close a stage's progress bar (a callback without ``close`` is the caller's to end)."""
    if bar and hasattr(bar, "close"):
        bar.close()


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serializable: {type(o).__name__}")


def _simultaneous(c) -> str:
    """The simultaneous confidence; <= 0 means the certificate states nothing for all rows at once
    ("vacuous": a union bound above 1 is no statement, never printed as a negative probability)."""
    return "-" if c is None else (f"{c:.4g}" if c > 0 else "vacuous")


#: the table's groups: which statement the numbers under each header are (the proof is about the
#: mean map; the rollouts are single runs, counted; only a p_cert row states something about them)
TABLE_GROUPS = {
    "certificate": "certificate (gamma bounds the MEAN next state's gap, not single runs)",
    "proof": "proof (about the MEAN MAP m+ = E fhat(m, u(m)), not single runs)",
    "proof_nominal": "proof (about the MEAN MAP m+ = E fhat(m, u(m)); nominal: about f only)",
    "mean_map": "the mean map run in the simulator (the sequence a gap's proof is about)",
    "runs": "SINGLE RUNS in the simulator (counted; only p_cert, where stated, is a proof about them)",
}


#: summary.json's "statements": which statement each number of a method's entry is
SUMMARY_STATEMENTS = {
    "gamma, confidence_*, audit_*": "the certificate: gamma bounds the gap of the MEAN next state |E fhat - f| "
                                    "(audited at fresh points), not the gap of single runs",
    "winning_cells": "proved on the model: from each winning cell (an invariant-set run: 1 when the set E is "
                     "proved) the MEAN MAP m+ = E fhat(m, u(m)) satisfies the spec; for the nominal model a "
                     "statement about f alone, none about the simulator",
    "mean_map_satisfies": "the mean map run in the simulator from x0 (the sequence a gap's proof is about) "
                          "satisfies the spec: checked, one sequence",
    "failures, n_rollouts, per_run_empirical, rollouts_in_set": "SINGLE RUNS in the simulator: counted, not "
                                                                "proved; only per_run_empirical.p_cert, where "
                                                                "stated (a box tube's noise tube), bounds them",
    "rollout_average_satisfies": "the average of the single runs satisfies the spec; not the mean map",
}


def _clip(text: str, width: int = 56) -> str:
    """A table cell of at most ``width`` characters (the whole text is in summary.json)."""
    return text if len(text) <= width else text[:width - 3] + "..."


def _entry_statement(e: dict, method: Optional[str]) -> dict:
    """A method entry's statement (summary.json's ``statement``); for a summary written before
    statements existed, the proof's count alone in the method's name (never another method's words)."""
    if e.get("statement"):
        return e["statement"]
    m, count = method or "grid", e.get("winning_cells", 0)
    row = {"label": "winning cells", "value": f"{count:,}"} if m == "grid" else \
        {"label": "proved", "value": "yes" if count else "no"}
    return {"name": METHOD_NAMES.get(m, m), "proved": bool(count), "notes": [],
            "rows": [{**row, "about": "proof", "confidence": None}]}


def _rests_on(e: dict) -> str:
    """What a set method's proof rests on: f alone, a deterministic gap (no probability), or the
    certificate's all-rows confidence (the proof takes gamma's sup over a set)."""
    if isinstance(e.get("gap"), str):
        return "f only (no gap)"
    c = e.get("confidence_proof")
    return "a gap without noise (no probability)" if c is None else f"all-rows confidence {_simultaneous(c)}"


def _warning_consequence(w: str, st: Optional[dict]) -> str:
    """What a noisy L_gap warning does to gamma and whether the certificate and the proof stand."""
    if "L_gap entries are mostly" not in w:
        return ""
    proved = "" if st is None else (f"; the {st['name']} proof above used this gamma and "
                                    f"{'holds' if st['proved'] else 'failed'}")
    return (" -- what it does: noise inflates the largest slopes, so those L_gap entries, and gamma with "
            "them, come out larger (more conservative), and gamma takes the smaller of two valid bounds per "
            f"dimension: the certificate stands at its stated confidence{proved}")


def _audit_notes(summary: dict, cols) -> list:
    """A note for each audit whose points were all inconclusive: no violation, but nothing confirmed."""
    out = []
    for m in cols:
        e = summary["methods"][m]
        h, v = e.get("audit_pass_rate_joint"), e.get("audit_violated_joint")
        if h is not None and v is not None and h == 0 and v == 0:
            out += ["", f"audit ({m}): no violation, but every audited point was inconclusive (pass rate "
                        "0.000): the runs' mean could not be told apart from gamma at any point (its noise larger "
                        "than the margin); the audit did not fail, and it is no evidence for gamma either"]
    return out


def comparison_table(summary: dict) -> str:
    """The readable comparison table of a summary (deterministic vs stochastic; with an invariant-set
    synthesis also the nominal model without a gap), in groups headed by :data:`TABLE_GROUPS`: what
    the certificate bounds, what the synthesis proved (about the mean map), the mean map run in the
    simulator, and the single runs (counted, not proved), so that a set "proved" and "1000 / 1000"
    single runs failing read as the two different statements they are."""
    names = summary["system"]["state_names"]
    cols = [m for m in METHODS + ("nominal",) if m in summary["methods"]]
    rows = [("",) + tuple(cols)]
    method = (summary.get("sections", {}).get("synthesis") or {}).get("method")
    invariant = method in set_synthesis.SET_METHODS

    def fmt(v, f="{:.4g}"):
        return "-" if v is None else f.format(v)

    def both(fn):
        return [fn(summary["methods"][m]) for m in cols]

    def group(key):  # a header line across the table (a str row, not a cell row)
        rows.append(TABLE_GROUPS[key])

    def row(label, *cells):
        rows.append(("  " + label, *cells))

    group("certificate")
    gap_term = any(summary["methods"][m]["gamma"].get("lipschitz_term") == "gap" for m in METHODS)
    for i, nm in enumerate(names):
        row(f"gamma max [{nm}]" + (" (gap's term)" if gap_term else ""),
            *both(lambda e: fmt(e["gamma"]["max"][i]) if isinstance(e.get("gamma"), dict) else "-"))
    if gap_term:  # the same certificates with the paper's Lipschitz term, side by side
        for i, nm in enumerate(names):
            row(f"gamma max [{nm}] (paper's term)",
                *both(lambda e: fmt(e["gamma"].get("max_paper_term", [None] * len(names))[i])
                      if isinstance(e.get("gamma"), dict) else "-"))
    for i, nm in enumerate(names):
        row(f"confidence [{nm}]", *both(lambda e: fmt((e.get("confidence_per_dim") or [None] * len(names))[i])))
    row("joint conf. pointwise (one row)", *both(lambda e: _simultaneous(e.get("confidence_joint_pointwise"))))
    row("joint conf. all rows (a set's proof)", *both(lambda e: _simultaneous(e.get("confidence_joint_simultaneous"))))
    row("proof confidence (sup over the set)", *both(lambda e: "-" if e.get("confidence_joint") is None else
                                                     _simultaneous(e.get("confidence_all_rounds",
                                                                         e.get("confidence_joint_simultaneous")))))
    row("audit pass rate (joint)", *both(lambda e: fmt(e.get("audit_pass_rate_joint"), "{:.3f}")))
    row("audit violated (joint)", *both(lambda e: fmt(e.get("audit_violated_joint"), "{:.3f}")))
    group("proof_nominal" if "nominal" in cols else "proof")
    stmts = {m: _entry_statement(summary["methods"][m], method) for m in cols}
    names_row = {m: st["name"] for m, st in stmts.items()}
    if len(set(names_row.values())) > 1 or invariant:
        row("method (its own words)", *[names_row[m] for m in cols])

    def statement_rows(about):  # every label any column states, in order, its value per column
        labels = list(dict.fromkeys(r["label"] for m in cols for r in stmts[m]["rows"] if r["about"] == about))
        for label in labels:
            row(label, *[next((r["value"] for r in stmts[m]["rows"] if r["label"] == label), "-") for m in cols])
    statement_rows("proof")
    if invariant:
        row("proof rests on", *both(_rests_on))
    has_ca = any("closest_approach" in summary["methods"][m] for m in cols)
    group("mean_map")
    row("mean map satisfies the spec", *both(lambda e: str(e.get("mean_map_satisfies", "-"))))
    statement_rows("mean_map")
    if has_ca:
        row("closest approach, mean map [m]", *both(lambda e: fmt(e.get("closest_approach", {}).get("mean_map"),
                                                                 "{:.3f}")))
    group("runs")
    row("single runs failing" + (" from x0" if invariant else ""),
        *both(lambda e: f"{e['failures']} / {e['n_rollouts']}" if "failures" in e else
              ("nothing proved (reason below)" if invariant and not e["winning_cells"] else
               e["rollouts"].get("skipped", "-")[:40])))
    if any("per_run_empirical" in summary["methods"][m] for m in cols):
        def pe(e):
            r = e.get("per_run_empirical")
            return "-" if r is None else f"{r['p_emp']:.4f} +- {r['se']:.4f}"
        row("p_emp(x0) per run +- SE", *both(pe))
        row("p_cert(x0) per run", *both(lambda e: "-" if e.get("per_run_empirical") is None else
                                        ("none stated" if e["per_run_empirical"]["p_cert"] is None
                                         else f"{e['per_run_empirical']['p_cert']:.4f}")))
    statement_rows("single_runs")
    row("rollout average satisfies", *both(lambda e: str(e.get("rollout_average_satisfies", "-"))))
    if has_ca:
        def ca(key):
            return lambda e: fmt(e.get("closest_approach", {}).get(key), "{:.3f}")
        row("closest approach min [m]", *both(ca("min")))
        row("closest approach 5 % quantile [m]", *both(ca("q05")))
    nc = len(rows[0])
    rows = [r if isinstance(r, str) else tuple(_clip(str(c)) for c in r) for r in rows]
    cells = [r for r in rows if not isinstance(r, str)]
    w = [max(len(str(r[c])) for r in cells) for c in range(nc)]
    lines = [r if isinstance(r, str) else
             "  ".join(str(r[c]).ljust(w[c]) if c == 0 else str(r[c]).rjust(w[c]) for c in range(nc)) for r in rows]
    lines.insert(1, "-" * len(lines[0]))
    warnings = [(m, w) for m in METHODS for w in summary["methods"][m].get("warnings", [])]
    for m in cols:
        d = (summary["methods"][m].get("synthesis") or {}).get("diagnosis") if invariant else None
        notes = ([d] if d else []) + [x for x in stmts[m]["notes"] if x != d]
        lines += ["", *(f"{m}: {x}" for x in notes)] if notes else []
        lv = (summary["methods"][m].get("synthesis") or {}).get("levers_text") if invariant else None
        if lv:  # what each way out would need (simgap.synthesis.tube_design.levers)
            lines += [f"{m}: what gamma would have to lose per state, and what each lever needs:"]
            lines += ["  " + x for x in lv]
    lines += _audit_notes(summary, cols)
    if warnings:
        lines.append("")
        lines += [f"warning ({m} certificate): {w}" + _warning_consequence(w, stmts.get(m)) for m, w in warnings]
    vac = [m for m in METHODS if m in summary["methods"] and (summary["methods"][m].get("confidence_joint_simultaneous")
                                                              or 1.0) <= 0]
    if vac:
        lines += ["", f"vacuous ({', '.join(vac)}): the all-rows reading, a union bound over the K cover rows, sums "
                  "the failure probabilities to more than 1, so it states nothing; the synthesis takes gamma's sup over "
                  "many rows at once and needs it. Certify with uniform = true ([certify], --uniform), or collect "
                  "over a [collect] region (a local certificate is uniform by default)."]
    regions = {m: summary["methods"][m].get("region") for m in METHODS if summary["methods"].get(m, {}).get("region")}
    if regions:
        names = summary["system"]["state_names"]
        r = next(iter(regions.values()))
        lines += ["", "local certificate: gamma holds on the region " + " x ".join(
            f"{nm} [{a:g}, {b:g}]" for nm, a, b in zip(names, r[0], r[1])) + " only"]
    rr = summary.get("rounds")
    if rr:  # the stochastic certificate came from anytime-valid rounds (simgap.rounds)
        lines += ["", "stochastic data in anytime-valid rounds (betas / 2^k; the proof states every round's "
                  "certificate at once): " + "; ".join(
                      f"round {r['round']} N1hat {r['n_runs']:,} " + ("proved" if r["proved"] else "not proved")
                      + ("" if r["gap_scale"] is None else f" (tolerable {r['gap_scale']:.3g} x gamma)")
                      for r in rr["rounds"]) + f"; {rr['stopped']}"]
    secs = summary.get("seconds", {})
    if secs:
        lines.append("")
        lines.append("wall time per stage: " + ", ".join(f"{k} {v:.1f} s" for k, v in secs.items()))
    if summary.get("wall_seconds") is not None:
        lines.append(f"wall time of the whole run: {summary['wall_seconds']:.1f} s (checks, estimates and files "
                     "included; the recording comes after)")
    return "\n".join(lines)

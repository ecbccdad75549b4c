"""The per-run stage of ``simgap run``: certify, synthesize and validate guarantees about single runs.

Runs when the experiment has a ``[perrun]`` section. From the stochastic data set and the
experiment's simulator it

1. certifies the realization gap gamma^alpha (``cert_run.json``);
2. synthesizes the union-bound baseline: the robust controller on gamma^alpha, whose one-run
   success probability is at least 1 - H n alpha (H sampling periods, n state dimensions: each
   period's deviation is inside gamma^alpha with probability >= 1 - n alpha) in its winning domain;
3. builds the interval MDP from fresh simulator samples and synthesizes the per-run controller
   with p_cert per cell (``controller_perrun.npz``);
4. validates every controller (the case study's deterministic- and stochastic-gap controllers,
   the baseline, the per-run controller): R batched rollouts from x0 and from ``n_states``
   initial states drawn in its own winning domain, p_emp with a Clopper-Pearson interval next to
   p_cert (None where a method states no per-run probability).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, Dict, Optional

import numpy as np

from ..errors import SimgapError
from .orderstats import alpha_min

SAMPLES = "perrun_samples"   # the interval MDP's chunk stores in a results folder (resumable)
KEYS = {"alpha", "beta", "eta", "hold", "n_runs", "pilot_runs", "horizon", "n_rollouts", "n_states", "seed",
        "baseline_eta", "baseline_hold", "split", "invariant", "share", "check_states"}


def check_eta(eta, system, what: str = "eta") -> None:
    """Refuse cell widths that are not one positive number or one per state dimension (before any
    size is projected from them: a wrong length must not reach the grid arithmetic)."""
    try:
        a = np.asarray(eta, dtype=float)
    except (TypeError, ValueError):
        raise SimgapError(f"{what}: expected numbers (cell widths), got {eta!r}") from None
    if a.ndim > 1 or (a.ndim == 1 and a.size not in (1, system.n)):
        raise SimgapError(f"{what}: need one cell width or {system.n} (one per state "
                          f"{', '.join(system.state_names)}), got {a.size}: {eta!r}")
    if not np.all(np.isfinite(a)) or np.any(a <= 0):
        raise SimgapError(f"{what}: cell widths must be finite and > 0, got {eta!r}")


def check_section(sec: dict, system, n_pairs: int, n_runs: int, horizon) -> dict:
    """Validate ``[perrun]`` before any work (so bad input writes nothing); returns it with defaults."""
    bad = set(sec) - KEYS
    if bad:
        raise SimgapError(f"experiment section [perrun]: unknown keys {sorted(bad)}; allowed: {sorted(KEYS)}")
    o = {"alpha": 0.05, "beta": 0.01, "hold": 20, "n_runs": 2000, "pilot_runs": 200, "n_rollouts": 10000,
         "n_states": 20, "seed": 0, "check_states": 64, **sec}
    a = o["alpha"]
    if not (isinstance(a, (int, float)) and 0.0 < float(a) < 1.0):
        raise SimgapError(f"[perrun] alpha must be in (0, 1), got {a!r}")
    b = o["beta"]
    if not (isinstance(b, (int, float)) and 0.0 < float(b) < 1.0):
        raise SimgapError(f"[perrun] beta must be in (0, 1), got {b!r}")
    a_min = alpha_min(int(n_runs), float(b) / (n_pairs * system.n))
    if float(a) < a_min:
        raise SimgapError(f"[perrun] alpha = {a:g} is below what N1hat = {n_runs} runs per pair support: the smallest "
                          f"supported alpha is {a_min:.4g} (beta = {b:g}, union over {n_pairs} pairs x {system.n} dims)")
    o["horizon"] = int(o.get("horizon", horizon or 0))
    if o["horizon"] < 1:
        raise SimgapError(f"[perrun] horizon must be >= 1 sampling period, got {o['horizon']}")
    if "eta" not in o:
        raise SimgapError("[perrun] eta (interval-MDP cell widths) is required")
    check_eta(o["eta"], system, "[perrun] eta")
    inv = o.get("invariant") or []
    if not isinstance(inv, list) or any(v not in system.state_names or system.state_names.index(v) in system.angle_dims
                                        for v in inv):
        raise SimgapError(f"[perrun] invariant must list non-angle state names of {system.name!r} "
                          f"({list(system.state_names)}), got {inv!r}")
    for k in ("hold", "n_runs", "pilot_runs", "n_rollouts", "n_states"):
        if int(o[k]) < 1:
            raise SimgapError(f"[perrun] {k} must be >= 1, got {o[k]}")
    c = o["check_states"]
    if isinstance(c, bool) or not isinstance(c, int) or c < 0:
        raise SimgapError(f"[perrun] check_states (fresh states per interval-MDP row for the containment check; "
                          f"0 = no check) must be a whole number >= 0, got {c!r}")
    from .imdp import Allocation, IMDPOptions
    o["split"] = o.get("split", IMDPOptions.split)
    try:
        Allocation.of(o["split"])
        if o.get("share") is not None:
            if inv:
                raise SimgapError("share and invariant exclude each other: with invariant the runs of one cell "
                                  "per class already serve every cell of the class")
            IMDPOptions(eta=o["eta"], share=o["share"]).validate(system.n)
    except SimgapError as e:
        raise SimgapError(f"[perrun] {e}") from None
    return o


def build(sim, spec, o: dict, log, on_progress=None, executor=None, workers=None, address=None, store=None,
          replace_other=False):
    """The interval MDP of checked ``[perrun]`` options ``o``: sampled per cell (or shared), its simulator
    work in chunks on ``executor`` (a local pool, Ray at ``address``; None: this process with ``sim``),
    kept in and resumed from the folder ``store`` (:mod:`simgap.perrun.sampling`); or with ``invariant``
    (state names) once per class of cells and shifted (:mod:`simgap.perrun.translation`, in this
    process: classes x inputs runs, no chunks); then the
    containment check (``check_states`` fresh states per row, :mod:`simgap.perrun.containment`),
    recorded in the meta as ``containment`` (``passed`` None when not run) and logged, with a
    warning when it fails."""
    from .containment import check_containment
    from .imdp import IMDPOptions
    from .sampling import build_imdp
    from .translation import build_imdp_translation

    opts = IMDPOptions(eta=o["eta"], hold=int(o["hold"]), n_runs=int(o["n_runs"]), pilot_runs=int(o["pilot_runs"]),
                       beta=float(o["beta"]), seed=int(o["seed"]), split=o["split"], share=o.get("share"))
    if o.get("invariant"):
        names = list(sim.system.state_names)
        imdp = build_imdp_translation(sim, spec, opts, [names.index(v) for v in o["invariant"]], log=log,
                                      on_progress=on_progress)
    else:
        imdp = build_imdp(sim, spec, opts, log=log, on_progress=on_progress, executor=executor, workers=workers,
                          address=address, store=store, replace_other=replace_other)
    imdp.meta["randomization"] = randomization_note(sim)
    n_check = int(o.get("check_states", 64))
    if n_check > 0:
        rep = check_containment(sim, spec, imdp, n_check, seed=int(o["seed"]))
        imdp.meta["containment"] = rep.to_dict()
        log(rep.summary())
    else:
        imdp.meta["containment"] = {"passed": None, "what": "not run ([perrun] check_states = 0)"}
        log("containment check not run ([perrun] check_states = 0)")
    return imdp


def synthesize_experiment(exp, horizon=None, x0=None, eta=None, hold=None, log=print, on_progress=None,
                          executor="local", workers=None, address=None, store=None):
    """Interval-MDP controller of an experiment (``[perrun]`` options, overridable); returns (controller, summary text).

    The sampling runs on ``executor`` (default a local pool of ``workers`` processes; ``ray`` at
    ``address``), kept in and resumed from the folder ``store`` if given. Bad input (no [perrun]
    section, horizon < 1, x0 outside X) and work the machine cannot hold (the projected cost is
    logged first) raise before any sampling."""
    from ..experiment_spec import experiment_spec
    from ..simulators import make_simulator
    from .value_iteration import check_horizon, synthesize_imdp

    sec = exp.section("perrun")
    if not sec:
        raise SimgapError(f"experiment {exp.name!r} (profile {exp.profile}) has no [perrun] section")
    sec.update({k: v for k, v in (("horizon", horizon), ("eta", eta), ("hold", hold)) if v is not None})
    plan = exp.plan()
    o = check_section(sec, exp.system, plan.n_pairs, exp.collect.n_runs, exp.section("rollout").get("horizon"))
    from ..executors import make_executor
    ex = make_executor(executor or "local", workers, address)
    project_cost(o, exp, ex, log, rollouts=False)
    spec, map_x0, _ = experiment_spec(exp)
    x0 = np.asarray(x0 if x0 is not None else exp.section("rollout").get("x0", map_x0), dtype=float) \
        if (x0 is not None or exp.section("rollout").get("x0") is not None or map_x0 is not None) else None
    if x0 is not None:
        exp.system.check_states(np.atleast_2d(x0), "x0")
    check_horizon(spec.kind, int(o["horizon"]), int(o["hold"]))
    with make_simulator(exp.simulator.to_dict(), system=exp.system) as sim:
        imdp = build(sim, spec, o, log, on_progress, executor=ex, store=store)
    ctl = synthesize_imdp(imdp, int(o["horizon"]), spec.kind)
    lines = [f"p_cert is {imdp.meta['p_cert_conditional_on']}", containment_line(imdp.meta["containment"]),
             f"interval MDP: {imdp.C} cells ({int(imdp.live.sum())} live) x {imdp.M} inputs, hold {imdp.hold}, "
             f"{imdp.nnz} interval entries ({imdp.nbytes() / 2**20:.1f} MiB), {imdp.meta['bounds']} one-sided "
             f"Clopper-Pearson bounds, levels " + ", ".join(f"{f} {v:.3g}" for f, v in imdp.meta["levels"].items())
             + f" (total beta {o['beta']:g})",
             f"horizon {o['horizon']} periods = {ctl.steps} abstract steps of {imdp.hold} "
             f"({ctl.meta['horizon_rule']}); cells with p_cert > 0: "
             f"{int((ctl.p_cert > 0).sum())}; max p_cert {ctl.p_cert.max():.4f}"]
    if x0 is not None:
        lines.append(f"p_cert(x0 = {np.round(x0, 6).tolist()}) = {float(ctl.certified(np.atleast_2d(x0))[0]):.4f}")
    return ctl, "\n".join(lines)


def project_cost(o: dict, exp, ex, log, rollouts: bool = True) -> dict:
    """Log the per-run stage's projected cost (simulator steps, CPU-hours at the rates calibrated here,
    interval entries, memory) for executor ``ex`` and refuse what this machine cannot hold, with the
    numbers (:func:`simgap.perrun.cost.check_perrun`). The memory is checked first, from the sizes alone;
    then the simulator's rate and the sampling's own rate and support per row (bookkeeping included,
    :func:`simgap.perrun.sampling.calibrate_sampling`) are measured and the check repeated with them. With Ray at an address the
    projection counts ``ex.workers`` CPUs (``--workers``: default this machine's cores). ``rollouts``:
    the validation's rollouts are part of the work (``simgap run``; not ``simgap synthesize``)."""
    from . import cost
    from ..experiment_spec import experiment_spec
    from ..simulators import make_simulator
    # on a Ray cluster the workers are its CPUs (give --workers to project them); they hold no memory here
    local = 1 if ex.name == "serial" or (ex.name == "ray" and ex.address) else ex.workers
    nc = 3 if rollouts else 0
    cost.check_perrun(o, exp.system, None, ex.workers, local_workers=local, n_controllers=nc)  # memory first
    rate = cost.calibrated_rate(exp.simulator, exp.system)
    cal = None
    if not o.get("invariant"):
        from .imdp import IMDPOptions
        from .sampling import calibrate_sampling
        opts = IMDPOptions(eta=o["eta"], hold=int(o["hold"]), n_runs=int(o["n_runs"]), pilot_runs=int(o["pilot_runs"]),
                           seed=int(o["seed"]), split=o["split"], share=o.get("share"))
        with make_simulator(exp.simulator.to_dict(), system=exp.system) as sim:
            cal = calibrate_sampling(sim, experiment_spec(exp)[0], opts)
    kw = dict(local_workers=local, n_controllers=nc, sampling_rate=cal and cal["rate"],
              entries_per_row=cal and cal["entries_per_row"])
    e = cost.perrun_size(o, exp.system, rate, ex.workers, **kw)
    log(cost.perrun_cost_text(e, rate, ex.workers))
    return cost.check_perrun(o, exp.system, rate, ex.workers, **kw)


def validate_controller(name: str, input_fn, hold: int, sim, spec, x0, domain_states, p_cert_fn, o: dict,
                        on_progress=None) -> dict:
    """Rollouts from x0 and the sampled domain states: per state x0, p_cert, p_emp, ci95, se, n_rollouts, horizon."""
    from .validation import empirical, success_counts

    xs = np.concatenate([np.atleast_2d(x0), domain_states]) if len(domain_states) else np.atleast_2d(x0)
    R, H = int(o["n_rollouts"]), int(o["horizon"])
    t0 = time.perf_counter()
    k = success_counts(input_fn, hold, sim, spec, xs, R, H, seed=int(o["seed"]) + 17, on_progress=on_progress)
    e = empirical(k, R)
    pc = p_cert_fn(xs)
    states = [{"x0": xs[i].tolist(), "p_cert": None if pc is None else float(pc[i]), "p_emp": e["p_emp"][i],
               "ci95": e["ci95"][i], "se": e["se"][i], "n_rollouts": R, "horizon": H} for i in range(len(xs))]
    return {"controller": name, "states": states, "seconds": round(time.perf_counter() - t0, 3)}


def run_stage(exp, out: Path, data, controllers: Dict[str, object], spec, x0, o: dict, sim=None,
              log: Callable[[str], None] = print, progress: Optional[Callable] = None, executor=None,
              workers: Optional[int] = None, address: Optional[str] = None, wrote=None) -> dict:
    """Run the per-run stage (module docstring); ``controllers`` are the case study's {method: Controller}.

    The interval MDP's sampling runs on ``executor`` (a name or an Executor; None: in this process with
    ``sim``) and is kept in ``out/perrun_samples`` (resumed by a second run, replaced when the ``[perrun]``
    options changed; :mod:`simgap.perrun.sampling`).

    ``sim``: the experiment's stochastic simulator (default: built from the experiment).
    ``progress(name, unit)``, if given, returns an ``on_progress(done, total)`` callback for the
    interval-MDP sampling ("pairs") and for each controller's rollouts ("periods").
    ``wrote(name)``, if given, is called after each result file is written into ``out`` (the results
    folder's journal, :func:`simgap.results_folder.record`)."""
    import contextlib

    from ..simulators import make_simulator
    from ..synthesis.controller import synthesize
    from ..rollout import resolve_hold
    from .realization import certify_run
    from .validation import sample_in_cells
    from .value_iteration import synthesize_imdp

    bar = progress or (lambda name, unit: None)
    wrote = wrote or (lambda name: None)
    system = exp.system
    H, n = int(o["horizon"]), system.n
    rng = np.random.default_rng([int(o["seed"]), 3])
    res: dict = {"horizon": H, "n_rollouts": int(o["n_rollouts"]), "alpha": float(o["alpha"]),
                 "beta": float(o["beta"]), "controllers": {}}
    with (contextlib.nullcontext(sim) if sim is not None else
          make_simulator(exp.simulator.to_dict(), system=system)) as sim:
        t0 = time.perf_counter()
        cert = certify_run(data, alpha=float(o["alpha"]), beta=float(o["beta"]), seed=int(o["seed"]), simulator=sim)
        cert.save(out / "cert_run.json")
        wrote("cert_run.json")
        res["run_certificate"] = {"gamma_range": [d.scp["gamma_range_on_data"] for d in cert.dims],
                                  "order_statistic": cert.options["order_statistic"],
                                  "alpha_min": cert.options["alpha_min"], "seconds": round(time.perf_counter() - t0, 3)}
        log(f"[perrun] gamma^alpha certified (alpha = {o['alpha']:g})")

        syn_eta = o.get("baseline_eta", exp.section("synthesis").get("eta"))
        syn_hold = int(o.get("baseline_hold", exp.section("synthesis").get("hold", 1)))
        # composing gamma^alpha over held periods is valid here: the union bound covers every period
        base = synthesize(system, spec, syn_eta, gap=cert, hold=syn_hold, x0=x0, compose_hold=True).controller
        base.save(out / "controller_run_baseline.npz")
        wrote("controller_run_baseline.npz")
        p_union = max(0.0, 1.0 - H * n * float(o["alpha"]))
        res["baseline_rule"] = f"p >= 1 - H n alpha = 1 - {H}*{n}*{o['alpha']:g} = {1 - H * n * float(o['alpha']):.4g}" \
                               f" (clipped at 0) in the winning domain, at confidence 1 - beta"

        t0 = time.perf_counter()
        imdp = build(sim, spec, o, lambda m: log(f"[perrun] {m}"), bar("perrun/imdp", "pairs"), executor=executor,
                     workers=workers, address=address, store=out / SAMPLES, replace_other=True)
        t_build = time.perf_counter() - t0
        ctl = synthesize_imdp(imdp, H, spec.kind)
        ctl.save(out / "controller_perrun.npz")
        wrote("controller_perrun.npz")
        res["imdp"] = {"cells": int(imdp.C), "live_cells": int(imdp.live.sum()), "inputs": int(imdp.M),
                       "nnz": imdp.nnz, "bytes": imdp.nbytes(), "hold": imdp.hold, "steps": ctl.steps,
                       "certified_periods": ctl.meta["certified_periods"], "horizon_rule": ctl.meta["horizon_rule"],
                       "seconds_build": round(t_build, 3), "seconds_vi": round(ctl.meta["seconds_vi"], 3),
                       **{k: imdp.meta[k] for k in ("n_runs", "pilot_runs", "bounds", "split", "levels", "rho",
                                                    "lipschitz", "samples", "union_bound", "assumption", "share",
                                                    "anchors", "containment") if k in imdp.meta}}
        res["p_cert_conditional_on"] = imdp.meta["p_cert_conditional_on"]
        res["randomization"] = imdp.meta["randomization"]
        log(f"[perrun] interval MDP {imdp.nnz} entries in {t_build:.1f} s; value iteration "
            f"{ctl.meta['seconds_vi']:.1f} s; p_cert(x0) = {float(ctl.certified(np.atleast_2d(x0))[0]):.4f}")

        def domain(grid, cells):
            return sample_in_cells(grid, cells, int(o["n_states"]), rng)

        entries = []
        for name, c in controllers.items():
            entries.append((name, lambda x, t, c=c: c.input_index(x), resolve_hold(c, sim),
                            domain(c.grid, np.flatnonzero(c.winning_mask)), lambda xs: None))
        entries.append(("run_baseline", lambda x, t: base.input_index(x), resolve_hold(base, sim),
                        domain(base.grid, np.flatnonzero(base.winning_mask)),
                        lambda xs: np.where(base.winning(xs), p_union, 0.0)))
        entries.append(("perrun", lambda x, t: ctl.input_index(x, t), ctl.hold,
                        domain(ctl.grid, np.flatnonzero(ctl.p_cert > 0)), ctl.certified))
        for name, fn, hold, dom, pc in entries:
            log(f"[perrun] rollouts: {name} ({len(dom) + 1} initial states x {o['n_rollouts']})")
            res["controllers"][name] = validate_controller(name, fn, hold, sim, spec, x0, dom, pc, o,
                                                           bar(f"perrun/{name}", "periods"))
    return res


def sound(p_cert, p_emp: float, se: float, n_rollouts: int) -> bool:
    """The validation's soundness check at one initial state: p_emp >= p_cert - 3 SE (SE at least
    1/R, so a state with no observed failure still has a margin); True where there is no p_cert."""
    return p_cert is None or p_emp >= p_cert - 3 * max(se, 1 / n_rollouts)


def randomization_note(sim) -> str:
    """How the simulator draws its per-run parameters, against the interval MDP's Markov assumption."""
    if getattr(sim, "per_episode", False):
        return ("per episode (randomize.per = 'episode'): rollouts keep their per-run parameters for the whole run, "
                "while the interval MDP was sampled with them redrawn every period (its Markov assumption): p_cert "
                "does not cover these runs")
    return ("per period: per-run parameters redrawn every sampling period, as the interval MDP's Markov assumption "
            "needs (a real robot keeps its parameters for a whole run: randomize.per = 'episode' validates that)")


def containment_line(c: Optional[dict]) -> str:
    """One line on the containment check recorded in a per-run certificate's meta (or its absence)."""
    if not c or c.get("passed") is None:
        return "containment check: not run"
    if c["passed"]:
        return f"containment check: passed ({c['runs']} fresh runs in {c['rows_checked']} rows)"
    return (f"containment check: FAILED in {c['cells_failed']} cell(s) ({c['outside_box']} of {c['runs']} fresh runs "
            f"outside their widened box, {c['unaccounted']} unaccounted): p_cert is not supported there")


def table(res: dict) -> str:
    """Per controller: p_cert and p_emp (95 % CI) at x0, the lowest p_emp over its initial states, and
    the share of states with p_emp >= p_cert - 3 SE ("-" for a controller that states no p_cert).
    The header says what p_cert is conditional on and how the containment check went."""
    rule = (res.get("imdp") or {}).get("horizon_rule")
    lines = [f"per-run guarantees: horizon {res['horizon']} periods, {res['n_rollouts']} rollouts per initial state"
             + (f"; p_cert: {rule}" if rule else ""),
             "p_cert: conditional on the estimated Lipschitz constants and the Markov assumption "
             "(summary.json per_run.p_cert_conditional_on); " + containment_line(res.get("imdp", {}).get("containment"))
             + ("; RANDOMIZATION PER EPISODE: outside the Markov assumption" if str(res.get("randomization", ""))
                .startswith("per episode") else ""),
             f"{'controller':<15}{'p_cert(x0)':>11}{'p_emp(x0)':>11}{'95% CI':>19}{'states':>8}{'min p_emp':>11}"
             f"{'sound':>7}"]
    for name, c in res["controllers"].items():
        s0 = c["states"][0]
        stated = [s for s in c["states"] if s["p_cert"] is not None]
        ok = sum(sound(s["p_cert"], s["p_emp"], s["se"], s["n_rollouts"]) for s in stated)
        pc = "-" if s0["p_cert"] is None else f"{s0['p_cert']:.4f}"
        ci = f"[{s0['ci95'][0]:.4f}, {s0['ci95'][1]:.4f}]"
        verdict = f"{ok}/{len(stated)}" if stated else "-"
        lines.append(f"{name:<15}{pc:>11}{s0['p_emp']:>11.4f}{ci:>19}{len(c['states']):>8}"
                     f"{min(s['p_emp'] for s in c['states']):>11.4f}{verdict:>7}")
    return "\n".join(lines)

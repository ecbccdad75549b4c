"""The app's only door into the engine: thin calls into ``simgap`` stages, and formatting of results.

Nothing here computes a gap, a bound, an abstraction or a rollout: each function translates the
app's :class:`~simgap_viz.settings.Settings` into the engine's arguments and calls it. A stage
whose engine module is not importable is reported by :func:`availability` and its button stays
disabled with a note (never faked).
"""

from __future__ import annotations

import importlib
import os
import tempfile
from pathlib import Path
from typing import Optional

import numpy as np

from simgap.errors import SimgapError
from simgap.systems import System, get_system


def _plugin_names(kind: str) -> list:
    """Names installed plugins register (simgap.plugins), offered next to the built-ins."""
    from simgap import plugins
    try:
        return sorted(plugins.system_plugins() if kind == "systems" else plugins.simulator_plugins())
    except Exception:  # a broken plugin package must not keep the app from starting
        return []


SYSTEMS = ["pendulum", "turtlebot"] + _plugin_names("systems")
# the generic kinds need an experiment's [simulator.options] (a model file and its joints) to run
SIMULATORS = ["numpy", "pybullet_pendulum", "pybullet_turtlebot", "pybullet_urdf", "mujoco"] + _plugin_names("simulators")

# stage -> modules that must import for the stage to be offered
_NEEDS = {
    "collect": ("simgap.collect", "simgap.cover"),
    "certify": ("simgap.certify.pipeline", "simgap.certify.certificate"),
    "synthesize": ("simgap.synthesis.controller",),
    "rollout": ("simgap.rollout",),
    "refine": ("simgap.refine.report", "simgap.refine.data"),
}
_ATTRS = {"certify": ("simgap.certify.pipeline", "certify"),
          "synthesize": ("simgap.synthesis.controller", "synthesize"),
          "refine": ("simgap.refine.report", "refine")}


def availability() -> dict:
    """stage -> (available, reason)."""
    out = {}
    for stage, mods in _NEEDS.items():
        ok, why = True, ""
        for m in mods:
            try:
                importlib.import_module(m)
            except ImportError as e:
                ok, why = False, f"engine module {m} is not available ({e})"
                break
        if ok and stage in _ATTRS:
            mod, attr = _ATTRS[stage]
            if not hasattr(importlib.import_module(mod), attr):
                ok, why = False, f"{mod}.{attr} is not available in this engine version"
        out[stage] = (ok, why)
    return out


def require(stage: str) -> None:
    ok, why = availability()[stage]
    if not ok:
        raise SimgapError(f"{stage} is disabled: {why}")


def unavailable_note(stage: str) -> str:
    ok, why = availability()[stage]
    return "" if ok else f"*{stage} is disabled: {why}*"


# ----- systems, specs ----------------------------------------------------------------------
# refined models the user switched to: name -> (refined System, the base System the simulator runs)
REFINED: dict = {}
# systems from a system file (or a Python System) the app was given: name -> System
USER: dict = {}


def register_user(system: System) -> str:
    """Make a system-file model selectable by name (the simulator runs it as it is)."""
    USER[system.name] = system.with_steps(1)
    if system.name not in SYSTEMS:
        SYSTEMS.append(system.name)
    return system.name


def system_by_name(name: str, steps: int = 1) -> System:
    """A selectable system by name: a registered refined or system-file model, else a built-in or plugin."""
    if name in REFINED:
        return REFINED[name][0].with_steps(int(steps))
    if name in USER:
        return USER[name].with_steps(int(steps))
    return get_system(name, steps=int(steps))


def register_refined(refined: System, base: System) -> str:
    """Make a refined model selectable by name (its simulator stays the base system's)."""
    REFINED[refined.name] = (refined, base)
    if refined.name not in SYSTEMS:
        SYSTEMS.append(refined.name)
    return refined.name


def base_system(system: System) -> System:
    """The system the simulator simulates: the base of a refined model, else the system itself."""
    return REFINED[system.name][1] if system.name in REFINED else system


def rebase(dataset, system: System):
    """The same data with f_nom = f'(x_r, u) of another nominal model (as simgap.refine.compare does):
    the empirical means are unchanged, the observed gap becomes |mean - f'|."""
    import dataclasses
    system = system.with_steps(dataset.system.steps)
    return dataclasses.replace(dataset, system=system, f_nom=system.f(dataset.x, dataset.u),
                               manifest={**dataset.manifest, "hash": f"{dataset.hash}-{system.name}"})


def make_system(settings, experiment=None) -> System:
    """The nominal system of the settings; the experiment's own (e.g. its input set) if it names the same."""
    if experiment is not None and experiment.system.name == settings.system and settings.system not in REFINED:
        return experiment.system.with_steps(int(settings.steps))
    return system_by_name(settings.system, int(settings.steps))


def default_simulator(system_name: str, current: str) -> str:
    """Keep the simulator if it fits the system (numpy fits all), else the system's PyBullet one."""
    if current == "numpy" or current.endswith(system_name):
        return current
    return "numpy"


def default_eta(system: System) -> tuple:
    """A grid of about 40 cells per dimension (a GUI starting point, not a recommendation)."""
    return tuple(float(f"{w:.3g}") for w in (system.x_hi - system.x_lo) / 40.0)


def check_terms(system: System, text: str) -> str:
    """Validate comma-separated extra basis terms with the engine's parser; return the text."""
    text = (text or "").strip()
    if not text:
        return ""
    from simgap.certify.basis import parse_term
    for t in _split_terms(text):
        parse_term(t, system)
    return text


def _split_terms(text: str) -> list:
    """Split on commas that are not inside parentheses."""
    out, depth, cur = [], 0, ""
    for ch in text:
        if ch == "(":
            depth += 1
        elif ch == ")":
            depth -= 1
        if ch == "," and depth == 0:
            out.append(cur.strip())
            cur = ""
        else:
            cur += ch
    if cur.strip():
        out.append(cur.strip())
    return [t for t in out if t]


def default_spec(system: System, arena=None):
    """The specification used when the experiment gives none: the paper's.

    Pendulum: invariance of the safe set [0, 0.2] x [-0.5, 0.5] (paper, Sec. V). TurtleBot:
    reach-avoid in the ``arena`` map (target, obstacles grown by the robot radius). A system file
    or plugin system: invariance of its whole state set X (give the experiment's [synthesis]
    section for another specification).
    """
    from simgap.synthesis.spec import Box, Spec
    name = base_system(system).name
    if arena is None and name == "turtlebot":
        from simgap.maps import load_map
        arena = load_map("arena")
    if arena is not None:
        return arena.spec(system)
    if name == "pendulum":
        return Spec("invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    from simgap.systems import BUILTIN
    if name not in BUILTIN:
        return Spec("invariance", safe=Box(system.x_lo, system.x_hi))
    raise SimgapError(f"no specification for system {system.name!r}: start the app with --experiment")


def simulator_config(settings, system: System):
    from simgap.simulators.base import SimulatorConfig
    noise = {"actuation_std": float(settings.noise_std)} if settings.simulator == "numpy" else {}
    return SimulatorConfig(kind=settings.simulator, system=system.name, steps=int(system.steps), noise=noise)


# ----- stages ----------------------------------------------------------------------------
_WORKDIR: Optional[Path] = None


def workdir() -> Path:
    global _WORKDIR
    if _WORKDIR is None:
        _WORKDIR = Path(os.environ.get("SIMGAP_GUI_WORKDIR") or tempfile.mkdtemp(prefix="simgap-gui-"))
        _WORKDIR.mkdir(parents=True, exist_ok=True)
    return _WORKDIR


def collect(settings, system: System, ctx, experiment=None, executor: str = "local"):
    """Collect the data set: cover X with radius epsilon, N1hat runs per (x_r, u) (simgap.collect).

    With an experiment for the same system and simulator kind, its simulator configuration
    (noise, effects) and cover options (declared invariances) are used, with the settings'
    epsilon, N1hat and seed; otherwise a plain cover and the settings' noise std.
    """
    from simgap.collect import CollectionPlan, collect as run_collect

    if system.name in REFINED:  # collect on the simulated base system, then measure the gap to f'
        return rebase(collect(settings, base_system(system), ctx, experiment, executor), system)

    cover, simcfg = _collect_setup(settings, system, experiment)
    plan = CollectionPlan(system=system, simulator=simcfg, cover=cover,
                          n_runs=int(settings.n_runs), seed=int(settings.seed))
    store = workdir() / f"store-{plan.hash()}"
    res = run_collect(plan, store, executor=executor, on_progress=ctx.progress, should_stop=ctx.cancelled)
    if res.cancelled or not res.complete:
        ctx.check()
        raise SimgapError(f"collection stopped with {res.done}/{res.n_chunks} chunks")
    if res.runs and res.seconds > 0 and res.computed:  # the measured rate makes the next estimate
        _RATES[_rate_key(settings, system, executor)] = (res.runs / res.seconds, "measured by the last collection")
    return res.dataset(system)


def _collect_setup(settings, system: System, experiment=None):
    """(cover, simulator config) of a collection for the settings (see :func:`collect`)."""
    import dataclasses

    from simgap.cover import CoverSpec, make_cover
    if experiment is not None and experiment.system.name == system.name \
            and experiment.simulator.kind == settings.simulator:
        cspec = dataclasses.replace(experiment.cover_spec(), epsilon=float(settings.epsilon))
        simcfg = dataclasses.replace(experiment.simulator, steps=int(system.steps))
    else:
        cspec = CoverSpec(epsilon=float(settings.epsilon))
        simcfg = simulator_config(settings, system)
    return make_cover(system, cspec), simcfg


# simulator runs per second of all workers, per (simulator, system, steps, noise, executor):
# calibrated (simgap.cover.calibrate_rate, one process, times the workers) or measured by a collection
_RATES: dict = {}


def _rate_key(settings, system: System, executor: str) -> tuple:
    return (settings.simulator, base_system(system).name, int(system.steps), float(settings.noise_std),
            settings.experiment, executor)


def collect_estimate(settings, system: System, experiment=None, executor: str = "local", calibrate: bool = False):
    """The engine's cost estimate of collecting for the settings (:func:`simgap.cover.estimate_cost`):
    cover points x inputs = (x_r, u) pairs, x N1hat simulator runs, and the time

        seconds = pairs * N1hat / rate,

    ``rate`` the simulator runs per second of all workers: the last collection's measured rate for the
    same simulator and executor, else (``calibrate``) :func:`simgap.cover.calibrate_rate` on this
    machine (about a second: the simulator is built and timed) times the executor's workers, else
    unknown (``seconds`` None). Returns a :class:`simgap.cover.CostEstimate`."""
    from simgap.cover import calibrate_rate, estimate_cost
    from simgap.executors import make_executor
    from simgap.simulators import make_simulator

    sysb = base_system(system)
    cover, simcfg = _collect_setup(settings, sysb, experiment)
    key = _rate_key(settings, system, executor)
    if key not in _RATES and calibrate:
        workers = make_executor(executor).workers if executor in ("serial", "local") else 1
        with make_simulator(simcfg, sysb) as sim:
            _RATES[key] = (calibrate_rate(sim, budget=0.3) * workers, f"calibrated here, {workers} worker" + ("s" if workers != 1 else ""))
    rate, source = _RATES.get(key, (None, ""))
    return estimate_cost(cover, int(settings.n_runs), rate_per_worker=rate, workers=1, rate_source=source)


def collect_estimate_text(est) -> str:
    """One line: pairs, simulator steps and the estimated time (or why there is none)."""
    from simgap.cover import format_duration
    t = f"about {format_duration(est.seconds)}" if est.seconds is not None else "time not estimated yet"
    return (f"{est.n_pairs:,} (x_r, u) pairs x N1hat {est.n_runs} = {est.sim_steps:,} simulator steps, {t}"
            + (f" ({est.rate_source})" if est.rate_source else ""))


def certify_options(settings, n: int):
    """CertifyOptions from the app's settings.

    A target joint confidence c is split evenly: beta_1i = beta_2i = (1 - c) / (2 n), and the
    engine computes the smallest deltas that reach them; per-dimension deltas are passed as given
    (the engine computes the betas).
    """
    from simgap.certify.bounds import BoundOptions
    from simgap.certify.pipeline import CertifyOptions

    terms = _split_terms(settings.terms)
    kw = dict(degree=int(settings.degree), terms={-1: terms} if terms else {},
              bounds=BoundOptions(concentration=settings.concentration, value_range=settings.value_range),
              value_range=settings.value_range)
    if settings.delta1 is not None and settings.delta2 is not None:
        kw.update(delta1=list(settings.delta1), delta2=list(settings.delta2))
    else:
        b = (1.0 - float(settings.confidence)) / (2.0 * n)
        kw.update(beta1=b, beta2=b)
    return CertifyOptions(**kw)


def warm_up() -> None:
    """Import the certification's solver stack (cvxpy, about half a second) ahead of the first
    re-certification, on a background thread, so that the first knob change does not pay it."""
    import threading

    def load():
        try:
            importlib.import_module("cvxpy")
        except Exception:  # reported by certify itself when it runs
            pass
    threading.Thread(target=load, name="simgap-warm-up", daemon=True).start()


def certify(dataset, settings, ctx):
    """The certificate of ``dataset`` for the settings' deltas/confidence, basis and bound (simgap.certify)."""
    from simgap.certify.pipeline import certify as run_certify
    ctx.check()
    return run_certify(dataset, certify_options(settings, dataset.system.n))


def synthesize(system, spec, cert, settings, ctx):
    """A symbolic controller for x+ in f(x,u) + [-gamma, gamma] (or f alone without a certificate),
    grid eta, input held ``hold`` sampling periods (simgap.synthesis.controller.synthesize)."""
    from simgap.synthesis.controller import synthesize as run_synthesize
    ctx.check()
    gap = cert if settings.use_gap else None
    return run_synthesize(system, spec, eta=list(settings.eta), gap=gap, hold=int(settings.hold),
                          x0=None if settings.x0 is None else list(settings.x0))


def rollout_simulator(settings, system, experiment=None):
    """The simulator of the rollouts: the collection's (the experiment's config if it matches)."""
    import dataclasses

    from simgap.simulators import make_simulator
    system = base_system(system)
    if experiment is not None and experiment.system.name == system.name \
            and experiment.simulator.kind == settings.simulator:
        cfg = dataclasses.replace(experiment.simulator, steps=int(system.steps))
    else:
        cfg = simulator_config(settings, system)
    return make_simulator(cfg, system=system)


def initial_state(settings, system, syn, spec, arena=None) -> np.ndarray:
    """x0 of the rollouts: the settings', else the map's, else the winning cell nearest the
    centre of the target (reach-avoid) or safe set (invariance)."""
    if settings.x0 is not None:
        return np.asarray(settings.x0, dtype=float)
    if arena is not None:
        return arena.x0(system)
    ctrl = syn.controller
    ids = np.flatnonzero(ctrl.winning_mask & ~ctrl.target)
    if ids.size == 0:
        raise SimgapError("empty winning domain: no initial state to roll out from (change eta, hold or the gap)")
    pts = ctrl.grid.points(ids)
    box = spec.target if spec.kind == "reach_avoid" else spec.safe
    c = 0.5 * (np.clip(box.lo, system.x_lo, system.x_hi) + np.clip(box.hi, system.x_lo, system.x_hi))
    return pts[np.argmin(np.linalg.norm((pts - c) / (system.x_hi - system.x_lo), axis=1))]


def rollout(system, spec, syn, settings, ctx, experiment=None, arena=None):
    """R closed-loop rollouts of the controller in the stochastic simulator (simgap.rollout)."""
    from simgap.rollout import rollout as run_rollout
    ctx.check()
    sim = rollout_simulator(settings, system, experiment)
    try:
        x0 = initial_state(settings, system, syn, spec, arena)
        kw = {}
        import inspect
        if "progress" in inspect.signature(run_rollout).parameters:
            kw["progress"] = ctx.progress  # per simulator step; raises JobCancelled after cancel
        return run_rollout(syn.controller, sim, x0=x0, n_rollouts=int(settings.n_rollouts),
                           horizon=int(settings.horizon), seed=int(settings.rollout_seed), spec=spec, **kw)
    finally:
        sim.close()


def refine(dataset, settings, ctx):
    """Refine the nominal model on the data's empirical means (simgap.refine): residuals, selected
    effects, the refined system f' = f + tau sum_k c_k g_k."""
    from simgap.refine.data import from_dataset
    from simgap.refine.report import refine as run_refine
    ctx.check()
    return run_refine(dataset.system, from_dataset(dataset))


# ----- result accessors -------------------------------------------------------------------
def gamma_function(cert):
    """gamma(x (B,n), u (B,m)) -> (B,n) of a certificate [state units]."""
    return cert.gamma


def winning_cells(res):
    """Winning domain projected on (x1, x2): (centers (C,2), widths (2,), fraction (C,) in (0,1]).

    Cells of higher dimensions (e.g. headings) with the same (x1, x2) are merged; ``fraction``
    is the share of them that is winning. Only columns with a winning cell are returned. Target
    cells are not winning cells here (``geometry.WINNING_CELLS``, the CLI table's count): a 2-D
    grid returns exactly ``controller.size`` cells.
    """
    ctrl = res.controller
    g = ctrl.grid
    win = np.asarray(ctrl.winning_mask & ~np.asarray(ctrl.target, bool)).reshape(g.shape)
    if win.ndim > 2:
        frac = win.reshape(g.shape[0], g.shape[1], -1).mean(axis=2)
    elif win.ndim == 2:
        frac = win.astype(float)
    else:
        frac = win.astype(float)[:, None]
    i, j = np.nonzero(frac > 0)
    if win.ndim >= 2:
        mi = np.zeros((i.size, g.n), np.int64)
        mi[:, 0], mi[:, 1] = i, j
        centers = g.multi_to_points(mi)[:, :2]
        widths = np.asarray(g.eta[:2], float)
    else:
        centers = g.multi_to_points(i[:, None])
        widths = np.asarray(g.eta, float)
    return centers, widths, frac[i, j]


def cell_labels(res):
    """(blocked (N,), allowed (N,)) cell labels of a synthesis result's grid for its spec
    (simgap.synthesis.controller.label_cells: obstacle/outside-X cells, safe or target cells)."""
    from simgap.synthesis.controller import label_cells
    ctrl = res.controller
    sysm = ctrl.system
    x_lo, x_hi = (sysm.x_lo, sysm.x_hi) if sysm is not None else (ctrl.grid.lo, ctrl.grid.hi)
    return label_cells(ctrl.grid, ctrl.spec, x_lo, x_hi, strict_domain=bool(ctrl.meta.get("strict_domain", True)))


def mean_map_trajectory(res):
    """The mean-map trajectory of a rollout result (the closed loop of x -> E[x+]), if the engine
    computed one, else None."""
    v = getattr(res, "mean_map_trajectory", None)
    return None if v is None else np.asarray(v)


def rollout_arrays(res):
    """(trajectories (R,T+1,n), failed (R,), mean (T+1,n), nominal (T+1,n) or None)."""
    return (np.asarray(res.trajectories), ~np.asarray(res.success), np.asarray(res.mean_trajectory),
            getattr(res, "nominal_trajectory", None))


def certificate_markdown(cert) -> str:
    """The certificate's summary as a markdown table: gamma per dimension, betas, confidences."""
    def f(v, p=3):
        return "-" if v is None else f"{v:.{p}g}"

    # one column per state dimension, one row per quantity: short cells that fit the panel
    rng = [d.scp.get("gamma_range_on_data", [None, None]) for d in cert.dims]
    quantities = (("max observed gap", [f(d.gap_max) for d in cert.dims]),
                  ("delta_1", [f(d.delta1) for d in cert.dims]), ("delta_2", [f(d.delta2) for d in cert.dims]),
                  ("beta_1", [f(d.beta1) for d in cert.dims]), ("beta_2", [f(d.beta2) for d in cert.dims]),
                  ("gamma on data, min", [f(r[0]) for r in rng]), ("gamma on data, max", [f(r[1]) for r in rng]),
                  ("confidence", [f(d.confidence, 4) for d in cert.dims]))
    rows = ["| | " + " | ".join(cert.state_names) + " |", "|---|" + "---|" * len(cert.dims)]
    rows += [f"| {q} | " + " | ".join(v) + " |" for q, v in quantities]
    jc = cert.joint_confidence
    rows.append("")
    rows.append(f"**joint confidence**: {'not stated (deterministic)' if jc is None else f'{jc:.4f}'}  ")
    rows.append("gamma_i = (L_f + Lhat + L_2) eps + q_i^T p_i + delta_2i: "
                + ", ".join(f"{n} {d.L_x * cert.epsilon:.3g} + fit + {d.delta2:.3g}"
                            for n, d in zip(cert.state_names, cert.dims)) + "  ")
    rows.append(f"eps = {cert.epsilon:g}, N1hat = {cert.n_runs}, K = {cert.K}, method {cert.method}")
    return "\n".join(rows)


def lines_table(lines, header: str = "") -> str:
    """The engine's aligned "key   value" summary lines as a two-column markdown table (wraps in
    the panel, where a code block would be clipped); lines without a key become plain text."""
    import re
    rows, text = [], [header] if header else []
    for line in lines:
        parts = re.split(r"\s{2,}", line.strip(), maxsplit=1)
        if len(parts) == 2 and line.startswith(("  ", parts[0])) and len(parts[0]) <= 20:
            rows.append(f"| {parts[0]} | {parts[1].replace('|', '/')} |")
        elif line.strip():
            text.append(line.strip())
    return "  \n".join(text) + ("\n\n| | |\n|---|---|\n" + "\n".join(rows) if rows else "")


def synthesis_markdown(res) -> str:
    try:
        lines = res.summary().splitlines()
    except KeyError:  # a controller saved by an older engine lacks some statistics
        lines = [f"{k}  {v}" for k, v in res.stats.items() if not isinstance(v, (dict, list))]
    return lines_table(lines)


def rollout_markdown(res) -> str:
    return lines_table(res.summary_lines())


def compare_refined(dataset, res, settings, spec=None):
    """Certified gap and winning domain for f and f' on the same data (simgap.refine.compare)."""
    from simgap.refine.compare import gap_comparison
    return gap_comparison(dataset, res.refined, certify_options(settings, dataset.system.n), spec=spec,
                          eta=list(settings.eta) if spec is not None else None, hold=int(settings.hold))


def comparison_markdown(d: dict) -> str:
    rows = ["| | f | f' |", "|---|---|---|"]
    for key, label in (("observed_gap_max", "max observed gap"), ("gamma_max", "max gamma"),
                       ("gamma_mean", "mean gamma")):
        b, a = d.get(f"{key}_before"), d.get(f"{key}_after")
        if b is not None:
            rows.append(f"| {label} | {', '.join(f'{v:.3g}' for v in b)} | {', '.join(f'{v:.3g}' for v in a)} |")
    if "winning_before" in d:
        rows.append(f"| winning cells | {d['winning_before']} | {d['winning_after']} |")
    return "\n".join(rows)


def refine_markdown(res) -> str:
    from simgap.refine.report import format_table
    return "```\n" + format_table(res.report) + "\n```"


# ----- static geometry -----------------------------------------------------------------------
def body_meshes(app) -> list:
    """(name, trimesh, position) of the simulator's bodies (from their URDF geometry)."""
    from .layers.bodies import simulator_bodies
    return simulator_bodies(app.settings.simulator, base_system(app.system))


def model_bodies(app) -> tuple:
    """(:class:`~simgap_viz.layers.bodies.MjcfBodies` / ``UrdfBodies`` or None, note) of the
    experiment's ``mujoco`` or ``pybullet_urdf`` simulator when the app simulates with it (the note
    says why nothing is drawn)."""
    from .layers.bodies import model_bodies as bodies
    exp = getattr(app, "experiment", None)
    cfg = exp.simulator if exp is not None else None
    if cfg is None or cfg.kind != app.settings.simulator:
        return None, ""
    return bodies(cfg, base_system(app.system))

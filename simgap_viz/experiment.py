"""Turning command-line options (experiment, profile, dataset, system) into the app's inputs."""

from __future__ import annotations

from typing import Optional

import numpy as np

from simgap.errors import SimgapError

from . import engine
from .settings import Settings


def app_inputs(experiment: Optional[str] = None, profile: Optional[str] = None, dataset: Optional[str] = None,
               system: Optional[str] = None):
    """(settings, dataset or None, spec or None, arena map or None, ExperimentConfig or None) for the app."""
    settings = Settings()
    spec = arena = data = exp = None
    if experiment:
        settings, spec, arena, exp = settings_from_experiment(experiment, profile)
        _selectable(exp.system)  # a system-file or refined model: registered so the app can select it
    if system:
        system = _selectable(system)
        settings = settings.replace(system=system, simulator=engine.default_simulator(system, settings.simulator))
        if system == "turtlebot" and arena is None:
            from simgap.maps import load_map
            arena = load_map("arena")
    settings = settings.replace(eta=engine.default_eta(engine.make_system(settings))) \
        if len(settings.eta) != engine.make_system(settings).n else settings
    if dataset:
        from simgap.dataset import load_dataset
        data = load_dataset(dataset)
        _selectable(data.system)
    return settings, data, spec, arena, exp


def _selectable(system) -> str:
    """The app's name of a system given by name, system file, refined-system JSON or System: a
    refined model is registered with its base (the simulator runs the base system), a system-file
    model as it is, so the app can select it by name."""
    from simgap.systems import is_named
    from simgap.system_ref import resolve_system

    if is_named(system):
        return system
    s = resolve_system(system)
    if is_named(s.name):
        return s.name
    refined = s.params.get("_refined_json")
    if refined is not None:
        engine.register_refined(s, resolve_system(refined["base"], s.steps, paths=False))
    else:
        engine.register_user(s)
    return s.name


def from_stages(run) -> Settings:
    """Settings for stage-by-stage outputs (:func:`simgap_viz.results.load_stages`): their model
    (registered so the app can select it), the data's epsilon and N1hat when the data are there,
    the default grid (the controller's eta and hold are set by the app)."""
    s = run.system
    name = _selectable(s)
    st = Settings(system=name, steps=int(s.steps), simulator=engine.default_simulator(name, Settings().simulator),
                  eta=engine.default_eta(s))
    ds = next(iter(run.methods.values())).dataset
    if ds is not None:
        st = st.replace(epsilon=float(ds.epsilon), n_runs=int(ds.n_runs))
    return st


def settings_from_experiment(name: str, profile: Optional[str]):
    try:
        from simgap.config import load_experiment
    except ImportError:
        raise SimgapError("--experiment needs simgap.config, which this engine version does not have") from None
    exp = load_experiment(name, profile)
    st, spec, arena = from_experiment(exp)
    return st, spec, arena, exp


def _vec(v):
    if v is None:
        return None
    return tuple(float(x) for x in (v if isinstance(v, (list, tuple)) else [v]))


def _confidence_from_betas(cert: dict, n: int, default):
    """Joint confidence 1 - sum_i (beta_1i + beta_2i) of [certify] beta1/beta2 (scalars or per dim)."""
    if "beta1" not in cert and "beta2" not in cert:
        return default
    b1 = np.broadcast_to(np.asarray(cert.get("beta1", cert.get("beta2")), float), (n,))
    b2 = np.broadcast_to(np.asarray(cert.get("beta2", cert.get("beta1")), float), (n,))
    return float(1.0 - b1.sum() - b2.sum())


def from_experiment(exp):
    """Map a :class:`simgap.config.ExperimentConfig` to (Settings, spec or None, arena map or None).

    Reads [system], [simulator], [collect] (typed by the engine) and, when present, the keys
    ``degree, terms, delta1, delta2, confidence, concentration`` of [certify], ``eta, hold`` of
    [synthesis], ``n_rollouts, horizon, x0, seed`` of [rollout], and ``map`` of [synthesis]
    or [simulator.options].
    """
    s = exp.system
    c = exp.collect
    noise = exp.simulator.noise.get("actuation_std", 0.05)
    noise = float(np.max(noise)) if np.ndim(noise) else float(noise)
    st = Settings(system=s.name, steps=int(s.steps), simulator=exp.simulator.kind, noise_std=noise,
                  epsilon=float(c.epsilon), n_runs=int(c.n_runs), seed=int(c.seed), experiment=exp.name,
                  profile=exp.profile or "")
    cert = exp.section("certify")
    syn = exp.section("synthesis")
    ro = exp.section("rollout")
    d1, d2 = _vec(cert.get("delta1")), _vec(cert.get("delta2"))
    if d1 is not None and len(d1) == 1:
        d1 = d1 * s.n
    if d2 is not None and len(d2) == 1:
        d2 = d2 * s.n
    terms = cert.get("terms", "")
    if isinstance(terms, (list, tuple)):
        terms = ", ".join(str(t) for t in terms)
    st = st.replace(
        degree=int(cert.get("degree", st.degree)) if np.isscalar(cert.get("degree", st.degree)) else st.degree,
        terms=str(terms), delta1=d1 if d2 is not None else None, delta2=d2 if d1 is not None else None,
        confidence=float(cert.get("confidence", _confidence_from_betas(cert, s.n, st.confidence))),
        concentration=str(cert.get("concentration", st.concentration)),
        eta=_vec(syn.get("eta")) or engine.default_eta(s), hold=int(syn.get("hold", st.hold)),
        n_rollouts=int(ro.get("n_rollouts", ro.get("n", st.n_rollouts))), horizon=int(ro.get("horizon", st.horizon)),
        x0=_vec(ro.get("x0")), rollout_seed=int(ro.get("seed", st.rollout_seed)))
    if len(st.eta) == 1:
        st = st.replace(eta=st.eta * s.n)
    arena = None
    map_name = syn.get("map") or exp.simulator.options.get("map") or ("arena" if s.name == "turtlebot" else None)
    if map_name:
        from simgap.maps import load_map
        arena = load_map(map_name)
    spec = arena.spec(s) if arena is not None else spec_from_section(syn, s)
    return st, spec, arena


def spec_from_section(syn: dict, system):
    """The specification of an experiment's [synthesis] section, or None.

    ``spec`` may be a table in the :meth:`Spec.to_dict` layout, or the word ``invariance``
    (safe box ``safe = [lo..., hi...]`` as two lists, default all of X) or ``reach_avoid``
    (``target`` and ``obstacles`` as [lo, hi] pairs of lists).
    """
    from simgap.synthesis.spec import Box, Spec

    d = syn.get("spec")
    if not d:
        return None
    try:
        if isinstance(d, dict):
            return Spec.from_dict(d)
        if d == "invariance":
            safe = syn.get("safe")
            box = Box(system.x_lo, system.x_hi) if safe is None else Box(safe[0], safe[1])
            return Spec("invariance", safe=box)
        if d == "reach_avoid" and syn.get("target") is not None:
            t = syn["target"]
            return Spec("reach_avoid", target=Box(t[0], t[1]),
                        obstacles=tuple(Box(o[0], o[1]) for o in syn.get("obstacles", [])))
    except (KeyError, TypeError, IndexError, ValueError) as e:
        raise SimgapError(f"experiment: bad [synthesis] spec ({e})") from None
    return None

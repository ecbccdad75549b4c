"""A finished ``simgap run`` folder, loaded for the app (``simgap gui RESULTS_DIR``).

The folder layout is the pipeline's (:func:`simgap.pipeline.run_experiment`): ``summary.json``,
``data`` and ``data_deterministic`` (collection stores), and per method (``stochastic``,
``deterministic``) ``cert_<m>.json``, ``audit_<m>.json``, ``controller_<m>.npz`` and, when the
rollouts ran, ``rollouts_<m>.npz`` (an invariant-set run: the controller file holds E, kept as
``MethodResults.invariant_set``, and ``controller_nominal.npz`` / ``rollouts_nominal.npz`` the
nominal model's set, ``RunResults.nominal``); with a ``[perrun]`` section, the per-run results
(:mod:`.results_perrun`). Everything is read with the engine's own loaders (no
pickle; the stores verify their digests); only files inside the folder are opened.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from simgap.errors import SimgapError
from simgap.file_guard import read_json, resolved
from simgap.results_folder import check_complete, check_listed

METHODS = ("stochastic", "deterministic")
DATA_DIRS = {"stochastic": "data", "deterministic": "data_deterministic"}


@dataclass
class MethodResults:
    """One method's stage outputs: dataset, certificate, audit report, synthesis, rollouts (or None)."""

    dataset: object
    certificate: object
    audit: Optional[dict]
    synthesis: object
    rollouts: object = None
    invariant_set: object = None  # an invariant-set run: the proved E (EllipsoidController), else None


@dataclass
class RunResults:
    path: Path
    summary: dict
    experiment: object = None  # simgap.config.ExperimentConfig, when its TOML is still readable
    methods: dict = field(default_factory=dict)  # method -> MethodResults
    per_run: object = None  # results_perrun.PerRunResults, when the run had a [perrun] section
    nominal: object = None  # an invariant-set run: the nominal model's E and rollouts (MethodResults
    # without dataset, certificate or audit), when it proved one


def is_run_dir(path) -> bool:
    """True for a folder that holds a finished run's ``summary.json``."""
    p = Path(path)
    return p.is_dir() and (p / "summary.json").is_file()


def read_summary(root: Path) -> dict:
    """``root/summary.json`` of a finished run (a regular file, size- and depth-checked JSON with a
    ``methods`` table), after checking that every file it lists is there (a missing one is named)."""
    summary = read_json(root / "summary.json", "summary")
    if not isinstance(summary, dict) or not isinstance(summary.get("methods"), dict):
        raise SimgapError(f"{root / 'summary.json'} has no 'methods' table: not a `simgap run` summary")
    check_complete(root, summary)
    return summary


def _inside(root: Path, name: str) -> Path:
    p = resolved(root / name, "results folder file")
    if resolved(root, "results folder") not in p.parents:
        raise SimgapError(f"results folder: {name!r} points outside {root}")
    return p


def _experiment(summary: dict, root: Path):
    """The run's experiment config: the TOML text embedded in its summary (what the run used; the
    folder then opens from anywhere, moved, with the file deleted or edited since), else its TOML
    file if it still loads, else the built-in of that name. A system file the TOML names that is
    gone is replaced by the model the run's data embed."""
    from simgap.config import load_experiment
    name, profile = summary.get("experiment"), summary.get("profile") or "base"
    errors = []
    text = summary.get("experiment_toml")
    sources = [(summary.get("config_file") or f"{name}.toml", text)] if isinstance(text, str) else []
    sources += [(src, None) for src in (summary.get("config_file"), name) if src]
    for src, txt in sources:
        try:
            return load_experiment(src, profile, text=txt)
        except SimgapError as e:
            errors.append(("embedded configuration: " if txt is not None else "") + str(e))
            if "system file" in str(e) and (root / DATA_DIRS["stochastic"]).is_dir():
                from simgap.collect import load_store
                try:
                    embedded = load_store(_inside(root, DATA_DIRS["stochastic"])).system
                    return load_experiment(src, profile, system=embedded, text=txt)
                except SimgapError as e2:
                    errors.append(str(e2))
    raise SimgapError(f"results folder {root}: cannot load its experiment {name!r} (profile {profile}): "
                      + "; ".join(errors))


def proved_sets(run) -> list:
    """(method, EllipsoidController) of every invariant set an invariant-set run proved, the nominal
    model's last (none for a grid run)."""
    out = [(m, run.methods[m].invariant_set) for m in METHODS
           if m in run.methods and getattr(run.methods[m], "invariant_set", None) is not None]
    nom = getattr(run, "nominal", None)
    if nom is not None and nom.invariant_set is not None:
        out.append(("nominal", nom.invariant_set))
    return out


def unproved_sets(run) -> list:
    """(method, gap margin s or None) of every method of an invariant-set run whose proof failed."""
    summary = getattr(run, "summary", None) or {}
    if (summary.get("sections", {}).get("synthesis") or {}).get("method") != "invariant_set" \
            and not any(isinstance(e, dict) and "gap_scale" in (e.get("synthesis") or {})
                        for e in summary.get("methods", {}).values()):
        return []
    out = []
    for m in (*METHODS[::-1], "nominal"):
        e = summary.get("methods", {}).get(m)
        if isinstance(e, dict) and not e.get("winning_cells"):
            s_ = (e.get("synthesis") or {}).get("gap_scale")
            out.append((m, float(s_) if isinstance(s_, (int, float)) else None))
    return out


def _nominal(root: Path, summary: dict, system) -> Optional[MethodResults]:
    """An invariant-set run's nominal-model set (``controller_nominal.npz``) and its rollouts, when proved."""
    if not isinstance(summary["methods"].get("nominal"), dict) or not (root / "controller_nominal.npz").is_file():
        return None
    from simgap.rollout import load_rollout
    from simgap.synthesis.controller import Controller
    for name in ("controller_nominal.npz", "rollouts_nominal.npz"):
        if (root / name).is_file():
            check_listed(root, summary, name)
    ctrl = Controller.load(_inside(root, "controller_nominal.npz"), system=system)
    if not getattr(ctrl, "continuous_input", False):
        raise SimgapError(f"results folder {root}: controller_nominal.npz is not an invariant-set controller")
    rp = _inside(root, "rollouts_nominal.npz")
    return MethodResults(dataset=None, certificate=None, audit=None, synthesis=None,
                         rollouts=load_rollout(rp) if rp.is_file() else None, invariant_set=ctrl)


def load_run(path) -> RunResults:
    """Load every stage output of a finished run (see module docstring).

    Raises SimgapError naming the folder and the missing or unreadable file.
    """
    from simgap.certify.certificate import load as load_certificate
    from simgap.collect import load_store
    from simgap.synthesis.controller import Controller, SynthesisResult
    from simgap.rollout import load_rollout

    from .results_perrun import load_per_run

    root = Path(path)
    if not root.is_dir():
        raise SimgapError(f"results folder {str(root)!r} does not exist")
    if not (root / "summary.json").is_file():
        raise SimgapError(f"{str(root)!r} has no summary.json: not a finished `simgap run` folder "
                          "(run `simgap run EXPERIMENT` first, or give --experiment/--dataset)")
    summary = read_summary(root)
    exp = _experiment(summary, root)
    run = RunResults(path=root, summary=summary, experiment=exp)
    for m in METHODS:
        if m not in summary["methods"]:
            continue
        for name in (f"cert_{m}.json", f"audit_{m}.json", f"controller_{m}.npz", f"rollouts_{m}.npz"):
            if (root / name).is_file():
                check_listed(root, summary, name, digest=False)  # a stray of another run: refused first
        ds = load_store(_inside(root, DATA_DIRS[m]), system=exp.system)
        want = summary["methods"][m].get("dataset_hash") if isinstance(summary["methods"][m], dict) else None
        if want is not None and ds.hash != want:
            raise SimgapError(f"results folder {root}: the data in {DATA_DIRS[m]} are not the ones this run certified "
                              f"(dataset hash {ds.hash[:12]}..., summary.json says {str(want)[:12]}...; refused)")
        cert = load_certificate(_inside(root, f"cert_{m}.json"))
        audit = None
        ap = _inside(root, f"audit_{m}.json")
        if ap.is_file():
            audit = read_json(ap, "audit report")
        cp = _inside(root, f"controller_{m}.npz")
        invariant = (summary.get("sections", {}).get("synthesis") or {}).get("method") == "invariant_set"
        if not cp.is_file() and not (invariant and not summary["methods"][m].get("winning_cells")):
            raise SimgapError(f"results folder {root}: {cp.name} is missing")
        syn = ell = None  # an invariant-set run: no set proved (no file), or E
        if cp.is_file():
            ctrl = Controller.load(cp, system=exp.system)
            if getattr(ctrl, "continuous_input", False):
                ell = ctrl
            else:
                syn = SynthesisResult(ctrl, dict(ctrl.meta.get("stats", {})))
        rp = _inside(root, f"rollouts_{m}.npz")
        ro = load_rollout(rp) if rp.is_file() else None
        # each file's own checks ran first (their messages are the more specific); then: is it
        # the file this run wrote, not one of another run's?
        for name in (f"cert_{m}.json", f"audit_{m}.json", f"controller_{m}.npz", f"rollouts_{m}.npz"):
            if (root / name).is_file():
                check_listed(root, summary, name)
        run.methods[m] = MethodResults(dataset=ds, certificate=cert, audit=audit, synthesis=syn, rollouts=ro,
                                       invariant_set=ell)
    if not run.methods:
        raise SimgapError(f"{root / 'summary.json'} lists no method results")
    run.nominal = _nominal(root, summary, exp.system)
    run.per_run = load_per_run(root, summary, exp.system)
    return run

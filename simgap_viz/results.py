"""A finished ``simgap run`` folder, loaded for the app (``simgap gui RESULTS_DIR``).

The folder layout is the pipeline's (:func:`simgap.pipeline.run_experiment`): ``summary.json``,
``data`` and ``data_deterministic`` (collection stores), and per method (``stochastic``,
``deterministic``) ``cert_<m>.json``, ``audit_<m>.json``, ``controller_<m>.npz`` and, when the
rollouts ran, ``rollouts_<m>.npz`` (an invariant-set run: the controller file holds E, kept as
``MethodResults.invariant_set``, and ``controller_nominal.npz`` / ``rollouts_nominal.npz`` the
nominal model's set, ``RunResults.nominal``); with a ``[perrun]`` section, the per-run results
(:mod:`.results_perrun`). Everything is read with the engine's own loaders (no
pickle; the stores verify their digests); only files inside the folder are opened.

Stage-by-stage outputs (``simgap collect``, ``certify``, ``synthesize``, ``rollout`` run one by
one) load with :func:`load_stages`: a data set (store folder or .npz), a certificate, a
controller and rollouts (the ``--trajectories`` .npz of ``simgap rollout``), any of them absent,
given as files or found in one folder. They are checked against each other before anything is
shown: the certificate's data hash against the data set, the controller's gap against the
certificate (its digest) and its system against the certificate's, the rollouts' controller digest
(or, for files written before rollouts recorded it, system and specification) against the
controller.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import re
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
    invariant_set: object = None  # a set method's controller (ellipsoid, box tube) when proved, else None
    statement: object = None  # what the method proved, in its words (simgap.synthesis.statement.Statement)


@dataclass
class RunResults:
    path: Path
    summary: dict
    experiment: object = None  # simgap.config.ExperimentConfig, when its TOML is still readable
    methods: dict = field(default_factory=dict)  # method -> MethodResults
    per_run: object = None  # results_perrun.PerRunResults, when the run had a [perrun] section
    # stage-by-stage outputs (load_stages): {role: path or None (absent)}; None for a run folder
    stages: Optional[dict] = None
    stage_system: object = None  # their nominal model (no experiment)
    spec: object = None  # their specification (the controller's or the rollouts'), or None
    notes: list = field(default_factory=list)  # what a folder held that is not shown, and why

    @property
    def system(self):
        """The nominal model of the results: the experiment's, else the stage outputs' own."""
        return self.experiment.system if self.experiment is not None else self.stage_system
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
    if (summary.get("sections", {}).get("synthesis") or {}).get("method") not in ("invariant_set", "box_tube") \
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
                         rollouts=load_rollout(rp) if rp.is_file() else None, invariant_set=ctrl,
                         statement=method_statement(summary, "nominal", ctrl))


def run_method(summary: dict) -> str:
    """The synthesis method of a run folder's experiment (``grid`` when it names none)."""
    return (summary.get("sections", {}).get("synthesis") or {}).get("method") or "grid"


def method_statement(summary: dict, m: str, ctrl):
    """The statement of method entry ``m`` (deterministic, stochastic, nominal): the controller's own
    with the summary's counts, or the method's "not proved" with its diagnosis."""
    from simgap.synthesis.statement import statement_of
    e = summary.get("methods", {}).get(m) or {}
    return statement_of(run_method(summary), ctrl, e.get("synthesis") or {}, e)


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
    from simgap.results_folder import unfinished
    if unfinished(root):
        raise SimgapError(unfinished(root))
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
        entry = summary["methods"][m] if isinstance(summary["methods"][m], dict) else {}
        sub = entry.get("data_dir", DATA_DIRS[m])  # the last round's store when the run collected in rounds
        if not (sub == DATA_DIRS[m] or (m == "stochastic" and re.fullmatch(r"data_round[0-9]{1,3}", str(sub)))):
            raise SimgapError(f"results folder {root}: summary.json names the data folder {sub!r} (refused)")
        ds = load_store(_inside(root, sub), system=exp.system)
        want = entry.get("dataset_hash")
        if want is not None and ds.hash != want:
            raise SimgapError(f"results folder {root}: the data in {sub} are not the ones this run certified "
                              f"(dataset hash {ds.hash[:12]}..., summary.json says {str(want)[:12]}...; refused)")
        cert = load_certificate(_inside(root, f"cert_{m}.json"))
        audit = None
        ap = _inside(root, f"audit_{m}.json")
        if ap.is_file():
            audit = read_json(ap, "audit report")
        cp = _inside(root, f"controller_{m}.npz")
        invariant = run_method(summary) in ("invariant_set", "box_tube")
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
                                       invariant_set=ell,
                                       statement=method_statement(summary, m, ell if syn is None else syn.controller))
    if not run.methods:
        raise SimgapError(f"{root / 'summary.json'} lists no method results")
    run.nominal = _nominal(root, summary, exp.system)
    run.per_run = load_per_run(root, summary, exp.system)
    return run


# ----- stage-by-stage outputs ----------------------------------------------------------------

#: the stage outputs, by the flag that names each (simgap gui / simgap plot)
ROLES = ("dataset", "cert", "controller", "rollouts")
ROLE_WHAT = {"dataset": "data set", "cert": "certificate", "controller": "controller", "rollouts": "rollouts"}
ROLE_MAKES = {"dataset": "simgap collect EXPERIMENT --out DIR", "cert": "simgap certify DATA --out cert.json",
              "controller": "simgap synthesize ... --out ctrl.npz",
              "rollouts": "simgap rollout ... --out report.json --trajectories rollouts.npz"}


def add_stage_arguments(parser) -> None:
    """The flags that name stage outputs (``simgap gui``, ``simgap plot``)."""
    parser.add_argument("--cert", default=None, metavar="FILE", help="a certificate JSON (simgap certify --out)")
    parser.add_argument("--controller", default=None, metavar="FILE", help="a controller .npz (simgap synthesize --out)")
    parser.add_argument("--rollouts", default=None, metavar="FILE",
                        help="rollouts .npz (simgap rollout --trajectories; the JSON report has no trajectories)")


def _sniff(p: Path):
    """The role of one entry of a stage folder (a ROLES name, "report" for a rollout's JSON report,
    or None for anything else); reads headers only, never unpickles."""
    from simgap.dataset import ARRAYS
    from simgap.errors import BAD_FILE_ERRORS
    from simgap.file_guard import loads_json
    from simgap.store import MANIFEST
    if p.is_dir():
        return "dataset" if (p / MANIFEST).is_file() else None
    if not p.is_file():
        return None
    if p.suffix == ".npz":
        import numpy as np
        try:
            with np.load(p, allow_pickle=False) as z:
                names = set(z.files)
                if "meta" in names and "simgap-controller" in str(z["meta"])[:100000]:
                    meta = loads_json(str(z["meta"]), f"{p}: its metadata")
                    if isinstance(meta, dict) and meta.get("format") == "simgap-controller":
                        return "controller"
        except BAD_FILE_ERRORS as e:
            raise SimgapError(f"{str(p)!r} in the stage folder is not a readable .npz ({e}); move it away or name "
                              "the stage files with --dataset/--cert/--controller/--rollouts") from None
        if "meta_json" in names and "trajectories" in names:
            return "rollouts"
        return "dataset" if set(ARRAYS) <= names else None
    if p.suffix == ".json":
        try:
            d = read_json(p, "JSON file")
        except SimgapError:
            return None
        if isinstance(d, dict) and "dims" in d and "provenance" in d and "digest" in d:
            return "cert"
        if isinstance(d, dict) and "n_rollouts" in d and "outcomes" in d:
            return "report"
    return None


def stage_files(folder) -> tuple:
    """({role: path} of the stage outputs in ``folder``, notes on entries not shown). Two files of
    one role are refused, naming both (the flags then say which one)."""
    from simgap.file_guard import printable
    root = Path(folder)
    if not root.exists():
        raise SimgapError(f"{str(root)!r} does not exist")
    if not root.is_dir():
        raise SimgapError(f"{str(root)!r} is not a folder (name a single stage file with --dataset/--cert/"
                          "--controller/--rollouts)")
    from simgap.results_folder import unfinished
    if unfinished(root):  # not a folder of stage outputs: a run that stopped (its two stores are not a choice)
        raise SimgapError(unfinished(root))
    found: dict = {r: [] for r in ROLES}
    notes = []
    for p in sorted(root.iterdir()):
        if p.name.startswith("."):
            continue
        role = _sniff(p)
        if role in found:
            found[role].append(p)
        elif role == "report":
            notes.append(f"{p.name} is a rollout report (JSON): the rollouts are drawn from the .npz `simgap rollout "
                         "--trajectories` writes")
    out = {}
    for r, ps in found.items():
        if len(ps) > 1:
            raise SimgapError(f"{str(root)!r} holds {len(ps)} {ROLE_WHAT[r]}s ({', '.join(printable(q.name) for q in ps)}): "
                              f"name the one to show with --{r} FILE")
        if ps:
            out[r] = ps[0]
    return out, notes


def load_stages(folder=None, dataset=None, cert=None, controller=None, rollouts=None) -> RunResults:
    """Stage-by-stage outputs as one :class:`RunResults` (one method: the certificate's, else
    stochastic), each loaded with the engine's own loader (digests verified, no pickle) and checked
    against the others (module docstring). Files given by name take the place of the folder's.

    Raises SimgapError naming the file that is missing, unreadable or belongs to something else.
    """
    from simgap.certify.certificate import load as load_certificate
    from simgap.dataset import load_dataset
    from simgap.rollout import load_rollout
    from simgap.synthesis.controller import Controller, SynthesisResult

    paths, notes = stage_files(folder) if folder is not None else ({}, [])
    for role, given in zip(ROLES, (dataset, cert, controller, rollouts)):
        if given is not None:
            paths[role] = Path(given)
    if not paths:
        where = (f"{str(folder)!r} is neither a `simgap run` folder (no summary.json) nor holds stage outputs"
                 if folder is not None else "no stage output given")
        raise SimgapError(f"{where}: give a data set (--dataset), certificate (--cert), controller (--controller) or "
                          "rollouts (--rollouts, the .npz of simgap rollout --trajectories)")
    for role, p in paths.items():
        if not p.exists():
            raise SimgapError(f"--{role} {str(p)!r}: no such file or folder")
    if "rollouts" in paths and paths["rollouts"].suffix == ".json":
        raise SimgapError(f"--rollouts {str(paths['rollouts'])!r} is a JSON report; the rollouts are drawn from the "
                          ".npz that `simgap rollout --trajectories FILE.npz` writes")
    ds = load_dataset(paths["dataset"]) if "dataset" in paths else None
    ce = load_certificate(paths["cert"]) if "cert" in paths else None
    ctrl = Controller.load(paths["controller"]) if "controller" in paths else None
    ro = load_rollout(paths["rollouts"]) if "rollouts" in paths else None
    if ce is not None and ce.method not in METHODS:
        raise SimgapError(f"certificate {str(paths['cert'])!r} is a {ce.method}-level certificate; the views show "
                          f"mean-level ones ({', '.join(METHODS)})")
    _check_together(paths, ds, ce, ctrl, ro)

    if ds is not None:
        system = ds.system
    elif ce is not None and ce.nominal_system() is not None:
        system = ce.nominal_system()
    elif ctrl is not None and ctrl.system is not None:
        system = ctrl.system
    else:
        from simgap.system_ref import resolve_system
        try:
            system = resolve_system(ro.system, paths=False)
        except SimgapError:
            raise SimgapError(f"rollouts {str(paths['rollouts'])!r} name the system {ro.system!r} only: give its "
                              "controller (--controller) or data (--dataset) too") from None
    syn = ell = None
    if ctrl is not None and not getattr(ctrl, "continuous_input", False):
        syn = SynthesisResult(ctrl, dict(ctrl.meta.get("stats", {})))
    elif ctrl is not None:
        ell = ctrl  # a set method's controller: its sets are drawn (layer "Proved sets")
    spec = getattr(ctrl, "spec", None) if ctrl is not None else None
    spec = spec if spec is not None else (ro.spec if ro is not None else None)
    x0 = (ctrl.meta.get("x0") if ctrl is not None else None)
    x0 = x0 if x0 is not None else (ro.x0.tolist() if ro is not None else None)
    summary = {"x0": x0, "sections": {"rollout": {"n": ro.n_rollouts, "seed": ro.seed}} if ro is not None else {}}
    method = ce.method if ce is not None else "stochastic"
    first = next(iter(paths.values()))
    run = RunResults(path=Path(folder) if folder is not None else first.parent, summary=summary,
                     stages={r: (str(paths[r]) if r in paths else None) for r in ROLES}, stage_system=system,
                     spec=spec, notes=notes)
    from simgap.synthesis.statement import statement_of
    run.methods[method] = MethodResults(dataset=ds, certificate=ce, audit=None, synthesis=syn, rollouts=ro,
                                        invariant_set=ell, statement=None if ctrl is None else statement_of(
                                            getattr(ctrl, "kind", "grid"), ctrl, ctrl.meta.get("stats", {})))
    return run


def _check_together(paths: dict, ds, ce, ctrl, ro) -> None:
    """Refuse stage outputs that do not belong together, naming both files."""
    from simgap.synthesis.controller import gap_source

    def name(role):
        return f"{ROLE_WHAT[role]} {str(paths[role])!r}"

    if ds is not None and ce is not None:
        want = ce.provenance.get("dataset_hash")
        if want and want != ds.hash:
            raise SimgapError(f"{name('cert')} was made from the data set with content hash {str(want)[:12]}..., not "
                              f"from {name('dataset')} (hash {ds.hash[:12]}...): give the data it certifies (refused)")
    if ce is not None and ctrl is not None:
        if ctrl.system is not None:
            try:
                ce.check_system(ctrl.system)
            except SimgapError as e:
                raise SimgapError(f"{name('cert')} does not belong to {name('controller')}: {e} (refused)") from None
        kind, digest = gap_source(ctrl.meta)
        if kind != "certificate":
            how = "on the nominal model alone" if kind == "none" else f"with a {kind} gap"
            raise SimgapError(f"{name('controller')} was synthesized {how}, not with {name('cert')}: drop --cert or "
                              "give the controller synthesized with it (refused)")
        if digest != ce.digest:
            raise SimgapError(f"{name('controller')} was synthesized with another certificate (digest "
                              f"{str(digest)[:16]}...) than {name('cert')} (digest {ce.digest[:16]}...) (refused)")
    if ds is not None and ctrl is not None and ctrl.system is not None and ctrl.system.name != ds.system.name:
        raise SimgapError(f"{name('controller')} is for system {ctrl.system.name!r}, {name('dataset')} for "
                          f"{ds.system.name!r} (refused)")
    if ro is not None and ctrl is not None:
        have = ctrl.meta.get("digest")
        if ro.controller_digest is not None:
            if ro.controller_digest != have:
                raise SimgapError(f"{name('rollouts')} are of another controller (digest {ro.controller_digest[:16]}...) "
                                  f"than {name('controller')} (digest {str(have)[:16]}...) (refused)")
        elif (ctrl.system is not None and ro.system != ctrl.system.name) or \
                (ctrl.spec is not None and ro.spec.to_dict() != ctrl.spec.to_dict()):
            raise SimgapError(f"{name('rollouts')} (system {ro.system!r}) do not match {name('controller')} (system "
                              f"{getattr(ctrl.system, 'name', '?')!r}): another system or specification (refused)")
    for role, obj in (("dataset", ds), ("cert", ce)):
        if ro is not None and obj is not None:
            other = obj.system.name if role == "dataset" else obj.system_name
            if ro.system != other:
                raise SimgapError(f"{name('rollouts')} are of system {ro.system!r}, {name(role)} of {other!r} (refused)")


def describe_stages(run: RunResults) -> list:
    """One line per stage output of ``run`` (:func:`load_stages`): what is shown, or that it is absent
    and which command writes it."""
    if run.stages is None:
        return []
    m = next(iter(run.methods.values()))
    lines = []
    for role in ROLES:
        p = run.stages[role]
        if p is None:
            lines.append(f"{ROLE_WHAT[role]}: absent (written by `{ROLE_MAKES[role]}`)")
            continue
        if role == "dataset":
            what = f"K = {m.dataset.K} pairs, N1hat = {m.dataset.n_runs}, epsilon = {m.dataset.epsilon:g}"
        elif role == "cert":
            what = f"{m.certificate.method}, system {m.certificate.system_name}"
        elif role == "controller":
            what = (f"{m.synthesis.controller.size:,} winning cells" if m.synthesis is not None
                    else m.invariant_set.statement().name + " (layer Proved sets)")
        else:
            what = f"{m.rollouts.n_rollouts} rollouts, {m.rollouts.n_failures} failed"
        lines.append(f"{ROLE_WHAT[role]}: {p} ({what})")
    return lines + list(run.notes)


def run_spec(run: RunResults) -> tuple:
    """(spec, x0, arena map) of a run folder (its experiment's) or of stage outputs (the
    controller's or rollouts' spec and x0; no arena)."""
    if run.experiment is not None:
        from simgap.pipeline import experiment_spec
        return experiment_spec(run.experiment)
    return run.spec, run.summary.get("x0"), None

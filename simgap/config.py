"""Experiment configurations: TOML files with a base configuration and named profiles.

Layout (``assets/experiments/pendulum.toml`` is a complete example; every section and key with
its type and range is in :mod:`simgap.schema`)::

    description = "..."                      # optional
    [system]      name, steps, inputs (list of input vectors) or input_grid = {lo, hi, counts}
                  (name: a built-in, a plugin system, a system file .toml or a refined-system .json
                  in the experiment's folder; ``system = "my_model.toml"`` is short for
                  ``[system] name = "my_model.toml"``)
    [simulator]   kind, noise, randomize, effects, options      (see simgap.simulators)
    [collect]     epsilon, spacing, invariant_dims, fixed, n_runs, seed, chunk_size, batch_runs,
                  keep_samples, executor, workers, address, out
    [certify], [audit], [synthesis], [rollout]   the other stages' options (simgap run)
    [profiles.<name>.<section>]              overrides any key of <section> for that profile

A profile is merged over the base key by key (nested tables merge recursively), then explicit
overrides (CLI flags) are merged over the profile. Unknown sections and keys are errors naming
the nearest valid name. ``system``, ``simulator`` and ``collect`` become typed objects; the
other sections are returned as checked plain dicts in ``sections``.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from . import schema
from .file_guard import read_text
from .collect import DEFAULT_BATCH_RUNS, CollectionPlan
from .cover import Cover, CoverSpec, make_cover
from .errors import SimgapError
from .paths import ASSETS_DIR
from .profiles import DEFAULT_PROFILE, DefaultProfile
from .simulators.base import SimulatorConfig, simulator_class
from .systems import BUILTIN, System, get_system, input_grid, is_named
from .system_ref import resolve_system

EXPERIMENTS_DIR = ASSETS_DIR / "experiments"

@dataclass
class CollectSettings:
    """The ``[collect]`` section: the cover, N1hat, the seed, chunking and where to run."""

    epsilon: float
    n_runs: int
    seed: int = 0
    spacing: Optional[tuple] = None
    invariant_dims: tuple = ()
    fixed: dict = field(default_factory=dict)
    region: dict = field(default_factory=dict)   # a sub-box of X covered instead of X (cover.region_box)
    tube_margin: Optional[tuple] = None          # a cover along the box tube (simgap.tube_collect.along_tube)
    boxes: tuple = ()                            # ... its boxes, computed from the nominal tube (not a TOML key)
    budget_runs: Optional[int] = None            # anytime-valid rounds (simgap.rounds)
    budget_minutes: Optional[float] = None
    chunk_size: Optional[int] = None
    batch_runs: int = DEFAULT_BATCH_RUNS
    keep_samples: bool = False
    executor: str = "local"
    workers: Optional[int] = None
    address: Optional[str] = None
    out: Optional[str] = None


@dataclass
class ExperimentConfig:
    """A loaded experiment (one profile): typed collection inputs plus every raw section."""

    name: str
    profile: Optional[str]
    path: Path
    system: System
    simulator: SimulatorConfig
    collect: CollectSettings
    sections: dict
    description: str = ""

    def section(self, name: str) -> dict:
        """A raw section (e.g. ``certify``) as a dict; empty if absent."""
        return copy.deepcopy(self.sections.get(name, {}))

    def cover_spec(self) -> CoverSpec:
        c = self.collect
        return CoverSpec(epsilon=c.epsilon, spacing=c.spacing, invariant_dims=tuple(c.invariant_dims),
                         fixed=dict(c.fixed), region={k: list(v) for k, v in c.region.items()}, boxes=c.boxes)

    def cover(self) -> Cover:
        return make_cover(self.system, self.cover_spec())

    def plan(self, cover: Optional[Cover] = None) -> CollectionPlan:
        """The :class:`~simgap.collect.CollectionPlan` this experiment describes."""
        c = self.collect
        return CollectionPlan(system=self.system, simulator=self.simulator, cover=cover or self.cover(),
                              n_runs=c.n_runs, seed=c.seed, chunk_size=c.chunk_size, batch_runs=c.batch_runs,
                              keep_samples=c.keep_samples)

    def store_dir(self) -> Path:
        """Where the data go: ``collect.out`` or ``results/<name>-<profile>/data`` (relative to cwd), the
        folder ``simgap run`` collects into, so a ``simgap collect`` is resumed (or reused) by ``simgap run``."""
        if self.collect.out:
            return Path(self.collect.out)
        return Path("results") / f"{self.name}-{self.profile or 'base'}" / "data"


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def builtin_experiments() -> list:
    """Names of the experiments shipped in ``assets/experiments`` (sorted)."""
    return sorted(x.stem for x in EXPERIMENTS_DIR.glob("*.toml"))


def resolve_experiment(path_or_name: str | Path) -> Path:
    """A TOML path, or a bare name resolved to ``assets/experiments/<name>.toml``."""
    p = Path(path_or_name)
    if p.is_file():
        return p
    s = str(path_or_name)
    if "/" not in s and not s.endswith(".toml"):
        q = EXPERIMENTS_DIR / f"{s}.toml"
        if q.is_file():
            return q
        known = builtin_experiments()
        raise SimgapError(f"unknown experiment {s!r}; built-in experiments: {', '.join(known) or 'none'} "
                          "(or give a path to a .toml file)")
    raise SimgapError(f"experiment file {s!r} does not exist")


def load_experiment(path_or_name: str | Path, profile: Optional[str] = DEFAULT_PROFILE,
                    overrides: Optional[dict] = None, system: Optional[System] = None, *,
                    text: Optional[str] = None) -> ExperimentConfig:
    """Load an experiment TOML, apply ``profile`` and ``overrides`` ({section: {key: value}}).

    ``system`` replaces what ``[system]`` names (its file is then not read): a results folder
    reopened after its system file is gone passes the model its data embed.

    ``profile`` None or ``"base"`` uses the top-level configuration as is; the default
    (:data:`DEFAULT_PROFILE`) is ``small`` when the file defines it, else the base.

    The whole file is checked against :mod:`simgap.schema` before anything runs: every profile
    (a typo in one that is not used is still an error), then the requested one with the
    overrides. Paths written in the file (``collect.out``, a ``synthesis.map`` file) are
    resolved against the file's folder and must stay inside it; ``collect.out`` given in
    ``overrides`` (the command line) is used as given.

    Raises SimgapError for a missing/unparsable file, an unknown profile, an unknown section or
    key (naming the nearest valid one), a badly typed value, an unknown system, a bad input set,
    or a path that leaves the experiment's folder.

    ``text``, if given, is the file's content (e.g. embedded in a results folder's summary.json):
    ``path_or_name`` is then only where it was (its name and folder), and need not exist.
    """
    path = Path(path_or_name) if text is not None else resolve_experiment(path_or_name)
    try:
        raw = tomllib.loads(text if text is not None else read_text(path, "experiment"))
    except tomllib.TOMLDecodeError as e:
        raise SimgapError(f"experiment {str(path)!r} is not valid TOML: {e}") from None
    except RecursionError:
        raise SimgapError(f"experiment {str(path)!r} nests too deeply (refused)") from None
    profiles = raw.pop("profiles", {})
    for table in [raw] + [p for p in (profiles.values() if isinstance(profiles, dict) else ()) if isinstance(p, dict)]:
        _system_shorthand(table)
    schema.check_profiles(profiles, f"experiment {path.name}")
    if profile == "base" or (isinstance(profile, DefaultProfile) and profile not in profiles):
        profile = None  # the top-level configuration without any profile
    if profile is not None and profile not in profiles:
        raise SimgapError(f"experiment {str(path)!r} has no profile {profile!r}; "
                          f"profiles: {', '.join(sorted(profiles)) or 'none'} (or base)")
    merged = _merge(raw, profiles[profile]) if profile else raw
    cli = {k: {kk: vv for kk, vv in v.items() if vv is not None} for k, v in (overrides or {}).items()}
    cli_out = cli.get("collect", {}).pop("out", None)
    merged = _merge(merged, cli)
    model = _validate(merged, path, profile, profiles.get(profile, {}) if profile else {})
    for name in sorted(set(profiles) - {profile}):  # typos in the other profiles are errors too
        _validate(_merge(raw, profiles[name]), path, name, profiles[name])
    where = f"experiment {path.name}" + (f" (profile {profile})" if profile else "")

    folder = path.resolve().parent
    out = None
    if cli_out is not None:
        out = str(cli_out)
    elif model.collect.out is not None:
        out = str(confined(model.collect.out, folder, f"{where}: collect.out"))
        merged["collect"]["out"] = out
    syn_map = model.synthesis.map
    if syn_map is not None and ("/" in syn_map or "\\" in syn_map or syn_map.endswith(".toml")):
        merged["synthesis"]["map"] = str(confined(syn_map, folder, f"{where}: synthesis.map"))
    if system is None:
        system = _system(model.system, where, folder)
    terms = (merged.get("certify") or {}).get("terms")
    if terms:  # keys name the system's states (or all, or 0-based numbers): checked with the system
        from .certify.basis import terms_by_dimension
        terms_by_dimension(terms, system, f"{where}: [certify] terms")
    _radii_match(merged.get("collect", {}), system, where)
    simulator = _simulator(model.simulator, merged["simulator"], system, where, folder)
    collect = _collect(model.collect, out)
    return ExperimentConfig(name=path.stem, profile=profile, path=path, system=system, simulator=simulator,
                            collect=collect, sections=merged, description=model.description)


def _system_shorthand(table: dict) -> None:
    """``system = "file.toml"`` (top level or in a profile) means ``[system] name = "file.toml"``."""
    if isinstance(table.get("system"), str):
        table["system"] = {"name": table["system"]}


def _validate(table: dict, path: Path, profile: Optional[str], ptable: dict) -> schema.Experiment:
    """Schema-check one merged configuration; errors name the table a key was written in."""
    def origin(loc: tuple) -> str:  # (section, key, ...) -> the table it was written in
        node = ptable
        for part in loc:
            if not isinstance(node, dict) or part not in node:
                return str(loc[0])
            node = node[part]
        return f"profiles.{profile}.{loc[0]}"

    where = f"experiment {path.name}" + (f" (profile {profile})" if profile else "")
    return schema.validate(table, where, origin)


def confined(value: str, folder: Path, what: str) -> Path:
    """``folder / value`` resolved; SimgapError if it leaves ``folder`` (also through symlinks)."""
    _no_nul(value, what)
    p = (folder / value).resolve()
    if not p.is_relative_to(folder):
        raise SimgapError(f"{what} {value!r} leads outside the experiment's folder {str(folder)!r}")
    return p


def _no_nul(value: str, what: str) -> None:
    """No path holds a NUL byte (the operating system cannot name such a file): refused by name."""
    if "\x00" in value:
        from .file_guard import printable
        raise SimgapError(f"{what} '{printable(value)}' contains a NUL byte (\\x00), which no file name can hold: "
                          "write the file's name without it")


def _system(d: schema.SystemSection, where: str, folder: Path) -> System:
    """A built-in or plugin system by name, or a system file (.toml) or refined-system JSON (in the
    experiment's folder), read once here: its content travels embedded in manifests, data sets,
    certificates and controllers from now on."""
    steps = d.steps if "steps" in d.model_fields_set else None  # unset: a system file's own steps (else 1)
    if is_named(d.name):
        s = get_system(d.name, steps=d.steps)
    elif d.name.endswith((".json", ".toml")):
        p = confined(d.name, folder, f"{where}: system.name")
        if not p.is_file():
            raise SimgapError(f"{where}: system file {d.name!r} does not exist in the experiment's folder "
                              f"{str(folder)!r}")
        try:
            s = resolve_system(p, steps=steps)
        except SimgapError as e:
            raise SimgapError(f"{where}: system.name: {e}") from None
    else:
        from . import plugins
        raise SimgapError(f"{where}: unknown system {d.name!r} in system.name; built-in systems: "
                          f"{', '.join(sorted(BUILTIN))}, a system file .toml or a refined-system .json"
                          + plugins.installed_note(plugins.SYSTEM_GROUP))
    if d.inputs is not None:
        U = np.array(d.inputs, dtype=float)
        if U.ndim == 1 and U.size and s.m == 1:
            U = U[:, None]
        if U.ndim != 2 or U.shape[0] == 0:
            raise SimgapError(f"{where}: system.inputs is empty or malformed (need a non-empty list of "
                              f"{s.m}-vectors)")
        if U.shape[1] != s.m:
            raise SimgapError(f"{where}: system.inputs has {U.shape[1]} components, system {s.name!r} has {s.m}")
        s = dataclasses.replace(s, inputs=U)
    elif d.input_grid is not None:
        g = d.input_grid
        if not (len(g.lo) == len(g.hi) == len(g.counts) == s.m):
            raise SimgapError(f"{where}: system.input_grid needs lo, hi, counts with {s.m} entries each")
        s = dataclasses.replace(s, inputs=input_grid(g.lo, g.hi, g.counts))
    return s


def _radii_match(collect: dict, system: System, where: str) -> None:
    """``[collect] epsilon`` as a list: one radius per covered dimension, checked here by its own name
    (the schema turns the list into a ``spacing`` of twice the radii, which a cover would report)."""
    eps = collect.get("epsilon")
    if not isinstance(eps, list):
        return
    from .cover import _dim_index
    inv = set()
    for d in collect.get("invariant_dims", []):
        try:
            inv.add(_dim_index(system, d))
        except SimgapError:
            return  # the cover names the unknown dimension
    covered = [system.state_names[i] for i in range(system.n) if i not in inv]
    if len(eps) != len(covered):
        raise SimgapError(f"{where}: [collect] epsilon = {eps!r} gives {len(eps)} radii but the cover has "
                          f"{len(covered)} covered dimension(s) ({', '.join(covered)}): give one radius per covered "
                          f"dimension in that order, or one number for all")


def _simulator(d: schema.SimulatorSection, raw: dict, system: System, where: str, folder: Path) -> SimulatorConfig:
    if d.system not in (None, system.name, system.params.get("base_system")):
        raise SimgapError(f"{where}: simulator.system {d.system!r} differs from system.name {system.name!r}")
    if d.steps not in (None, system.steps):
        raise SimgapError(f"{where}: simulator.steps {d.steps!r} differs from system.steps {system.steps}")
    try:
        simulator_class(d.kind)
    except SimgapError as e:
        raise SimgapError(f"{where}: simulator.kind: {e}") from None
    options = _model_files(d.kind, dict(raw.get("options", {})), folder, where)
    return SimulatorConfig(kind=d.kind, system=system.name, steps=system.steps, noise=dict(d.noise),
                           randomize=dict(d.randomize), effects=dict(d.effects), options=options)


def _model_files(kind: str, options: dict, folder: Path, where: str) -> dict:
    """The simulator's model-file options (its ``PATH_OPTIONS``) resolved inside the experiment's
    folder, each with the file's sha256 (``<key>_sha256``) so that a later command that rebuilds
    the simulator from a manifest notices a changed file."""
    for key in getattr(simulator_class(kind), "PATH_OPTIONS", ()):
        if key not in options:
            continue
        if not isinstance(options[key], str) or not options[key]:
            raise SimgapError(f"{where}: simulator.options.{key} must be a file name, got {options[key]!r}")
        p = _model_path(options[key], folder, f"{where}: simulator.options.{key}")
        if not p.is_file():
            raise SimgapError(f"{where}: simulator.options.{key}: model file {str(p)!r} does not exist")
        options[key] = str(p)
        options[f"{key}_sha256"] = hashlib.sha256(p.read_bytes()).hexdigest()
    return options


#: a model-file option starting so names a file of the installed pybullet_data package
PYBULLET_DATA = "pybullet_data:"


def _model_path(value: str, folder: Path, what: str) -> Path:
    """A model file inside the experiment's folder, or, spelled ``pybullet_data:<path>``, inside the
    installed ``pybullet_data`` package (PyBullet's robot files, meshes next to them), confined there."""
    _no_nul(value, what)
    if not value.startswith(PYBULLET_DATA):
        return confined(value, folder, what)
    try:
        import pybullet_data
    except ImportError:
        raise SimgapError(f"{what} {value!r} needs the pybullet_data package (installed with pybullet: "
                          "pip install pybullet)") from None
    root = Path(pybullet_data.getDataPath()).resolve()
    p = (root / value[len(PYBULLET_DATA):]).resolve()
    if not p.is_relative_to(root):
        raise SimgapError(f"{what} {value!r} leads outside pybullet_data's folder {str(root)!r}")
    return p


def _collect(d: schema.CollectSection, out: Optional[str]) -> CollectSettings:
    return CollectSettings(
        epsilon=float(d.epsilon), n_runs=d.n_runs, seed=d.seed,
        spacing=None if d.spacing is None else tuple(d.spacing), invariant_dims=tuple(d.invariant_dims),
        fixed=dict(d.fixed), region={k: list(v) for k, v in d.region.items()}, chunk_size=d.chunk_size, batch_runs=d.batch_runs, keep_samples=d.keep_samples,
        tube_margin=None if d.tube_margin is None else tuple(np.atleast_1d(d.tube_margin).tolist()),
        budget_runs=d.budget_runs, budget_minutes=d.budget_minutes,
        executor=d.executor, workers=d.workers or None, address=d.address, out=out)

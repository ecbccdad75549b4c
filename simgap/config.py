"""Experiment configurations: TOML files with a base configuration and named profiles.

Schema (``assets/experiments/pendulum.toml`` is a complete example)::

    description = "..."                      # optional
    [system]      name, steps, inputs (list of input vectors) or input_grid = {lo, hi, counts}
    [simulator]   kind, noise, randomize, effects, options      (see simgap.simulators)
    [collect]     epsilon, spacing, invariant_dims, fixed, n_runs, seed, chunk_size, batch_runs,
                  keep_samples, executor, workers, address, out
    [certify], [synthesis], [rollout], ...   other stages' sections, kept as plain dicts
    [profiles.<name>.<section>]              overrides any key of <section> for that profile

A profile is merged over the base key by key (nested tables merge recursively), then explicit
overrides (CLI flags) are merged over the profile. Only ``system``, ``simulator`` and
``collect`` are validated here; other sections are returned untouched in ``sections``.
"""

from __future__ import annotations

import copy
import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from .collect import DEFAULT_BATCH_RUNS, CollectionPlan, _int
from .cover import Cover, CoverSpec, make_cover
from .errors import SimgapError
from .paths import ASSETS_DIR
from .executors import EXECUTORS
from .simulators.base import SimulatorConfig
from .systems import System, get_system, input_grid

EXPERIMENTS_DIR = ASSETS_DIR / "experiments"

SYSTEM_KEYS = {"name", "steps", "inputs", "input_grid"}
SIMULATOR_KEYS = {"kind", "noise", "randomize", "effects", "options", "system", "steps"}
COLLECT_KEYS = {"epsilon", "spacing", "invariant_dims", "fixed", "n_runs", "seed", "chunk_size", "batch_runs",
                "keep_samples", "executor", "workers", "address", "out"}


@dataclass
class CollectSettings:
    """The ``[collect]`` section: the cover, N1hat, the seed, chunking and where to run."""

    epsilon: float
    n_runs: int
    seed: int = 0
    spacing: Optional[tuple] = None
    invariant_dims: tuple = ()
    fixed: dict = field(default_factory=dict)
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
                         fixed=dict(c.fixed))

    def cover(self) -> Cover:
        return make_cover(self.system, self.cover_spec())

    def plan(self, cover: Optional[Cover] = None) -> CollectionPlan:
        """The :class:`~simgap.collect.CollectionPlan` this experiment describes."""
        c = self.collect
        return CollectionPlan(system=self.system, simulator=self.simulator, cover=cover or self.cover(),
                              n_runs=c.n_runs, seed=c.seed, chunk_size=c.chunk_size, batch_runs=c.batch_runs,
                              keep_samples=c.keep_samples)

    def store_dir(self) -> Path:
        """Where the data go: ``collect.out`` or ``runs/<name>-<profile>/data`` (relative to cwd)."""
        if self.collect.out:
            return Path(self.collect.out)
        return Path("runs") / f"{self.name}-{self.profile or 'base'}" / "data"


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


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
        known = sorted(x.stem for x in EXPERIMENTS_DIR.glob("*.toml"))
        raise SimgapError(f"unknown experiment {s!r}; built-in experiments: {', '.join(known) or 'none'} "
                          "(or give a path to a .toml file)")
    raise SimgapError(f"experiment file {s!r} does not exist")


def load_experiment(path_or_name: str | Path, profile: Optional[str] = "small",
                    overrides: Optional[dict] = None) -> ExperimentConfig:
    """Load an experiment TOML, apply ``profile`` and ``overrides`` ({section: {key: value}}).

    ``profile`` None or ``"base"`` uses the top-level configuration as is.

    Raises SimgapError for a missing/unparsable file, an unknown profile, unknown or badly
    typed keys in [system]/[simulator]/[collect], an unknown system, or a bad input set.
    """
    path = resolve_experiment(path_or_name)
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise SimgapError(f"experiment {str(path)!r} is not valid TOML: {e}") from None
    except OSError as e:
        raise SimgapError(f"experiment {str(path)!r} is unreadable: {e}") from None
    profiles = raw.pop("profiles", {})
    if not isinstance(profiles, dict):
        raise SimgapError(f"experiment {str(path)!r}: [profiles] must be a table")
    if profile == "base":  # the top-level configuration without any profile
        profile = None
    if profile is not None:
        if profile not in profiles:
            raise SimgapError(f"experiment {str(path)!r} has no profile {profile!r}; "
                              f"profiles: {', '.join(sorted(profiles)) or 'none'}")
        raw = _merge(raw, profiles[profile])
    if overrides:
        raw = _merge(raw, {k: {kk: vv for kk, vv in v.items() if vv is not None} for k, v in overrides.items()})
    where = f"experiment {path.name}" + (f" (profile {profile})" if profile else "")

    for sec in ("system", "simulator", "collect"):
        if not isinstance(raw.get(sec), dict):
            raise SimgapError(f"{where}: missing [{sec}] section")
    system = _system(raw["system"], where)
    simulator = _simulator(raw["simulator"], system, where)
    collect = _collect(raw["collect"], where)
    desc = raw.get("description", "")
    name = path.stem
    return ExperimentConfig(name=name, profile=profile, path=path, system=system, simulator=simulator,
                            collect=collect, sections=raw, description=str(desc))


def _unknown(d: dict, allowed: set, where: str, sec: str) -> None:
    bad = set(d) - allowed
    if bad:
        raise SimgapError(f"{where}: unknown keys in [{sec}]: {', '.join(sorted(bad))}; "
                          f"allowed: {', '.join(sorted(allowed))}")


def _system(d: dict, where: str) -> System:
    _unknown(d, SYSTEM_KEYS, where, "system")
    if "name" not in d:
        raise SimgapError(f"{where}: [system] needs a name")
    steps = d.get("steps", 1)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise SimgapError(f"{where}: system.steps must be an integer >= 1, got {steps!r}")
    s = get_system(str(d["name"]), steps=steps)
    if "inputs" in d and "input_grid" in d:
        raise SimgapError(f"{where}: give system.inputs or system.input_grid, not both")
    if "inputs" in d:
        try:
            U = np.array(d["inputs"], dtype=float)
        except (TypeError, ValueError):
            raise SimgapError(f"{where}: system.inputs is malformed (need a list of input vectors)") from None
        if U.ndim == 1 and U.size and s.m == 1:
            U = U[:, None]
        if U.ndim != 2 or U.shape[0] == 0:
            raise SimgapError(f"{where}: system.inputs is empty or malformed (need a non-empty list of "
                              f"{s.m}-vectors)")
        if U.shape[1] != s.m:
            raise SimgapError(f"{where}: system.inputs has {U.shape[1]} components, system {s.name!r} has {s.m}")
        s = dataclasses.replace(s, inputs=U)
    elif "input_grid" in d:
        g = d["input_grid"]
        try:
            lo, hi, counts = g["lo"], g["hi"], g["counts"]
            if not (len(lo) == len(hi) == len(counts) == s.m) or any(int(c) < 1 for c in counts):
                raise ValueError
            U = input_grid(lo, hi, counts)
        except (TypeError, ValueError, KeyError):
            raise SimgapError(f"{where}: system.input_grid needs lo, hi, counts with {s.m} entries each "
                              "(counts >= 1)") from None
        s = dataclasses.replace(s, inputs=U)
    return s


def _simulator(d: dict, system: System, where: str) -> SimulatorConfig:
    _unknown(d, SIMULATOR_KEYS, where, "simulator")
    if "kind" not in d:
        raise SimgapError(f"{where}: [simulator] needs a kind")
    if d.get("system", system.name) != system.name:
        raise SimgapError(f"{where}: simulator.system {d['system']!r} differs from system.name {system.name!r}")
    if d.get("steps", system.steps) != system.steps:
        raise SimgapError(f"{where}: simulator.steps {d['steps']!r} differs from system.steps {system.steps}")
    for k in ("noise", "randomize", "effects", "options"):
        if not isinstance(d.get(k, {}), dict):
            raise SimgapError(f"{where}: simulator.{k} must be a table")
    return SimulatorConfig(kind=str(d["kind"]), system=system.name, steps=system.steps,
                           noise=dict(d.get("noise", {})), randomize=dict(d.get("randomize", {})),
                           effects=dict(d.get("effects", {})), options=dict(d.get("options", {})))


def _collect(d: dict, where: str) -> CollectSettings:
    _unknown(d, COLLECT_KEYS, where, "collect")
    for k in ("epsilon", "n_runs"):
        if k not in d:
            raise SimgapError(f"{where}: [collect] needs {k}")
    eps = d["epsilon"]
    if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not eps > 0:
        raise SimgapError(f"{where}: collect.epsilon must be a number > 0, got {eps!r}")
    ex = d.get("executor", "local")
    if ex not in EXECUTORS:
        raise SimgapError(f"{where}: collect.executor must be one of {', '.join(EXECUTORS)}, got {ex!r}")
    inv = d.get("invariant_dims", [])
    fixed = d.get("fixed", {})
    if not isinstance(inv, list) or not isinstance(fixed, dict):
        raise SimgapError(f"{where}: collect.invariant_dims must be a list and collect.fixed a table")
    workers = d.get("workers")
    return CollectSettings(
        epsilon=float(eps),
        n_runs=_int(d["n_runs"], f"{where}: collect.n_runs", 2, f"{where}: collect.n_runs (N1hat) must be >= 2"),
        seed=_int(d.get("seed", 0), f"{where}: collect.seed", 0),
        spacing=None if d.get("spacing") is None else tuple(d["spacing"]),
        invariant_dims=tuple(inv), fixed=dict(fixed), chunk_size=d.get("chunk_size"),
        batch_runs=d.get("batch_runs", DEFAULT_BATCH_RUNS), keep_samples=bool(d.get("keep_samples", False)),
        executor=ex, workers=None if workers in (None, 0) else workers, address=d.get("address"),
        out=d.get("out"))

"""The stochastic simulator interface shared by every backend.

A simulator is the high-fidelity, stochastic map x+ ~ fhat(x, u, w): given B states, B inputs
and a seeded ``numpy.random.Generator`` it returns B next states after the system's sampling
time tau with the input held constant. All randomness w is drawn from that generator by
:meth:`Simulator.draw_noise`, and :meth:`Simulator.step_with_noise` is deterministic, so a
batched call gives exactly the rows a one-at-a-time call gives for the same draws (PyBullet
itself is deterministic).

Per-run parameters (``randomize``: masses, lengths, wheel radius, friction) are drawn by
:meth:`Simulator.draw_noise` like every other draw, i.e. afresh at every sampling period: the
Markov assumption the per-run interval MDP needs, but not how a real robot behaves, which keeps
its parameters for a whole run. ``randomize.per = "episode"`` selects persistent randomization:
rollouts draw the parameters once per episode (:meth:`Simulator.draw_episode`, the same draws
in the same order, only the parameter keys kept) and every step uses them in place of the
period's fresh draws (:meth:`Simulator.with_episode`); rows stay independent, so batched and
one-at-a-time runs give the same results for the same draws.

Simulators are built from a :class:`SimulatorConfig`, a plain JSON-able description, so worker
processes (local pool or Ray) can rebuild the same simulator and manifests can record it.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass, field
from typing import Dict, Optional

import numpy as np

from .. import entry_points
from ..errors import SimgapError
from ..systems import System, get_system
from ..typed import check_section


@dataclass(frozen=True)
class SimulatorConfig:
    """JSON-able description of a stochastic simulator.

    Attributes
    ----------
    kind : str
        Backend: ``numpy``, ``pybullet_pendulum``, ``pybullet_turtlebot``, ``pybullet_urdf``, ``mujoco``,
        or a kind an installed plugin registers (entry-point group ``simgap.simulators``, see
        :mod:`simgap.plugins`).
    system : str
        Name of the nominal system it simulates (its X, U, base_tau, names).
    steps : int
        Base periods per sampling period (tau = steps * base_tau), input held.
    noise : dict
        Per-run noise, e.g. ``actuation_std``, ``sensor_std``, ``process_std`` (backend keys).
    randomize : dict
        Per-run parameter randomization, e.g. ``{"mass": 0.05}`` (relative std; backend keys), and
        ``per``: ``"period"`` (default: redrawn every sampling period) or ``"episode"`` (drawn once
        per rollout; module docstring).
    effects : dict
        Undeclared effects the nominal model lacks, e.g. ``{"joint_damping": 0.05}``.
    options : dict
        Anything else the backend takes (e.g. ``map`` for the TurtleBot world).
    """

    kind: str
    system: str
    steps: int = 1
    noise: Dict = field(default_factory=dict)
    randomize: Dict = field(default_factory=dict)
    effects: Dict = field(default_factory=dict)
    options: Dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "SimulatorConfig":
        unknown = set(d) - {"kind", "system", "steps", "noise", "randomize", "effects", "options"}
        if unknown:
            raise SimgapError(f"simulator config: unknown keys {sorted(unknown)}")
        if "kind" not in d or "system" not in d:
            raise SimgapError("simulator config: needs 'kind' and 'system'")
        return cls(**{k: (dict(v) if isinstance(v, dict) else v) for k, v in d.items()})


class Simulator(ABC):
    """Batch interface of a stochastic simulator (see module docstring)."""

    #: keys each config section accepts; subclasses override
    NOISE_KEYS: tuple = ()
    RANDOMIZE_KEYS: tuple = ()
    EFFECT_KEYS: tuple = ()
    OPTION_KEYS: tuple = ()
    #: options naming a model file: an experiment file's value is resolved against its folder (and
    #: must stay inside it); the file's sha256 is recorded as option ``<key>_sha256`` and checked
    PATH_OPTIONS: tuple = ()
    #: keys of :meth:`draw_noise` that are per-run physical parameters (held for an episode with
    #: ``randomize.per = "episode"``); subclasses with ``randomize`` keys override
    PARAMETER_DRAWS: tuple = ()
    #: the type of each key, {section: {key: kind}} (kinds: :mod:`simgap.typed`), checked
    #: before the backend reads a value: ``base_pose = "false"`` is refused by name, never read as true
    TYPES: dict = {}

    def __init__(self, config: SimulatorConfig, system: System | None = None):
        self.config = config
        self.system = (system or get_system(config.system)).with_steps(config.steps)
        self.randomize_per = config.randomize.get("per", "period")
        if not isinstance(self.randomize_per, str) or self.randomize_per not in RANDOMIZE_PER:
            raise SimgapError(f"simulator {config.kind!r}: randomize.per must be one of {list(RANDOMIZE_PER)}, "
                              f"got {self.randomize_per!r}")
        if self.randomize_per == "episode" and not self.PARAMETER_DRAWS:
            raise SimgapError(f"simulator {config.kind!r}: randomize.per = 'episode' but this backend has no per-run "
                              f"parameters to hold")
        for section, allowed in (("noise", self.NOISE_KEYS), ("randomize", self.RANDOMIZE_KEYS + ("per",)),
                                 ("effects", self.EFFECT_KEYS), ("options", self.OPTION_KEYS)):
            bad = set(getattr(config, section)) - set(allowed)
            if bad:
                raise SimgapError(
                    f"simulator {config.kind!r}: unknown {section} keys {sorted(bad)}; allowed: {sorted(allowed)}")
            check_section(getattr(config, section), {"per": "name", **self.TYPES.get(section, {})}
                          if section == "randomize" else self.TYPES.get(section, {}), f"simulator.{section}")

    @property
    def per_episode(self) -> bool:
        """True if per-run parameters are held for a whole rollout (``randomize.per = "episode"``)."""
        return self.randomize_per == "episode"

    def draw_episode(self, B: int, rng: np.random.Generator) -> Dict[str, np.ndarray]:
        """Per-run parameters of B episodes: :meth:`draw_noise` (same draws, same order) with only
        the :attr:`PARAMETER_DRAWS` keys kept; empty unless ``randomize.per = "episode"``."""
        if not self.per_episode:
            return {}
        noise = self.draw_noise(B, rng)
        return {k: noise[k] for k in self.PARAMETER_DRAWS if k in noise}

    def with_episode(self, noise: Dict[str, np.ndarray], episode: Dict[str, np.ndarray] | None) -> Dict[str, np.ndarray]:
        """``noise`` (B rows) with its per-run parameters replaced by the episode's (B rows, aligned)."""
        return {**noise, **episode} if episode else noise

    @abstractmethod
    def draw_noise(self, B: int, rng: np.random.Generator) -> Dict[str, np.ndarray]:
        """Draw all randomness for B independent runs, each array with leading dimension B."""

    @abstractmethod
    def step_with_noise(self, x: np.ndarray, u: np.ndarray, noise: Dict[str, np.ndarray]) -> np.ndarray:
        """Deterministic next states (B,n) for states x (B,n), inputs u (B,m) and drawn noise."""

    def step(self, x: np.ndarray, u: np.ndarray, rng: np.random.Generator,
             episode: Dict[str, np.ndarray] | None = None, on_rows=None) -> np.ndarray:
        """B independent runs: next states (B,n) after tau from x (B,n) with u (B,m) held.

        ``episode``: per-run parameters (B rows, from :meth:`draw_episode`) used instead of this
        period's draws (which are still drawn, so the other draws do not depend on the mode).
        ``on_rows(done)``, if given, is called with the rows finished so far while the batch runs
        in parts (:meth:`step_with_noise_in_parts`): the same numbers as one call."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        if x.shape[0] != u.shape[0]:
            raise SimgapError(f"simulator: {x.shape[0]} states but {u.shape[0]} inputs")
        noise = self.with_episode(self.draw_noise(x.shape[0], rng), episode)
        out = self.step_with_noise(x, u, noise) if on_rows is None else \
            self.step_with_noise_in_parts(x, u, noise, on_rows)
        if not np.all(np.isfinite(out)):
            bad = int((~np.isfinite(out)).any(axis=1).sum())
            raise SimgapError(f"simulator {self.config.kind!r} returned NaN/inf for {bad} of {len(out)} runs")
        return out

    def step_with_noise_in_parts(self, x: np.ndarray, u: np.ndarray, noise: Dict[str, np.ndarray], on_rows,
                                 parts: int = 50, min_rows: int = 4096) -> np.ndarray:
        """:meth:`step_with_noise` in about ``parts`` slices of rows (at least ``min_rows`` each),
        calling ``on_rows(done)`` after each: for progress on a long batch. Every backend computes
        row i from (x_i, u_i, noise_i) alone, so the result is the one call's."""
        B = x.shape[0]
        size = max(int(min_rows), -(-B // max(1, int(parts))))
        out = None
        for a in range(0, B, size):
            b = min(B, a + size)
            part = self.step_with_noise(x[a:b], u[a:b], {k: v[a:b] for k, v in noise.items()})
            if out is None:
                out = np.empty((B,) + part.shape[1:], dtype=part.dtype)
            out[a:b] = part
            on_rows(b)
        return out if out is not None else self.step_with_noise(x, u, noise)

    def close(self) -> None:
        """Release backend resources (PyBullet client)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


RANDOMIZE_PER = ("period", "episode")

# kind -> "module:Class", imported lazily so that numpy-only users never import pybullet
_BACKENDS = {
    "numpy": "simgap.simulators.numpy_sim:NumpySimulator",
    "pybullet_pendulum": "simgap.simulators.pybullet_pendulum:PendulumSimulator",
    "pybullet_turtlebot": "simgap.simulators.pybullet_turtlebot:TurtlebotSimulator",
    "pybullet_urdf": "simgap.simulators.pybullet_urdf:UrdfSimulator",
    "mujoco": "simgap.simulators.mujoco_sim:MujocoSimulator",
}


def build_simulator(config: SimulatorConfig | dict, system: System | None = None) -> Simulator:
    """One simulator in this process from its config (a :class:`SimulatorConfig` or its dict).

    :func:`simgap.simulators.make_simulator` (module :mod:`simgap.simulators.factory`) adds the
    ``workers`` option on top; a helper process of :class:`simgap.simulators.parallel.ParallelSimulator`
    builds its simulator here.
    """
    if isinstance(config, dict):
        config = SimulatorConfig.from_dict(config)
    return simulator_class(config.kind)(config, system)


def simulator_class(kind: str) -> type:
    """The Simulator class of a built-in kind (imported lazily) or of an installed plugin."""
    target = _BACKENDS.get(kind) if isinstance(kind, str) else None
    if target is not None:
        mod, cls = target.split(":")
        return getattr(importlib.import_module(mod), cls)
    cls = load_plugin_simulator(kind) if isinstance(kind, str) else None
    if cls is None:
        raise SimgapError(f"unknown simulator kind {kind!r}; built-in: {', '.join(sorted(_BACKENDS))}"
                          + entry_points.installed_note(entry_points.SIMULATOR_GROUP, simulator_plugins()))
    return cls


def simulator_kinds() -> list:
    """Every simulator kind this installation offers: built-ins, then plugins."""
    return sorted(_BACKENDS) + sorted(simulator_plugins())


def simulator_plugins() -> dict:
    """kind -> :class:`simgap.entry_points.Plugin` of the installed simulator plugins (built-in kinds excluded)."""
    return entry_points.registered(entry_points.SIMULATOR_GROUP, _BACKENDS)


def load_plugin_simulator(kind: str) -> Optional[type]:
    """The Simulator class registered as ``kind``, or None when no installed plugin registers it."""
    if kind not in simulator_plugins():
        return None
    cls, plugin = entry_points.load(entry_points.SIMULATOR_GROUP, kind)
    if not (isinstance(cls, type) and issubclass(cls, Simulator)):
        raise SimgapError(f"plugin simulator {kind!r} ({plugin.origin()}) is not a subclass of "
                          f"simgap.simulators.Simulator")
    return cls


def as_vector(value, size: int, name: str) -> np.ndarray:
    """A scalar or length-``size`` sequence as a non-negative float vector."""
    v = np.broadcast_to(np.asarray(value, dtype=float), (size,)).copy() if np.ndim(value) == 0 \
        else np.asarray(value, dtype=float)
    if v.shape != (size,) or not np.all(np.isfinite(v)) or np.any(v < 0):
        raise SimgapError(f"{name}: need a non-negative scalar or {size} values, got {value!r}")
    return v

"""Obstacle maps for planar robots (the TurtleBot): one TOML file, used by synthesis, PyBullet and the GUI.

Map format (``assets/maps/<name>.toml``; every length in metres, angles in radians)::

    name = "arena"
    description = "free text"
    bounds = [0.0, 4.0, 0.0, 4.0]          # the arena [x_lo, x_hi, y_lo, y_hi]
    robot_radius = 0.1                     # optional, default 0; inflates obstacles for the spec
    initial_state = [3.5, 2.0, 1.5]        # (x, y, theta); extra components for other systems
    target = [0.2, 0.9, 0.2, 0.9]          # [x_lo, x_hi, y_lo, y_hi]
    obstacles = [                          # physical boxes [x_lo, x_hi, y_lo, y_hi]
      [1.6, 2.1, 0.0, 2.6],
    ]

Conventions
-----------
* Boxes are closed axis-aligned rectangles in the (x, y) plane, written [x_lo, x_hi, y_lo, y_hi],
  with x_lo < x_hi and y_lo < y_hi (a box of zero area is an error).
* ``obstacles`` are the *physical* boxes: the PyBullet world builds them as solid bodies
  (:attr:`ArenaMap.obstacle_boxes`). The robot's reference point is the centre of its base, so
  the specification avoids the obstacles grown by ``robot_radius`` on every side
  (:attr:`ArenaMap.inflated_obstacles`). The grown box contains the Minkowski sum of the box and
  a disc of that radius, so a centre outside every grown box means no contact.
* The spec of a system with state dimension n >= 2 lifts each planar box to n dimensions: the
  first two state components are (x, y); every other component (the heading) is unconstrained
  (-inf, inf). Staying in X is part of the spec anyway.
* The target must lie inside ``bounds`` and must not overlap a grown obstacle; the initial
  state must lie inside ``bounds`` and outside every grown obstacle. Obstacles may extend past
  ``bounds`` (walls).

Validation errors raise :class:`~simgap.errors.SimgapError` naming the map and the problem.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import List

import numpy as np

from .errors import SimgapError
from .paths import ASSETS_DIR
from .synthesis.spec import Box, Spec

#: where named maps live (repository assets, installed editable)
MAPS_DIR = ASSETS_DIR / "maps"

_KEYS = {"name", "description", "bounds", "robot_radius", "initial_state", "target", "obstacles"}


def _rect(value, what: str, src: str) -> np.ndarray:
    """Validate one planar box [x_lo, x_hi, y_lo, y_hi] -> (4,) float array."""
    try:
        r = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise SimgapError(f"map {src}: {what} must be 4 numbers [x_lo, x_hi, y_lo, y_hi], got {value!r}") from None
    if r.shape != (4,) or not np.all(np.isfinite(r)):
        raise SimgapError(f"map {src}: {what} must be 4 finite numbers [x_lo, x_hi, y_lo, y_hi], got {value!r}")
    if not (r[0] < r[1] and r[2] < r[3]):
        raise SimgapError(f"map {src}: {what} {r.tolist()} is empty (need x_lo < x_hi and y_lo < y_hi)")
    return r


def _overlap_area(a: np.ndarray, b: np.ndarray) -> float:
    """Area of the intersection of two planar boxes [x_lo, x_hi, y_lo, y_hi]."""
    w = min(a[1], b[1]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[2], b[2])
    return max(w, 0.0) * max(h, 0.0)


def _in_rect(p: np.ndarray, r: np.ndarray) -> bool:
    return bool(r[0] <= p[0] <= r[1] and r[2] <= p[1] <= r[3])


@dataclass(frozen=True, eq=False)
class ArenaMap:
    """A validated planar map (see the module docstring for the format and conventions).

    Attributes
    ----------
    name, description : str
    bounds : (4,) array
        Arena [x_lo, x_hi, y_lo, y_hi] [m].
    robot_radius : float
        Obstacles are grown by this much for the specification [m].
    initial_state : (k,) array
        Initial state; its first two components are (x, y) [m].
    target : (4,) array
        Target box [m].
    obstacles : (K, 4) array
        Physical obstacle boxes [m].
    source : str
        File the map came from (for messages and provenance).
    """

    name: str
    bounds: np.ndarray
    initial_state: np.ndarray
    target: np.ndarray
    obstacles: np.ndarray
    robot_radius: float = 0.0
    description: str = ""
    source: str = "<memory>"

    def __post_init__(self):
        src = self.source
        bounds = _rect(self.bounds, "bounds", src)
        target = _rect(self.target, "target", src)
        obs = [_rect(o, f"obstacle {i}", src) for i, o in enumerate(np.asarray(self.obstacles, dtype=float).reshape(-1, 4))] \
            if np.size(self.obstacles) else []
        obs = np.array(obs, dtype=float).reshape(-1, 4)
        r = float(self.robot_radius)
        if not (np.isfinite(r) and r >= 0):
            raise SimgapError(f"map {src}: robot_radius must be a finite number >= 0, got {self.robot_radius!r}")
        x0 = np.asarray(self.initial_state, dtype=float).ravel()
        if x0.size < 2 or not np.all(np.isfinite(x0)):
            raise SimgapError(f"map {src}: initial_state needs at least (x, y) as finite numbers, got {self.initial_state!r}")
        object.__setattr__(self, "bounds", bounds)
        object.__setattr__(self, "target", target)
        object.__setattr__(self, "obstacles", obs)
        object.__setattr__(self, "robot_radius", r)
        object.__setattr__(self, "initial_state", x0)

        # the target: inside the arena, not overlapping any grown obstacle
        if not (bounds[0] <= target[0] and target[1] <= bounds[1] and bounds[2] <= target[2] and target[3] <= bounds[3]):
            raise SimgapError(f"map {src}: target {target.tolist()} is not inside the arena bounds {bounds.tolist()}")
        grown = self.inflated_obstacles
        for i, g in enumerate(grown):
            if _overlap_area(target, g) > 0:
                raise SimgapError(
                    f"map {src}: target {target.tolist()} overlaps obstacle {i} {obs[i].tolist()}"
                    + (f" grown by robot_radius {r:g}" if r > 0 else ""))
        # the initial state: inside the arena, outside every grown obstacle
        if not _in_rect(x0, bounds):
            raise SimgapError(f"map {src}: initial_state {x0.tolist()} is outside the arena bounds {bounds.tolist()}")
        for i, g in enumerate(grown):
            if _in_rect(x0, g):
                raise SimgapError(
                    f"map {src}: initial_state {x0.tolist()} lies in obstacle {i} {obs[i].tolist()}"
                    + (f" grown by robot_radius {r:g}" if r > 0 else ""))

    # ----- derived geometry ---------------------------------------------------------------
    @property
    def inflated_obstacles(self) -> np.ndarray:
        """(K, 4) obstacles grown by ``robot_radius`` on every side: what the robot centre avoids."""
        r = self.robot_radius
        return self.obstacles + np.array([-r, r, -r, r])

    def clearance(self, xy: np.ndarray) -> np.ndarray:
        """Signed distance [m] from robot centres ``xy`` (..., >= 2; only x, y used) to the nearest
        grown obstacle (:attr:`inflated_obstacles`, what the specification avoids): the Euclidean
        distance outside, minus the depth inside (negative = the spec is violated there)."""
        p = np.asarray(xy, dtype=float)[..., None, :2]           # (..., 1, 2)
        g = self.inflated_obstacles                              # (K, 4)
        lo, hi = g[:, [0, 2]], g[:, [1, 3]]
        out = np.maximum(np.maximum(lo - p, p - hi), 0.0)        # per-axis distance outside
        inside = np.minimum(p - lo, hi - p).min(axis=-1)         # depth, > 0 only inside
        d = np.where(inside > 0, -inside, np.linalg.norm(out, axis=-1))
        return d.min(axis=-1) if g.shape[0] else np.full(p.shape[:-2], np.inf)

    @property
    def obstacle_boxes(self) -> List[List[float]]:
        """Physical obstacle boxes as plain lists [x_lo, x_hi, y_lo, y_hi] (PyBullet world)."""
        return [[float(v) for v in o] for o in self.obstacles]

    def simulator_options(self) -> dict:
        """``options`` for the PyBullet TurtleBot simulator config: the physical obstacles."""
        return {"obstacles": self.obstacle_boxes}

    # ----- specification ----------------------------------------------------------------
    def _lift(self, rect: np.ndarray, n: int) -> Box:
        lo = np.full(n, -np.inf)
        hi = np.full(n, np.inf)
        lo[:2] = rect[[0, 2]]
        hi[:2] = rect[[1, 3]]
        return Box(lo, hi)

    def spec(self, system) -> Spec:
        """Reach-avoid :class:`Spec` for ``system``: reach ``target``, avoid the grown obstacles.

        Boxes are lifted to the system's n dimensions with dimensions >= 2 unconstrained. Raises
        SimgapError when the system is not planar (n < 2) or the target leaves X.
        """
        n = system.n
        if n < 2:
            raise SimgapError(f"map {self.source}: system {system.name!r} has {n} state dimension(s); a map needs (x, y)")
        xl, xh = system.x_lo[:2], system.x_hi[:2]
        t = self.target
        if not (xl[0] <= t[0] and t[1] <= xh[0] and xl[1] <= t[2] and t[3] <= xh[1]):
            raise SimgapError(
                f"map {self.source}: target {t.tolist()} is not inside X of system {system.name!r} "
                f"([{xl[0]:g}, {xh[0]:g}] x [{xl[1]:g}, {xh[1]:g}])")
        return Spec(kind="reach_avoid", target=self._lift(t, n),
                    obstacles=tuple(self._lift(g, n) for g in self.inflated_obstacles))

    def x0(self, system) -> np.ndarray:
        """The initial state as an (n,) vector for ``system``, checked against X.

        A planar initial state (x, y) is padded with zeros for the remaining dimensions.
        """
        x0 = self.initial_state
        if x0.size > system.n:
            raise SimgapError(f"map {self.source}: initial_state has {x0.size} components, system {system.name!r} has {system.n}")
        x = np.zeros(system.n)
        x[:x0.size] = x0
        return system.check_states(x[None], what=f"map {self.source}: initial_state")[0]

    # ----- GUI ----------------------------------------------------------------------------
    def meshes(self, height: float = 0.3, inflated: bool = False) -> dict:
        """trimesh boxes for drawing: ``{"obstacles": [Trimesh, ...], "target": Trimesh}``.

        Obstacles are ``height`` tall (black), standing on z = 0; the target is a thin green slab
        (2 cm). With ``inflated=True`` the obstacles are the grown boxes the spec uses.
        """
        import trimesh

        def box(r, z0, z1, rgba):
            m = trimesh.creation.box(bounds=[[r[0], r[2], z0], [r[1], r[3], z1]])
            m.visual.face_colors = rgba
            return m

        obs = self.inflated_obstacles if inflated else self.obstacles
        return {"obstacles": [box(o, 0.0, height, [30, 30, 30, 255]) for o in obs],
                "target": box(self.target, 0.0, 0.02, [40, 180, 80, 200])}

    # ----- I/O ----------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON/TOML-ready description (the file format)."""
        return {"name": self.name, "description": self.description,
                "bounds": self.bounds.tolist(), "robot_radius": self.robot_radius,
                "initial_state": self.initial_state.tolist(), "target": self.target.tolist(),
                "obstacles": self.obstacles.tolist()}

    @classmethod
    def from_dict(cls, d: dict, source: str = "<memory>") -> "ArenaMap":
        if not isinstance(d, dict):
            raise SimgapError(f"map {source}: expected a table of keys, got {type(d).__name__}")
        unknown = set(d) - _KEYS
        if unknown:
            raise SimgapError(f"map {source}: unknown keys {sorted(unknown)}; allowed: {sorted(_KEYS)}")
        missing = [k for k in ("bounds", "initial_state", "target") if k not in d]
        if missing:
            raise SimgapError(f"map {source}: missing keys {missing}")
        obstacles = d.get("obstacles", [])
        if not isinstance(obstacles, (list, tuple)):
            raise SimgapError(f"map {source}: obstacles must be a list of [x_lo, x_hi, y_lo, y_hi] boxes")
        return cls(name=str(d.get("name", Path(source).stem)), description=str(d.get("description", "")),
                   bounds=d["bounds"], robot_radius=d.get("robot_radius", 0.0),
                   initial_state=d["initial_state"], target=d["target"],
                   obstacles=[_rect(o, f"obstacle {i}", source) for i, o in enumerate(obstacles)],
                   source=source)


def available_maps() -> List[str]:
    """Names of the maps shipped in ``assets/maps``."""
    return sorted(p.stem for p in MAPS_DIR.glob("*.toml"))


def load_map(path_or_name) -> ArenaMap:
    """Load and validate a map: a path to a ``.toml`` file, or the name of a shipped map (``arena``)."""
    p = Path(path_or_name)
    if not p.suffix and not p.exists():
        p = MAPS_DIR / f"{path_or_name}.toml"
        if not p.exists():
            raise SimgapError(f"unknown map {str(path_or_name)!r}; shipped maps: {', '.join(available_maps()) or 'none'}")
    if not p.is_file():
        raise SimgapError(f"map file {str(p)!r} does not exist")
    try:
        with open(p, "rb") as fh:
            d = tomllib.load(fh)
    except tomllib.TOMLDecodeError as e:
        raise SimgapError(f"map {p}: not valid TOML: {e}") from None
    return ArenaMap.from_dict(d, source=str(p))

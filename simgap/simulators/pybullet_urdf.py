"""A stochastic PyBullet simulator for any URDF: chosen joints are the state, chosen joints the input.

The experiment names the robot file (``options.urdf``, a path confined to the experiment's
folder, see :func:`simgap.config.load_experiment`) and which of its joints make the state and
the input. The state vector x is, in this order,

* the planar base pose (x [m], y [m], yaw [rad]) when ``options.base_pose = true`` (a mobile
  base; the base is then not fixed), then its forward speed along the heading [m/s] and yaw
  rate [rad/s] when ``options.base_velocity = true`` (the base starts each period moving so),
* the positions of the joints named in ``options.positions`` [rad or m],
* the velocities of the joints named in ``options.velocities`` [rad/s or m/s];

the input u drives the joints named in ``options.inputs``: by torque/force
(``input_mode = "torque"``, N m or N, re-applied every physics step), by velocity target
(``input_mode = "velocity"``, rad/s or m/s, a velocity motor of maximum force
``options.max_force``) or by position target (``input_mode = "position"``, rad or m: Bullet's
POSITION_CONTROL motor of maximum force ``options.max_force``, position gain
``options.position_gain`` (default 0.1, Bullet's) and velocity gain ``options.velocity_gain``
(default 1.0)). ``input_mode`` may also be a list, one mode per entry of ``options.inputs`` (a
car: its wheels by velocity, its steering hinges by position); ``max_force`` likewise a number or
one per entry.

One sampling period: every movable joint is reset (state joints to x, the others to 0 at rest),
a mobile base is placed at (x, y, yaw) at ``options.base_height`` at rest, the input is held for
``steps * substeps`` Bullet steps of dt = base_tau / substeps, and the state is read back (and
wrapped where the system says a dimension is an angle). Degrees of freedom that are not in the
state (base velocity, other joints) start at rest in every period: a URDF whose behaviour over
one period depends on them needs them in the state. With ``options.driven_start = "target"``
(velocity mode) the driven joints start each period at their velocity targets instead of at
rest (a wheel already turning as commanded, consistent with a base in ``base_velocity``).

Batching: ``options.copies`` copies of the robot share one world, all at the same place, with
collisions between copies filtered out (with ``options.ground`` they still touch the ground
plane); a batch runs ``copies`` rows at a time. Copies do not interact and every row is reset
completely (contact caches dropped by re-inserting the collision objects), so each row's result
depends on its own (x, u, noise) only: batched and one-at-a-time are bit-identical (tested).

Joints that keep their state across periods: a joint named in ``options.positions`` (or
``velocities``) is part of x, so every period starts where the previous one left it, also a
joint the input drives (a steering hinge in the state and driven by position: its angle is a
state dimension and the command moves it). A driven joint outside the state starts each period
at rest at 0, or, with ``driven_start = "target"``, at its target: a velocity-driven joint
turning at the commanded speed, a position-driven joint at the commanded position (at rest);
that is what it keeps between periods when the input stays the same (docs/simulators.md).

Randomness (all drawn by :meth:`draw_noise` from the caller's generator, once per run):

* ``noise.actuation_std``: scalar or one per input, u -> u + a, held for tau;
* ``noise.sensor_std``: scalar or one per state dimension, added to the read-back state;
* ``noise.process_std``: scalar or one per state dimension, added to the state after every base
  period (the state is read, perturbed and reset; joints not in the state keep their motion);
* ``randomize.mass`` (relative std): each link's mass and inertia times 1 + s z (z ~ N(0,1)
  clipped to +-3, a factor per link and run);
* ``randomize.joint_damping`` (relative std): each movable joint's damping times 1 + s z;
* ``randomize.friction`` (relative std): each link's lateral friction times 1 + s z.

Computed-torque inner loop (``options.inner_loop = "computed_torque"``): u (through ``input_map`` when
given) is the commanded joint acceleration a [rad/s^2 or m/s^2] of every movable joint (``options.inputs``
names them all; fixed base, torque mode). In every Bullet step the applied torque is

    tau = ID(q, qdot, a + a_noise) + c qdot + n,   clipped to the URDF's effort limits,

ID the recursive Newton-Euler inverse dynamics of the same URDF (``calculateInverseDynamics`` on a
reference copy in a client of its own: randomized masses or damping of the simulated copies are not
known to it), c the URDF's joint damping (which Bullet applies and ID leaves out), n ~ N(0,
``noise.torque_std``^2) per driven joint [N m], held for tau. Noise-free and unclipped, Bullet's
semi-implicit Euler steps then give qdot+ = qdot + tau a, q+ = q + tau qdot + tau^2 a (N + 1) / (2 N)
for N = ``steps * substeps`` steps: the double integrator per joint up to tau^2 a / (2 N) in q (tested).

Undeclared effects: ``effects.joint_damping`` [N m s/rad] adds viscous damping to every movable
joint (Bullet's joint damping: the explicit torque -c qdot in each physics step);
``effects.actuator_gain`` k scales the applied input: k (u + a).
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path
from typing import Dict, List

import numpy as np

from ..errors import SimgapError
from ._bullet import (BulletSimulator, bullet_client, capture_c_output, check_std, inertia_note, int_option,
                      links_without_inertia, pybullet_module, relative_factors)
from .base import as_vector
from ..typed import flag

MAX_COPIES = 256


def model_file(value, digest, what: str) -> Path:
    """The model file an option names (absolute after :func:`simgap.config.load_experiment`);
    SimgapError if it is missing or its sha256 differs from the recorded ``digest``."""
    if not isinstance(value, str) or not value:
        raise SimgapError(f"{what}: need the path of a model file, got {value!r}")
    path = Path(value).resolve()
    if not path.is_file():
        raise SimgapError(f"{what}: model file not found: {path}")
    if digest is not None:
        got = hashlib.sha256(path.read_bytes()).hexdigest()
        if got != digest:
            raise SimgapError(f"{what}: {path} changed since it was recorded (sha256 {got[:12]}..., "
                              f"recorded {str(digest)[:12]}...)")
    return path


def name_list(value, what: str) -> List[str]:
    """A list of names from a config value (a string is one name)."""
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) and v for v in value):
        raise SimgapError(f"{what}: need a list of names, got {value!r}")
    twice = sorted({v for v in value if list(value).count(v) > 1})
    if twice:  # two state components or two inputs on one joint: one would silently overwrite the other
        raise SimgapError(f"{what} names {', '.join(map(repr, twice))} twice; each joint once (one input per "
                          "joint: two inputs on one joint would overwrite each other)")
    return list(value)


def input_map(value, joints: List[str], system, backend: str = "pybullet_urdf", what: str = "joints"):
    """The (joints, m) matrix of ``options.input_map`` (a joint's target or an actuator's ctrl =
    its row . u), or None when the inputs drive one each (``options.inputs`` then names m)."""
    m, J = system.m, len(joints)
    if value is None:
        if J != m:
            raise SimgapError(f"{backend}: options.inputs names {J} {what} but system {system.name!r} has m={m} "
                              f"inputs; to drive {J} {what} from {m} inputs give options.input_map, one row of {m} "
                              f"coefficients per entry of options.inputs")
        return None
    try:
        A = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise SimgapError(f"{backend}: options.input_map must be a matrix of numbers, got {value!r}") from None
    if A.shape != (J, m):
        raise SimgapError(f"{backend}: options.input_map is {'x'.join(map(str, A.shape)) or 'a scalar'} but must be "
                          f"{J} x {m}: one row per entry of options.inputs ({', '.join(joints)}), one column per "
                          f"input of {system.name!r} ({', '.join(system.input_names)})")
    if not np.all(np.isfinite(A)):
        raise SimgapError(f"{backend}: options.input_map has a NaN or infinite entry")
    if np.linalg.matrix_rank(A) < m:
        raise SimgapError(f"{backend}: options.input_map has rank {np.linalg.matrix_rank(A)} < {m} inputs: two "
                          f"inputs would move the {what} alike (their gap could not be told apart)")
    return A


INPUT_MODES = ("torque", "velocity", "position")
INNER_LOOPS = ("none", "computed_torque")


def input_modes(value, joints: List[str]) -> List[str]:
    """One drive mode per driven joint from ``options.input_mode`` (one mode for all, or a list)."""
    if isinstance(value, str):
        value = [value] * len(joints)
    if not isinstance(value, (list, tuple)) or len(value) != len(joints):
        raise SimgapError(f"pybullet_urdf: options.input_mode must be one of {', '.join(INPUT_MODES)} or a list of "
                          f"them, one per entry of options.inputs ({len(joints)}), got {value!r}")
    bad = [v for v in value if v not in INPUT_MODES]
    if bad:
        raise SimgapError(f"pybullet_urdf: options.input_mode {bad[0]!r} is not one of {', '.join(INPUT_MODES)}")
    return list(value)


def per_input(value, joints: List[str], what: str) -> np.ndarray:
    """A non-negative number per driven joint from a number or a list of them (one per joint)."""
    vals = value if isinstance(value, (list, tuple)) else [value] * len(joints)
    if len(vals) != len(joints):
        raise SimgapError(f"pybullet_urdf: {what} must be a number or {len(joints)} numbers (one per entry of "
                          f"options.inputs), got {value!r}")
    return np.array([check_std(v, what) for v in vals])


_REPORTED: set = set()


def _report_load(path, no_inertia: list, rest: list) -> None:
    """Say once per process and robot file what loading it assumed (the links PyBullet gave 1 kg)
    and pass on anything else it printed; worker processes stay quiet (the main process said it)."""
    import multiprocessing
    key = str(path)
    if key in _REPORTED or multiprocessing.parent_process() is not None:
        return
    _REPORTED.add(key)
    lines = ([inertia_note(no_inertia, path)] if no_inertia else []) + list(dict.fromkeys(rest))
    for k, line in enumerate(lines):
        print(f"note: {line}" if k == 0 and no_inertia else line, file=sys.stderr, flush=True)


class UrdfSimulator(BulletSimulator):
    """Batched stochastic PyBullet simulator of a URDF (see module docstring for the keys)."""

    NOISE_KEYS = ("actuation_std", "sensor_std", "process_std", "torque_std")
    RANDOMIZE_KEYS = ("mass", "joint_damping", "friction")
    PARAMETER_DRAWS = ("mass", "damping", "friction")  # draw_noise keys held for an episode (randomize.per)
    EFFECT_KEYS = ("joint_damping", "actuator_gain")
    OPTION_KEYS = ("urdf", "urdf_sha256", "positions", "velocities", "inputs", "input_map", "input_mode", "max_force",
                   "position_gain", "velocity_gain",
                   "base_pose", "base_velocity", "driven_start", "base_height", "fixed_base", "ground", "substeps",
                   "copies", "gravity", "cone_friction", "inner_loop")
    TYPES = {"noise": dict.fromkeys(NOISE_KEYS, "numbers"), "randomize": dict.fromkeys(RANDOMIZE_KEYS, "number"),
             "effects": dict.fromkeys(EFFECT_KEYS, "number"),
             "options": {"urdf": "name", "urdf_sha256": "name", "positions": "names", "velocities": "names",
                         "inputs": "names", "input_map": "matrix", "input_mode": "names", "max_force": "numbers", "position_gain": "number", "velocity_gain": "number",
                         "base_pose": "bool", "base_velocity": "bool", "driven_start": "name", "base_height": "number",
                         "fixed_base": "bool", "ground": "bool", "substeps": "int", "copies": "int",
                         "gravity": "number", "cone_friction": "bool", "inner_loop": "name"}}
    #: options naming a file: resolved against (and confined to) the experiment's folder
    PATH_OPTIONS = ("urdf",)

    def __init__(self, config, system=None):
        super().__init__(config, system)
        s = self.system
        nz, rz, ef, op = config.noise, config.randomize, config.effects, config.options
        if "urdf" not in op:
            raise SimgapError("pybullet_urdf: options.urdf (the robot file) is required")
        self.path = model_file(op["urdf"], op.get("urdf_sha256"), "pybullet_urdf options.urdf")
        self.pos_names = name_list(op.get("positions", []), "options.positions")
        self.vel_names = name_list(op.get("velocities", []), "options.velocities")
        self.in_names = name_list(op.get("inputs", []), "options.inputs")
        where = "simulator.options"  # every value's type was checked by Simulator.__init__ (TYPES); flag() again
        self.base_pose = flag(op, "base_pose", False, where)
        self.fixed_base = flag(op, "fixed_base", not self.base_pose, where)
        if self.base_pose and self.fixed_base:
            raise SimgapError("pybullet_urdf: base_pose needs a mobile base (fixed_base = false)")
        self.base_velocity = flag(op, "base_velocity", False, where)
        if self.base_velocity and not self.base_pose:
            raise SimgapError("pybullet_urdf: base_velocity (forward speed and yaw rate in the state) needs "
                              "base_pose = true")
        self.nb = 3 * self.base_pose + 2 * self.base_velocity  # base components at the front of x
        n = self.nb + len(self.pos_names) + len(self.vel_names)
        if n != s.n:
            raise SimgapError(f"pybullet_urdf: the state has {n} components (base {self.nb}, "
                              f"{len(self.pos_names)} positions, {len(self.vel_names)} velocities) but system "
                              f"{s.name!r} has n={s.n}")
        self.input_map = input_map(op.get("input_map"), self.in_names, s)
        self.modes = input_modes(op.get("input_mode", "torque"), self.in_names)
        self.mode = self.modes[0] if len(set(self.modes)) == 1 else "mixed"
        self.driven_start = op.get("driven_start", "rest")
        if self.driven_start not in ("rest", "target"):
            raise SimgapError(f"pybullet_urdf: options.driven_start must be 'rest' or 'target', got "
                              f"{self.driven_start!r}")
        if self.driven_start == "target" and "torque" in self.modes:
            raise SimgapError("pybullet_urdf: driven_start = 'target' (driven joints start at their velocity or "
                              "position targets) needs input_mode 'velocity' or 'position' for every input; "
                              f"{self.in_names[self.modes.index('torque')]!r} is torque-driven")
        self.max_forces = per_input(op.get("max_force", 10.0), self.in_names, "options.max_force")
        self.max_force = float(self.max_forces.max()) if len(self.max_forces) else 10.0
        self.position_gain = check_std(op.get("position_gain", 0.1), "options.position_gain")
        self.velocity_gain = check_std(op.get("velocity_gain", 1.0), "options.velocity_gain")
        self.act_std = as_vector(nz.get("actuation_std", 0.0), s.m, "noise.actuation_std")
        self.sens_std = as_vector(nz.get("sensor_std", 0.0), s.n, "noise.sensor_std")
        self.proc_std = as_vector(nz.get("process_std", 0.0), s.n, "noise.process_std")
        self.mass_std = check_std(rz.get("mass", 0.0), "randomize.mass", 0.3)
        self.damp_std = check_std(rz.get("joint_damping", 0.0), "randomize.joint_damping", 0.3)
        self.fric_std = check_std(rz.get("friction", 0.0), "randomize.friction", 0.3)
        self.extra_damping = check_std(ef.get("joint_damping", 0.0), "effects.joint_damping")
        self.gain = check_std(ef.get("actuator_gain", 1.0), "effects.actuator_gain")
        self.substeps = int_option(op.get("substeps", 1), "options.substeps", 1, 1000)
        self.copies = int_option(op.get("copies", 16), "options.copies", 1, MAX_COPIES)
        self.base_height = float(op.get("base_height", 0.0))
        self.g = check_std(op.get("gravity", s.params.get("g", 9.81)), "options.gravity")
        self.dt = s.base_tau / self.substeps
        self.cone_friction = op.get("cone_friction", True)
        if not isinstance(self.cone_friction, bool):
            raise SimgapError(f"pybullet_urdf: options.cone_friction must be true or false, got {self.cone_friction!r}")
        self.inner_loop = op.get("inner_loop", "none")
        if self.inner_loop not in INNER_LOOPS:
            raise SimgapError(f"pybullet_urdf: options.inner_loop must be one of {', '.join(map(repr, INNER_LOOPS))}, "
                              f"got {self.inner_loop!r}")
        self.torque_std = per_input(nz.get("torque_std", 0.0), self.in_names, "noise.torque_std")
        if self.inner_loop == "computed_torque":
            if not self.fixed_base or self.base_pose:
                raise SimgapError("pybullet_urdf: options.inner_loop = 'computed_torque' needs a fixed base "
                                  "(the inverse dynamics of a floating base is not a joint torque per input)")
            if self.mode != "torque":
                raise SimgapError("pybullet_urdf: options.inner_loop = 'computed_torque' drives the joints by torque; "
                                  f"drop options.input_mode {op.get('input_mode')!r} (the inputs are joint accelerations)")
        elif np.any(self.torque_std > 0):
            raise SimgapError("pybullet_urdf: noise.torque_std is added to a computed torque: it needs options.inner_loop "
                              "= 'computed_torque' (for noise on a torque input use noise.actuation_std)")
        self._build(flag(op, "ground", False, where))

    # ----- construction ------------------------------------------------------------------
    def _build(self, ground: bool) -> None:
        pb = pybullet_module()
        c = self._client = bullet_client(self.dt, self.g, deterministic_pairs=ground)
        if not self.cone_friction:  # Bullet's pyramid approximation: two friction directions per contact
            c.setPhysicsEngineParameter(enableConeFriction=0)
        self._pb, self._cid = pb, c._client
        flags = pb.URDF_USE_INERTIA_FROM_FILE
        try:
            with capture_c_output() as said:  # PyBullet warns per link and per copy, on the C streams
                bodies = [c.loadURDF(str(self.path), basePosition=[0, 0, self.base_height],
                                     useFixedBase=self.fixed_base, flags=flags) for _ in range(self.copies)]
        except pb.error as e:
            raise SimgapError(f"pybullet_urdf: cannot load {self.path}: {e}") from None
        self.links_without_inertia, rest = links_without_inertia(said[0] if said else "")
        _report_load(self.path, self.links_without_inertia, rest)
        self.bodies = bodies
        b0 = bodies[0]
        nj = c.getNumJoints(b0)
        infos = [c.getJointInfo(b0, j) for j in range(nj)]
        by_name = {i[1].decode(): i for i in infos}
        movable = [i for i in infos if i[2] in (pb.JOINT_REVOLUTE, pb.JOINT_PRISMATIC)]
        self.movable = [i[0] for i in movable]
        names = sorted(i[1].decode() for i in movable)

        def index(name, what):
            i = by_name.get(name)
            if i is None or i[0] not in self.movable:
                raise SimgapError(f"pybullet_urdf: {self.path.name} has no revolute/prismatic joint {name!r} "
                                  f"(named in options.{what}); its movable joints: {', '.join(names) or 'none'}")
            return i[0]

        self.pos_idx = [index(nm, "positions") for nm in self.pos_names]
        self.vel_idx = [index(nm, "velocities") for nm in self.vel_names]
        self.in_idx = [index(nm, "inputs") for nm in self.in_names]
        # per-joint slots in the reset lists (every movable joint is reset each period)
        slot = {j: k for k, j in enumerate(self.movable)}
        self._pos_slot, self._vel_slot = [slot[j] for j in self.pos_idx], [slot[j] for j in self.vel_idx]
        self.links = ([-1] if not self.fixed_base else []) + list(range(nj))
        self.mass0 = np.array([c.getDynamicsInfo(b0, l)[0] for l in self.links])
        self.inertia0 = np.array([c.getDynamicsInfo(b0, l)[2] for l in self.links])
        self.friction0 = np.array([c.getDynamicsInfo(b0, l)[1] for l in self.links])
        self.damping0 = np.array([infos[j][6] for j in self.movable]) + self.extra_damping
        self._base0 = c.getBasePositionAndOrientation(b0)
        if ground:
            plane = c.createCollisionShape(pb.GEOM_PLANE)
            self.ground = c.createMultiBody(0, plane)
            c.setCollisionFilterGroupMask(self.ground, -1, 1, 2)
        for b in bodies:
            c.changeDynamics(b, -1, linearDamping=0.0, angularDamping=0.0,
                             activationState=pb.ACTIVATION_STATE_DISABLE_SLEEPING)
            for k, j in enumerate(self.movable):
                c.changeDynamics(b, j, linearDamping=0.0, angularDamping=0.0, jointDamping=float(self.damping0[k]))
            for l in [-1] + list(range(nj)):  # copies touch the ground (group 1) only, never each other
                c.setCollisionFilterGroupMask(b, l, 2, 1 if ground else 0)
            # the default velocity motors would act as stiff friction: off on every movable joint
            c.setJointMotorControlArray(b, self.movable, pb.VELOCITY_CONTROL,
                                        targetVelocities=[0.0] * len(self.movable), forces=[0.0] * len(self.movable))
        self._ground = ground
        if self.inner_loop == "computed_torque":
            self._build_inverse_dynamics(infos)
        self._per_row_dynamics = self.mass_std > 0 or self.damp_std > 0 or self.fric_std > 0
        self._process = bool(np.any(self.proc_std > 0))

    def _build_inverse_dynamics(self, infos) -> None:
        """The computed-torque loop's model: a reference copy of the URDF in a client of its own (never
        stepped, never randomized), the URDF's joint damping and effort limits, per movable joint."""
        missing = [i[1].decode() for i in infos if i[0] in self.movable and i[0] not in self.in_idx]
        if missing:
            raise SimgapError("pybullet_urdf: options.inner_loop = 'computed_torque' commands an acceleration for "
                              f"every movable joint; options.inputs leaves out {', '.join(missing)}")
        pb = self._pb
        ref = self._ref_client = bullet_client(self.dt, self.g)
        with capture_c_output():
            self._ref_body = ref.loadURDF(str(self.path), useFixedBase=True, flags=pb.URDF_USE_INERTIA_FROM_FILE)
        order = [self.movable.index(j) for j in self.in_idx]  # input k drives movable joint order[k]
        self._ct_order = np.array(order)
        self._ct_damping = np.array([infos[j][6] for j in self.movable])  # the URDF's own, as Bullet applies it
        limits = np.array([infos[j][10] for j in self.movable], dtype=float)
        self._ct_limit = np.where(limits > 0, limits, np.inf)  # 0: the URDF states no effort limit

    def close(self) -> None:
        ref = getattr(self, "_ref_client", None)
        if ref is not None:
            try:
                ref.disconnect()
            except Exception:  # already gone (e.g. interpreter shutdown)
                pass
            self._ref_client = None
        super().close()

    def _computed_torques(self, bodies, acc, torque_noise) -> None:
        """Apply tau = clip(ID(q, qdot, acc) + c qdot + n) to every movable joint of each body for the next
        Bullet step (``acc`` (b, J) commanded accelerations in movable-joint order, ``torque_noise`` (b, J))."""
        pb, cid, ref, rb = self._pb, self._cid, self._ref_client, self._ref_body
        for b, a, n in zip(bodies, acc.tolist(), torque_noise):
            st = pb.getJointStates(b, self.movable, physicsClientId=cid)
            q, qd = [s_[0] for s_ in st], [s_[1] for s_ in st]
            tau = np.asarray(ref.calculateInverseDynamics(rb, q, qd, a)) + self._ct_damping * np.asarray(qd) + n
            tau = np.clip(tau, -self._ct_limit, self._ct_limit)
            pb.setJointMotorControlArray(b, self.movable, pb.TORQUE_CONTROL, forces=tau.tolist(), physicsClientId=cid)

    # ----- randomness ----------------------------------------------------------------------
    def draw_noise(self, B: int, rng: np.random.Generator) -> Dict[str, np.ndarray]:
        """Per-run draws: ``act`` (B,m), ``sens`` (B,n), ``proc`` (B,steps,n) additive noise, ``torque`` (B, J)
        (the computed-torque loop's, J = len(options.inputs));
        ``mass``, ``friction`` (B, links) and ``damping`` (B, movable joints) relative factors.
        The same numbers are drawn whatever the configuration, in a fixed order."""
        s = self.system
        act = rng.standard_normal((B, s.m)) * self.act_std
        sens = rng.standard_normal((B, s.n)) * self.sens_std
        proc = rng.standard_normal((B, s.steps, s.n)) * self.proc_std
        L, J = len(self.links), len(self.movable)
        mass = relative_factors(rng, B * L, self.mass_std).reshape(B, L)
        damping = relative_factors(rng, B * J, self.damp_std).reshape(B, J)
        friction = relative_factors(rng, B * L, self.fric_std).reshape(B, L)
        # last, and only with the inner loop: every other configuration draws the stream it drew before
        torque = (rng.standard_normal((B, len(self.in_names))) * self.torque_std if self.inner_loop == "computed_torque"
                  else np.zeros((B, len(self.in_names))))
        return {"act": act, "sens": sens, "proc": proc, "mass": mass, "damping": damping, "friction": friction,
                "torque": torque}

    # ----- the batch step --------------------------------------------------------------------
    def step_with_noise(self, x, u, noise):
        """Next states (B,n) after tau from x (B,n) with u (B,m) held, for drawn noise.

        Rows run ``copies`` at a time on independent copies of the robot, each reset completely.
        """
        s = self.system
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        B = x.shape[0]
        if x.shape != (B, s.n) or u.shape != (B, s.m):
            raise SimgapError(f"pybullet_urdf: need x (B,{s.n}) and u (B,{s.m}), got {x.shape} and {u.shape}")
        drive = self.gain * (u + noise["act"])
        if self.input_map is not None:  # joint targets from the inputs (actuation noise on the inputs)
            drive = drive @ self.input_map.T
        out = np.empty((B, s.n))
        for r0 in range(0, B, self.copies):
            r1 = min(B, r0 + self.copies)
            out[r0:r1] = self._run_round(x[r0:r1], drive[r0:r1], {k: v[r0:r1] for k, v in noise.items()})
        return s.wrap(out + noise["sens"])

    def _set_state(self, bodies, x, targets=None):
        """Reset each body's state dofs to a row of x; other movable joints to 0 at rest (driven
        joints to their velocity ``targets`` with ``driven_start = "target"``)."""
        pb, cid = self._pb, self._cid
        nb, npos = self.nb, len(self.pos_idx)
        J = len(self.movable)
        slot = {j: k for k, j in enumerate(self.movable)}
        for i, (b, row) in enumerate(zip(bodies, x.tolist())):
            q, qd = [[0.0] for _ in range(J)], [[0.0] for _ in range(J)]
            if targets is not None and self.driven_start == "target":
                for j, v, mode in zip(self.in_idx, targets[i], self.modes):
                    if mode == "velocity":
                        qd[slot[j]] = [v]
                    else:  # position: at the commanded position, at rest
                        q[slot[j]] = [v]
            for k, v in zip(self._pos_slot, row[nb:nb + npos]):
                q[k] = [v]
            for k, v in zip(self._vel_slot, row[nb + npos:]):
                qd[k] = [v]
            if self.base_pose:
                pos = [row[0], row[1], self._base0[0][2]]
                pb.resetBasePositionAndOrientation(b, pos, pb.getQuaternionFromEuler([0, 0, row[2]]),
                                                   physicsClientId=cid)
                pb.resetBaseVelocity(b, *self._base_velocity(row), physicsClientId=cid)
            elif not self.fixed_base:
                pb.resetBasePositionAndOrientation(b, *self._base0, physicsClientId=cid)
                pb.resetBaseVelocity(b, [0, 0, 0], [0, 0, 0], physicsClientId=cid)
            pb.resetJointStatesMultiDof(b, self.movable, q, targetVelocities=qd, physicsClientId=cid)
            if self._ground:  # drop cached contact manifolds: the row must not remember earlier rows
                for l in [-1] + list(range(pb.getNumJoints(b, physicsClientId=cid))):
                    pb.setCollisionFilterGroupMask(b, l, 2, 1, physicsClientId=cid)

    def _base_velocity(self, row):
        """(linear, angular) base velocity of a state row: (v cos yaw, v sin yaw, 0), (0, 0, omega) with
        ``base_velocity``, else at rest."""
        if not self.base_velocity:
            return [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
        yaw, v, w = row[2], row[3], row[4]
        return [v * np.cos(yaw), v * np.sin(yaw), 0.0], [0.0, 0.0, w]

    def _get_state(self, bodies) -> np.ndarray:
        pb, cid = self._pb, self._cid
        rows = []
        for b in bodies:
            row = []
            if self.base_pose:
                pos, orn = pb.getBasePositionAndOrientation(b, physicsClientId=cid)
                yaw = pb.getEulerFromQuaternion(orn)[2]
                row += [pos[0], pos[1], yaw]
                if self.base_velocity:  # forward speed along the heading, yaw rate
                    lin, ang = pb.getBaseVelocity(b, physicsClientId=cid)
                    row += [lin[0] * np.cos(yaw) + lin[1] * np.sin(yaw), ang[2]]
            st = pb.getJointStates(b, self.movable, physicsClientId=cid)
            slot = {j: k for k, j in enumerate(self.movable)}
            row += [st[slot[j]][0] for j in self.pos_idx] + [st[slot[j]][1] for j in self.vel_idx]
            rows.append(row)
        return np.array(rows, dtype=float)

    def _run_round(self, x, drive, noise):
        """Rows x (b,n), b <= copies, on the first b copies; (b,n) next states before sensor noise."""
        pb, cid, s = self._pb, self._cid, self.system
        bodies = self.bodies[:x.shape[0]]
        if self._per_row_dynamics:
            for i, b in enumerate(bodies):
                for k, l in enumerate(self.links):
                    f = float(noise["mass"][i, k])
                    pb.changeDynamics(b, l, mass=float(self.mass0[k]) * f,
                                      localInertiaDiagonal=(self.inertia0[k] * f).tolist(),
                                      lateralFriction=float(self.friction0[k] * noise["friction"][i, k]),
                                      physicsClientId=cid)
                for k, j in enumerate(self.movable):
                    pb.changeDynamics(b, j, jointDamping=float(self.damping0[k] * noise["damping"][i, k]),
                                      physicsClientId=cid)
        targets = drive.tolist()
        self._set_state(bodies, x, targets)
        vel, pos, tor = ([k for k, md in enumerate(self.modes) if md == mode]
                         for mode in ("velocity", "position", "torque"))
        for b, t in zip(bodies, targets):
            if vel:
                pb.setJointMotorControlArray(b, [self.in_idx[k] for k in vel], pb.VELOCITY_CONTROL,
                                             targetVelocities=[t[k] for k in vel],
                                             forces=[float(self.max_forces[k]) for k in vel], physicsClientId=cid)
            if pos:
                pb.setJointMotorControlArray(b, [self.in_idx[k] for k in pos], pb.POSITION_CONTROL,
                                             targetPositions=[t[k] for k in pos], targetVelocities=[0.0] * len(pos),
                                             forces=[float(self.max_forces[k]) for k in pos],
                                             positionGains=[self.position_gain] * len(pos),
                                             velocityGains=[self.velocity_gain] * len(pos), physicsClientId=cid)
        tor_idx = [self.in_idx[k] for k in tor]
        if self.inner_loop == "computed_torque":  # inputs in movable-joint order, noise likewise
            acc, tn = np.empty_like(drive), np.empty_like(noise["torque"])
            acc[:, self._ct_order], tn[:, self._ct_order] = drive, noise["torque"]
        for k in range(s.steps):
            for _ in range(self.substeps):
                if self.inner_loop == "computed_torque":
                    self._computed_torques(bodies, acc, tn)
                elif tor:  # applied torques are cleared by every step: re-apply
                    for b, t in zip(bodies, targets):
                        pb.setJointMotorControlArray(b, tor_idx, pb.TORQUE_CONTROL, forces=[t[i] for i in tor],
                                                     physicsClientId=cid)
                pb.stepSimulation(physicsClientId=cid)
            if self._process and k < s.steps - 1:
                self._set_state_keep_rest(bodies, self._get_state(bodies) + noise["proc"][:, k])
        y = self._get_state(bodies)
        return y + noise["proc"][:, s.steps - 1] if self._process else y

    def _set_state_keep_rest(self, bodies, x):
        """Reset only the state dofs to x (process noise between base periods)."""
        pb, cid = self._pb, self._cid
        nb, npos = self.nb, len(self.pos_idx)
        for b, row in zip(bodies, x.tolist()):
            if self.base_pose:
                pos, orn = pb.getBasePositionAndOrientation(b, physicsClientId=cid)
                rpy = pb.getEulerFromQuaternion(orn)
                lin, ang = self._base_velocity(row) if self.base_velocity else \
                    pb.getBaseVelocity(b, physicsClientId=cid)
                pb.resetBasePositionAndOrientation(b, [row[0], row[1], pos[2]],
                                                   pb.getQuaternionFromEuler([rpy[0], rpy[1], row[2]]),
                                                   physicsClientId=cid)
                pb.resetBaseVelocity(b, lin, ang, physicsClientId=cid)
            st = pb.getJointStates(b, self.movable, physicsClientId=cid)
            q = {j: st[k][0] for k, j in enumerate(self.movable)}
            qd = {j: st[k][1] for k, j in enumerate(self.movable)}
            for j, v in zip(self.pos_idx, row[nb:nb + npos]):
                q[j] = v
            for j, v in zip(self.vel_idx, row[nb + npos:]):
                qd[j] = v
            pb.resetJointStatesMultiDof(b, self.movable, [[q[j]] for j in self.movable],
                                        targetVelocities=[[qd[j]] for j in self.movable], physicsClientId=cid)

"""Stochastic PyBullet pendulum: many independent pendulums on one fixed-base multibody.

The physical model is ``assets/urdf/pendulum.urdf``: a uniform rod (mass m, length l) on a
revolute joint about +y, angle 0 when the rod hangs straight down. Its dynamics are

    theta'' = -(3 g / 2 l) sin(theta) + 3 u / (m l^2),

the continuous-time model behind :func:`simgap.systems.pendulum` (whose sign of the gravity
term is restoring: a hanging pendulum, as in the paper's PyBullet model). Bullet integrates
with semi-implicit Euler at the physics step dt = base_tau / substeps:

    omega+ = omega + dt * theta''(theta, u),   theta+ = theta + dt * omega+,

so with one substep the noise-free simulator gives exactly the nominal x2+ and an x1+ that
differs from the nominal (explicit Euler) x1 + tau x2 by tau^2 theta'' = O(tau^2).

Speed: the batch is simulated ``branches`` at a time on ONE fixed-base multibody with that
many revolute branches (built with ``createMultiBody`` from the URDF's inertial data, pivots
3 l apart along x so that Bullet's broadphase finds no overlapping links). Branches on a fixed
base do not interact, so every row's result is bit-identical whatever branch or
batch it runs in. A batch of B rows takes ceil(B / branches) rounds of: reset joint states,
(apply torques, stepSimulation) x (steps * substeps), read joint states.

Randomness (all from :meth:`draw_noise`, one draw per run, held for the whole tau):

* ``noise.actuation_std`` [N m]: torque noise a ~ N(0, std^2), u -> u + a.
* ``noise.sensor_std`` [rad, rad/s]: scalar or 2 values, added to the read-back state.
* ``randomize.mass`` (relative std): m -> m (1 + std z), z ~ N(0,1) clipped to +-3.
* ``randomize.length`` (relative std <= 0.08): l -> l (1 + std z). The centre-of-mass offset of
  a built link cannot be changed, so each run gets the dynamically equivalent link: mass
  m' = m l / l0 at the fixed offset l0/2 (same gravity torque m g l / 2) and centroidal inertia
  m l^2 / 3 - m' (l0/2)^2 (same inertia about the pivot m l^2 / 3); valid for l > 0.75 l0.
  Randomization calls ``changeDynamics`` once per row, which costs about 2.5x in speed.

Undeclared effects (the nominal model lacks them):

* ``effects.joint_damping`` c [N m s/rad]: viscous torque -c omega. Uses Bullet's joint damping,
  verified to act as the explicit torque -c omega(t) in each physics step:
  omega+ = omega + dt (theta'' - c omega / (m l^2 / 3)).
* ``effects.coulomb_friction`` mu [N m]: dry joint friction, a velocity motor with target 0 and
  maximum torque mu (Bullet's constraint-based stiction: the joint sticks while the other
  torques stay below mu).
* ``effects.actuator_gain`` k: the applied torque is k (u + a).

Options: ``branches`` (pendulums per multibody, 1..120, default 50), ``substeps`` (physics
steps per base period, default 1), ``urdf`` (file name under assets/urdf).
"""

from __future__ import annotations

import operator
from itertools import chain
from typing import Dict

import numpy as np

from ..errors import SimgapError
from ._bullet import (BulletSimulator, bullet_client, check_std, int_option, pybullet_module, relative_factors,
                      urdf_path)
from .base import as_vector

MAX_BRANCHES = 120  # Bullet multibodies take at most ~128 links
# Pivots are spaced along x (BRANCH_SPACING * l apart): Bullet keeps a (shapeless) collision
# object per link, and with all pivots at one point the broadphase tested every pair of links at
# every step, which halved the throughput. Spacing changes no result bit (tested).
BRANCH_SPACING = 3.0
CHUNK_ROUNDS = 40  # rounds per chunk of argument lists
_POS_VEL = operator.itemgetter(0, 1)  # (position, velocity) of a getJointStates entry


class PendulumSimulator(BulletSimulator):
    """Batched stochastic PyBullet pendulum (see module docstring for the model and keys)."""

    NOISE_KEYS = ("actuation_std", "sensor_std")
    RANDOMIZE_KEYS = ("mass", "length")
    PARAMETER_DRAWS = ("mass", "length")  # draw_noise keys held for an episode (randomize.per)
    EFFECT_KEYS = ("joint_damping", "coulomb_friction", "actuator_gain")
    OPTION_KEYS = ("branches", "substeps", "urdf")
    TYPES = {"noise": {"actuation_std": "number", "sensor_std": "numbers"},
             "randomize": dict.fromkeys(RANDOMIZE_KEYS, "number"), "effects": dict.fromkeys(EFFECT_KEYS, "number"),
             "options": {"branches": "int", "substeps": "int", "urdf": "name"}}

    def __init__(self, config, system=None):
        super().__init__(config, system)
        s = self.system
        if s.n != 2 or s.m != 1:
            raise SimgapError(f"pybullet_pendulum: needs a system with 2 states and 1 input, "
                              f"got {s.name!r} with n={s.n}, m={s.m}")
        nz, rz, ef, op = config.noise, config.randomize, config.effects, config.options
        self.act_std = check_std(nz.get("actuation_std", 0.0), "noise.actuation_std")
        self.sens_std = as_vector(nz.get("sensor_std", 0.0), 2, "noise.sensor_std")
        self.mass_std = check_std(rz.get("mass", 0.0), "randomize.mass", 0.3)
        self.length_std = check_std(rz.get("length", 0.0), "randomize.length", 0.08)
        self.damping = check_std(ef.get("joint_damping", 0.0), "effects.joint_damping")
        self.coulomb = check_std(ef.get("coulomb_friction", 0.0), "effects.coulomb_friction")
        self.gain = check_std(ef.get("actuator_gain", 1.0), "effects.actuator_gain")
        self.branches = int_option(op.get("branches", 50), "options.branches", 1, MAX_BRANCHES)
        self.substeps = int_option(op.get("substeps", 1), "options.substeps", 1, 1000)
        self.n_physics = s.steps * self.substeps  # stepSimulation calls per sampling period
        self.dt = s.base_tau / self.substeps
        self.g = float(s.params.get("g", 9.81))
        self._build(op.get("urdf", "pendulum.urdf"))

    # ----- construction ------------------------------------------------------------------
    def _build(self, urdf: str) -> None:
        pybullet = pybullet_module()

        path = urdf_path(urdf)
        c = self._client = bullet_client(self.dt, self.g)
        # read the link's inertial data from the URDF, then rebuild it as NB branches
        ref = c.loadURDF(str(path), useFixedBase=True, flags=pybullet.URDF_USE_INERTIA_FROM_FILE)
        if c.getNumJoints(ref) != 1 or c.getJointInfo(ref, 0)[2] != pybullet.JOINT_REVOLUTE:
            raise SimgapError(f"pendulum URDF {path}: need exactly one revolute/continuous joint")
        info = c.getDynamicsInfo(ref, 0)
        axis = list(c.getJointInfo(ref, 0)[13])
        mass, inertia, com = float(info[0]), list(info[2]), list(info[3])
        c.removeBody(ref)
        # the system's nominal m, l must be what the URDF describes
        m_sys, l_sys = float(self.system.params.get("m", 1.0)), float(self.system.params.get("l", 1.0))
        l_urdf = 2.0 * float(np.linalg.norm(com))
        if not (np.isclose(mass, m_sys) and np.isclose(l_urdf, l_sys)):
            raise SimgapError(f"pendulum URDF {path} has m={mass:g}, l={l_urdf:g} but system "
                              f"{self.system.name!r} has m={m_sys:g}, l={l_sys:g}")
        self.m0, self.l0, self.inertia0, self.com0 = mass, l_urdf, inertia, com
        self.axis = np.asarray(axis, dtype=float)
        if abs(self.axis[0]) > 1e-12:
            raise SimgapError(f"pendulum URDF {path}: the joint axis must be perpendicular to x "
                              f"(branches are spaced along x), got {axis}")
        NB = self.branches
        self.body = c.createMultiBody(
            baseMass=0.0, baseCollisionShapeIndex=-1, baseVisualShapeIndex=-1, basePosition=[0, 0, 0],
            linkMasses=[mass] * NB, linkCollisionShapeIndices=[-1] * NB, linkVisualShapeIndices=[-1] * NB,
            linkPositions=[[BRANCH_SPACING * self.l0 * j, 0, 0] for j in range(NB)],
            linkOrientations=[[0, 0, 0, 1]] * NB,
            linkInertialFramePositions=[com] * NB, linkInertialFrameOrientations=[[0, 0, 0, 1]] * NB,
            linkParentIndices=[0] * NB, linkJointTypes=[pybullet.JOINT_REVOLUTE] * NB,
            linkJointAxis=[axis] * NB)
        self.joints = list(range(NB))
        # no hidden damping; never put the body to sleep (it would freeze slow pendulums)
        c.changeDynamics(self.body, -1, linearDamping=0.0, angularDamping=0.0,
                         activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING)
        for j in self.joints:
            c.changeDynamics(self.body, j, linearDamping=0.0, angularDamping=0.0, mass=mass,
                             localInertiaDiagonal=inertia, jointDamping=self.damping)
        for j in [-1] + self.joints:
            c.setCollisionFilterGroupMask(self.body, j, 0, 0)  # nothing to collide with
        # the default velocity motors would act as stiff friction: off, or mu for Coulomb friction
        c.setJointMotorControlArray(self.body, self.joints, pybullet.VELOCITY_CONTROL,
                                    targetVelocities=[0.0] * NB, forces=[self.coulomb] * NB)
        # raw module functions with the client id: BulletClient.__getattr__ costs per call
        self._pb, self._cid = pybullet, c._client
        self._randomized = self.mass_std > 0 or self.length_std > 0

    # ----- randomness ----------------------------------------------------------------------
    def draw_noise(self, B: int, rng: np.random.Generator) -> Dict[str, np.ndarray]:
        """Per-run draws: ``act`` (B,1) torque noise [N m], ``sens`` (B,2) sensor noise,
        ``mass`` and ``length`` (B,) relative factors. The same number of normals is drawn
        whatever the configuration, in a fixed order."""
        act = rng.standard_normal((B, 1)) * self.act_std
        sens = rng.standard_normal((B, 2)) * self.sens_std
        mass = relative_factors(rng, B, self.mass_std)
        length = relative_factors(rng, B, self.length_std)
        return {"act": act, "sens": sens, "mass": mass, "length": length}

    def link_parameters(self, mass_factor: np.ndarray, length_factor: np.ndarray):
        """Per-run link mass m' [kg] and centroidal inertia about the joint axis [kg m^2].

        A rod of mass m = m0 f_m and length l = l0 f_l at the fixed centre-of-mass offset
        d0 = l0/2 is equivalent to mass m' = m l / l0 with inertia m l^2 / 3 - m' d0^2
        (same gravity torque and same inertia about the pivot).
        """
        m = self.m0 * np.asarray(mass_factor, dtype=float)
        l = self.l0 * np.asarray(length_factor, dtype=float)
        m_eq = m * l / self.l0
        d0 = 0.5 * self.l0
        i_eq = m * l * l / 3.0 - m_eq * d0 * d0
        return m_eq, i_eq

    # ----- the batch step --------------------------------------------------------------------
    def step_with_noise(self, x, u, noise):
        """Next states (B,2) after tau from x (B,2) with torque u (B,1) held, for drawn noise.

        Row i depends only on (x_i, u_i, noise_i): rows run on independent branches.
        """
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        B = x.shape[0]
        if x.shape != (B, 2) or u.shape != (B, 1):
            raise SimgapError(f"pybullet_pendulum: need x (B,2) and u (B,1), got {x.shape} and {u.shape}")
        torque = self.gain * (u[:, 0] + noise["act"][:, 0])
        if self._randomized:
            m_eq, i_eq = self.link_parameters(noise["mass"], noise["length"])
            inertia = np.tile(np.asarray(self.inertia0, dtype=float), (B, 1))
            # the joint axis sees the inertia component along it; others stay positive and unused
            inertia[:, np.argmax(np.abs(self.axis))] = i_eq
        out = np.empty((B, 2))
        # rows go in chunks of whole rounds; the argument lists of a chunk are built at once
        # (vectorized). Chunks stay small: millions of live small lists make the GC crawl.
        chunk = self.branches * CHUNK_ROUNDS
        for c0 in range(0, B, chunk):
            c1 = min(B, c0 + chunk)
            out[c0:c1] = self._run_rows(x[c0:c1], torque[c0:c1],
                                        None if not self._randomized else (m_eq[c0:c1], inertia[c0:c1]))
        return out + noise["sens"]

    def _run_rows(self, x, torque, params):
        """Simulate rows x (b,2) with torques (b,) in rounds of ``branches`` rows; (b,2) out.

        Rows past the end of the last round leave their branches idle at rest with zero
        torque (branches never interact). ``params`` = (mass (b,), inertia (b,3)) or None.
        """
        pb, cid, body, J, NB = self._pb, self._cid, self.body, self.joints, self.branches
        b = x.shape[0]
        R = -(-b // NB)
        pad = R * NB - b
        q = np.pad(x[:, 0], (0, pad)).reshape(R, NB, 1).tolist()
        qd = np.pad(x[:, 1], (0, pad)).reshape(R, NB, 1).tolist()
        tq = np.pad(torque, (0, pad)).reshape(R, NB).tolist()
        if params is not None:
            m_eq, inertia = params[0].tolist(), params[1].tolist()
        reset, motor, step, read = (pb.resetJointStatesMultiDof, pb.setJointMotorControlArray,
                                    pb.stepSimulation, pb.getJointStates)
        mode, n_physics = pb.TORQUE_CONTROL, self.n_physics
        flat = []  # floats, not tuples: nothing for the GC to traverse
        for r in range(R):
            if params is not None:
                for j in range(min(NB, b - r * NB)):
                    pb.changeDynamics(body, j, mass=m_eq[r * NB + j],
                                      localInertiaDiagonal=inertia[r * NB + j], physicsClientId=cid)
            reset(body, J, q[r], targetVelocities=qd[r], physicsClientId=cid)
            forces = tq[r]
            for _ in range(n_physics):
                # applied torques are cleared after every stepSimulation: re-apply each time
                motor(body, J, mode, forces=forces, physicsClientId=cid)
                step(physicsClientId=cid)
            flat.extend(chain.from_iterable(map(_POS_VEL, read(body, J, physicsClientId=cid))))
        return np.array(flat[:2 * b], dtype=float).reshape(b, 2)



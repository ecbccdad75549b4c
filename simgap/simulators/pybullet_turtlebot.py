"""Stochastic PyBullet TurtleBot: a primitive-shape differential-drive robot on a plane.

The robot is ``assets/urdf/diffbot.urdf`` (TurtleBot3-Burger-like: wheel radius r = 0.033 m,
track b = 0.16 m, cylinder chassis, two frictionless ball casters). The state (x, y, theta) is
the pose of the robot's base frame, i.e. the axle midpoint and the heading (yaw of the body x
axis), theta wrapped to [-pi, pi). The input (v, omega) of the unicycle model
:func:`simgap.systems.turtlebot` is turned into wheel-speed targets of Bullet's velocity
motors (maximum torque ``motor_force``):

    wL = (v - omega b / 2) / r,   wR = (v + omega b / 2) / r        [rad/s]

and held for tau = steps * base_tau (base_tau = 0.01 s) of physics at dt = base_tau / substeps
(default substeps = 4, dt = 2.5 ms).

Reset (every run starts from scratch, nothing carries over between runs): the base is placed
at (x, y) with heading theta in its settled resting height and tilt (found once at start-up);
the base's linear and angular velocities are set to the motion the wheel targets produce
(v cos theta, v sin theta, omega), and the wheel joint velocities to the targets. The unicycle
model has no acceleration phase, so the simulator starts each run already moving at the
commanded speed. Contact caches are cleared at every reset (the robot's collision objects are
re-inserted), so a run's result depends on its own (x, u, noise) only, never on the previous
run: batched and one-at-a-time results are bit-identical.

Randomness (all drawn by :meth:`draw_noise`, one draw per run, held for the whole tau unless
said otherwise):

* ``noise.actuation_std`` [m/s, rad/s]: scalar or 2 values, (v, omega) -> (v, omega) + a.
* ``noise.sensor_std`` [m, m, rad]: scalar or 3 values, added to the read-back state.
* ``randomize.wheel_radius`` (relative std): the wheels roll with radius r (1 + s z) while the
  wheel speeds are still computed with the nominal r. The collision cylinder of a built body
  cannot change per run, so this is applied as its kinematic effect: both wheel-speed targets
  scaled by (1 + s z) (the robot then moves (1 + s z) times faster, as with a larger wheel).
* ``randomize.mass`` (relative std): chassis mass and inertia scaled by (1 + s z).
* ``randomize.friction`` (relative std): wheel-ground friction coefficient mu (1 + s z).
  All factors use z ~ N(0,1) clipped to +-3.

Stress stochasticity (drawn only when configured; the experiment's ``gazebo_stress`` profile;
Gazebo's own models have neither, docs/simulators.md):

* ``noise.wheel_slip`` [p, s] (0 <= p <= 1, 0 <= s <= 1): intermittent loss of traction. In each
  run each wheel, independently, slips with probability p and then covers only (1 - s V) of the
  ground its rotation would, V ~ U(0, 1). Applied as its kinematic effect (the wheel's speed
  target times its factor); one slipping wheel turns the robot: rare, large heading errors.
* ``noise.actuation_jitter`` [m/s, rad/s] (scalar or 2 values): a fresh (v, omega) perturbation
  in every base period of the hold (new wheel targets every base_tau), on top of the held
  ``actuation_std`` draw.

Undeclared effects (the nominal model lacks them):

* ``effects.actuator_gain`` k (scalar or 2 values): (v, omega) -> (k_v v, k_omega omega).
* ``effects.wheel_radius_error`` e (scalar or [e_left, e_right], |e| <= 0.05): the wheels are
  built with radius r (1 + e) (real geometry) while the wheel speeds use the nominal r; unequal
  errors make the robot curve.

Options: ``substeps`` (default 4), ``robots`` (robots simulated together in one world, default
1; they share the origin but collision filtering keeps them from touching each other),
``obstacles`` (list of [x_lo, x_hi, y_lo, y_hi] boxes [m], static, 0.5 m high), ``motor_force``
(wheel motor torque limit [N m], default 10), ``friction`` (nominal wheel friction, default 1),
``solver_iterations`` (Bullet's, default 50), ``urdf``.
"""

from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Dict

import numpy as np

from ..errors import SimgapError
from ..systems import wrap_angle
from ._bullet import (BulletSimulator, bullet_client, check_std, int_option, pybullet_module, relative_factors,
                      urdf_path)
from .base import as_vector

# collision filter groups: the world (plane, obstacles) and the robots; robots only hit the world
_WORLD, _ROBOT = 1, 2
_SETTLE_STEPS = 800  # physics steps to find the resting height and tilt at start-up


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions (..., 4) in Bullet's (x, y, z, w) order."""
    ax, ay, az, aw = np.moveaxis(a, -1, 0)
    bx, by, bz, bw = np.moveaxis(b, -1, 0)
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4) (x, y, z, w)."""
    u, w = q[..., :3], q[..., 3:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_yaw(q: np.ndarray) -> np.ndarray:
    """Heading of the body x axis, atan2(R10, R00) (the z angle of Z-Y-X Euler angles)."""
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


class TurtlebotSimulator(BulletSimulator):
    """Stochastic PyBullet differential-drive robot (see module docstring)."""

    NOISE_KEYS = ("actuation_std", "sensor_std", "wheel_slip", "actuation_jitter")
    RANDOMIZE_KEYS = ("wheel_radius", "mass", "friction")
    PARAMETER_DRAWS = ("radius", "mass", "friction")  # draw_noise keys held for an episode (randomize.per)
    EFFECT_KEYS = ("actuator_gain", "wheel_radius_error")
    _PHYSICS_DRAWS = ("act", "radius", "mass", "friction", "slip", "jitter")  # what the physics sees (not "sens")
    OPTION_KEYS = ("substeps", "robots", "obstacles", "motor_force", "friction", "solver_iterations", "urdf")
    TYPES = {"noise": dict.fromkeys(NOISE_KEYS, "numbers"), "randomize": dict.fromkeys(RANDOMIZE_KEYS, "number"),
             "effects": dict.fromkeys(EFFECT_KEYS, "numbers"),
             "options": {"substeps": "int", "robots": "int", "obstacles": "boxes", "motor_force": "number",
                         "friction": "number", "solver_iterations": "int", "urdf": "name"}}

    def __init__(self, config, system=None):
        super().__init__(config, system)
        s = self.system
        if s.n != 3 or s.m != 2:
            raise SimgapError(f"pybullet_turtlebot: needs a system with 3 states (x, y, theta) and 2 inputs "
                              f"(v, omega), got {s.name!r} with n={s.n}, m={s.m}")
        nz, rz, ef, op = config.noise, config.randomize, config.effects, config.options
        self.act_std = as_vector(nz.get("actuation_std", 0.0), 2, "noise.actuation_std")
        self.sens_std = as_vector(nz.get("sensor_std", 0.0), 3, "noise.sensor_std")
        self.slip = _slip_option(nz.get("wheel_slip", [0.0, 0.0]))
        self.jitter_std = as_vector(nz.get("actuation_jitter", 0.0), 2, "noise.actuation_jitter")
        self.radius_std = check_std(rz.get("wheel_radius", 0.0), "randomize.wheel_radius", 0.3)
        self.mass_std = check_std(rz.get("mass", 0.0), "randomize.mass", 0.3)
        self.friction_std = check_std(rz.get("friction", 0.0), "randomize.friction", 0.3)
        self.gain = as_vector(ef.get("actuator_gain", 1.0), 2, "effects.actuator_gain")
        err = np.broadcast_to(np.asarray(ef.get("wheel_radius_error", 0.0), dtype=float), (2,)) \
            if np.ndim(ef.get("wheel_radius_error", 0.0)) == 0 else np.asarray(ef["wheel_radius_error"], dtype=float)
        if err.shape != (2,) or not np.all(np.abs(err) <= 0.05):
            raise SimgapError(f"effects.wheel_radius_error: need a scalar or [left, right] with |e| <= 0.05 "
                              f"(the casters sit 2 mm above the wheels), got {ef.get('wheel_radius_error')!r}")
        self.radius_error = err.copy()
        self.substeps = int_option(op.get("substeps", 4), "options.substeps", 1, 100)
        self.robots = int_option(op.get("robots", 1), "options.robots", 1, 256)
        self.solver_iterations = int_option(op.get("solver_iterations", 50), "options.solver_iterations", 1, 1000)
        self.motor_force = check_std(op.get("motor_force", 10.0), "options.motor_force")
        self.friction = check_std(op.get("friction", 1.0), "options.friction")
        if self.motor_force <= 0:
            raise SimgapError("options.motor_force: must be > 0")
        self.obstacles = _parse_obstacles(op.get("obstacles", []))
        self.n_physics = s.steps * self.substeps
        self.dt = s.base_tau / self.substeps
        self._randomized = self.mass_std > 0 or self.friction_std > 0
        self._build(op.get("urdf", "diffbot.urdf"))

    # ----- construction ------------------------------------------------------------------
    def _build(self, urdf: str) -> None:
        pybullet = pybullet_module()

        path = urdf_path(urdf)
        c = self._client = bullet_client(self.dt, 9.81, deterministic_pairs=True)
        c.setPhysicsEngineParameter(numSolverIterations=self.solver_iterations)
        self._pb, self._cid = pybullet, c._client
        plane = c.createMultiBody(0.0, c.createCollisionShape(pybullet.GEOM_PLANE))
        world = [plane]
        for xl, xh, yl, yh in self.obstacles:
            shape = c.createCollisionShape(pybullet.GEOM_BOX, halfExtents=[(xh - xl) / 2, (yh - yl) / 2, 0.25])
            world.append(c.createMultiBody(0.0, shape, -1, [(xl + xh) / 2, (yl + yh) / 2, 0.25]))
        for body in world:
            c.setCollisionFilterGroupMask(body, -1, _WORLD, _ROBOT)

        text, self.r_nominal, self.r_true = _robot_urdf(path, self.radius_error)
        fd, tmp = tempfile.mkstemp(suffix=".urdf", prefix="simgap_diffbot_")
        try:
            with os.fdopen(fd, "w") as fh:
                fh.write(text)
            self.bodies = [c.loadURDF(tmp, [0, 0, 0.2], flags=pybullet.URDF_USE_INERTIA_FROM_FILE)
                           for _ in range(self.robots)]
        finally:
            os.unlink(tmp)
        b0 = self.bodies[0]
        names = [c.getJointInfo(b0, j)[1].decode() for j in range(c.getNumJoints(b0))]
        try:
            self.wheels = [names.index("wheel_left_joint"), names.index("wheel_right_joint")]
        except ValueError:
            raise SimgapError(f"robot URDF {path}: needs joints wheel_left_joint and wheel_right_joint, has {names}")
        yl = c.getJointInfo(b0, self.wheels[0])[14][1]
        yr = c.getJointInfo(b0, self.wheels[1])[14][1]
        self.track = float(yl - yr)
        if self.track <= 0:
            raise SimgapError(f"robot URDF {path}: the left wheel must be at +y, the right at -y")
        info = c.getDynamicsInfo(b0, -1)
        self.mass0, self.inertia0 = float(info[0]), np.asarray(info[2], dtype=float)
        self.com_local = np.asarray(info[3], dtype=float)  # base inertial frame in the link frame
        self.links = [-1] + list(range(c.getNumJoints(b0)))
        for body in self.bodies:
            # casters (part of the base) slide freely; no hidden damping; never sleep
            c.changeDynamics(body, -1, lateralFriction=0.0, rollingFriction=0.0, spinningFriction=0.0,
                             linearDamping=0.0, angularDamping=0.0,
                             activationState=pybullet.ACTIVATION_STATE_DISABLE_SLEEPING)
            for j in self.wheels:
                c.changeDynamics(body, j, lateralFriction=self.friction, rollingFriction=0.0,
                                 spinningFriction=0.0, linearDamping=0.0, angularDamping=0.0)
            for link in self.links:
                c.setCollisionFilterGroupMask(body, link, _ROBOT, _WORLD)
        self._settle()

    def _settle(self) -> None:
        """Let robot 0 come to rest at the origin; record its resting height and tilt.

        Every reset places the base at this height and tilt, rotated to the run's heading.
        """
        pybullet = pybullet_module()
        c, body = self._client, self.bodies[0]
        c.setJointMotorControlArray(body, self.wheels, pybullet.VELOCITY_CONTROL,
                                    targetVelocities=[0.0, 0.0], forces=[self.motor_force] * 2)
        for _ in range(_SETTLE_STEPS):
            c.stepSimulation()
        pos, orn = c.getBasePositionAndOrientation(body)
        vel, ang = c.getBaseVelocity(body)
        if np.linalg.norm(vel) > 1e-3 or np.linalg.norm(ang) > 1e-2:
            raise SimgapError(f"pybullet_turtlebot: the robot did not come to rest (v={vel}, w={ang})")
        q = np.asarray(orn, dtype=float)
        yaw = quat_yaw(q)
        # remove the settled yaw: rest pose = tilt only, heading 0
        self.rest_quat = quat_mul(np.array([0.0, 0.0, np.sin(-yaw / 2), np.cos(-yaw / 2)]), q)
        link_pos = np.asarray(pos) - quat_rotate(q, self.com_local)
        self.rest_z = float(link_pos[2])
        self.rest_com = quat_rotate(self.rest_quat, self.com_local)  # COM offset at heading 0

    # ----- randomness ----------------------------------------------------------------------
    def draw_noise(self, B: int, rng: np.random.Generator) -> Dict[str, np.ndarray]:
        """Per-run draws: ``act`` (B,2) input noise, ``sens`` (B,3) sensor noise, relative
        factors ``radius``, ``mass``, ``friction`` (B,), always, in this order and count; then
        only if configured (so that the streams of configurations without them are unchanged)
        ``slip`` (B,2) rim-speed factors of the left and right wheel and ``jitter`` (B,steps,2)
        (v, omega) perturbations, one per base period."""
        act = rng.standard_normal((B, 2)) * self.act_std
        sens = rng.standard_normal((B, 3)) * self.sens_std
        radius = relative_factors(rng, B, self.radius_std)
        mass = relative_factors(rng, B, self.mass_std)
        friction = relative_factors(rng, B, self.friction_std)
        out = {"act": act, "sens": sens, "radius": radius, "mass": mass, "friction": friction}
        if self.slip[0] > 0:  # per wheel: slips with probability p, losing a uniform share of [0, s]
            hit = rng.random((B, 2)) < self.slip[0]
            out["slip"] = 1.0 - hit * (self.slip[1] * rng.random((B, 2)))
        if np.any(self.jitter_std > 0):
            out["jitter"] = rng.standard_normal((B, self.system.steps, 2)) * self.jitter_std
        return out

    # ----- kinematics -----------------------------------------------------------------------
    def wheel_targets(self, u: np.ndarray, noise: Dict[str, np.ndarray]) -> np.ndarray:
        """Wheel-speed targets [rad/s] for inputs u (B,2): noise, gain, radius and slip factors;
        (B,2), or (B,steps,2) (one per base period) with actuation jitter."""
        v_cmd = u + noise["act"]
        if "jitter" in noise:
            v_cmd = v_cmd[:, None, :] + noise["jitter"]
        v_cmd = v_cmd * self.gain
        half = 0.5 * self.track * v_cmd[..., 1]
        w = np.stack([v_cmd[..., 0] - half, v_cmd[..., 0] + half], axis=-1) / self.r_nominal
        factor = noise["radius"][:, None] * noise.get("slip", 1.0)
        return w * (factor[:, None, :] if w.ndim == 3 else factor)

    def body_velocity(self, w: np.ndarray) -> np.ndarray:
        """(v, omega) (B,2) that wheel speeds w (B,2) give with the true wheel radii (no slip)."""
        rim = w * self.r_true
        return np.stack([rim.mean(axis=1), (rim[:, 1] - rim[:, 0]) / self.track], axis=1)

    # ----- the batch step --------------------------------------------------------------------
    def step_with_noise(self, x, u, noise):
        """Next states (B,3) after tau from x (B,3) with (v, omega) u (B,2) held, for drawn noise."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        B = x.shape[0]
        if x.shape != (B, 3) or u.shape != (B, 2):
            raise SimgapError(f"pybullet_turtlebot: need x (B,3) and u (B,2), got {x.shape} and {u.shape}")
        # identical rows (same x, u and physics draws) give identical results: simulate each once
        # (a noise-free simulator repeats every (x, u) N1hat times in collection)
        draws = [k for k in self._PHYSICS_DRAWS if k in noise]
        key = np.column_stack([x, u] + [noise[k].reshape(B, -1) for k in draws]) + 0.0  # -0.0 -> 0.0
        _, first, inverse = np.unique(key.view(np.dtype((np.void, key.dtype.itemsize * key.shape[1]))).ravel(),
                                      return_index=True, return_inverse=True)
        if len(first) < B:
            phys = {k: noise[k][first] for k in draws}
            out = self._simulate(x[first], u[first], phys)[inverse.ravel()]
        else:
            out = self._simulate(x, u, noise)
        out += noise["sens"]
        out[:, 2] = wrap_angle(out[:, 2])
        return out

    def _simulate(self, x: np.ndarray, u: np.ndarray, noise: Dict[str, np.ndarray]) -> np.ndarray:
        """Noise-free read-back poses (B,3) (theta not wrapped) of runs from x with u and draws."""
        B, R = x.shape[0], self.robots
        w_all = self.wheel_targets(u, noise)  # (B,2) or, with jitter, (B,steps,2)
        w = w_all[:, 0] if w_all.ndim == 3 else w_all
        vel = self.body_velocity(w)
        th = x[:, 2]
        # base (centre-of-mass) pose and velocity for every row, vectorized
        half = 0.5 * th
        qz = np.stack([np.zeros(B), np.zeros(B), np.sin(half), np.cos(half)], axis=1)
        quat = quat_mul(qz, self.rest_quat)
        com_off = quat_rotate(qz, np.broadcast_to(self.rest_com, (B, 3)))
        com = np.column_stack([x[:, 0], x[:, 1], np.full(B, self.rest_z)]) + com_off
        lin = np.column_stack([vel[:, 0] * np.cos(th), vel[:, 0] * np.sin(th), np.zeros(B)])
        lin += np.cross(np.column_stack([np.zeros(B), np.zeros(B), vel[:, 1]]), com_off)  # omega x r
        ang = np.column_stack([np.zeros(B), np.zeros(B), vel[:, 1]])
        mass = self.mass0 * noise["mass"]
        inertia = self.inertia0[None, :] * noise["mass"][:, None]
        mu = self.friction * noise["friction"]
        # pad to whole rounds with copies of row 0: idle robots then do harmless, known work
        n_rounds = -(-B // R)
        idx = np.concatenate([np.arange(B), np.zeros(n_rounds * R - B, dtype=int)]).tolist()
        com_l, quat_l, lin_l, ang_l = com.tolist(), quat.tolist(), lin.tolist(), ang.tolist()
        w_l = w.tolist()
        w_periods = w_all.tolist() if w_all.ndim == 3 else None
        if self._randomized:
            mass_l, inertia_l, mu_l = mass.tolist(), inertia.tolist(), mu.tolist()
        pb, cid, wheels, links, F = self._pb, self._cid, self.wheels, self.links, [self.motor_force] * 2
        zero2 = [[0.0], [0.0]]
        poses = []
        for r0 in range(0, n_rounds * R, R):
            for body, i in zip(self.bodies, idx[r0:r0 + R]):
                # re-inserting the collision objects drops cached contacts: runs are independent
                for link in links:
                    pb.setCollisionFilterGroupMask(body, link, _ROBOT, _WORLD, physicsClientId=cid)
                if self._randomized:
                    pb.changeDynamics(body, -1, mass=mass_l[i], localInertiaDiagonal=inertia_l[i],
                                      physicsClientId=cid)
                    for j in wheels:
                        pb.changeDynamics(body, j, lateralFriction=mu_l[i], physicsClientId=cid)
                pb.resetBasePositionAndOrientation(body, com_l[i], quat_l[i], physicsClientId=cid)
                pb.resetBaseVelocity(body, lin_l[i], ang_l[i], physicsClientId=cid)
                wl, wr = w_l[i]
                pb.resetJointStatesMultiDof(body, wheels, zero2, targetVelocities=[[wl], [wr]], physicsClientId=cid)
                pb.setJointMotorControlArray(body, wheels, pb.VELOCITY_CONTROL, targetVelocities=w_l[i],
                                             forces=F, physicsClientId=cid)
            if w_periods is None:
                for _ in range(self.n_physics):
                    pb.stepSimulation(physicsClientId=cid)
            else:  # actuation jitter: new wheel targets every base period
                for k in range(self.system.steps):
                    if k:
                        for body, i in zip(self.bodies, idx[r0:r0 + R]):
                            pb.setJointMotorControlArray(body, wheels, pb.VELOCITY_CONTROL,
                                                         targetVelocities=w_periods[i][k], forces=F,
                                                         physicsClientId=cid)
                    for _ in range(self.substeps):
                        pb.stepSimulation(physicsClientId=cid)
            for body in self.bodies:
                pos, orn = pb.getBasePositionAndOrientation(body, physicsClientId=cid)
                poses.append(pos + orn)
        P = np.asarray(poses[:B], dtype=float).reshape(B, 7)
        q = P[:, 3:]
        link = P[:, :3] - quat_rotate(q, np.broadcast_to(self.com_local, (B, 3)))
        return np.column_stack([link[:, 0], link[:, 1], quat_yaw(q)])



def _slip_option(value) -> np.ndarray:
    """Validate ``noise.wheel_slip``: [probability p, largest lost share s], both in [0, 1]."""
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        v = np.empty(0)
    if v.shape != (2,) or not np.all(np.isfinite(v)) or np.any(v < 0) or np.any(v > 1):
        raise SimgapError(f"noise.wheel_slip: need [probability, largest lost share], both in [0, 1], got {value!r}")
    return v


def _parse_obstacles(obstacles) -> list:
    """Validate ``options.obstacles``: a list of [x_lo, x_hi, y_lo, y_hi] with lo < hi."""
    try:
        boxes = [tuple(float(v) for v in box) for box in obstacles]
    except (TypeError, ValueError):
        raise SimgapError(f"options.obstacles: need a list of [x_lo, x_hi, y_lo, y_hi] boxes, got {obstacles!r}") \
            from None
    for box in boxes:
        if len(box) != 4 or not np.all(np.isfinite(box)) or not (box[0] < box[1] and box[2] < box[3]):
            raise SimgapError(f"options.obstacles: bad box {list(box)}; need [x_lo, x_hi, y_lo, y_hi], lo < hi")
    return boxes


def _robot_urdf(path: Path, radius_error: np.ndarray):
    """URDF text with the wheel cylinders scaled by (1 + e_left), (1 + e_right).

    Returns (text, nominal wheel radius [m], true radii (2,) [m]).
    """
    try:
        tree = ET.parse(path)
    except ET.ParseError as exc:
        raise SimgapError(f"robot URDF {path}: {exc}") from None
    root = tree.getroot()
    radii = []
    for name, e in zip(("wheel_left", "wheel_right"), radius_error):
        link = root.find(f"./link[@name='{name}']")
        geom = None
        if link is not None:  # (an Element without children is falsy: test against None)
            geom = link.find("./collision/geometry/cylinder")
            if geom is None:
                geom = link.find("./collision/geometry/sphere")
        if geom is None:
            raise SimgapError(f"robot URDF {path}: link {name!r} needs a cylinder or sphere collision geometry")
        r = float(geom.get("radius"))
        radii.append(r)
        for tag in ("cylinder", "sphere"):
            for g in link.iter(tag):
                g.set("radius", repr(r * (1.0 + float(e))))
    if not np.isclose(radii[0], radii[1]):
        raise SimgapError(f"robot URDF {path}: the two wheels have different radii {radii}")
    r0 = radii[0]
    text = ET.tostring(root, encoding="unicode")
    return text, r0, r0 * (1.0 + radius_error)

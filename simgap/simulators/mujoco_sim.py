"""A stochastic MuJoCo simulator for any MJCF: named joints are the state, named actuators the input.

Needs the optional extra ``simgap[mujoco]`` (MuJoCo's own Python package, ``mujoco>=3.3``; 4.0
checked). The experiment names the model (``options.model``, a path confined to the
experiment's folder, see :func:`simgap.config.load_experiment`) and

* ``options.positions``: joints whose qpos are state components (hinge [rad] or slide [m]),
* ``options.velocities``: joints whose qvel are state components [rad/s or m/s],
* ``options.inputs``: actuators whose ctrl are the input components (the actuator's own units;
  MuJoCo clamps ctrl to a ``ctrlrange`` the MJCF declares),
* ``options.base_pose`` (a mobile base): the planar pose (x [m], y [m], yaw [rad]) of the model's
  one free joint, or of ``options.base_joints`` = [slide along x, slide along y, hinge about z]
  (a planar base as in assets/urdf/diffbot.xml), first in the state; with
  ``options.base_velocity`` its forward speed along the heading [m/s] and yaw rate [rad/s]
  follow the pose (the base starts each period moving so),
* ``options.driven_start = "target"``: the joints the input actuators drive start each period at
  the target the actuators command instead of at rest at qpos0: a velocity actuator
  (``<velocity>``) its joint velocity ctrl / gear (or, through a fixed tendon, the least-norm
  joint velocities whose tendon velocities are ctrl / gear), a position actuator
  (``<position>``, on a hinge or slide joint) its joint position ctrl / gear, at rest; ``"rest"``
  (default). Position- and velocity-controlled inputs are the MJCF's own actuator types
  (``<position kp=...>``, ``<velocity kv=...>``; ``ctrl`` is then the target).

A joint keeps its state across periods when it is in the state (``positions``/``velocities``),
driven or not; a driven joint outside the state starts at its target with ``driven_start =
"target"`` (what it holds between periods while the input stays the same).

State x = (base pose, base velocity, positions..., velocities...), in the order named. One sampling period tau = steps *
base_tau is ``steps * substeps`` MuJoCo steps of timestep base_tau / substeps (this *replaces*
the MJCF's ``timestep``; ``substeps`` defaults to base_tau / timestep when that is an integer)
with the ctrl held. Every period starts from the model's reference configuration ``qpos0`` at
rest with the state joints set to x (joints not in the state start there in every period; driven
joints at their targets with ``driven_start = "target"``) and a zero constraint-solver warm start, so each row's result depends on its own (x, u, noise) only.

Batches go through MuJoCo's multithreaded ``mujoco.rollout`` (a persistent ``Rollout`` thread
pool of ``options.threads`` threads, one ``MjData`` per thread); rows never share state, so
batched and one-at-a-time results are bit-identical (tested), whatever the thread count.

Randomness (drawn by :meth:`draw_noise` from the caller's generator, once per run, held for tau):

* ``noise.actuation_std``: scalar or one per input, ctrl -> ctrl + a;
* ``noise.force_std``: scalar or one per state joint: a random generalized force [N or N m]
  on each joint named in ``positions`` (``qfrc_applied``);
* ``noise.sensor_std``: scalar or one per state dimension, added to the read-back state;
* ``randomize.mass`` (relative std): each body's mass and inertia times 1 + s z (z ~ N(0,1)
  clipped to +-3, a factor per body and run);
* ``randomize.damping`` (relative std): each dof's damping times 1 + s z.

Per-run randomization gives each row its own model: the rows go ``options.models_per_batch`` at
a time through a pool of model copies whose masses and damping are overwritten per row (copying
an MjModel costs about 0.2 ms, overwriting a few fields about 2 us).
"""

from __future__ import annotations

import os
from typing import Dict

import numpy as np

from ..errors import SimgapError
from ._bullet import check_std, int_option, relative_factors
from .base import Simulator, as_vector
from .pybullet_urdf import input_map, model_file, name_list
from ..typed import flag


def mujoco_module():
    """The ``mujoco`` module; a SimgapError naming the extra to install when it is missing."""
    try:
        import mujoco
        from mujoco import rollout  # noqa: F401  (the batched stepping this backend needs)
    except ImportError as e:
        from ..paths import install_command
        raise SimgapError("simulator kind 'mujoco' needs MuJoCo's Python package: "
                          f"{install_command('mujoco')} (import failed: {e})") from None
    return mujoco


class MujocoSimulator(Simulator):
    """Batched stochastic MuJoCo simulator of an MJCF model (see module docstring for the keys)."""

    NOISE_KEYS = ("actuation_std", "force_std", "sensor_std")
    RANDOMIZE_KEYS = ("mass", "damping")
    PARAMETER_DRAWS = ("mass", "damping")  # draw_noise keys held for an episode (randomize.per)
    EFFECT_KEYS = ()
    OPTION_KEYS = ("model", "model_sha256", "positions", "velocities", "inputs", "input_map", "substeps", "threads",
                   "models_per_batch", "base_pose", "base_joints", "base_velocity", "driven_start")
    TYPES = {"noise": dict.fromkeys(NOISE_KEYS, "numbers"), "randomize": dict.fromkeys(RANDOMIZE_KEYS, "number"),
             "options": {"model": "name", "model_sha256": "name", "positions": "names", "velocities": "names",
                         "inputs": "names", "input_map": "matrix", "substeps": "int", "threads": "int",
                         "models_per_batch": "int", "base_pose": "bool", "base_joints": "names",
                         "base_velocity": "bool", "driven_start": "name"}}
    #: options naming a file: resolved against (and confined to) the experiment's folder
    PATH_OPTIONS = ("model",)

    _rollout = None

    def __init__(self, config, system=None):
        super().__init__(config, system)
        mujoco = self._mj = mujoco_module()
        s = self.system
        nz, rz, op = config.noise, config.randomize, config.options
        if "model" not in op:
            raise SimgapError("mujoco: options.model (the MJCF file) is required")
        self.path = model_file(op["model"], op.get("model_sha256"), "mujoco options.model")
        try:
            m = mujoco.MjModel.from_xml_path(str(self.path))
        except ValueError as e:
            raise SimgapError(f"mujoco: cannot load {self.path}: {e}") from None
        pos_names = name_list(op.get("positions", []), "options.positions")
        vel_names = name_list(op.get("velocities", []), "options.velocities")
        in_names = name_list(op.get("inputs", []), "options.inputs")
        self.base_pose = flag(op, "base_pose", False, "simulator.options")
        self.base_velocity = flag(op, "base_velocity", False, "simulator.options")
        if self.base_velocity and not self.base_pose:
            raise SimgapError("mujoco: base_velocity (forward speed and yaw rate in the state) needs base_pose = true")
        if "base_joints" in op and not self.base_pose:
            raise SimgapError("mujoco: options.base_joints names the planar base of base_pose = true; set base_pose")
        self.base = self._base(m, op.get("base_joints")) if self.base_pose else None
        self.nb = 3 * self.base_pose + 2 * self.base_velocity  # base components at the front of x
        if self.nb + len(pos_names) + len(vel_names) != s.n:
            raise SimgapError(f"mujoco: the state has {self.nb + len(pos_names) + len(vel_names)} components (base "
                              f"{self.nb}, {len(pos_names)} positions, {len(vel_names)} velocities) but system "
                              f"{s.name!r} has n={s.n}")
        self.input_map = input_map(op.get("input_map"), in_names, s, "mujoco", "actuators")
        self.pos_adr = [self._joint(m, nm, "positions")[0] for nm in pos_names]
        self.vel_adr = [self._joint(m, nm, "velocities")[1] for nm in vel_names]
        self.force_dof = [self._joint(m, nm, "positions")[1] for nm in pos_names]
        self.act_id = [self._actuator(m, nm) for nm in in_names]
        if self.base is not None and self.base[0] == "planar":
            twice = sorted(set(op["base_joints"]) & (set(pos_names) | set(vel_names)))
            if twice:
                raise SimgapError(f"mujoco: {', '.join(twice)} in options.base_joints and in options.positions/"
                                  "velocities: the base's state comes from base_pose (and base_velocity) alone")
        self.driven_start = op.get("driven_start", "rest")
        if self.driven_start not in ("rest", "target"):
            raise SimgapError(f"mujoco: options.driven_start must be 'rest' or 'target', got {self.driven_start!r}")
        # velocity actuators: (their input indices, driven dofs, dofs x actuators) whose joint velocities meet
        # their targets; position actuators: (their input indices, qpos addresses, gears)
        self.drive_vel = self.drive_pos = None
        if self.driven_start == "target":
            self.drive_vel, self.drive_pos = self._drive_targets(m, in_names)

        steps_default = s.base_tau / m.opt.timestep
        if "substeps" in op:
            self.substeps = int_option(op["substeps"], "options.substeps", 1, 10000)
        elif abs(steps_default - round(steps_default)) < 1e-9 and round(steps_default) >= 1:
            self.substeps = int(round(steps_default))
        else:
            raise SimgapError(f"mujoco: base_tau {s.base_tau:g} s of system {s.name!r} is not a multiple of the "
                              f"MJCF timestep {m.opt.timestep:g} s: give options.substeps")
        m.opt.timestep = s.base_tau / self.substeps
        self.nstep = s.steps * self.substeps
        self.model = m
        threads = op.get("threads", min(4, os.cpu_count() or 1))
        self.threads = int_option(threads, "options.threads", 1, 256)
        self.chunk = int_option(op.get("models_per_batch", 1000), "options.models_per_batch", 1, 100000)

        self.act_std = as_vector(nz.get("actuation_std", 0.0), s.m, "noise.actuation_std")
        self.force_std = as_vector(nz.get("force_std", 0.0), len(pos_names), "noise.force_std")
        self.sens_std = as_vector(nz.get("sensor_std", 0.0), s.n, "noise.sensor_std")
        self.mass_std = check_std(rz.get("mass", 0.0), "randomize.mass", 0.3)
        self.damp_std = check_std(rz.get("damping", 0.0), "randomize.damping", 0.3)
        self._randomized = self.mass_std > 0 or self.damp_std > 0

        # the full physics state at qpos0, at rest; rows overwrite their state components in it
        S = mujoco.mjtState
        self.spec = int(S.mjSTATE_FULLPHYSICS)
        self.control_spec = int(S.mjSTATE_CTRL | S.mjSTATE_QFRC_APPLIED)
        d = mujoco.MjData(m)
        mujoco.mj_resetData(m, d)
        self.state0 = np.empty(mujoco.mj_stateSize(m, self.spec))
        mujoco.mj_getState(m, d, self.state0, self.spec)
        off_q = mujoco.mj_stateSize(m, S.mjSTATE_TIME)
        off_v = off_q + mujoco.mj_stateSize(m, S.mjSTATE_QPOS)
        self.off_q, self.off_v = off_q, off_v
        self.x_cols = np.array([off_q + a for a in self.pos_adr] + [off_v + a for a in self.vel_adr], dtype=int)
        self.mass0, self.inertia0 = m.body_mass.copy(), m.body_inertia.copy()
        self.damping0 = m.dof_damping.copy()
        self._datas = [mujoco.MjData(m) for _ in range(self.threads)]
        self._models = None  # the pool of per-row model copies, made on first use

    def _joint(self, m, name, what):
        """(qpos address, dof address) of a hinge or slide joint; SimgapError naming the valid ones."""
        mj = self._mj
        names = [m.joint(i).name for i in range(m.njnt)]
        if name not in names:
            bodies = [m.body(i).name for i in range(m.nbody)]
            if name in bodies and m.body_jntnum[bodies.index(name)] == 0:  # welded: MJCF's fixed joint
                raise SimgapError(f"mujoco: {name!r} (named in options.{what}) is a body of {self.path.name} fixed to "
                                  f"its parent (no joint): it has no {'velocity' if what == 'velocities' else 'motion'}"
                                  f" to be a state; its joints: {', '.join(names) or 'none'}")
            raise SimgapError(f"mujoco: {self.path.name} has no joint {name!r} (named in options.{what}); "
                              f"its joints: {', '.join(names) or 'none'}")
        j = m.joint(name)
        if int(m.jnt_type[j.id]) not in (int(mj.mjtJoint.mjJNT_HINGE), int(mj.mjtJoint.mjJNT_SLIDE)):
            raise SimgapError(f"mujoco: joint {name!r} of {self.path.name} is not a hinge or slide joint "
                              "(only 1-dof joints can be state components)")
        return int(j.qposadr[0]), int(j.dofadr[0])

    def _actuator(self, m, name):
        """The actuator's id: by its name, or "#i" for the i-th actuator of the MJCF (0-based; for
        MJCFs whose actuators have no name, such as Gymnasium's reacher.xml)."""
        names = [m.actuator(i).name for i in range(m.nu)]
        if name.startswith("#") and name[1:].isdigit():
            if int(name[1:]) < m.nu:
                return int(name[1:])
            raise SimgapError(f"mujoco: {self.path.name} has no actuator {name!r} (named in options.inputs): it has "
                              f"{m.nu} actuators, #0..#{m.nu - 1}")
        if name not in names:
            listed = ", ".join(nm or f"#{i} (no name)" for i, nm in enumerate(names))
            raise SimgapError(f"mujoco: {self.path.name} has no actuator {name!r} (named in options.inputs); "
                              f"its actuators: {listed or 'none'} (an actuator without a name is \"#i\", "
                              "its 0-based index)")
        return int(m.actuator(name).id)

    def _base(self, m, names):
        """The mobile base: ("free", qpos adr, dof adr) of the model's one free joint, or ("planar",
        qpos adrs, dof adrs) of ``base_joints`` [slide along x, slide along y, hinge about z]."""
        mj = self._mj
        if names is None:
            free = [i for i in range(m.njnt) if int(m.jnt_type[i]) == int(mj.mjtJoint.mjJNT_FREE)]
            if len(free) != 1:
                raise SimgapError(f"mujoco: base_pose needs the model's one free joint (a floating base), but "
                                  f"{self.path.name} has {len(free)}; for a base on joints name them in "
                                  "options.base_joints = [slide along x, slide along y, hinge about z]")
            j = free[0]
            return ("free", int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j]))
        names = name_list(names, "options.base_joints")
        if len(names) != 3:
            raise SimgapError(f"mujoco: options.base_joints names {len(names)} joints; it needs three: a slide along "
                              "x, a slide along y and a hinge about z")
        want = [(mj.mjtJoint.mjJNT_SLIDE, (1, 0, 0)), (mj.mjtJoint.mjJNT_SLIDE, (0, 1, 0)),
                (mj.mjtJoint.mjJNT_HINGE, (0, 0, 1))]
        qa, da = [], []
        for nm, (kind, axis) in zip(names, want):
            q, d = self._joint(m, nm, "base_joints")
            j = m.joint(nm).id
            if int(m.jnt_type[j]) != int(kind) or not np.allclose(m.jnt_axis[j], axis) \
                    or m.jnt_bodyid[j] != m.jnt_bodyid[m.joint(names[0]).id]:
                raise SimgapError(f"mujoco: options.base_joints: {nm!r} must be a {kind.name[6:].lower()} along "
                                  f"{axis} of the same body as {names[0]!r} (x slide, y slide, yaw hinge)")
            qa.append(q)
            da.append(d)
        return ("planar", qa, da)

    def _drive_targets(self, m, in_names):
        """((velocity inputs k, driven dofs, (dofs x actuators) matrix P), (position inputs k, qpos addresses,
        gears)): with ctrl c of the velocity actuators, qvel[dofs] = P c meets every velocity target (the
        least-norm solution through fixed tendons); a position actuator's joint starts at qpos = c / gear.
        Refused unless every input actuator is a velocity actuator on a 1-dof joint or a fixed tendon, or a
        position actuator on a hinge or slide joint."""
        mj = self._mj
        rows, vel_k, pos_k, pos_adr, pos_gear = [], [], [], [], []
        for k, nm in enumerate(in_names):
            a = self._actuator(m, nm)
            kg = float(m.actuator_gainprm[a, 0])
            affine = (int(m.actuator_gaintype[a]) == int(mj.mjtGain.mjGAIN_FIXED)
                      and int(m.actuator_biastype[a]) == int(mj.mjtBias.mjBIAS_AFFINE) and kg != 0
                      and m.actuator_biasprm[a, 0] == 0)
            velocity = affine and m.actuator_biasprm[a, 1] == 0 and np.isclose(m.actuator_biasprm[a, 2], -kg)
            position = affine and np.isclose(m.actuator_biasprm[a, 1], -kg)  # force kp (ctrl - q) - kv qdot
            gear = float(m.actuator_gear[a, 0])
            trn, tid = int(m.actuator_trntype[a]), int(m.actuator_trnid[a, 0])
            if position:
                if trn != int(mj.mjtTrn.mjTRN_JOINT) or int(m.jnt_type[tid]) not in (int(mj.mjtJoint.mjJNT_HINGE),
                                                                                  int(mj.mjtJoint.mjJNT_SLIDE)):
                    raise SimgapError(f"mujoco: driven_start = 'target': position actuator {nm!r} of {self.path.name} "
                                      "must drive a hinge or slide joint")
                pos_k.append(k)
                pos_adr.append(int(m.jnt_qposadr[tid]))
                pos_gear.append(gear)
                continue
            if not velocity:
                raise SimgapError(f"mujoco: driven_start = 'target' (driven joints start at their targets) needs "
                                  f"velocity actuators (<velocity>: force kv (ctrl - velocity)) or position actuators "
                                  f"(<position>: force kp (ctrl - q) - kv qdot); actuator {nm!r} of {self.path.name} "
                                  "is neither")
            vel_k.append(k)
            row = np.zeros(m.nv)
            if trn == int(mj.mjtTrn.mjTRN_JOINT) and int(m.jnt_type[tid]) in (int(mj.mjtJoint.mjJNT_HINGE),
                                                                           int(mj.mjtJoint.mjJNT_SLIDE)):
                row[int(m.jnt_dofadr[tid])] = gear
            elif trn == int(mj.mjtTrn.mjTRN_TENDON) and all(
                    int(m.wrap_type[w]) == int(mj.mjtWrap.mjWRAP_JOINT)
                    for w in range(m.tendon_adr[tid], m.tendon_adr[tid] + m.tendon_num[tid])):
                for w in range(m.tendon_adr[tid], m.tendon_adr[tid] + m.tendon_num[tid]):
                    row[int(m.jnt_dofadr[m.wrap_objid[w]])] += gear * float(m.wrap_prm[w])
            else:
                raise SimgapError(f"mujoco: driven_start = 'target': actuator {nm!r} of {self.path.name} drives "
                                  "neither a hinge/slide joint nor a fixed tendon of such joints")
            rows.append(row)
        if len(set(pos_adr)) != len(pos_adr):
            raise SimgapError("mujoco: driven_start = 'target': two position actuators drive the same joint")
        pos = (np.array(pos_k, dtype=int), np.array(pos_adr, dtype=int), np.array(pos_gear)) if pos_k else None
        if not rows:
            return None, pos
        A = np.array(rows)
        dofs = np.flatnonzero(np.any(A != 0, axis=0))
        if np.linalg.matrix_rank(A[:, dofs]) < len(rows):
            raise SimgapError("mujoco: driven_start = 'target': the input actuators' velocity targets cannot all be "
                              "met at once (two actuators drive the same motion)")
        return (np.array(vel_k, dtype=int), dofs, np.linalg.pinv(A[:, dofs])), pos

    # ----- randomness ----------------------------------------------------------------------
    def draw_noise(self, B: int, rng: np.random.Generator) -> Dict[str, np.ndarray]:
        """Per-run draws: ``act`` (B,m) ctrl noise, ``force`` (B, state joints) generalized forces,
        ``sens`` (B,n) sensor noise; ``mass`` (B, bodies) and ``damping`` (B, dofs) relative
        factors. The same numbers are drawn whatever the configuration, in a fixed order."""
        s, m = self.system, self.model
        act = rng.standard_normal((B, s.m)) * self.act_std
        force = rng.standard_normal((B, len(self.pos_adr))) * self.force_std
        sens = rng.standard_normal((B, s.n)) * self.sens_std
        mass = relative_factors(rng, B * m.nbody, self.mass_std).reshape(B, m.nbody)
        damping = relative_factors(rng, B * m.nv, self.damp_std).reshape(B, m.nv)
        return {"act": act, "force": force, "sens": sens, "mass": mass, "damping": damping}

    # ----- the batch step --------------------------------------------------------------------
    def step_with_noise(self, x, u, noise):
        """Next states (B,n) after tau from x (B,n) with ctrl u (B,m) held, for drawn noise."""
        s, m = self.system, self.model
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        B = x.shape[0]
        if x.shape != (B, s.n) or u.shape != (B, s.m):
            raise SimgapError(f"mujoco: need x (B,{s.n}) and u (B,{s.m}), got {x.shape} and {u.shape}")
        if B == 0:
            return np.empty((0, s.n))
        state = np.tile(self.state0, (B, 1))
        nb = self.nb
        state[:, self.x_cols] = x[:, nb:]
        control = np.zeros((B, 1, m.nu + m.nv))
        ctrl = u + noise["act"]
        ctrl = ctrl if self.input_map is None else ctrl @ self.input_map.T
        control[:, 0, self.act_id] = ctrl
        if self.driven_start == "target":  # driven joints start at what the (clamped) ctrl commands
            lim = m.actuator_ctrllimited[self.act_id].astype(bool)
            lo, hi = m.actuator_ctrlrange[self.act_id, 0], m.actuator_ctrlrange[self.act_id, 1]
            c = np.where(lim, np.clip(ctrl, lo, hi), ctrl)
            if self.drive_vel is not None:
                k, dofs, P = self.drive_vel
                # row by row (a matrix product's rounding may depend on the batch size: batched == one at a time)
                state[:, self.off_v + dofs] = (c[:, None, k] * P[None]).sum(axis=2)
            if self.drive_pos is not None:
                k, adr, gear = self.drive_pos
                state[:, self.off_q + adr] = c[:, k] / gear
            state[:, self.x_cols] = x[:, nb:]  # a driven joint that is also in the state starts at x (as in the URDF backend)
        if self.base_pose:
            self._set_base(state, x)
        control[:, 0, m.nu + np.asarray(self.force_dof, dtype=int)] = noise["force"]
        control = np.repeat(control, self.nstep, axis=1)  # held for the whole period
        out = np.empty((B, s.n))
        step = self.chunk if self._randomized else B
        for r0 in range(0, B, step):
            r1 = min(B, r0 + step)
            models = self._row_models(noise["mass"][r0:r1], noise["damping"][r0:r1]) if self._randomized \
                else self.model
            out[r0:r1] = self._roll(models, state[r0:r1], control[r0:r1])
        return s.wrap(out + noise["sens"])

    def _roll(self, models, state, control):
        """The last state's (B,n) state components after ``nstep`` steps of each row."""
        if self._rollout is None:
            from mujoco import rollout
            self._rollout = rollout.Rollout(nthread=self.threads)
        B, m = state.shape[0], self.model
        if not isinstance(models, list):
            models = [models] * B
        # every array is built here with its exact shape (C-contiguous float64), so MuJoCo's per-call
        # checks (an mj_stateSize per model) are skipped; outputs must then be allocated by the caller
        res = np.empty((B, self.nstep, state.shape[1]))
        sensors = np.empty((B, self.nstep, m.nsensordata))
        self._rollout.rollout(models, self._datas, np.ascontiguousarray(state), np.ascontiguousarray(control),
                              control_spec=self.control_spec, nstep=self.nstep,
                              initial_warmstart=np.zeros((B, m.nv)), state=res, sensordata=sensors,
                              skip_checks=True)
        last = res[:, -1, :]
        x = last[:, self.x_cols]
        return np.concatenate([self._get_base(last), x], axis=1) if self.base_pose else x

    def _set_base(self, state, x):
        """Write the base pose (and velocity) of rows x into full physics states (in place)."""
        yaw = x[:, 2]
        v, w = (x[:, 3], x[:, 4]) if self.base_velocity else (0.0, 0.0)
        kind, qa, da = self.base
        oq, ov = self.off_q, self.off_v
        if kind == "free":  # qpos: position, quaternion (w, x, y, z); qvel: world linear, local angular
            state[:, oq + qa] = x[:, 0]
            state[:, oq + qa + 1] = x[:, 1]
            state[:, oq + qa + 3:oq + qa + 7] = 0.0
            state[:, oq + qa + 3] = np.cos(yaw / 2)
            state[:, oq + qa + 6] = np.sin(yaw / 2)
            state[:, ov + da:ov + da + 6] = 0.0
            state[:, ov + da] = v * np.cos(yaw)
            state[:, ov + da + 1] = v * np.sin(yaw)
            state[:, ov + da + 5] = w  # the body's z axis is the world's (upright)
        else:
            state[:, oq + np.asarray(qa)] = x[:, :3]
            state[:, ov + da[0]] = v * np.cos(yaw)
            state[:, ov + da[1]] = v * np.sin(yaw)
            state[:, ov + da[2]] = w

    def _get_base(self, last):
        """(B, nb) base pose (and forward speed, yaw rate) from full physics states."""
        kind, qa, da = self.base
        oq, ov = self.off_q, self.off_v
        if kind == "free":
            qw, qx, qy, qz = (last[:, oq + qa + 3 + k] for k in range(4))
            yaw = np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
            vx, vy = last[:, ov + da], last[:, ov + da + 1]
            wl = last[:, ov + da + 3:ov + da + 6]  # local frame: the world z row of the rotation matrix
            rz = np.stack([2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)], axis=1)
            cols = [last[:, oq + qa], last[:, oq + qa + 1], yaw]
            w = np.sum(rz * wl, axis=1)
        else:
            cols = [last[:, oq + a] for a in qa]
            yaw, vx, vy, w = cols[2], last[:, ov + da[0]], last[:, ov + da[1]], last[:, ov + da[2]]
        if self.base_velocity:
            cols += [vx * np.cos(yaw) + vy * np.sin(yaw), w]
        return np.stack(cols, axis=1)

    def _row_models(self, mass, damping):
        """One model per row with that row's masses, inertias and damping (a reused pool of copies)."""
        import copy
        b = mass.shape[0]
        if self._models is None:
            self._models = []
        while len(self._models) < b:
            self._models.append(copy.copy(self.model))
        inertia = self.inertia0[None] * mass[:, :, None]
        masses, damps = self.mass0[None] * mass, self.damping0[None] * damping
        for i in range(b):
            mi = self._models[i]
            mi.body_mass[:] = masses[i]
            mi.body_inertia[:] = inertia[i]
            mi.dof_damping[:] = damps[i]
        return self._models[:b]

    def close(self) -> None:
        if self._rollout is not None:
            try:
                self._rollout.close()
            except Exception:  # interpreter shutdown
                pass
            self._rollout = None

    def __del__(self):
        self.close()

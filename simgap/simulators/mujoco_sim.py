"""A stochastic MuJoCo simulator for any MJCF: named joints are the state, named actuators the input.

Needs the optional extra ``simgap[mujoco]`` (MuJoCo's own Python package, ``mujoco>=3.3``; 4.0
checked). The experiment names the model (``options.model``, a path confined to the
experiment's folder, see :func:`simgap.config.load_experiment`) and

* ``options.positions``: joints whose qpos are state components (hinge [rad] or slide [m]),
* ``options.velocities``: joints whose qvel are state components [rad/s or m/s],
* ``options.inputs``: actuators whose ctrl are the input components (the actuator's own units;
  MuJoCo clamps ctrl to a ``ctrlrange`` the MJCF declares).

State x = (positions..., velocities...), in the order named. One sampling period tau = steps *
base_tau is ``steps * substeps`` MuJoCo steps of timestep base_tau / substeps (this *replaces*
the MJCF's ``timestep``; ``substeps`` defaults to base_tau / timestep when that is an integer)
with the ctrl held. Every period starts from the model's reference configuration ``qpos0`` at
rest with the state joints set to x (joints not in the state start there in every period) and a
zero constraint-solver warm start, so each row's result depends on its own (x, u, noise) only.

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


def mujoco_module():
    """The ``mujoco`` module; a SimgapError naming the extra to install when it is missing."""
    try:
        import mujoco
        from mujoco import rollout  # noqa: F401  (the batched stepping this backend needs)
    except ImportError as e:
        raise SimgapError("simulator kind 'mujoco' needs MuJoCo's Python package: "
                          f"pip install 'simgap[mujoco]' (import failed: {e})") from None
    return mujoco


class MujocoSimulator(Simulator):
    """Batched stochastic MuJoCo simulator of an MJCF model (see module docstring for the keys)."""

    NOISE_KEYS = ("actuation_std", "force_std", "sensor_std")
    RANDOMIZE_KEYS = ("mass", "damping")
    PARAMETER_DRAWS = ("mass", "damping")  # draw_noise keys held for an episode (randomize.per)
    EFFECT_KEYS = ()
    OPTION_KEYS = ("model", "model_sha256", "positions", "velocities", "inputs", "input_map", "substeps", "threads",
                   "models_per_batch")
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
        if len(pos_names) + len(vel_names) != s.n:
            raise SimgapError(f"mujoco: the state has {len(pos_names)} positions + {len(vel_names)} velocities "
                              f"but system {s.name!r} has n={s.n}")
        self.input_map = input_map(op.get("input_map"), in_names, s, "mujoco", "actuators")
        self.pos_adr = [self._joint(m, nm, "positions")[0] for nm in pos_names]
        self.vel_adr = [self._joint(m, nm, "velocities")[1] for nm in vel_names]
        self.force_dof = [self._joint(m, nm, "positions")[1] for nm in pos_names]
        self.act_id = [self._actuator(m, nm) for nm in in_names]

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
            raise SimgapError(f"mujoco: {self.path.name} has no joint {name!r} (named in options.{what}); "
                              f"its joints: {', '.join(names) or 'none'}")
        j = m.joint(name)
        if int(m.jnt_type[j.id]) not in (int(mj.mjtJoint.mjJNT_HINGE), int(mj.mjtJoint.mjJNT_SLIDE)):
            raise SimgapError(f"mujoco: joint {name!r} of {self.path.name} is not a hinge or slide joint "
                              "(only 1-dof joints can be state components)")
        return int(j.qposadr[0]), int(j.dofadr[0])

    def _actuator(self, m, name):
        names = [m.actuator(i).name for i in range(m.nu)]
        if name not in names:
            raise SimgapError(f"mujoco: {self.path.name} has no actuator {name!r} (named in options.inputs); "
                              f"its actuators: {', '.join(names) or 'none'}")
        return int(m.actuator(name).id)

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
        state[:, self.x_cols] = x
        control = np.zeros((B, 1, m.nu + m.nv))
        ctrl = u + noise["act"]
        control[:, 0, self.act_id] = ctrl if self.input_map is None else ctrl @ self.input_map.T
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
        return res[:, -1, :][:, self.x_cols]

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

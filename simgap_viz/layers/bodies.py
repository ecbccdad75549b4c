"""The simulator's bodies as trimesh meshes: URDF geometry through PyBullet, MJCF geometry through MuJoCo.

A URDF is loaded into a private DIRECT client; every visual shape (box, sphere, cylinder,
capsule; mesh files through trimesh) is built at its world pose, composed as
link frame (``getLinkState`` [4], [5]; the base pose for link -1) times the shape's local
visual frame. Units: metres.

An MJCF (simulator kind ``mujoco``) is loaded by the simulator itself
(:class:`simgap.simulators.mujoco_sim.MujocoSimulator`: the same path confinement, sha256 check
and joint lookup), the state's joints are set in ``qpos`` (the rest at the model's ``qpos0``, as
every simulated period starts) and ``mj_forward`` places every geom at ``geom_xpos``,
``geom_xmat``: :class:`MjcfBodies` keeps one mesh per geom in the geom's own frame and gives
their world poses for any state, so the GUI moves nodes instead of re-sending geometry.
:class:`UrdfBodies` does the same for the URDF of a ``pybullet_urdf`` simulator config (the state
set by the simulator's own reset, the visual shapes posed by their links).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from simgap.systems import System
from simgap.simulators._bullet import direct_client, pybullet_module


def _quat_matrix(q) -> np.ndarray:
    """Rotation matrix of a PyBullet quaternion (x, y, z, w)."""
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _shape_mesh(geom: int, dims, mesh_file: bytes, scale_hint=None):
    import trimesh

    pybullet = pybullet_module()

    if geom == pybullet.GEOM_BOX:
        return trimesh.creation.box(extents=np.maximum(np.asarray(dims[:3], float), 1e-4))
    if geom == pybullet.GEOM_SPHERE:
        return trimesh.creation.icosphere(subdivisions=2, radius=max(float(dims[0]), 1e-4))
    if geom == pybullet.GEOM_CYLINDER:
        return trimesh.creation.cylinder(radius=max(float(dims[1]), 1e-4), height=max(float(dims[0]), 1e-4),
                                         sections=24)
    if geom == pybullet.GEOM_CAPSULE:
        return trimesh.creation.capsule(radius=max(float(dims[1]), 1e-4), height=max(float(dims[0]), 1e-4))
    if geom == pybullet.GEOM_MESH and mesh_file:
        path = mesh_file.decode() if isinstance(mesh_file, bytes) else str(mesh_file)
        if Path(path).is_file():
            m = trimesh.load(path, force="mesh")
            m.apply_scale(np.asarray(dims[:3], float))
            return m
    return None


def urdf_meshes(urdf: str | Path, base_position: Sequence[float] = (0.0, 0.0, 0.0),
                joint_positions: Optional[Sequence[float]] = None, fixed_base: bool = True) -> list:
    """(name, trimesh) for every visual shape of ``urdf`` at its world pose (metres).

    ``joint_positions`` sets the joints (radians / metres) before reading the link frames.
    """
    c = direct_client()
    try:
        b = c.loadURDF(str(urdf), basePosition=list(base_position), useFixedBase=fixed_base)
        if joint_positions is not None:
            for j, q in enumerate(joint_positions):
                c.resetJointState(b, j, float(q))
        out = []
        for k, v in enumerate(c.getVisualShapeData(b)):
            link, geom, dims, mfile, lpos, lorn, rgba = v[1], v[2], v[3], v[4], v[5], v[6], v[7]
            if link == -1:
                wpos, worn = c.getBasePositionAndOrientation(b)
            else:
                st = c.getLinkState(b, link, computeForwardKinematics=True)
                wpos, worn = st[4], st[5]
            m = _shape_mesh(geom, dims, mfile)
            if m is None:
                continue
            T = np.eye(4)
            Rw, Rl = _quat_matrix(worn), _quat_matrix(lorn)
            T[:3, :3] = Rw @ Rl
            T[:3, 3] = np.asarray(wpos) + Rw @ np.asarray(lpos)
            m.apply_transform(T)
            m.visual.face_colors = (np.clip(np.asarray(rgba), 0, 1) * 255).astype(np.uint8)
            out.append((f"link{link}_shape{k}", m))
        return out
    finally:
        c.disconnect()


class MjcfBodies:
    """The geoms of the MJCF a ``mujoco`` simulator config names, posed by the state x.

    ``names`` and ``meshes`` (trimesh, in each geom's frame, metres, face colours from
    ``geom_rgba``) are fixed; :meth:`poses` gives their world positions (K,3) and rotations
    (K,4) as (w, x, y, z) for a state x (n,): the joints of ``options.positions`` set to
    x[:len(positions)] (velocities do not move geometry). Planes become a 1 mm thin box of their
    size (an infinite plane, size 0, is left out); geoms of an unknown type (height fields, SDFs)
    are left out.
    """

    def __init__(self, config, system: System):
        from simgap.simulators.mujoco_sim import MujocoSimulator
        sim = MujocoSimulator(config, system)  # SimgapError without mujoco or with a bad model / name
        try:
            self._mj, self.model = sim._mj, sim.model
            self.path = sim.path
            self.pos_adr = np.asarray(sim.pos_adr, dtype=int)
        finally:
            sim.close()
        self.data = self._mj.MjData(self.model)
        self.geom_ids, self.names, self.meshes = [], [], []
        m = self.model
        for g in range(m.ngeom):
            mesh = _geom_mesh(self._mj, m, g)
            if mesh is None:
                continue
            mesh.visual.face_colors = (np.clip(m.geom_rgba[g], 0, 1) * 255).astype(np.uint8)
            self.geom_ids.append(g)
            self.names.append(m.geom(g).name or f"geom{g}")
            self.meshes.append(mesh)
        self.geom_ids = np.asarray(self.geom_ids, dtype=int)

    def poses(self, x) -> tuple:
        """(positions (K,3) [m], wxyz (K,4)) of the kept geoms at state x (n,)."""
        mj, m, d = self._mj, self.model, self.data
        x = np.asarray(x, dtype=float).ravel()
        d.qpos[:] = m.qpos0
        d.qvel[:] = 0.0
        d.qpos[self.pos_adr] = x[:self.pos_adr.size]
        mj.mj_kinematics(m, d)
        pos = np.array(d.geom_xpos[self.geom_ids], dtype=float)
        wxyz = np.empty((self.geom_ids.size, 4))
        for k, g in enumerate(self.geom_ids):
            mj.mju_mat2Quat(wxyz[k], d.geom_xmat[g])
        return pos, wxyz

    def meshes_at(self, x) -> list:
        """(name, trimesh) of every kept geom at its world pose for state x (copies, metres)."""
        return _placed(self, x)


class UrdfBodies:
    """The visual shapes of the URDF a ``pybullet_urdf`` simulator config names, posed by the state x.

    Same interface as :class:`MjcfBodies`. The simulator itself (one copy of the robot) loads the
    file, looks up the joints and resets them to x (:meth:`UrdfSimulator._set_state`: state joints
    to x, the other movable joints to 0, a mobile base to its planar pose); a shape's world pose
    is its link's URDF frame (``getLinkState`` [4], [5]; for the base, the centre-of-mass pose
    times the inverse of its local inertial frame) times the shape's local visual frame.
    """

    def __init__(self, config, system: System):
        import dataclasses

        from simgap.simulators.pybullet_urdf import UrdfSimulator
        cfg = dataclasses.replace(config, options={**config.options, "copies": 1})
        self._sim = sim = UrdfSimulator(cfg, system)  # SimgapError for a bad file or joint name
        self.path = sim.path
        c, b = sim._client, sim.bodies[0]
        self.names, self.meshes, self._links, self._local = [], [], [], []
        for k, v in enumerate(c.getVisualShapeData(b)):
            link, geom, dims, mfile, lpos, lorn, rgba = v[1], v[2], v[3], v[4], v[5], v[6], v[7]
            mesh = _shape_mesh(geom, dims, mfile)
            if mesh is None:
                continue
            mesh.visual.face_colors = (np.clip(np.asarray(rgba), 0, 1) * 255).astype(np.uint8)
            self.names.append(f"link{link}_shape{k}")
            self.meshes.append(mesh)
            self._links.append(int(link))
            self._local.append(_frame(lpos, lorn))
        ipos, iorn = c.getDynamicsInfo(b, -1)[3:5]
        self._base_inertial_inv = np.linalg.inv(_frame(ipos, iorn))

    def poses(self, x) -> tuple:
        """(positions (K,3) [m], wxyz (K,4)) of the visual shapes at state x (n,)."""
        sim = self._sim
        c, b = sim._client, sim.bodies[0]
        sim._set_state([b], np.asarray(x, dtype=float).reshape(1, -1))
        frames = {}
        for link in set(self._links):
            if link == -1:
                frames[-1] = _frame(*c.getBasePositionAndOrientation(b)) @ self._base_inertial_inv
            else:
                st = c.getLinkState(b, link, computeForwardKinematics=True)
                frames[link] = _frame(st[4], st[5])
        T = np.stack([frames[link] @ L for link, L in zip(self._links, self._local)]) if self._links \
            else np.zeros((0, 4, 4))
        return T[:, :3, 3].copy(), np.array([_wxyz(R) for R in T[:, :3, :3]]).reshape(-1, 4)

    def meshes_at(self, x) -> list:
        """(name, trimesh) of every visual shape at its world pose for state x (copies, metres)."""
        return _placed(self, x)

    def close(self) -> None:
        self._sim.close()


def _frame(pos, quat_xyzw) -> np.ndarray:
    """4x4 transform of a position and a PyBullet quaternion (x, y, z, w)."""
    T = np.eye(4)
    T[:3, :3] = _quat_matrix(quat_xyzw)
    T[:3, 3] = pos
    return T


def _wxyz(R) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation matrix."""
    from scipy.spatial.transform import Rotation
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def _placed(bodies, x) -> list:
    """(name, mesh moved to its world pose at state x) for :class:`MjcfBodies` / :class:`UrdfBodies`."""
    pos, wxyz = bodies.poses(x)
    out = []
    for name, mesh, p, q in zip(bodies.names, bodies.meshes, pos, wxyz):
        out.append((name, mesh.copy().apply_transform(_frame(p, (q[1], q[2], q[3], q[0])))))
    return out


def _geom_mesh(mj, m, g: int):
    """A trimesh of geom ``g`` in its own frame (MuJoCo's sizes: half extents, radii, half lengths
    along the geom's z), or None for a type not drawn."""
    import trimesh

    T = mj.mjtGeom
    t, size = int(m.geom_type[g]), np.asarray(m.geom_size[g], dtype=float)
    if t == int(T.mjGEOM_BOX):
        return trimesh.creation.box(extents=np.maximum(2 * size, 1e-4))
    if t == int(T.mjGEOM_SPHERE):
        return trimesh.creation.icosphere(subdivisions=2, radius=max(size[0], 1e-4))
    if t == int(T.mjGEOM_CAPSULE):
        return trimesh.creation.capsule(radius=max(size[0], 1e-4), height=max(2 * size[1], 1e-4), count=[24, 12])
    if t == int(T.mjGEOM_CYLINDER):
        return trimesh.creation.cylinder(radius=max(size[0], 1e-4), height=max(2 * size[1], 1e-4), sections=24)
    if t == int(T.mjGEOM_ELLIPSOID):
        e = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        e.apply_scale(np.maximum(size, 1e-4))
        return e
    if t == int(T.mjGEOM_PLANE):
        if size[0] <= 0 or size[1] <= 0:  # infinite plane: nothing finite to draw
            return None
        b = trimesh.creation.box(extents=(2 * size[0], 2 * size[1], 1e-3))
        b.apply_translation((0.0, 0.0, -5e-4))  # its top face is the plane
        return b
    if t == int(T.mjGEOM_MESH) and m.geom_dataid[g] >= 0:
        i = int(m.geom_dataid[g])
        v0, nv = int(m.mesh_vertadr[i]), int(m.mesh_vertnum[i])
        f0, nf = int(m.mesh_faceadr[i]), int(m.mesh_facenum[i])
        return trimesh.Trimesh(vertices=np.array(m.mesh_vert[v0:v0 + nv], dtype=float),
                               faces=np.array(m.mesh_face[f0:f0 + nf], dtype=np.int64), process=False)
    return None


#: simulator kinds whose configuration names a robot file that can be drawn, and its reader
MODEL_BODIES = {"mujoco": ("MuJoCo", MjcfBodies), "pybullet_urdf": ("PyBullet", UrdfBodies)}


def model_bodies(config, system: System):
    """(:class:`MjcfBodies` / :class:`UrdfBodies` or None, note): the geometry of the robot file a
    ``mujoco`` or ``pybullet_urdf`` simulator config names, or None and why not (MuJoCo not
    installed, the file missing or changed, a joint not in it); (None, "") for other kinds."""
    from simgap.errors import SimgapError
    kind = getattr(config, "kind", None)
    if config is None or kind not in MODEL_BODIES:
        return None, ""
    engine_name, cls = MODEL_BODIES[kind]
    try:
        return cls(config, system), ""
    except SimgapError as e:
        return None, f"{engine_name} bodies not drawn: {e}"


def simulator_bodies(kind: str, system: System) -> list:
    """(name, trimesh, position) of the bodies the PyBullet simulator of ``kind`` builds.

    Pendulum: ``assets/urdf/pendulum.urdf`` with its pivot raised to 1.2 m. TurtleBot: the robot
    (``assets/urdf/diffbot.urdf``) at its map's initial position and the arena's obstacle boxes.
    Empty for the numpy simulator's systems that have no geometry.
    """
    from simgap.simulators._bullet import URDF_DIR

    out = []
    if system.name == "pendulum":
        p = URDF_DIR / "pendulum.urdf"
        if p.is_file():
            out += [(f"pendulum_{n}", m, (0.0, 0.0, 1.2)) for n, m in urdf_meshes(p, joint_positions=[0.1])]
    elif system.name == "turtlebot":
        try:
            from simgap.maps import load_map
            arena = load_map("arena")
            p = URDF_DIR / "diffbot.urdf"  # the PyBullet TurtleBot simulator's robot
            if p.is_file():
                pos = (float(arena.initial_state[0]) - 2.0, float(arena.initial_state[1]) - 2.0, 0.0)
                out += [(f"robot_{n}", m, pos) for n, m in urdf_meshes(p, fixed_base=True)]
            meshes = arena.meshes()
            out += [(f"obstacle_{i}", m, (-2.0, -2.0, 0.0)) for i, m in enumerate(meshes["obstacles"])]
            out.append(("target", meshes["target"], (-2.0, -2.0, 0.0)))
        except Exception:  # no arena map in this installation
            pass
    return out

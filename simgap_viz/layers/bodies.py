"""The simulator's bodies as trimesh meshes, read from their URDF geometry through PyBullet.

A URDF is loaded into a private DIRECT client; every visual shape (box, sphere, cylinder,
capsule; mesh files through trimesh) is built at its world pose, composed as
link frame (``getLinkState`` [4], [5]; the base pose for link -1) times the shape's local
visual frame. Units: metres.
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

"""The GUI's robot-file bodies: the MJCF's geoms (MuJoCo) and the URDF's visual shapes (PyBullet) as
trimesh meshes at the state's pose, and the app drawing them for the cart-pole and arm experiments
(simgap_viz/layers/bodies.py: MjcfBodies, UrdfBodies; simgap_viz/layers/scene.py: draw_model_bodies)."""

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from simgap.config import load_experiment  # noqa: E402
from simgap.simulators.base import SimulatorConfig  # noqa: E402
from simgap_viz.layers.bodies import MjcfBodies, UrdfBodies, model_bodies  # noqa: E402

R_POLE, L_POLE = 0.049, 0.6  # the MJCF's pole capsule: fromto (0 0 0) -> (0.001 0 0.6), radius 0.049
TOL = 2e-3                   # tessellation: a 24-section circle reaches r cos(pi / 24) = 0.991 r sideways


@pytest.fixture(scope="module")
def exp():
    return load_experiment("cartpole", profile=None)


def _bounds(bodies, x):
    return {n: m.bounds for n, m in bodies.meshes_at(x)}


def test_cartpole_meshes_have_the_mjcf_sizes_and_follow_the_state(exp):
    """Rail capsule (r 0.02, half-length 1, along x), cart capsule (r 0.1, half-length 0.1, along x)
    and pole capsule (r 0.049, 0.6 m up) at x = 0; at p = 0.3, theta = 0.4 the cart moves by +0.3
    in x and the pole's top by + l sin(theta) (positive theta tilts the top to +x), the rail stays.
    Catches a quaternion in the wrong order, the wrong joint for a state component, sizes read
    as full instead of half lengths, and the colour of another geom."""
    b = MjcfBodies(exp.simulator, exp.system)
    assert b.names == ["rail", "cart", "cpole"]
    b0 = _bounds(b, [0.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(b0["rail"], [[-1.02, -0.02, -0.02], [1.02, 0.02, 0.02]], atol=TOL)
    np.testing.assert_allclose(b0["cart"], [[-0.2, -0.1, -0.1], [0.2, 0.1, 0.1]], atol=TOL)
    np.testing.assert_allclose(b0["cpole"], [[-R_POLE, -R_POLE, -R_POLE], [0.001 + R_POLE, R_POLE, L_POLE + R_POLE]],
                               atol=TOL)
    p, th = 0.3, 0.4
    b1 = _bounds(b, [p, th, 0.7, -0.5])  # velocities do not move geometry
    np.testing.assert_allclose(b1["rail"], b0["rail"], atol=1e-12)
    np.testing.assert_allclose(b1["cart"], b0["cart"] + [[p, 0, 0], [p, 0, 0]], atol=1e-9)
    top = np.array([p + L_POLE * np.sin(th), 0.0, L_POLE * np.cos(th)])  # the pole's end, 1 mm tilt aside
    assert b1["cpole"][1][0] == pytest.approx(top[0] + R_POLE, abs=TOL)
    assert b1["cpole"][1][2] == pytest.approx(top[2] + R_POLE, abs=TOL)
    assert b1["cpole"][0][0] == pytest.approx(p - R_POLE, abs=TOL)  # the hinge end rides on the cart
    # the vertex highest up is the pole's top, moved to +x
    pole = dict(b.meshes_at([p, th, 0, 0]))["cpole"]
    assert pole.vertices[np.argmax(pole.vertices[:, 2])][0] > p + 0.2
    cols = {n: tuple(m.visual.face_colors[0]) for n, m in zip(b.names, b.meshes)}
    assert cols["cpole"] == (0, 178, 178, 255) and cols["cart"] == (178, 178, 0, 255) \
        and cols["rail"] == (76, 76, 178, 255)


MJCF_ALL = """<mujoco>
  <asset><mesh name="tet" vertex="0 0 0  0.2 0 0  0 0.3 0  0 0 0.4"/></asset>
  <worldbody>
    <geom name="floor" type="plane" size="0.5 0.4 0.1" pos="0 0 -1"/>
    <geom name="infinite" type="plane" size="0 0 1" pos="0 0 -2"/>
    <body name="cart">
      <joint name="slider" type="slide" axis="1 0 0"/>
      <geom name="box" type="box" size="0.1 0.2 0.3" pos="0 0 0"/>
      <geom name="ball" type="sphere" size="0.15" pos="1 0 0"/>
      <geom name="can" type="cylinder" size="0.05 0.25" pos="2 0 0"/>
      <geom name="egg" type="ellipsoid" size="0.1 0.2 0.3" pos="3 0 0"/>
      <geom name="tet" type="mesh" mesh="tet" pos="4 0 0"/>
      <body name="pole">
        <joint name="hinge" type="hinge" axis="0 1 0"/>
        <geom name="stick" type="capsule" fromto="0 0 0 0 0 0.5" size="0.02"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor name="slide" joint="slider"/></actuator>
</mujoco>
"""


def test_every_geom_type_has_its_mjcf_size(exp, tmp_path):
    """Box (half sizes), sphere, cylinder (radius, half-length), ellipsoid (radii), a finite plane
    (a 1 mm box of its half sizes, top face at the plane) and a mesh geom (the model's mesh
    vertices at the geom's pose); an infinite plane is left out."""
    f = tmp_path / "all.xml"
    f.write_text(MJCF_ALL)
    cfg = SimulatorConfig(kind="mujoco", system="cartpole", steps=1,
                          options={"model": str(f), "positions": ["slider", "hinge"],
                                   "velocities": ["slider", "hinge"], "inputs": ["slide"], "substeps": 1})
    b = MjcfBodies(cfg, exp.system)
    assert "infinite" not in b.names
    bx = _bounds(b, [0.5, 0.0, 0.0, 0.0])
    ext = {n: v[1] - v[0] for n, v in bx.items()}
    np.testing.assert_allclose(ext["box"], [0.2, 0.4, 0.6], atol=1e-9)
    np.testing.assert_allclose(bx["box"].mean(axis=0), [0.5, 0, 0], atol=1e-9)
    np.testing.assert_allclose(ext["ball"], [0.3, 0.3, 0.3], atol=0.02)
    np.testing.assert_allclose(ext["can"][2], 0.5, atol=1e-9)
    np.testing.assert_allclose(ext["can"][:2], [0.1, 0.1], atol=TOL)
    np.testing.assert_allclose(ext["egg"], [0.2, 0.4, 0.6], atol=0.04)
    np.testing.assert_allclose(bx["floor"], [[-0.5, -0.4, -1.001], [0.5, 0.4, -1.0]], atol=1e-9)
    # the tetrahedron's extents, wherever MuJoCo put its frame (it re-centres meshes at their centroid)
    np.testing.assert_allclose(ext["tet"], [0.2, 0.3, 0.4], atol=1e-6)
    assert bx["tet"][0][0] == pytest.approx(4.5, abs=1e-6)
    np.testing.assert_allclose(ext["stick"], [0.04, 0.04, 0.54], atol=TOL)


def test_without_mujoco_no_bodies_and_a_note(exp, monkeypatch):
    """MuJoCo not installed: no bodies, a note naming the extra, no exception."""
    monkeypatch.setitem(sys.modules, "mujoco", None)
    bodies, note = model_bodies(exp.simulator, exp.system)
    assert bodies is None and "[mujoco]" in note and "pip install" in note


def test_app_draws_and_poses_the_cartpole(exp, monkeypatch):
    """The app with the cart-pole experiment: one scene node per geom under /bodies/mjcf, posed at
    the rollouts' initial state, moved by a rollout state, the scene bounds widened to hold them;
    without MuJoCo the app starts and shows the note."""
    from simgap_viz.app import SimgapApp
    from simgap_viz.experiment import app_inputs
    from simgap_viz.layers import scene

    settings, _, spec, _, e = app_inputs(experiment="cartpole", profile="small")
    assert settings.simulator == "mujoco"
    app = SimgapApp(port=0, settings=settings, spec=spec, experiment=e, executor="serial")
    try:
        bodies, handles = app.body_model
        assert bodies.names == ["rail", "cart", "cpole"] and len(handles) == 3
        x0 = np.asarray(app.settings.x0, dtype=float)  # the experiment's [rollout] x0: theta = 0.05
        pos, wxyz = bodies.poses(x0)
        np.testing.assert_allclose(handles[2].wxyz, wxyz[2]) and np.testing.assert_allclose(handles[2].position, pos[2])
        scene.pose_bodies(app, [0.4, -0.3, 0.0, 0.0])
        assert handles[1].position[0] == pytest.approx(0.4, abs=1e-9)          # the cart moved to p
        # the pole turned about y by theta = -0.3: the node's rotation takes the capsule's axis (its
        # local z; fromto points it down the pole) to +-(sin th', 0, cos th'), th' = theta plus the
        # MJCF's 1 mm tilt
        w, qx, qy, qz = handles[2].wxyz
        axis = np.array([2 * (qx * qz + qy * w), 2 * (qy * qz - qx * w), 1 - 2 * (qx * qx + qy * qy)])
        th = -0.3 + np.arctan2(0.001, 0.6)
        assert abs(axis @ [np.sin(th), 0.0, np.cos(th)]) == pytest.approx(1.0, abs=1e-9)
        lo, hi = scene.scene_bounds(app)
        assert hi[0] >= scene.MODEL_LEFT + 2.0  # the 2.04 m rail beside the square
        assert app.server.scene._handle_from_node_name.get("/bodies/model") is not None
    finally:
        app.stop()

    monkeypatch.setitem(sys.modules, "mujoco", None)
    app = SimgapApp(port=0, settings=settings, spec=spec, experiment=e, executor="serial")
    try:
        assert app.body_model is None and app.body_frame is None
        assert "/bodies/label" in app.server.scene._handle_from_node_name
    finally:
        app.stop()


ARM = Path(__file__).resolve().parents[1] / "examples" / "arm"


def test_urdf_link_follows_the_state_like_the_mjcf():
    """examples/arm: the URDF's 0.6 m cylinder (r 0.02) hangs from the shoulder at theta = 0 and,
    at theta = 0.3, lies where the MJCF's capsule of the same link lies (both turn about +y, the
    bottom end to -x): the same centre to 2e-3 (tessellation), the pose to 1e-6. Catches a link frame taken at the centre
    of mass, a local visual frame left out, and the wrong joint set."""
    urdf = load_experiment(ARM / "arm_urdf.toml", profile=None)
    ub = UrdfBodies(urdf.simulator, urdf.system)
    try:
        (name, rod), = ub.meshes_at([0.0, 0.0])
        np.testing.assert_allclose(rod.bounds, [[-0.02, -0.02, -0.6], [0.02, 0.02, 0.0]], atol=2e-3)
        th = 0.3
        (_, rod), = ub.meshes_at([th, 0.4])
        mj = dict(MjcfBodies(load_experiment(ARM / "arm_mujoco.toml", profile=None).simulator,
                             urdf.system).meshes_at([th, 0.4]))["link"]
        np.testing.assert_allclose(rod.bounds.mean(axis=0)[[0, 2]], [-0.3 * np.sin(th), -0.3 * np.cos(th)],
                                   atol=2e-3)
        np.testing.assert_allclose(rod.bounds.mean(axis=0), mj.bounds.mean(axis=0), atol=2e-3)
        pos, wxyz = ub.poses([th, 0.0])
        w, qx, qy, qz = wxyz[0]
        assert 2 * np.arctan2(qy, w) == pytest.approx(th, abs=1e-6) and abs(qx) + abs(qz) < 1e-6  # PyBullet's floats
        np.testing.assert_allclose(pos[0], [-0.3 * np.sin(th), 0.0, -0.3 * np.cos(th)], atol=1e-6)
    finally:
        ub.close()


URDF_OFFSET_BASE = """<?xml version="1.0"?>
<robot name="offset">
  <link name="base">
    <inertial><origin xyz="0.3 0 0"/><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>
    <visual><origin xyz="0 0 0.5"/><geometry><box size="0.2 0.4 0.6"/></geometry></visual>
  </link>
  <link name="arm">
    <inertial><origin xyz="0 0 -0.25"/><mass value="1"/><inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.01"/></inertial>
    <visual><origin xyz="0 0 -0.25"/><geometry><sphere radius="0.1"/></geometry></visual>
  </link>
  <joint name="j" type="continuous"><parent link="base"/><child link="arm"/><origin xyz="1 0 0"/><axis xyz="0 1 0"/></joint>
</robot>
"""


def test_urdf_base_visual_is_placed_from_the_link_frame_not_the_centre_of_mass(tmp_path):
    """A base whose centre of mass is 0.3 m off its link frame: its box stands at the link frame
    plus the visual origin (PyBullet's base pose is the centre of mass: the offset must be undone),
    the child's sphere at the joint origin plus its visual origin turned by the joint angle."""
    from simgap.simulators.base import SimulatorConfig
    from simgap.system_ref import resolve_system

    f = tmp_path / "offset.urdf"
    f.write_text(URDF_OFFSET_BASE)
    cfg = SimulatorConfig(kind="pybullet_urdf", system="arm", steps=1,
                          options={"urdf": str(f), "positions": ["j"], "velocities": ["j"], "inputs": ["j"]})
    b = UrdfBodies(cfg, resolve_system(str(ARM / "arm.toml")))
    try:
        shapes = dict(b.meshes_at([0.5, 0.0]))
        box = next(m for n, m in shapes.items() if n.startswith("link-1"))
        ball = next(m for n, m in shapes.items() if n.startswith("link0"))
        np.testing.assert_allclose(box.bounds, [[-0.1, -0.2, 0.2], [0.1, 0.2, 0.8]], atol=1e-6)
        np.testing.assert_allclose(ball.bounds.mean(axis=0), [1 - 0.25 * np.sin(0.5), 0, -0.25 * np.cos(0.5)],
                                   atol=2e-3)
    finally:
        b.close()


def test_app_draws_the_urdf_arm():
    """The app with examples/arm/arm_urdf.toml: the link under /bodies/model, labelled PyBullet."""
    from simgap_viz.app import SimgapApp
    from simgap_viz.experiment import app_inputs

    settings, _, spec, _, e = app_inputs(experiment=str(ARM / "arm_urdf.toml"), profile="base")
    assert settings.simulator == "pybullet_urdf"
    app = SimgapApp(port=0, settings=settings, spec=spec, experiment=e, executor="serial")
    try:
        bodies, handles = app.body_model
        assert isinstance(bodies, UrdfBodies) and len(handles) == 1
        assert "/bodies/label" in app.server.scene._handle_from_node_name
    finally:
        app.stop()

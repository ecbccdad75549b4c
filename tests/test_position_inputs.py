"""Position- and velocity-controlled inputs (URDF: POSITION_CONTROL, per-joint modes; MJCF: position
actuators) and driven joints that start each period at their targets."""

import copy
from pathlib import Path

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.simulators import make_simulator

pytest.importorskip("pybullet")

REPO = Path(__file__).resolve().parents[1]
URDF = str(REPO / "assets" / "urdf" / "pendulum.urdf")

# the pendulum URDF's hinge as a position-driven joint: u is the target angle [rad]
HINGE = """name = "hinge_target"
states = ["theta", "omega"]
inputs = ["target"]
x_lo = [-3.0, -10.0]
x_hi = [3.0, 10.0]
tau = 0.5
input_set = [[-0.5], [0.0], [0.5]]
[dynamics]
kind = "discrete"
theta = "target"
omega = "0"
"""


def _system(tmp_path, text):
    from simgap.system_ref import resolve_system
    f = tmp_path / (text.split('"')[1] + ".toml")
    f.write_text(text)
    return resolve_system(str(f))


def _hinge(tmp_path, **options):
    s = _system(tmp_path, HINGE)
    return {"kind": "pybullet_urdf", "system": s.name,
            "options": {"urdf": URDF, "positions": ["hinge"], "velocities": ["hinge"], "inputs": ["hinge"],
                        "substeps": 100, **options}}, s


def test_urdf_position_mode_holds_the_joint_at_its_target(tmp_path):
    """POSITION_CONTROL with a strong motor ends the period at the target angle at rest, from any
    start; the same input as a torque does something else entirely."""
    c, s = _hinge(tmp_path, input_mode="position", max_force=200, position_gain=0.3)
    x = np.array([[1.0, 0.0], [-1.0, 2.0], [0.0, 0.0]])
    u = np.array([[0.5], [-0.5], [0.0]])
    with make_simulator(c, s) as sim:
        y = sim.step(x, u, np.random.default_rng(0))
    assert np.allclose(y[:, 0], u[:, 0], atol=0.02), y
    assert np.all(np.abs(y[:, 1]) < 0.1), y
    c2, _ = _hinge(tmp_path, input_mode="torque")
    with make_simulator(c2, s) as sim:
        y2 = sim.step(x, u, np.random.default_rng(0))
    assert np.abs(y2[:, 0] - u[:, 0]).max() > 0.3


def test_urdf_mixed_modes_batched_equals_one_at_a_time(tmp_path):
    pytest.importorskip("pybullet_data")
    c, s = _racecar(tmp_path, driven_start="target")
    c["noise"] = {"actuation_std": [0.05, 0.02], "sensor_std": 0.001}
    rng = np.random.default_rng(3)
    x = np.c_[np.full(5, 1.0), np.full(5, 1.0), rng.uniform(-3, 3, 5)]
    u = s.inputs[rng.integers(0, len(s.inputs), 5)]
    with make_simulator(c, s) as sim:
        noise = sim.draw_noise(5, np.random.default_rng(4))
        yb = sim.step_with_noise(x, u, noise)
        y1 = np.concatenate([sim.step_with_noise(x[i:i + 1], u[i:i + 1], {k: v[i:i + 1] for k, v in noise.items()})
                             for i in range(5)])
    assert np.array_equal(yb, y1)


RACECAR = """name = "racecar_t"
states = ["x", "y", "theta"]
inputs = ["v", "delta"]
x_lo = [0.0, 0.0, -3.14159265]
x_hi = [2.0, 2.0, 3.14159265]
tau = 0.5
angles = ["theta"]
input_set = [[1.0, 0.0], [1.0, 0.4], [1.0, -0.4]]
[dynamics]
kind = "discrete"
x = "x + dt*v*cos(theta)"
y = "y + dt*v*sin(theta)"
theta = "theta + dt*v*tan(delta)/0.325"
"""


def _racecar(tmp_path, **options):
    import pybullet_data
    s = _system(tmp_path, RACECAR)
    urdf = str(Path(pybullet_data.getDataPath()) / "racecar" / "racecar.urdf")
    return {"kind": "pybullet_urdf", "system": s.name, "options": {
        "urdf": urdf, "base_pose": True, "ground": True, "base_height": 0.05, "substeps": 20, "copies": 4,
        "inputs": ["left_rear_wheel_joint", "right_rear_wheel_joint", "left_steering_hinge_joint",
                   "right_steering_hinge_joint"],
        "input_mode": ["velocity", "velocity", "position", "position"],
        "input_map": [[20.0, 0.0], [20.0, 0.0], [0.0, 1.0], [0.0, 1.0]],
        "max_force": [10, 10, 50, 50], "position_gain": 0.3, **options}}, s


def test_urdf_steering_by_position_turns_the_car_and_target_start_turns_it_more(tmp_path):
    """The racecar's steering hinges by position, its rear wheels by velocity: +delta turns left,
    -delta right, 0 drives straight; starting each period with the steering at its target (the angle
    the previous period's command left it at) turns more than starting straight."""
    pytest.importorskip("pybullet_data")
    x = np.array([[1.0, 1.0, 0.0]] * 3)
    u = np.array([[1.0, 0.0], [1.0, 0.4], [1.0, -0.4]])
    turns = {}
    for start in ("rest", "target"):
        # a slow steering servo (small gain and force): from straight it takes most of the period to turn
        c, s = _racecar(tmp_path, driven_start=start, position_gain=0.01, max_force=[10, 10, 2, 2])
        with make_simulator(c, s) as sim:
            y = sim.step(x, u, np.random.default_rng(0))
        d = s.diff(y, x)
        assert abs(d[0, 2]) < 0.02 and d[0, 0] > 0.05, (start, d)
        assert d[1, 2] > 0.01 and d[2, 2] < -0.01, (start, d)
        turns[start] = d[1, 2] - d[2, 2]
    assert turns["target"] > 1.3 * turns["rest"], turns


@pytest.mark.parametrize("options,words", [
    ({"input_mode": "pos"}, ["input_mode 'pos'", "torque, velocity, position"]),
    ({"input_mode": ["position", "velocity"]}, ["one per entry of options.inputs (1)"]),
    ({"max_force": [1, 2]}, ["options.max_force", "1 numbers"]),
    ({"input_mode": "torque", "driven_start": "target"}, ["driven_start = 'target'", "'hinge' is torque-driven"]),
    ({"position_gain": -1}, ["options.position_gain"]),
])
def test_urdf_input_mode_bad_input(tmp_path, options, words):
    c, s = _hinge(tmp_path, **options)
    with pytest.raises(SimgapError) as e:
        make_simulator(c, s)
    for w in words:
        assert w in str(e.value), (w, str(e.value))


# MJCF: a slide driven by a position actuator (kp 100, kv 20, gear 2) and not in the state; the state is
# a second body's position, pushed by a spring from the first: where the first starts matters
SLIDES = """<mujoco><option timestep="0.001" gravity="0 0 0"/>
<worldbody>
<body name="a"><joint name="sa" type="slide" axis="1 0 0"/><geom type="box" size="0.05 0.05 0.05" mass="1"/></body>
<body name="b"><joint name="sb" type="slide" axis="1 0 0"/><geom type="box" size="0.05 0.05 0.05" mass="1"
  contype="0" conaffinity="0"/></body>
</worldbody>
<tendon><fixed name="spring" stiffness="50"><joint joint="sa" coef="1"/><joint joint="sb" coef="-1"/></fixed></tendon>
<actuator><position name="hold" joint="sa" kp="100" kv="20" gear="2"/></actuator>
</mujoco>"""
FOLLOWER = """name = "follower"
states = ["pb"]
inputs = ["c"]
x_lo = [-5]
x_hi = [5]
tau = 0.01
input_set = [[0.0], [1.0]]
[dynamics]
kind = "discrete"
pb = "pb"
"""


def test_mujoco_position_actuator_joint_starts_at_ctrl_over_gear(tmp_path):
    """driven_start = "target" puts the position actuator's joint at ctrl / gear at the start: the
    spring then pulls the state body towards it at once; from rest at qpos0 it pulls it less."""
    pytest.importorskip("mujoco")
    (tmp_path / "slides.xml").write_text(SLIDES)
    s = _system(tmp_path, FOLLOWER)
    moved = {}
    for start in ("rest", "target"):
        c = {"kind": "mujoco", "system": s.name, "options": {"model": str(tmp_path / "slides.xml"),
                                                             "positions": ["sb"], "inputs": ["hold"],
                                                             "driven_start": start, "threads": 1}}
        with make_simulator(c, s) as sim:
            y = sim.step(np.zeros((1, 1)), np.array([[1.0]]), np.random.default_rng(0))
        moved[start] = float(y[0, 0])
    # spring force 50 (0.5 - 0) on a 1 kg body for 0.01 s: about 0.5 * 25 * 1e-4 = 1.25e-3 m from the target start
    assert moved["target"] == pytest.approx(50 * 0.5 * 0.01 ** 2 / 2, rel=0.2), moved
    assert abs(moved["rest"]) < 0.3 * moved["target"], moved


def test_mujoco_driven_start_refuses_a_motor(tmp_path):
    pytest.importorskip("mujoco")
    xml = SLIDES.replace('<position name="hold" joint="sa" kp="100" kv="20" gear="2"/>', '<motor name="hold" joint="sa"/>')
    (tmp_path / "slides.xml").write_text(xml)
    s = _system(tmp_path, FOLLOWER)
    c = {"kind": "mujoco", "system": s.name, "options": {"model": str(tmp_path / "slides.xml"), "positions": ["sb"],
                                                         "inputs": ["hold"], "driven_start": "target"}}
    with pytest.raises(SimgapError, match="neither"):
        make_simulator(c, s)

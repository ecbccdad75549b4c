"""Generic simulator backends (any URDF through PyBullet, any MJCF through MuJoCo): agreement with
the built-in pendulum, batched == one-at-a-time (bit-identical), randomization against the
formula, model files confined to the experiment's folder, bad input and a missing extra."""

import builtins
import copy
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.simulators import make_simulator
from simgap.systems import get_system

pytest.importorskip("pybullet")

REPO = Path(__file__).resolve().parents[1]
URDF = str(REPO / "assets" / "urdf" / "pendulum.urdf")
MJCF = str(REPO / "assets" / "urdf" / "pendulum.xml")
CARTPOLE = REPO / "assets" / "experiments" / "cartpole" / "inverted_pendulum.xml"
PEND = {"kind": "pybullet_pendulum", "system": "pendulum"}
PEND_URDF = {"kind": "pybullet_urdf", "system": "pendulum",
             "options": {"urdf": URDF, "positions": ["hinge"], "velocities": ["hinge"], "inputs": ["hinge"]}}
PEND_MJ = {"kind": "mujoco", "system": "pendulum",
           "options": {"model": MJCF, "positions": ["hinge"], "velocities": ["hinge"], "inputs": ["torque"]}}
G, M, L = 9.81, 1.0, 1.0
I_PIVOT = M * L * L / 3.0


def cfg(base, **sections):
    out = copy.deepcopy(base)
    for k, v in sections.items():
        out[k] = {**out.get(k, {}), **v} if isinstance(v, dict) else v
    return out


def rows(noise, i, j):
    return {k: v[i:j] for k, v in noise.items()}


def samples(rng, B, system="pendulum"):
    s = get_system(system)
    return rng.uniform(s.x_lo, s.x_hi, (B, s.n)), s.inputs[rng.integers(0, len(s.inputs), B)]


def one_at_a_time(sim, x, u, noise):
    return np.concatenate([sim.step_with_noise(x[i:i + 1], u[i:i + 1], rows(noise, i, i + 1))
                           for i in range(len(x))])


# ----------------------------------------------------------------------------------------
# pybullet_urdf
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("steps", [1, 3])
def test_urdf_pendulum_agrees_with_pybullet_pendulum(rng, steps):
    """The built-in pendulum written as a pybullet_urdf config gives the pybullet_pendulum
    simulator's numbers (same actuation noise, same joint damping) to 1e-12."""
    x, u = samples(rng, 120)
    act = 0.3 * rng.standard_normal((120, 1))
    with make_simulator(cfg(PEND, steps=steps, effects={"joint_damping": 0.2})) as a, \
            make_simulator(cfg(PEND_URDF, steps=steps, effects={"joint_damping": 0.2})) as b:
        na, nb = a.draw_noise(120, rng), b.draw_noise(120, rng)
        na["act"], nb["act"] = act, act
        ya, yb = a.step_with_noise(x, u, na), b.step_with_noise(x, u, nb)
    assert np.max(np.abs(ya - yb)) <= 1e-12
    assert np.max(np.abs(yb - x)) > 1e-4  # it moved
    if steps == 1:  # and it is the pendulum: the nominal omega+ at u + a, less the damping's tau c omega / I
        nominal = get_system("pendulum").f(x, u + act)[:, 1] - 0.005 * 0.2 * x[:, 1] / I_PIVOT
        assert np.max(np.abs(yb[:, 1] - nominal)) < 1e-12


def test_urdf_batched_equals_one_at_a_time_all_keys(rng):
    """Every noise and randomization key on, copies fewer than rows: bit-identical rows."""
    c = cfg(PEND_URDF, steps=3, noise={"actuation_std": 0.2, "sensor_std": 1e-3, "process_std": [1e-3, 1e-2]},
            randomize={"mass": 0.2, "joint_damping": 0.2, "friction": 0.1}, effects={"joint_damping": 0.1},
            options={"copies": 4})
    x, u = samples(rng, 11)
    with make_simulator(c) as sim:
        noise = sim.draw_noise(11, np.random.default_rng(3))
        y = sim.step_with_noise(x, u, noise)
        rev = {k: v[::-1] for k, v in noise.items()}
        assert np.array_equal(y, one_at_a_time(sim, x[::-1], u[::-1], rev)[::-1])
        assert np.array_equal(y, sim.step(x, u, np.random.default_rng(3)))  # seeded: same draws
        assert not np.array_equal(y, sim.step(x, u, np.random.default_rng(4)))


def test_urdf_randomized_mass_and_damping_follow_the_model(rng):
    """Mass (and inertia) times f leaves the gravity term and divides the torque term by f; damping
    c times f_d: omega+ = omega + tau (-(3g/2l) sin th + 3 u / (f m l^2) - f_d c omega / (f I))."""
    c0, tau = 0.3, 0.005
    c = cfg(PEND_URDF, randomize={"mass": 0.2, "joint_damping": 0.2}, effects={"joint_damping": c0},
            options={"copies": 7})
    x, u = samples(rng, 40)
    with make_simulator(c) as sim:
        noise = sim.draw_noise(40, rng)
        y = sim.step_with_noise(x, u, noise)
        f = noise["mass"][:, sim.links.index(0)]
        fd = noise["damping"][:, 0]
    assert np.std(f) > 0.05 and np.std(fd) > 0.05
    th, om, uu = x[:, 0], x[:, 1], u[:, 0]
    om_next = om + tau * (-(3 * G / (2 * L)) * np.sin(th) + 3 * uu / (f * M * L * L) - fd * c0 * om / (f * I_PIVOT))
    assert np.max(np.abs(y[:, 1] - om_next)) < 1e-12
    assert np.max(np.abs(y[:, 0] - (th + tau * om_next))) < 1e-12


def test_urdf_mobile_base_drives_and_is_batch_independent(rng):
    """A differential drive (the TurtleBot URDF) with its planar pose as the state and wheel velocity
    targets as inputs: equal wheel speeds drive it along its heading; rows are bit-identical alone."""
    tb = get_system("turtlebot")
    c = {"kind": "pybullet_urdf", "system": "turtlebot", "steps": 10,
         "noise": {"actuation_std": 0.5}, "randomize": {"friction": 0.1},
         "options": {"urdf": str(REPO / "assets" / "urdf" / "diffbot.urdf"), "base_pose": True, "ground": True,
                     "inputs": ["wheel_left_joint", "wheel_right_joint"], "input_mode": "velocity",
                     "base_height": 0.034, "substeps": 2, "copies": 3}}
    import dataclasses
    s = dataclasses.replace(tb, inputs=np.array([[10.0, 10.0], [5.0, -5.0]]), input_names=("wl", "wr"))
    x = np.array([[0.5, 0.5, 0.0], [0.5, 0.5, np.pi / 2], [1.0, 1.0, 0.3], [1.0, 1.0, -2.0]])
    u = np.array([[10.0, 10.0], [10.0, 10.0], [5.0, -5.0], [10.0, 10.0]])
    with make_simulator(c, s) as sim:
        noise = sim.draw_noise(4, rng)
        y = sim.step_with_noise(x, u, noise)
        assert np.array_equal(y, one_at_a_time(sim, x, u, noise))
        quiet = {k: (np.ones_like(v) if k in ("mass", "damping", "friction") else np.zeros_like(v))
                 for k, v in noise.items()}
        y0 = sim.step_with_noise(x, u, quiet)
    d = y0[:, :2] - x[:, :2]
    assert d[0, 0] > 0.01 and abs(d[0, 1]) < 0.2 * d[0, 0]      # heading 0: along +x
    assert d[1, 1] > 0.01 and abs(d[1, 0]) < 0.2 * d[1, 1]      # heading pi/2: along +y
    assert abs(y0[2, 2] - x[2, 2]) > 0.05                        # opposite wheels turn it


# ----------------------------------------------------------------------------------------
# mujoco
# ----------------------------------------------------------------------------------------

def test_mujoco_diff_drive_follows_the_unicycle_inputs(rng):
    """assets/urdf/diffbot.xml (bench/bench_mujoco_turtlebot.py): v drives along the heading, omega > 0
    turns left (the tendon signs), the state is the planar pose; rows are bit-identical alone."""
    pytest.importorskip("mujoco")
    c = {"kind": "mujoco", "system": "turtlebot", "steps": 30, "noise": {"actuation_std": [0.03, 0.03]},
         "options": {"model": str(REPO / "assets" / "urdf" / "diffbot.xml"), "threads": 1,
                     "positions": ["root_x", "root_y", "root_yaw"], "velocities": [], "inputs": ["v", "omega"]}}
    s = get_system("turtlebot", steps=30)
    x = np.array([[2.0, 2.0, 0.0], [2.0, 2.0, np.pi / 2], [2.0, 2.0, 0.3], [2.0, 2.0, 0.3]])
    u = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    with make_simulator(c, s) as sim:
        noise = sim.draw_noise(4, rng)
        assert np.array_equal(sim.step_with_noise(x, u, noise), one_at_a_time(sim, x, u, noise))
        y = sim.step_with_noise(x, u, {k: np.zeros_like(v) for k, v in noise.items()})
    f = s.f(x, u)   # the unicycle: 0.3 m along the heading, or +-0.3 rad in place
    assert np.all(np.abs(s.diff(y, f)) < [0.1, 0.1, 0.15])    # starts at rest: up to 0.05 m short (docs)
    assert y[0, 0] - 2.0 > 0.2 and abs(y[0, 1] - 2.0) < 0.01 and y[1, 1] - 2.0 > 0.2 and abs(y[1, 0] - 2.0) < 0.01
    assert y[2, 2] - 0.3 > 0.2 and 0.3 - y[3, 2] > 0.2


@pytest.mark.parametrize("steps", [1, 3])
def test_mujoco_pendulum_agrees_with_pybullet_pendulum(rng, steps):
    """The same rod as MJCF: MuJoCo's semi-implicit Euler gives Bullet's numbers to 1e-12."""
    pytest.importorskip("mujoco")
    x, u = samples(rng, 200)
    act = 0.3 * rng.standard_normal((200, 1))
    with make_simulator(cfg(PEND, steps=steps)) as a, make_simulator(cfg(PEND_MJ, steps=steps)) as b:
        na, nb = a.draw_noise(200, rng), b.draw_noise(200, rng)
        na["act"], nb["act"] = act, act
        ya, yb = a.step_with_noise(x, u, na), b.step_with_noise(x, u, nb)
    assert np.max(np.abs(ya - yb)) <= 1e-12
    assert np.max(np.abs(yb - x)) > 1e-4


def test_mujoco_batched_equals_one_at_a_time_randomized_threads(rng):
    """Noise and per-run models on, 2 threads, model pool smaller than the batch: rows bit-identical
    alone, in another order, and seeded."""
    pytest.importorskip("mujoco")
    c = cfg(PEND_MJ, steps=2, noise={"actuation_std": 0.2, "force_std": 0.1, "sensor_std": 1e-3},
            randomize={"mass": 0.2, "damping": 0.2}, options={"threads": 2, "models_per_batch": 5})
    x, u = samples(rng, 23)
    with make_simulator(c) as sim:
        noise = sim.draw_noise(23, np.random.default_rng(5))
        y = sim.step_with_noise(x, u, noise)
        assert np.array_equal(y, one_at_a_time(sim, x, u, noise))
        p = rng.permutation(23)
        assert np.array_equal(y[p], sim.step_with_noise(x[p], u[p], {k: v[p] for k, v in noise.items()}))
        assert np.array_equal(y, sim.step(x, u, np.random.default_rng(5)))


def test_mujoco_mass_randomization_and_force_noise_follow_the_model(rng):
    """Mass factor f: omega+ = omega + tau (-(3g/2l) sin th + 3 (u + F) / (f m l^2)) with F the
    per-run generalized force on the hinge (force_std)."""
    pytest.importorskip("mujoco")
    tau = 0.005
    c = cfg(PEND_MJ, noise={"force_std": 0.5}, randomize={"mass": 0.2}, options={"models_per_batch": 7})
    x, u = samples(rng, 30)
    with make_simulator(c) as sim:
        noise = sim.draw_noise(30, rng)
        y = sim.step_with_noise(x, u, noise)
        f, F = noise["mass"][:, sim.model.body("rod").id], noise["force"][:, 0]
    assert np.std(f) > 0.05 and np.std(F) > 0.2
    om_next = x[:, 1] + tau * (-(3 * G / (2 * L)) * np.sin(x[:, 0]) + 3 * (u[:, 0] + F) / (f * M * L * L))
    assert np.max(np.abs(y[:, 1] - om_next)) < 1e-12


def test_mujoco_damping_randomization_per_row_on_the_cartpole(rng):
    """Each row runs with its own dof damping: the row equals a direct MuJoCo run of a model whose
    damping is that row's factors times the MJCF's (catches factors applied to the wrong row)."""
    mujoco = pytest.importorskip("mujoco")
    import dataclasses
    s = dataclasses.replace(get_system("pendulum"), name="cp", x_lo=np.full(4, -0.1), x_hi=np.full(4, 0.1),
                            state_names=("p", "th", "pd", "thd"), base_tau=0.04, inputs=np.array([[1.0]]))
    c = {"kind": "mujoco", "system": "pendulum", "randomize": {"damping": 0.3},
         "options": {"model": str(CARTPOLE), "positions": ["slider", "hinge"], "velocities": ["slider", "hinge"],
                     "inputs": ["slide"], "models_per_batch": 3}}
    x = rng.uniform(-0.1, 0.1, (8, 4))
    u = rng.uniform(-1, 1, (8, 1))
    with make_simulator(c, s) as sim:
        noise = sim.draw_noise(8, rng)
        y = sim.step_with_noise(x, u, noise)
        assert sim.substeps == 2
    m = mujoco.MjModel.from_xml_path(str(CARTPOLE))
    m.opt.timestep = 0.02
    d = mujoco.MjData(m)
    for i in range(8):
        m.dof_damping[:] = np.array([1.0, 1.0]) * noise["damping"][i]
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:], d.ctrl[:] = x[i, :2], x[i, 2:], u[i]
        for _ in range(2):
            mujoco.mj_step(m, d)
        assert np.array_equal(y[i], np.r_[d.qpos, d.qvel]), i


# a body on a slide joint driven by a velocity servo (kv 10, gear 2), one period tau = 0.1 s; a welded
# body "lamp" (no joint) and a motor "push" for the refusals
SLIDE_MJCF = """<mujoco><option timestep="0.01" gravity="0 0 0"/>
<worldbody><body name="cart"><joint name="slide" type="slide" axis="1 0 0"/>
<geom type="box" size="0.1 0.1 0.1" mass="1"/>
<body name="lamp" pos="0 0 0.2"><geom type="sphere" size="0.02" mass="0.01"/></body></body></worldbody>
<actuator><velocity name="drive" joint="slide" kv="10" gear="2"/><motor name="push" joint="slide"/></actuator>
</mujoco>"""
SLIDE_SYSTEM = """name = "slide1"
states = ["p"]
inputs = ["v"]
x_lo = [-10]
x_hi = [10]
tau = 0.1
input_set = [[0], [1]]
[dynamics]
kind = "discrete"
p = "p + dt*v"
"""
UNICYCLE5 = """name = "unicycle5"
states = ["x", "y", "theta", "v", "w"]
inputs = ["vc", "wc"]
x_lo = [-5, -5, -3.14159, -1, -2]
x_hi = [5, 5, 3.14159, 1, 2]
tau = 0.01
angles = ["theta"]
input_set = [[0, 0], [0.5, 0], [0, 1.0], [0.5, 1.0]]
[dynamics]
kind = "discrete"
x = "x + dt*vc*cos(theta)"
y = "y + dt*vc*sin(theta)"
theta = "theta + dt*wc"
v = "vc"
w = "wc"
"""
DIFFBOT_MJ = REPO / "assets" / "urdf" / "diffbot.xml"


def _user_system(tmp_path, text, steps=1):
    from simgap.system_ref import resolve_system
    f = tmp_path / (text.split('"')[1] + ".toml")
    f.write_text(text)
    return resolve_system(str(f), steps)


def _slide(tmp_path, **options):
    (tmp_path / "slide.xml").write_text(SLIDE_MJCF)
    s = _user_system(tmp_path, SLIDE_SYSTEM)
    return {"kind": "mujoco", "system": s.name, "options": {"model": str(tmp_path / "slide.xml"),
                                                            "positions": ["slide"], "inputs": ["drive"], **options}}, s


def test_mujoco_velocity_driven_body_in_steady_motion_covers_v_tau(tmp_path):
    """driven_start = "target": the slide starts each period at ctrl / gear and covers v tau within 2 %,
    period after period; started at rest (the default) it covers about 85 % of it (time constant m / (kv gear^2) = 0.025 s)."""
    pytest.importorskip("mujoco")
    for start, lo, hi in (("target", 0.98, 1.02), ("rest", 0.5, 0.9)):
        c, s = _slide(tmp_path, driven_start=start)
        with make_simulator(c, s) as sim:
            x = np.zeros((1, 1))
            for k in range(3):
                y = sim.step(x, np.array([[2.0]]), np.random.default_rng(k))  # ctrl 2, gear 2: 1 m/s
                assert lo < (y - x)[0, 0] / (1.0 * 0.1) < hi, (start, k, y)
                x = y


@pytest.mark.parametrize("base", ["planar", "free"])
def test_mujoco_mobile_base_in_steady_motion_follows_v_tau_within_2_percent(tmp_path, rng, base):
    """assets/urdf/diffbot.xml (a planar base on slides and a yaw hinge, wheels on tendons) and the
    same robot on a free joint: with the base's forward speed and yaw rate in the state and the wheels
    starting at their (tendon) targets, a base moving at the commanded speed covers v tau per period
    within 2 % along its heading, at any heading; started at rest the cover depends on the heading
    (the old behaviour). Noisy rows are bit-identical batched and one at a time, on 2 threads."""
    pytest.importorskip("mujoco")
    model = DIFFBOT_MJ
    options = {"base_joints": ["root_x", "root_y", "root_yaw"]}
    if base == "free":
        text = DIFFBOT_MJ.read_text().replace('<joint name="root_x" type="slide" axis="1 0 0"/>',
                                              '<freejoint name="root"/>')
        text = "\n".join(line for line in text.splitlines()
                         if not any(f'name="root_{k}"' in line for k in ("y", "z", "yaw")))
        model = tmp_path / "diffbot_free.xml"
        model.write_text(text)
        options = {}
    s = _user_system(tmp_path, UNICYCLE5, steps=30)
    c = {"kind": "mujoco", "system": s.name, "steps": 30,
         "options": {"model": str(model), "threads": 2, "base_pose": True, "base_velocity": True,
                     "driven_start": "target", "positions": [], "velocities": [], "inputs": ["v", "omega"],
                     **options}}
    tau = 0.3
    with make_simulator(c, s) as sim:
        for v, heading in ((0.5, 0.0), (0.5, 2.0), (0.3, -1.0)):
            z = np.array([[0.0, 0.0, heading, v, 0.0]])
            for k in range(3):
                z2 = sim.step(z, np.array([[v, 0.0]]), np.random.default_rng(k))
                step = z2[0, :2] - z[0, :2]
                assert abs(np.hypot(*step) / (v * tau) - 1) < 0.02, (base, v, heading, k, z2)
                assert abs(np.arctan2(step[1], step[0]) - heading) < 0.01
                z = z2
        # turning: the yaw servo (kv 0.5 N m s) settles 3.5 % below the commanded rate under wheel slip
        z = np.array([[0.0, 0.0, 0.3, 0.5, 1.0]])
        z2 = sim.step(z, np.array([[0.5, 1.0]]), np.random.default_rng(0))
        assert abs((z2[0, 2] - 0.3) / tau - 1) < 0.05 and abs(z2[0, 4] - 1.0) < 0.05, z2
        x = np.column_stack([rng.uniform(-1, 1, (9, 2)), rng.uniform(-3, 3, 9), rng.uniform(0, 0.5, 9),
                             rng.uniform(-1, 1, 9)])
        u = np.column_stack([rng.uniform(0, 0.5, 9), rng.uniform(-1, 1, 9)])
        noise = sim.draw_noise(9, rng)
        noise["act"] = 0.05 * rng.standard_normal((9, 2))
        assert np.array_equal(sim.step_with_noise(x, u, noise), one_at_a_time(sim, x, u, noise))
    if base == "planar":  # at rest: the cover depends on the heading by far more than 2 %
        t = get_system("turtlebot", steps=30)
        rest = {"kind": "mujoco", "system": "turtlebot", "steps": 30,
                "options": {"model": str(DIFFBOT_MJ), "threads": 1, "positions": ["root_x", "root_y", "root_yaw"],
                            "velocities": [], "inputs": ["v", "omega"]}}
        with make_simulator(rest, t) as sim:
            y = sim.step(np.array([[0, 0, 0.0], [0, 0, 2.0]]), np.array([[0.5, 0], [0.5, 0]]),
                         np.random.default_rng(0))
        cover = np.hypot(y[:, 0], y[:, 1]) / (0.5 * tau)
        assert np.max(np.abs(cover - 1)) > 0.05, cover


@pytest.mark.parametrize("options,words", [
    ({"base_velocity": True}, ["base_velocity", "needs base_pose = true"]),
    ({"base_pose": True}, ["base_pose needs the model's one free joint", "options.base_joints"]),
    ({"base_pose": True, "base_joints": ["slide"]}, ["needs three"]),
    ({"base_pose": True, "base_joints": ["slide", "slide", "slide"]}, ["'slide' twice"]),
    ({"driven_start": "moving"}, ["driven_start must be 'rest' or 'target'"]),
    ({"inputs": ["push"], "driven_start": "target"}, ["needs velocity actuators", "'push'"]),
    ({"velocities": ["lamp"], "positions": []}, ["'lamp'", "fixed to its parent", "no velocity"]),
])
def test_mujoco_moving_start_options_are_checked(tmp_path, options, words):
    """A velocity state for a welded body (MJCF's fixed joint), driven_start without velocity
    actuators, a base without a free joint or base_joints: each refused, naming it."""
    pytest.importorskip("mujoco")
    c, s = _slide(tmp_path)
    c["options"].update(options)
    with pytest.raises(SimgapError) as e:
        make_simulator(c, s)
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_mujoco_missing_extra_names_it(monkeypatch):
    """Without the mujoco package the backend says which extra to install, as the install at hand takes it
    (an editable clone: pip install -e ".[mujoco]"; an installed package: pip install 'simgap[mujoco]')."""
    real = builtins.__import__

    def no_mujoco(name, *a, **k):
        if name == "mujoco" or name.startswith("mujoco."):
            raise ImportError("No module named 'mujoco'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_mujoco)
    with pytest.raises(SimgapError, match=r"pip install (-e \"\.\[mujoco\]\"|'simgap\[mujoco\]')"):
        make_simulator(PEND_MJ)


@pytest.mark.parametrize("base,section,value,match", [
    (PEND_URDF, "options", {"positions": ["elbow"]}, r"no revolute/prismatic joint 'elbow'.*hinge"),
    (PEND_URDF, "options", {"inputs": ["hinge", "other"]}, "names 2 joints"),
    (PEND_URDF, "options", {"input_mode": "pos"}, "input_mode"),
    (PEND_URDF, "options", {"urdf": "/nonexistent/robot.urdf"}, "not found"),
    (PEND_URDF, "options", {"urdf_sha256": "0" * 64}, "changed since it was recorded"),
    (PEND_URDF, "randomize", {"length": 0.1}, "unknown randomize keys"),
    (PEND_MJ, "options", {"inputs": ["motor"]}, r"no actuator 'motor'.*torque"),
    (PEND_MJ, "options", {"velocities": ["knee"]}, r"no joint 'knee'.*hinge"),
    (PEND_MJ, "options", {"substeps": 0}, "substeps"),
    (PEND_MJ, "noise", {"force_std": -1}, "force_std"),
])
def test_generic_bad_config(base, section, value, match):
    if base is PEND_MJ:
        pytest.importorskip("mujoco")
    with pytest.raises(SimgapError, match=match):
        make_simulator(cfg(base, **{section: value}))


EXP = """
[system]
name = "pendulum"
[simulator]
kind = "{kind}"
options = {{ {model} = "{path}", positions = ["hinge"], velocities = ["hinge"], inputs = ["{inp}"] }}
[collect]
epsilon = 0.1
n_runs = 4
seed = 1
executor = "serial"
"""


def run_cli(*args, cwd):
    import os
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "simgap", *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("kind,model,inp,path,words", [
    ("pybullet_urdf", "urdf", "hinge", "../pendulum.urdf", ["options.urdf", "no .."]),
    ("mujoco", "model", "torque", "../pendulum.xml", ["leads outside the experiment's folder", "options.model"]),
    ("mujoco", "model", "motor", "pendulum.xml", ["no actuator 'motor'"]),
    ("pybullet_urdf", "urdf", "elbow", "pendulum.urdf", ["no revolute/prismatic joint 'elbow'"]),
    ("mujoco", "model", "torque", "missing.xml", ["does not exist"]),
])
def test_model_file_bad_input_through_the_cli(tmp_path, kind, model, inp, path, words):
    """Through the real command line: non-zero exit, the problem named, no traceback, nothing written."""
    if kind == "mujoco":
        pytest.importorskip("mujoco")
    exp_dir = tmp_path / "exp"
    exp_dir.mkdir()
    for f in (URDF, MJCF):
        shutil.copy(f, tmp_path)
        shutil.copy(f, exp_dir)
    (exp_dir / "e.toml").write_text(EXP.format(kind=kind, model=model, path=path, inp=inp))
    before = sorted(p.name for p in tmp_path.rglob("*"))
    r = run_cli("collect", "e.toml", "--profile", "base", "--out", "data", cwd=exp_dir)
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stdout + r.stderr
    for w in words:
        assert w in r.stdout + r.stderr, r.stdout + r.stderr
    assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_experiment_resolves_and_pins_the_model_file(tmp_path):
    """A model named in an experiment is resolved in its folder and its sha256 recorded; a changed
    file is then refused when the simulator is rebuilt from that configuration."""
    from simgap.config import load_experiment
    shutil.copy(URDF, tmp_path)
    (tmp_path / "e.toml").write_text(EXP.format(kind="pybullet_urdf", model="urdf", path="pendulum.urdf",
                                                inp="hinge"))
    exp = load_experiment(tmp_path / "e.toml", profile=None)
    op = exp.simulator.options
    assert op["urdf"] == str((tmp_path / "pendulum.urdf").resolve()) and len(op["urdf_sha256"]) == 64
    make_simulator(exp.simulator).close()
    with open(tmp_path / "pendulum.urdf", "a") as fh:
        fh.write("<!-- edited -->\n")
    with pytest.raises(SimgapError, match="changed since it was recorded"):
        make_simulator(exp.simulator)

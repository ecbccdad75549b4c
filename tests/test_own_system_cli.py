"""A user's own robot through the command line: experiments without profiles, robot files
nobody here wrote (PyBullet's husky: links without inertial data), the smaller fixes."""

import shutil
import sys
from pathlib import Path

import pytest

from cli_helpers import REPO, refused, simgap

sys.path.insert(0, str(REPO))

DUFFING = REPO / "examples" / "duffing"

HUSKY_SYSTEM = """
name = "husky_unicycle"
states = ["x", "y", "theta"]
inputs = ["fl", "fr", "rl", "rr"]
x_lo = [-2.0, -2.0, -3.14159]
x_hi = [2.0, 2.0, 3.14159]
tau = 0.5
angles = ["theta"]
input_set = [[0, 0, 0, 0], [5, 5, 5, 5]]
[params]
r = 0.165
[dynamics]
kind = "discrete"
x = "x + dt*r*(fl + fr + rl + rr)/4*cos(theta)"
y = "y + dt*r*(fl + fr + rl + rr)/4*sin(theta)"
theta = "theta"
"""

HUSKY_EXPERIMENT = """
system = "unicycle.toml"
[simulator]
kind = "pybullet_urdf"
[simulator.options]
urdf = "husky.urdf"
base_pose = true
inputs = ["front_left_wheel", "front_right_wheel", "rear_left_wheel", "rear_right_wheel"]
input_mode = "velocity"
max_force = 50
ground = true
substeps = 100
copies = 4
base_height = 0.2
[collect]
epsilon = 1.0
n_runs = 2
"""


@pytest.fixture
def duffing(tmp_path):
    d = tmp_path / "duffing"
    shutil.copytree(DUFFING, d)
    return d


def test_an_experiment_without_profiles_runs_with_its_base_settings(duffing):
    from simgap.config import load_experiment
    assert "[profiles" not in (duffing / "experiment.toml").read_text()
    exp = load_experiment(duffing / "experiment.toml")  # the docs' snippet: no profile named
    assert exp.profile is None and exp.collect.n_runs == 30
    r = simgap("collect", "experiment.toml", "--dry-run", cwd=duffing)
    assert r.returncode == 0, r.stderr
    assert "(profile base)" in r.stdout and "experiment-base" in r.stdout
    # an explicit profile must exist
    refused(simgap("collect", "experiment.toml", "--profile", "small", "--dry-run", cwd=duffing),
            "has no profile 'small'")


def test_a_file_with_a_small_profile_still_gets_it():
    from simgap.config import load_experiment
    exp = load_experiment(REPO / "examples" / "arm" / "arm_mujoco.toml")
    assert exp.profile == "small"


def test_links_without_inertial_data_are_summarized_once(tmp_path):
    pybullet_data = pytest.importorskip("pybullet_data")
    src = Path(pybullet_data.getDataPath()) / "husky"
    d = tmp_path / "husky"
    shutil.copytree(src, d)
    (d / "unicycle.toml").write_text(HUSKY_SYSTEM)
    (d / "exp.toml").write_text(HUSKY_EXPERIMENT)
    r = simgap("collect", "exp.toml", "--dry-run", cwd=d, timeout=300)  # builds, calibrates (~1 s), estimates
    assert r.returncode == 0, r.stderr
    err = r.stderr
    assert "No inertial data" not in err and "b3Warning" not in err, err
    line = ("husky.urdf: 6 links without inertial data: assumed 1 kg each (PyBullet's default, unit inertia): "
            "base_footprint, imu_link, top_plate_link, user_rail_link, front_bumper_link, rear_bumper_link")
    assert err.count("links without inertial data") == 1 and line in err, err


def test_rollout_takes_the_experiments_rollout_seed(duffing):
    import json
    text = (duffing / "experiment.toml").read_text().replace("x0 = [0.1, 0.1]", "x0 = [0.1, 0.1]\nseed = 5")
    (duffing / "experiment.toml").write_text(text)
    r = simgap("synthesize", "--no-gap", "--spec", "experiment.toml", "--out", "c.npz", cwd=duffing)
    assert r.returncode == 0, r.stderr
    r = simgap("rollout", "--controller", "c.npz", "--simulator", "experiment.toml", "--n", "20", "--out", "a.json",
               cwd=duffing)
    assert r.returncode == 0, r.stderr
    assert "seed 5" in r.stdout and "[rollout] of experiment.toml" in r.stdout, r.stdout
    a = json.loads((duffing / "a.json").read_text())
    assert a["seed"] == 5 and a["horizon"] == 50, (a["seed"], a["horizon"])  # [rollout] seed and horizon
    r = simgap("rollout", "--controller", "c.npz", "--simulator", "experiment.toml", "--n", "20", "--seed", "2",
               "--out", "b.json", cwd=duffing)
    assert r.returncode == 0 and json.loads((duffing / "b.json").read_text())["seed"] == 2


def test_synthesize_says_when_x0_is_outside_the_winning_domain(duffing):
    r = simgap("synthesize", "--gamma", "0.005,0.03", "--spec", "experiment.toml", "--x0", "0.75,1.15",
               "--out", "c.npz", cwd=duffing)
    assert r.returncode == 3, r.stdout + r.stderr
    assert "is OUTSIDE the winning domain" in r.stdout and (duffing / "c.npz").exists()
    r = simgap("synthesize", "--gamma", "0.005,0.03", "--spec", "experiment.toml", "--x0", "0,0",
               "--out", "d.npz", cwd=duffing)
    assert r.returncode == 0 and "x0            [0.0, 0.0]: winning" in r.stdout, r.stdout


def test_an_output_in_a_missing_folder_says_how_to_fix_it(duffing):
    r = simgap("synthesize", "--no-gap", "--spec", "experiment.toml", "--out", "runs/x.npz", cwd=duffing)
    refused(r, "folder 'runs' does not exist", "mkdir -p 'runs'")
    assert not (duffing / "runs").exists()


@pytest.mark.parametrize("key,value,words", [
    ("inputs", '["shoulder", "shoulder"]', ["options.inputs names 'shoulder' twice"]),
    ("velocities", '["shoulder", "shoulder"]', ["options.velocities names 'shoulder' twice"]),
])
def test_a_joint_named_twice_is_refused(tmp_path, key, value, words):
    d = tmp_path / "arm"
    shutil.copytree(REPO / "examples" / "arm", d)
    for name in ("arm_urdf.toml", "arm_mujoco.toml"):
        text = (d / name).read_text()
        lines = [(f"{key} = {value}" if ln.startswith(f"{key} = ") else ln) for ln in text.splitlines()]
        (d / name).write_text("\n".join(lines) + "\n")
        r = simgap("collect", name, "--dry-run", cwd=d, timeout=300)
        if name == "arm_mujoco.toml" and "extra" in r.stderr and "mujoco" in r.stderr:
            continue  # MuJoCo not installed here: its refusal names the extra instead
        refused(r, *words)


def test_a_velocity_state_on_a_fixed_joint_is_refused(tmp_path):
    pybullet_data = pytest.importorskip("pybullet_data")
    d = tmp_path / "husky"
    shutil.copytree(Path(pybullet_data.getDataPath()) / "husky", d)
    (d / "unicycle.toml").write_text(HUSKY_SYSTEM.replace('states = ["x", "y", "theta"]',
                                                          'states = ["x", "y", "theta", "w"]')
                                     .replace("x_lo = [-2.0, -2.0, -3.14159]", "x_lo = [-2.0, -2.0, -3.14159, -1]")
                                     .replace("x_hi = [2.0, 2.0, 3.14159]", "x_hi = [2.0, 2.0, 3.14159, 1]")
                                     .replace('theta = "theta"', 'theta = "theta"\nw = "w"'))
    (d / "exp.toml").write_text(HUSKY_EXPERIMENT.replace("base_pose = true", 'base_pose = true\nvelocities = ["imu_joint"]'))
    refused(simgap("collect", "exp.toml", "--dry-run", cwd=d, timeout=300),
            "no revolute/prismatic joint 'imu_joint'", "options.velocities", "front_left_wheel")


VW_SYSTEM = """
name = "husky_vw"
states = ["x", "y", "theta"]
inputs = ["v", "w"]
x_lo = [-2.0, -2.0, -3.14159]
x_hi = [2.0, 2.0, 3.14159]
tau = 0.5
angles = ["theta"]
input_set = [[0, 0], [0.5, 0], [0, 1.0], [0.5, 1.0]]
[dynamics]
kind = "discrete"
x = "x + dt*v*cos(theta)"
y = "y + dt*v*sin(theta)"
theta = "theta + dt*w"
"""
#: (v, w) -> (front left, front right, rear left, rear right) wheel speeds [rad/s]: (v -+ w b / 2) / r
VW_MAP = "[[6.06, -1.68], [6.06, 1.68], [6.06, -1.68], [6.06, 1.68]]"


def _husky(tmp_path, system: str, experiment: str):
    pybullet_data = pytest.importorskip("pybullet_data")
    d = tmp_path / "husky"
    if not d.exists():
        shutil.copytree(Path(pybullet_data.getDataPath()) / "husky", d)
    (d / "unicycle.toml").write_text(system)
    (d / "exp.toml").write_text(experiment)
    from simgap.config import load_experiment
    return load_experiment(d / "exp.toml", "base")


def test_an_input_map_drives_several_joints_as_the_same_targets_would(tmp_path):
    """(v, w) through input_map gives bit for bit what four inputs set to the mapped wheel speeds give."""
    import numpy as np
    from simgap.simulators import make_simulator
    mapped = _husky(tmp_path, VW_SYSTEM, HUSKY_EXPERIMENT.replace(
        'input_mode = "velocity"', f'input_mode = "velocity"\ninput_map = {VW_MAP}'))
    direct = _husky(tmp_path, HUSKY_SYSTEM, HUSKY_EXPERIMENT)
    A = np.array(eval(VW_MAP))  # noqa: S307  (the test's own literal)
    x = np.array([[0.0, 0.0, 0.0], [0.5, -0.3, 1.0], [-1.0, 1.0, -2.0]])
    vw = np.array([[0.5, 0.0], [0.0, 1.0], [0.5, 1.0]])
    with make_simulator(mapped.simulator, mapped.system) as a, make_simulator(direct.simulator, direct.system) as b:
        ya = a.step(x, vw, np.random.default_rng(0))
        yb = b.step(x, vw @ A.T, np.random.default_rng(0))
    assert np.array_equal(ya, yb)
    assert ya[0, 0] > 0.05 and ya[1, 2] > 0.0  # forward moves forward, a positive w turns left


@pytest.mark.parametrize("value,words", [
    ("[[6.06, -1.68], [6.06, 1.68], [6.06, -1.68]]", ["options.input_map is 3x2 but must be 4 x 2",
                                                      "front_left_wheel, front_right_wheel"]),
    ("[[1, 2], [1, 2], [1, 2], [1, 2]]", ["rank 1 < 2 inputs"]),
    (None, ["options.inputs names 4 joints but system 'husky_vw' has m=2", "options.input_map"]),
])
def test_a_bad_input_map_is_refused(tmp_path, value, words):
    exp = HUSKY_EXPERIMENT if value is None else HUSKY_EXPERIMENT.replace(
        'input_mode = "velocity"', f'input_mode = "velocity"\ninput_map = {value}')
    _husky(tmp_path, VW_SYSTEM, exp)
    refused(simgap("collect", "exp.toml", "--dry-run", cwd=tmp_path / "husky", timeout=300), *words)


def test_an_input_map_in_mujoco_sets_the_mapped_ctrl(tmp_path):
    """MuJoCo: input_map [[2]] gives bit for bit what the doubled ctrl gives (noise off); a wrong
    shape is refused naming the actuators."""
    import dataclasses
    import numpy as np
    pytest.importorskip("mujoco")
    from simgap.config import load_experiment
    from simgap.simulators import make_simulator
    d = tmp_path / "arm"
    shutil.copytree(REPO / "examples" / "arm", d)
    exp = load_experiment(d / "arm_mujoco.toml")
    plain = dataclasses.replace(exp.simulator, noise={}, randomize={})
    mapped = dataclasses.replace(plain, options={**plain.options, "input_map": [[2.0]]})
    x, u = np.array([[0.2, 0.5], [-0.1, 0.0]]), np.array([[0.3], [-0.4]])
    with make_simulator(mapped, exp.system) as a, make_simulator(plain, exp.system) as b:
        assert np.array_equal(a.step(x, u, np.random.default_rng(0)), b.step(x, 2 * u, np.random.default_rng(0)))
    bad = dataclasses.replace(plain, options={**plain.options, "input_map": [[1.0], [1.0]]})
    from simgap.errors import SimgapError
    with pytest.raises(SimgapError, match=r"options.input_map is 2x1 but must be 1 x 1.*\(torque\)"):
        make_simulator(bad, exp.system)


VW5_SYSTEM = """
name = "husky_vw5"
states = ["x", "y", "theta", "v", "w"]
inputs = ["vc", "wc"]
x_lo = [-2.0, -2.0, -3.14159, -1, -2]
x_hi = [2.0, 2.0, 3.14159, 1, 2]
tau = 0.5
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
#: the husky's wheels: radius 0.17775 m, track 2 x 0.2854 m: (v -+ w b / 2) / r
VW5_MAP = "[[5.626, -1.606], [5.626, 1.606], [5.626, -1.606], [5.626, 1.606]]"


def test_a_base_in_steady_motion_follows_v_tau_within_2_percent(tmp_path):
    """With the base's velocity in the state and the wheels starting at their targets, a base moving
    at the commanded speed covers v tau per period (within 2 %), period after period, at any heading;
    started at rest (the default), it covers far less."""
    import numpy as np
    from simgap.simulators import make_simulator
    moving = HUSKY_EXPERIMENT.replace('base_pose = true', 'base_pose = true\nbase_velocity = true\n'
                                      'driven_start = "target"').replace(
        'input_mode = "velocity"', f'input_mode = "velocity"\ninput_map = {VW5_MAP}')
    exp = _husky(tmp_path, VW5_SYSTEM, moving)
    with make_simulator(exp.simulator, exp.system) as sim:
        for v, heading in ((0.5, 0.0), (0.5, 2.0), (0.3, -1.0)):
            z, u = np.array([[0.0, 0.0, heading, v, 0.0]]), np.array([[v, 0.0]])
            for k in range(3):
                z2 = sim.step(z, u, np.random.default_rng(k))
                step = z2[0, :2] - z[0, :2]
                assert abs(np.hypot(*step) / (v * 0.5) - 1) < 0.02, (v, heading, k, z2)
                assert abs(np.arctan2(step[1], step[0]) - heading) < 0.01
                z = z2
    at_rest = _husky(tmp_path, VW_SYSTEM, HUSKY_EXPERIMENT.replace(
        'input_mode = "velocity"', f'input_mode = "velocity"\ninput_map = {VW5_MAP}'))
    with make_simulator(at_rest.simulator, at_rest.system) as sim:
        y = sim.step(np.zeros((1, 3)), np.array([[0.5, 0.0]]), np.random.default_rng(0))
    assert y[0, 0] < 0.9 * 0.25  # it spends the period reaching the speed


@pytest.mark.parametrize("change,words", [
    (('base_pose = true', 'base_velocity = true'), ["base_velocity", "needs base_pose = true"]),
    (('input_mode = "velocity"', 'input_mode = "torque"\ndriven_start = "target"'),
     ["driven_start = 'target'", "needs input_mode 'velocity' or 'position'"]),
])
def test_moving_start_options_are_checked(tmp_path, change, words):
    _husky(tmp_path, HUSKY_SYSTEM, HUSKY_EXPERIMENT.replace(*change))
    refused(simgap("collect", "exp.toml", "--dry-run", cwd=tmp_path / "husky", timeout=300), *words)

"""examples/arm (docs/own-system.md): a system file written from a user's MJCF and URDF. Its numbers
are the models', and without the joint damping both simulators follow it; with it, the gap is the
damping the file leaves out."""

from pathlib import Path

import numpy as np
import pytest

from simgap.config import load_experiment
from simgap.simulators import make_simulator

ARM = Path(__file__).resolve().parents[1] / "examples" / "arm"


def test_system_file_is_the_mjcf_link():
    """m and the inertia about the shoulder m l^2 / 3 in the file are what MuJoCo compiles."""
    mujoco = pytest.importorskip("mujoco")
    exp = load_experiment(ARM / "arm_mujoco.toml", profile=None)
    p = exp.system.params
    m = mujoco.MjModel.from_xml_path(exp.simulator.options["model"])
    link = m.body("link")
    assert np.isclose(link.mass[0], p["m"], rtol=1e-12)
    i_shoulder = link.inertia[1] + link.mass[0] * link.ipos[2] ** 2  # parallel axes, about y
    assert np.isclose(i_shoulder, p["m"] * p["l"] ** 2 / 3, rtol=1e-9)
    assert np.isclose(-link.ipos[2], p["l"] / 2) and np.isclose(m.opt.timestep, exp.system.base_tau)


@pytest.mark.parametrize("experiment", ["arm_mujoco.toml", "arm_urdf.toml"])
def test_simulators_follow_the_model_up_to_the_damping(experiment, tmp_path):
    """Noise-free, MuJoCo (RK4) and PyBullet (1 ms semi-implicit Euler) follow the file's RK4 model
    closely once the joint damping is taken out of the robot file (within 1e-5 and 2e-4 per
    period); with the damping c = 0.05 N m s/rad the omega gap is -tau c omega_mid / I (I = m l^2 / 3)
    to 10 %: the simulators have the damping the file leaves out, and nothing else."""
    import dataclasses
    if experiment == "arm_mujoco.toml":
        pytest.importorskip("mujoco")
    exp = load_experiment(ARM / experiment, profile=None)
    s = exp.system
    key = "model" if exp.simulator.kind == "mujoco" else "urdf"
    src = Path(exp.simulator.options[key])
    undamped = tmp_path / src.name
    undamped.write_text(src.read_text().replace('damping="0.05"', 'damping="0"'))
    assert undamped.read_text() != src.read_text()
    opts = {k: v for k, v in exp.simulator.options.items() if not k.endswith("_sha256")}
    rng = np.random.default_rng(0)
    x = rng.uniform(s.x_lo, s.x_hi, (200, 2))
    u = s.inputs[rng.integers(0, len(s.inputs), 200)]
    gaps = []
    for path in (src, undamped):
        cfg = dataclasses.replace(exp.simulator, noise={}, randomize={}, options={**opts, key: str(path)})
        with make_simulator(cfg, s) as sim:
            gaps.append(sim.step(x, u, np.random.default_rng(1)) - s.f(x, u))
    damped, free = gaps
    tol = 1e-5 if key == "model" else 2e-4  # RK4 vs RK4; 1 ms semi-implicit Euler vs RK4
    assert np.max(np.abs(free)) < tol, np.max(np.abs(free), axis=0)
    # the damping torque -c omega over the period, omega at the period's midpoint (gravity and the
    # torque change omega by up to 0.2 rad/s within it)
    omega_mid = 0.5 * (x[:, 1] + s.f(x, u)[:, 1])
    expect = -s.base_tau * 0.05 * omega_mid / (s.params["m"] * s.params["l"] ** 2 / 3)
    big = np.abs(omega_mid) > 0.3
    assert big.sum() > 50
    assert np.all(np.abs(damped[big, 1] - expect[big]) <= 0.1 * np.abs(expect[big]) + 2e-4)

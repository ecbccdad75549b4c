"""The double pendulum's pieces, as a user builds them (issue 52 item 8): a system file from the
Lagrangian of a cart with two poles (assets/experiments/double_pendulum/double_pendulum.toml) and
Gymnasium's inverted_double_pendulum.xml in the generic MuJoCo simulator. The file's numbers are the
MJCF's, its mass matrix is MuJoCo's, and noise-free the model is MuJoCo's own physics."""

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from simgap.config import load_experiment  # noqa: E402
from simgap.simulators import make_simulator  # noqa: E402


@pytest.fixture(scope="module")
def exp():
    return load_experiment("double_pendulum", profile=None)


def _M(p, t1, t2):
    """The system file's mass matrix, written again from its comment (the [definitions] are checked
    through the map itself below)."""
    m, l, L, I = p["m"], p["l"], p["L"], p["I"]
    ph = t1 + t2
    a, b, c = p["mc"] + 2 * m, m * l * np.cos(t1) + m * (L * np.cos(t1) + l * np.cos(ph)), m * l * np.cos(ph)
    d, e, f = 2 * I + m * l ** 2 + m * (L ** 2 + l ** 2 + 2 * L * l * np.cos(t2)), I + m * (l ** 2 + L * l * np.cos(t2)), \
        I + m * l ** 2
    return np.array([[a, b, c], [b, d, e], [c, e, f]])


def test_system_file_parameters_are_the_mjcf_bodies(exp):
    """Masses and the poles' inertia computed by hand from the capsules at density 1000 are what
    MuJoCo compiles, damping, gear, gravity and the period are the MJCF's, and the model's M(q) is
    MuJoCo's mj_fullM at 50 random poses (a wrong length, mass or cos term fails by > 1e-3)."""
    p = exp.system.params
    m = mujoco.MjModel.from_xml_path(exp.simulator.options["model"])
    assert np.isclose(p["mc"], m.body("cart").mass[0], rtol=1e-12)
    for b in ("pole", "pole2"):
        assert np.isclose(p["m"], m.body(b).mass[0], rtol=1e-12)
        assert np.isclose(p["I"], m.body(b).inertia[1], rtol=1e-12)   # about the hinge axis y
        assert np.isclose(p["l"], m.body(b).ipos[2], rtol=1e-12)
    assert np.allclose(m.dof_damping, p["damp"]) and np.allclose(m.dof_armature, 0.0)
    assert np.isclose(m.actuator_gear[0, 0], p["gear"])
    assert np.allclose(m.opt.gravity, [p["gx"], 0.0, -p["gz"]])
    assert np.isclose(m.opt.timestep * 5, exp.system.base_tau)
    d = mujoco.MjData(m)
    full = np.zeros((3, 3))
    for q in np.random.default_rng(1).uniform(-3, 3, (50, 3)):
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        mujoco.mj_fullM(m, d, full)
        assert np.allclose(full, _M(p, q[1], q[2]), rtol=0, atol=1e-12), (q, full)


def test_nominal_model_is_mujocos_noise_free_physics(exp):
    """Noise-free, MuJoCo's next state equals the system file's RK4 map over X (grid and continuous
    inputs) to rounding; with the noise on, the one-step velocity spread is at least a fifth of
    tau * gear * actuation_std / (mc + 2 m) (the cart's; the poles' is larger), so the noise is really
    applied."""
    s = exp.system
    rng = np.random.default_rng(0)
    B = 2000
    x = rng.uniform(s.x_lo, s.x_hi, (B, 6))
    for u in (s.inputs[rng.integers(0, len(s.inputs), B)], rng.uniform(-0.1, 0.1, (B, 1))):
        with make_simulator(exp.simulator, s) as sim:
            noise = sim.draw_noise(B, rng)
            quiet = {k: np.zeros_like(v) for k, v in noise.items()}
            free = sim.step_with_noise(x, u, quiet)
            noisy = sim.step_with_noise(x, u, noise)
        f = s.f(x, u)
        assert np.abs(free - f).max() < 1e-9, np.abs(free - f).max(axis=0)
        p = s.params
        floor = 0.2 * s.tau * p["gear"] * exp.simulator.noise["actuation_std"] / (p["mc"] + 2 * p["m"])
        assert np.all((noisy - f)[:, 3:].std(axis=0) > floor), ((noisy - f)[:, 3:].std(axis=0), floor)


@pytest.mark.slow
def test_simgap_run_double_pendulum_is_certified(tmp_path):
    """`simgap run double_pendulum` end to end (about 10 min at load 8 on 2026-12-08; docs/case-studies.md):
    data along the nominal tubes, the gap's slopes from the simulator, and the stochastic certificate
    proves the box tube the synthesis designed itself (no pace, gain or region in the experiment file)
    from x0; the 1000 MuJoCo runs all stay safe, and p_emp >= p_cert - 3 standard errors (SE from p_cert,
    at least 1/R). A certificate whose gamma the tube does not tolerate, or a tube leaving the data's
    boxes, ends without a controller and fails here."""
    import json
    import subprocess
    import sys
    out = tmp_path / "dp"
    r = subprocess.run([sys.executable, "-m", "simgap", "run", "double_pendulum", "--out", str(out), "--no-record"],
                       capture_output=True, text=True, timeout=3500)
    assert r.returncode == 0, r.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    st = s["methods"]["stochastic"]
    assert st["winning_cells"] == 1 and st["failures"] == 0 and st["n_rollouts"] == 1000
    syn = st["synthesis"]
    assert syn["verification"]["ok"] and syn["gap_scale"] >= 1.0
    assert len(syn["designs"]) > 1 and syn["pace_how"] and "chosen" in syn["K_how"]  # the tool's design
    pr = st["per_run_empirical"]
    assert pr["p_cert"] is not None
    R = pr["n_rollouts"]
    se = max(np.sqrt(pr["p_cert"] * (1 - pr["p_cert"]) / R), 1.0 / R)
    assert pr["p_emp"] >= pr["p_cert"] - 3 * se
    assert pr["in_noise_tube"] / R >= pr["p_cert"] - 3 * se

"""The reacher case study's pieces, as a user builds them: a system file from the two-link arm's
equations (assets/experiments/reacher/reacher.toml) and Gymnasium's reacher.xml in the generic MuJoCo
simulator. The file's numbers are the MJCF's, and with them the model is MuJoCo's own physics."""

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from simgap.config import load_experiment  # noqa: E402
from simgap.errors import SimgapError  # noqa: E402
from simgap.simulators import make_simulator  # noqa: E402


@pytest.fixture(scope="module")
def exp():
    return load_experiment("reacher", profile=None)


def test_experiment_parses(exp):
    """X, U, period, target pose, x0 (>= 0.3 rad from the target in each joint, inside X), the cover
    and both profiles load; the target's slide joints are not states."""
    s = exp.system
    assert s.state_names == ("q0", "q1", "v0", "v1") and s.input_names == ("a0", "a1")
    assert s.base_tau == 0.02 and len(s.inputs) == 25
    syn, ro = exp.section("synthesis"), exp.section("rollout")
    x_star, x0 = np.array(syn["x_star"]), np.array(ro["x0"])
    assert np.all(np.abs(x0[:2] - x_star[:2]) >= 0.3)
    assert np.all((s.x_lo <= x0) & (x0 <= s.x_hi)) and np.all((s.x_lo < x_star) & (x_star < s.x_hi))
    assert exp.simulator.options["positions"] == ["joint0", "joint1"]
    st = load_experiment("reacher", profile="stochastic")
    assert st.simulator.randomize == {"mass": 0.02, "damping": 0.1}
    assert exp.simulator.noise == {"actuation_std": 0.0167}


def test_system_file_parameters_are_the_mjcf_bodies(exp):
    """Masses, centres of mass and inertias computed by hand from the capsules and the fingertip
    sphere at density 1000 are what MuJoCo compiles; the model's mass matrix M(q) (armature
    included) is MuJoCo's mj_fullM at random elbow angles."""
    p = exp.system.params
    m = mujoco.MjModel.from_xml_path(exp.simulator.options["model"])
    assert np.isclose(p["m1"], m.body("body0").mass[0], rtol=1e-12)
    assert np.isclose(p["I1"], m.body("body0").inertia[1], rtol=1e-9)        # about z (capsule along x)
    m2 = m.body("body1").mass[0] + m.body("fingertip").mass[0]
    assert np.isclose(p["m2"], m2, rtol=1e-12)
    assert np.allclose(m.dof_armature[:2], p["arm"]) and np.allclose(m.dof_damping[:2], p["damp"])
    assert np.allclose(m.actuator_gear[:, 0], p["gear"]) and np.isclose(m.opt.timestep * 2, exp.system.base_tau)
    d = mujoco.MjData(m)
    A = p["I1"] + p["m1"] * p["c1"] ** 2 + p["I2"] + p["m2"] * (p["l1"] ** 2 + p["c2"] ** 2) + p["arm"]
    B, D = p["m2"] * p["l1"] * p["c2"], p["I2"] + p["m2"] * p["c2"] ** 2
    for q1 in np.random.default_rng(1).uniform(-3, 3, 20):
        d.qpos[:] = m.qpos0
        d.qpos[1] = q1
        mujoco.mj_forward(m, d)
        full = np.zeros((m.nv, m.nv))
        mujoco.mj_fullM(m, d, full)
        mine = np.array([[A + 2 * B * np.cos(q1), D + B * np.cos(q1)], [D + B * np.cos(q1), D + p["arm"]]])
        assert np.allclose(full[:2, :2], mine, rtol=0, atol=1e-12), (q1, full[:2, :2], mine)
        assert np.allclose(full[:2, 2:], 0.0)   # the target's slide joints do not couple to the arm


@pytest.mark.parametrize("profile", [None, "stochastic"])
def test_nominal_model_is_mujocos_noise_free_physics(profile):
    """Noise-free (zero actuation noise, nominal masses and damping), MuJoCo's next state equals the
    system file's RK4 map to 1e-12 over X, for grid and continuous inputs: the gap is rounding
    (measured 8.9e-16 on 2026-12-07). With the noise on, the one-step velocity spread is about tau * 200 * 0.0167
    / (M22 ~ 1 kg m^2) = 0.067 rad/s (std; measured 0.066), so the noise is really applied."""
    e = load_experiment("reacher", profile=profile)
    s = e.system
    rng = np.random.default_rng(0)
    B = 3000
    x = rng.uniform(s.x_lo, s.x_hi, (B, 4))
    for u in (s.inputs[rng.integers(0, len(s.inputs), B)], rng.uniform(-0.1, 0.1, (B, 2))):
        with make_simulator(e.simulator, s) as sim:
            noise = sim.draw_noise(B, rng)
            quiet = {k: (np.ones_like(v) if k in ("mass", "damping") else np.zeros_like(v)) for k, v in noise.items()}
            free = sim.step_with_noise(x, u, quiet)
            noisy = sim.step_with_noise(x, u, noise)
        f = s.f(x, u)
        assert np.abs(free - f).max() < 1e-12
        # MuJoCo clips ctrl to the MJCF's [-1, 1]: at the grid's end values half the noise is cut off, so
        # the spread is checked where u + noise stays inside the range
        inner = np.all(np.abs(u) < 0.9, axis=1)
        spread = (noisy - f)[inner][:, 2:].std(axis=0)
        assert np.all((0.06 < spread) & (spread < 0.07)), spread
        if not inner.all():  # and the clipped ones have less: the certificate sees what MuJoCo applies
            assert np.all((noisy - f)[~inner][:, 2:].std(axis=0) < spread)


def test_unnamed_actuators_by_index(exp):
    """reacher.xml's motors have no name: "#i" addresses them; an index out of range is refused
    naming the count."""
    from dataclasses import replace

    opts = dict(exp.simulator.options, inputs=["#0", "#2"])
    with pytest.raises(SimgapError, match=r"has no actuator '#2'.*2 actuators, #0..#1"):
        make_simulator(replace(exp.simulator, options=opts), exp.system)
    opts = dict(exp.simulator.options, inputs=["motor", "#1"])
    with pytest.raises(SimgapError, match=r"#0 \(no name\)"):
        make_simulator(replace(exp.simulator, options=opts), exp.system)


def test_local_profile_parses_and_its_set_must_lie_in_the_region(tmp_path):
    """The local profile's region and safe set load; simgap run's checks accept its safe set (inside
    the region) and refuse a safe set leaving it, naming the region, before any work."""
    from simgap.pipeline import check_experiment

    e = load_experiment("reacher", profile="local")
    assert e.collect.region == {"q1": [0.8, 1.2], "v0": [-0.5, 0.5], "v1": [-0.5, 0.5]}
    assert e.cover().points[:, 1].min() > 0.8 and np.abs(e.cover().points[:, 2:]).max() < 0.5
    check_experiment(e, tmp_path / "out")
    wide = load_experiment("reacher", profile="local", overrides={"synthesis": {"safe_lo": [0.3, 0.7, -0.5, -0.5]}})
    with pytest.raises(SimgapError, match=r"safe set leaves \[collect\] region in q1 \(q1: set \[0.7, 1.2\], "
                                          r"region \[0.8, 1.2\]\)"):
        check_experiment(wide, tmp_path / "out2")


@pytest.mark.slow
def test_simgap_run_reacher_is_certified_with_a_per_run_probability(tmp_path):
    """`simgap run reacher` end to end (about 13 min at load 18 on 2026-12-07): the stochastic certificate
    proves the tube the synthesis designed (no design keys in the experiment), its per-run statement
    reaches 0.99, and the 1000 MuJoCo runs agree
    with it: p_emp >= p_cert - 3 standard errors (SE from p_cert, at least 1/R), every run inside the
    noise tube counted, none failing."""
    import json
    import subprocess
    import sys
    out = tmp_path / "reacher"
    r = subprocess.run([sys.executable, "-m", "simgap", "run", "reacher", "--out", str(out), "--no-record"],
                       capture_output=True, text=True, timeout=3600)
    assert r.returncode == 0, r.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    st = s["methods"]["stochastic"]
    assert st["winning_cells"] == 1 and st["failures"] == 0 and st["n_rollouts"] == 1000
    pr = st["per_run_empirical"]
    assert pr["p_cert"] is not None and pr["p_cert"] >= 0.99  # the design's target ([certify] confidence 0.995)
    syn = st["synthesis"]
    assert len(syn["designs"]) > 1 and syn["pace_how"] and "chosen by the proof" in syn["K_how"]  # no design keys
    R = pr["n_rollouts"]
    se = max(np.sqrt(pr["p_cert"] * (1 - pr["p_cert"]) / R), 1.0 / R)
    assert pr["p_emp"] >= pr["p_cert"] - 3 * se
    assert pr["in_noise_tube"] / R >= pr["p_cert"] - 3 * se
    assert s["methods"]["deterministic"]["per_run_empirical"]["p_cert"] is None

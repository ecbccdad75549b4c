"""The cart-pole case study's pieces, as a user builds them: a system file from the textbook
equations (assets/experiments/cartpole/cartpole.toml) and Gymnasium's MJCF in the generic MuJoCo
simulator. Its numbers are the MJCF's, and the gap between them is the damping it leaves out."""

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from simgap.config import load_experiment  # noqa: E402
from simgap.simulators import make_simulator  # noqa: E402


@pytest.fixture(scope="module")
def exp():
    return load_experiment("cartpole", profile=None)


def test_system_file_masses_are_the_mjcf_bodies(exp):
    """M, m and the pole's inertia about its centre, computed by hand from the capsules' sizes at
    density 1000, are what MuJoCo compiles from the MJCF (catches a wrong size or formula)."""
    p = exp.system.params
    m = mujoco.MjModel.from_xml_path(exp.simulator.options["model"])
    assert np.isclose(p["M"], m.body("cart").mass[0], rtol=1e-9)
    # the MJCF's pole runs from (0, 0, 0) to (0.001, 0, 0.6): 0.6000008 m long, which the model ignores
    assert np.isclose(p["m"], m.body("pole").mass[0], rtol=2e-6)
    assert np.isclose(p["I"], m.body("pole").inertia[1], rtol=1e-5)  # about the hinge axis (y)
    assert np.isclose(p["l"], m.body("pole").ipos[2], rtol=1e-2)      # the MJCF tilts the pole by 1 mm
    assert np.isclose(exp.system.base_tau, m.opt.timestep)


def test_gap_is_the_damping_the_model_leaves_out(exp):
    """Noise-free and without the MJCF's damping, MuJoCo follows the model (omega within 2e-3 rad/s,
    the 1 mm pole tilt); with it, the omega gap is -tau c (M + m) / D omega, c = 1 N m s/rad."""
    s = exp.system
    rng = np.random.default_rng(0)
    B = 600
    x = rng.uniform(s.x_lo, s.x_hi, (B, 4))
    u = s.inputs[rng.integers(0, len(s.inputs), B)]
    with make_simulator(exp.simulator, s) as sim:
        noise = sim.draw_noise(B, rng)
        quiet = {k: (np.ones_like(v) if k == "mass" else np.zeros_like(v)) for k, v in noise.items()}
        free = sim.step_with_noise(x, u, quiet)
        quiet["damping"] = np.ones_like(quiet["damping"])
        damped = sim.step_with_noise(x, u, quiet)
    f = s.f(x, u)
    assert np.all(np.abs(free - f).max(axis=0) < [1e-5, 1e-4, 5e-4, 2e-3])
    gap = (damped - f)[:, 3]
    assert np.abs(gap).max() > 0.03
    p = s.params
    D = (p["M"] + p["m"]) * (p["I"] + p["m"] * p["l"] ** 2) - (p["m"] * p["l"]) ** 2
    slope = np.polyfit(x[:, 3], gap, 1)[0]
    assert slope == pytest.approx(-s.base_tau * 1.0 * (p["M"] + p["m"]) / D, rel=0.05)


def test_refine_names_the_hinge_damping_from_mujoco_episodes(tmp_path):
    """`simgap refine` on 40 MuJoCo episodes (clocks from 0, episode column) of the experiment's own
    noisy simulator names viscous friction on omega with the MJCF hinge damping's rate
    -(M + m) c / D (c = 1 N m s/rad), and the refined model's 10-step omega error is lower. Fails if
    the damping is not seen, or is named on the wrong state or with the wrong size."""
    import importlib.util
    import json
    from pathlib import Path

    from tests.cli_helpers import simgap

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("refine_cartpole", root / "bench" / "refine_cartpole.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    data = bench.mujoco_episodes(40, 250, seed=3)
    assert np.all(data["t"][data["episode"] == 7][:1] == 0.0) and np.abs(data["x"][:, 1]).max() < 0.2
    np.savez(tmp_path / "logs.npz", **data)
    r = simgap("refine", "--system", bench.SYSTEM_FILE, "--data", tmp_path / "logs.npz", "--out", tmp_path / "r.json",
               "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    report = json.loads((tmp_path / "r.json").read_text())
    from simgap.system_file import load_system_file

    want = bench.expected(load_system_file(bench.SYSTEM_FILE).params)[("omega", "omega")]
    named = {(e["name"], e["state_name"], e.get("variable")): e for e in report["effects"]}
    e = named[("viscous_friction", "omega", "omega")]
    assert abs(e["coefficient"] - want) < max(3 * e["stderr"], 0.1 * abs(want)), (e["coefficient"], e["stderr"], want)
    assert not any(k[1] in ("p", "theta") for k in named)
    ten = report["multistep"]["10"]
    assert ten["rms_after"][3] < 0.8 * ten["rms_before"][3]

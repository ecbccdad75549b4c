"""examples/husky: PyBullet's husky (from pybullet_data, not copied) as a fitted unicycle with two
inputs mapped onto its four wheels, its model files spelled pybullet_data:<path>, and the whole
case study (slow)."""

import dataclasses
import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import REPO, refused, simgap

pytest.importorskip("pybullet_data")
HUSKY = REPO / "examples" / "husky"


def _fit_module():
    spec = importlib.util.spec_from_file_location("husky_fit_gains", HUSKY / "fit_gains.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def exp():
    from simgap.config import load_experiment
    return load_experiment(HUSKY / "experiment.toml", "base")


def test_the_urdf_is_pybullet_datas_own_file_with_its_digest(exp):
    import hashlib
    import pybullet_data
    path = Path(exp.simulator.options["urdf"])
    assert path == (Path(pybullet_data.getDataPath()) / "husky" / "husky.urdf").resolve()
    assert exp.simulator.options["urdf_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert not list(HUSKY.glob("*.urdf")) and not (HUSKY / "meshes").exists()  # nothing copied


def test_two_inputs_drive_the_four_wheels_as_a_unicycle(exp):
    """(v, 0) moves forward along the heading, (0, +w) turns left on the spot, (0, -w) right, and the
    left wheels of a left turn run backwards: what the input map (v -+ w b / 2) / r says."""
    from simgap.simulators import make_simulator
    s = exp.system
    cfg = dataclasses.replace(exp.simulator, noise={}, randomize={})
    x = np.array([[3.0, 3.0, 0.7]] * 3)
    u = np.array([[0.5, 0.0], [0.0, 0.5], [0.0, -0.5]])
    with make_simulator(cfg, s) as sim:
        y = sim.step(x, u, np.random.default_rng(0))
        wheels = sim.input_map @ u[1]
    step = y[0, :2] - x[0, :2]
    assert 0.2 < np.hypot(*step) < 0.25 and abs(np.arctan2(step[1], step[0]) - 0.7) < 0.02, y[0]
    assert y[1, 2] - 0.7 > 0.1 and y[2, 2] - 0.7 < -0.1, y[:, 2]
    assert np.hypot(*(y[1, :2] - x[1, :2])) < 0.05  # on the spot (the pose is the centre of mass)
    assert wheels[0] < 0 < wheels[1] and wheels[2] < 0 < wheels[3]  # left wheels back, right forward


def test_the_files_gains_are_the_fit_and_leave_a_small_noise_free_gap(exp):
    """Refitting gives husky.toml's gains (a simulator change without a refit fails here), and the
    fitted model is within 2 cm and 0.03 rad of the noise-free simulator at every heading and input."""
    fit = _fit_module()
    gains, gap = fit.fit(HUSKY / "experiment.toml", headings=36)
    for k, v in gains.items():
        assert abs(v - exp.system.params[k]) < 0.02 * max(1.0, abs(v)), (k, v, exp.system.params[k])
    assert np.all(gap < [0.02, 0.02, 0.03]), gap
    # the unfitted unicycle (gains 1, no offset) is several times further off
    from simgap.simulators import make_simulator
    s = exp.system
    plain = fit.with_params(s, {"kv": 1.0, "kw": 1.0, "kwv": 0.0, "d": 0.0})
    th = np.linspace(-np.pi, np.pi, 8, endpoint=False)
    x = np.array([[3.0, 3.0, t] for t in th for _ in s.inputs])
    u = np.tile(s.inputs, (len(th), 1))
    with make_simulator(dataclasses.replace(exp.simulator, noise={}, randomize={}), s) as sim:
        y = sim.step(x, u, np.random.default_rng(0))
    g = np.abs(y - plain.f(x, u))
    g[:, 2] = np.minimum(g[:, 2], 2 * np.pi - g[:, 2])
    assert g[:, 2].max() > 3 * gap[2]


def test_cone_friction_switches_bullets_friction_model(exp):
    """The option reaches the engine: on the spot at heading 0 the husky turns several times further
    with the pyramid approximation (false) than with Bullet's default cone."""
    from simgap.simulators import make_simulator
    from simgap.errors import SimgapError
    x, u = np.array([[3.0, 3.0, 0.0]]), np.array([[0.0, 0.5]])
    turned = {}
    for cone in (True, False):
        cfg = dataclasses.replace(exp.simulator, noise={}, randomize={},
                                  options={**exp.simulator.options, "cone_friction": cone})
        with make_simulator(cfg, exp.system) as sim:
            turned[cone] = sim.step(x, u, np.random.default_rng(0))[0, 2]
    assert turned[False] > 3 * turned[True] > 0, turned
    bad = dataclasses.replace(exp.simulator, options={**exp.simulator.options, "cone_friction": "no"})
    with pytest.raises(SimgapError, match="options.cone_friction must be true or false"):
        make_simulator(bad, exp.system)


@pytest.mark.parametrize("value,words", [
    ("pybullet_data:../../../../etc/passwd", ["no absolute path, no ..", "pybullet_data:<path> for a file of the installed pybullet_data", "pybullet_data:../"]),
    ("pybullet_data:husky/no_such.urdf", ["does not exist", "no_such.urdf"]),
])
def test_a_pybullet_data_path_is_confined_and_checked(tmp_path, value, words):
    d = tmp_path / "husky"
    shutil.copytree(HUSKY, d)
    text = (d / "experiment.toml").read_text().replace('"pybullet_data:husky/husky.urdf"', json.dumps(value))
    (d / "experiment.toml").write_text(text)
    refused(simgap("collect", "experiment.toml", "--profile", "base", "--dry-run", cwd=d, timeout=300), *words)


def test_a_pybullet_data_path_cannot_leave_its_folder(tmp_path):
    """Below the schema's own check (no .., no absolute path): the resolved file must lie in pybullet_data."""
    from simgap.config import _model_path
    from simgap.errors import SimgapError
    with pytest.raises(SimgapError, match="leads outside pybullet_data's folder"):
        _model_path("pybullet_data:husky/../../../x.urdf", tmp_path, "options.urdf")
    assert _model_path("pybullet_data:husky/husky.urdf", tmp_path, "u").name == "husky.urdf"
    assert _model_path("robot.urdf", tmp_path, "u") == (tmp_path / "robot.urdf").resolve()  # plain: the folder


@pytest.mark.slow
def test_the_case_study_reaches_the_target_around_the_wall(tmp_path):
    """The whole run (7-17 min on 2 shared cores): the stochastic controller wins x0 and none of its
    1000 rollouts hits the wall; both audits pass."""
    r = simgap("run", HUSKY / "experiment.toml", "--profile", "base", "--out", tmp_path / "run", "--no-record",
               cwd=tmp_path, timeout=3600)
    assert r.returncode == 0, r.stdout + r.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    st = summary["methods"]["stochastic"]
    ro = st["rollouts"]
    assert "skipped" not in ro and ro["n_rollouts"] == 1000, ro
    assert ro["violation_kinds"].get("obstacle", 0) == 0 and ro["successes"] == 1000, ro["outcomes"]
    assert st["audit_pass_rate_joint"] >= 0.99, st["audit_pass_rate_joint"]

"""Rollouts with real synthesized controllers, the numpy simulator and PyBullet (small grids, few rollouts)."""

import json

import numpy as np
import pytest

from simgap.cli import main
from simgap.maps import load_map
from simgap.simulators.base import make_simulator
from simgap.synthesis.controller import Controller, synthesize
from simgap.rollout import load_rollout, rollout
from simgap.synthesis.spec import Box, Spec
from simgap.systems import input_grid, pendulum, turtlebot

K = 30  # TurtleBot abstract step: 30 base periods of 0.01 s (0.3 m at full speed)
ETA = [0.1, 0.1, 0.2]


@pytest.fixture(scope="module")
def arena():
    return load_map("arena")


@pytest.fixture(scope="module")
def tb_system():
    # 25 inputs instead of 441 keep synthesis at ~2 s
    return turtlebot(inputs=input_grid([-1, -1], [1, 1], [5, 5])).with_steps(K)


@pytest.fixture(scope="module")
def tb_ctrl(arena, tb_system):
    res = synthesize(tb_system, arena.spec(tb_system), ETA, x0=arena.x0(tb_system))
    assert res.controller.winning(arena.x0(tb_system)[None])[0]
    return res.controller


@pytest.fixture(scope="module")
def tb_ctrl_gap(arena, tb_system):
    res = synthesize(tb_system, arena.spec(tb_system), ETA, gap=[0.025, 0.025, 0.0], x0=arena.x0(tb_system))
    assert res.controller.winning(arena.x0(tb_system)[None])[0]
    return res.controller


def numpy_sim(system, steps=1, **kw):
    return make_simulator({"kind": "numpy", "system": "turtlebot", "steps": steps, **kw}, system)


def test_nominal_closed_loop_is_sound(arena, tb_ctrl, tb_system):
    """Synthesized without a gap: the nominal model must reach the target within the controller's
    worst-case steps-to-go, and a noise-free simulator without effects gives the same path."""
    x0 = arena.x0(tb_system)
    r = rollout(tb_ctrl, numpy_sim(tb_system), x0, n_rollouts=2, seed=0)
    assert r.hold == K
    assert r.nominal["outcome"] == "success"
    bound = K * int(tb_ctrl.steps_to_go(x0[None])[0])
    assert 0 < r.nominal["reach_time"] <= bound
    assert r.horizon >= bound
    assert r.n_failures == 0 and (r.reach_time == r.nominal["reach_time"]).all()
    np.testing.assert_allclose(r.trajectories[0], r.nominal_trajectory, atol=1e-9)
    # the same controller on a simulator whose step is the whole abstract step: queried every step
    r30 = rollout(tb_ctrl, numpy_sim(tb_system, steps=K), x0, n_rollouts=1, seed=0)
    assert r30.hold == 1 and r30.tau == pytest.approx(0.3) and r30.nominal["outcome"] == "success"


@pytest.mark.parametrize("bias", [[0.08, 0.08, 0.0], [-0.08, 0.08, 0.0], [0.08, -0.08, 0.0], [-0.08, -0.08, 0.0]])
def test_disturbance_within_the_gap_never_fails(arena, tb_ctrl_gap, tb_system, bias):
    """A constant drift of 0.08 m/s moves the robot 0.024 m per abstract step, inside the gap
    0.025 the controller was synthesized with: the specification must hold."""
    r = rollout(tb_ctrl_gap, numpy_sim(tb_system, effects={"bias": bias}), arena.x0(tb_system), n_rollouts=1, seed=0)
    assert r.n_failures == 0, r.to_dict(per_rollout=False)
    assert (r.left_domain_time == -1).all()


def test_noisy_rollouts_are_seeded_and_judged(arena, tb_ctrl, tb_system):
    sim = numpy_sim(tb_system, noise={"actuation_std": [0.2, 0.3]}, effects={"bias": [-0.1, 0.1, 0.0]})
    a = rollout(tb_ctrl, sim, arena.x0(tb_system), n_rollouts=150, seed=0)
    b = rollout(tb_ctrl, sim, arena.x0(tb_system), n_rollouts=150, seed=0)
    np.testing.assert_array_equal(a.trajectories, b.trajectories)
    # every failure is a real obstacle/X violation at its recorded time, every success is in the target
    spec = tb_ctrl.spec
    fail = ~a.success
    xv = a.trajectories[np.flatnonzero(fail), a.violation_time[fail]]
    assert spec.violated(xv, tb_system.x_lo, tb_system.x_hi).all() if fail.any() else True
    xr = a.trajectories[np.flatnonzero(~fail), a.reach_time[~fail]]
    assert spec.reached(xr).all()
    # no state before the end of a successful rollout violates the spec
    for i in np.flatnonzero(~fail)[:20]:
        path = a.trajectories[i, : a.lengths[i] + 1]
        assert not spec.violated(path, tb_system.x_lo, tb_system.x_hi).any()


@pytest.mark.slow  # 2 x 3 PyBullet runs through the arena to the target: the longest single test (7.5 min at
# load 17); PyBullet's physics and obstacles stay in the default suite (next test, test_simulators_pybullet.py)
def test_pybullet_turtlebot_in_the_arena(arena, tb_ctrl, tb_system):
    cfg = {"kind": "pybullet_turtlebot", "system": "turtlebot", "noise": {"actuation_std": [0.05, 0.1]},
           "options": arena.simulator_options()}
    with make_simulator(cfg, tb_system) as sim:
        a = rollout(tb_ctrl, sim, arena.x0(tb_system), n_rollouts=3, seed=1)
        b = rollout(tb_ctrl, sim, arena.x0(tb_system), n_rollouts=3, seed=1)
    np.testing.assert_array_equal(a.trajectories, b.trajectories)
    assert np.isfinite(a.trajectories).all()
    assert a.timing["robot_steps"] == int(a.lengths.sum())
    # PyBullet's differential drive follows the unicycle closely: every rollout ends in the target
    assert a.n_failures == 0, a.to_dict(per_rollout=False)
    assert np.all(np.abs(a.reach_time - a.nominal["reach_time"]) < 0.25 * a.nominal["reach_time"])


def test_pybullet_obstacles_are_physical(arena, tb_system):
    """Driving straight north into the block at x in [2.7, 3.1], y >= 3.5: the spec flags the
    collision where the grown box begins, and without the spec the body stops at the wall."""

    class North:
        system, hold = tb_system, 1
        spec = Spec("reach_avoid", target=Box([0.2, 0.2, -np.inf], [0.9, 0.9, np.inf]))

        def input_index(self, x):
            return np.full(len(np.atleast_2d(x)), 22)  # u = (v, omega) = (1, 0) in the 5x5 grid

    assert np.allclose(tb_system.inputs[22], [1.0, 0.0])
    cfg = {"kind": "pybullet_turtlebot", "system": "turtlebot", "options": arena.simulator_options()}
    x0 = [2.9, 2.8, np.pi / 2]
    with make_simulator(cfg, tb_system) as sim:
        free = rollout(North(), sim, x0, n_rollouts=1, horizon=150, seed=0)  # spec without obstacles
        judged = rollout(North(), sim, x0, n_rollouts=1, horizon=150, seed=0, spec=arena.spec(tb_system))
    y = free.trajectories[0, :, 1]
    assert y.max() < 3.5  # the body cannot enter the block
    assert y.max() > 3.5 - 0.2  # but got close to it (robot radius ~0.1)
    assert judged.outcome[0] == 1 and judged.violation_kind[0] == 1
    assert judged.trajectories[0, judged.violation_time[0], 1] >= 3.5 - arena.robot_radius


class ZeroTorque:
    hold = 1

    def __init__(self, system, spec):
        self.system, self.spec = system, spec

    def input_index(self, x):
        return np.full(len(np.atleast_2d(x)), 10)  # u = 0 of the 21 torques


def test_pendulum_invariance_in_pybullet():
    sys_ = pendulum()
    spec = Spec("invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    res = synthesize(sys_, spec, [0.005, 0.01])
    ctrl = res.controller
    cfg = {"kind": "pybullet_pendulum", "system": "pendulum", "noise": {"actuation_std": 0.02}}
    with make_simulator(cfg, sys_) as sim:
        r = rollout(ctrl, sim, [0.1, 0.0], n_rollouts=20, horizon=300, seed=0)
    assert r.nominal["satisfied"]  # the controller is sound for the nominal model
    assert r.lengths.max() <= 300 and np.isfinite(r.trajectories).all()
    # a controller-free pendulum from the same state leaves [0, 0.2] (it swings to about -0.1)
    with make_simulator(cfg, sys_) as sim:
        z = rollout(ZeroTorque(sys_, spec), sim, [0.1, 0.0], n_rollouts=5, horizon=300, seed=0)
    assert z.n_failures == 5 and (z.violation_kind == 3).all()
    # with small actuation noise the controlled pendulum stays in the safe set
    assert r.n_failures == 0, r.to_dict(per_rollout=False)


def test_cli_end_to_end(tmp_path, tb_ctrl, capsys):
    ctrl_path = tb_ctrl.save(tmp_path / "ctrl.npz")
    sim = {"kind": "numpy", "system": "turtlebot", "noise": {"actuation_std": [0.05, 0.1]}}
    (tmp_path / "sim.json").write_text(json.dumps(sim))
    out, traj = tmp_path / "report.json", tmp_path / "traj.npz"
    rc = main(["rollout", "--controller", str(ctrl_path), "--simulator", str(tmp_path / "sim.json"),
               "--n", "50", "--seed", "3", "--out", str(out), "--trajectories", str(traj)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "50 rollouts of turtlebot" in printed and "nominal model   success" in printed
    rep = json.loads(out.read_text())
    assert rep["n_rollouts"] == 50 and rep["seed"] == 3 and rep["hold"] == K
    assert rep["x0"] == [3.5, 2.0, 1.5]  # recorded in the controller
    t = load_rollout(traj)
    assert t.trajectories.shape[0] == 50 and t.n_failures == rep["failures"]
    # same run through the Python API gives the same numbers
    r = rollout(Controller.load(ctrl_path), make_simulator(sim, tb_ctrl.system), [3.5, 2.0, 1.5], n_rollouts=50, seed=3)
    np.testing.assert_array_equal(r.trajectories, t.trajectories)
    # an initial state outside the winning domain: error, no report
    rc = main(["rollout", "--controller", str(ctrl_path), "--simulator", str(tmp_path / "sim.json"),
               "--x0", "1.9,1.0,0", "--out", str(tmp_path / "bad.json")])
    assert rc == 2 and not (tmp_path / "bad.json").exists()
    assert "error:" in capsys.readouterr().err

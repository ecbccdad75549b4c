"""Closed-loop rollouts with the numpy simulator and small stand-in controllers."""

import json

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.simulators.base import make_simulator
from simgap.rollout import OUTCOMES, load_rollout, resolve_hold, rollout
from simgap.synthesis.spec import Box, Spec
from simgap.systems import pendulum, turtlebot

INF = np.inf


class Const:
    """Stand-in controller: always the input nearest to u; -1 outside an optional domain box."""

    def __init__(self, system, spec, u, hold=1, domain=None):
        self.system, self.spec, self.hold, self.domain = system, spec, hold, domain
        self.k = int(np.argmin(((system.inputs - np.asarray(u, float)) ** 2).sum(1)))
        self.calls = 0

    def input_index(self, x):
        x = np.atleast_2d(x)
        self.calls += 1
        out = np.full(len(x), self.k)
        if self.domain is not None:
            out[~self.domain.contains(x)] = -1
        return out


class PendulumFeedback:
    """Stand-in: u = sat(-K x) snapped to the input grid (keeps the pendulum upright)."""

    def __init__(self, system, spec, K=(30.0, 8.0)):
        self.system, self.spec, self.K = system, spec, np.asarray(K)

    def input_index(self, x):
        u = np.clip(-(np.atleast_2d(x) @ self.K), -1, 1)
        return np.abs(self.system.inputs[:, 0][None] - u[:, None]).argmin(1)


def north_spec(obstacles=()):
    return Spec("reach_avoid", target=Box([3.0, 3.0, -INF], [4.0, 4.0, INF]), obstacles=tuple(obstacles))


def tb_sim(std=(0.05, 0.3), steps=1, proc=0.0):
    return make_simulator({"kind": "numpy", "system": "turtlebot", "steps": steps,
                           "noise": {"actuation_std": list(std), "process_std": proc}})


X0 = [3.5, 2.0, 1.5]


def test_reach_time_matches_the_geometry():
    """Straight north at 1 m/s from y = 2 heading 1.5 rad: y(t) = 2 + 0.01 t sin(1.5); y >= 3 first at t = 101."""
    sys_ = turtlebot()
    r = rollout(Const(sys_, north_spec(), [1.0, 0.0]), tb_sim(std=(0, 0)), X0, n_rollouts=3, horizon=300, seed=0)
    t_exact = int(np.ceil(1.0 / (0.01 * np.sin(1.5))))
    assert t_exact == 101
    assert r.reach_time.tolist() == [t_exact] * 3 and r.n_failures == 0
    assert r.nominal["reach_time"] == t_exact and r.nominal["outcome"] == "success"
    assert r.lengths.tolist() == [t_exact] * 3
    # after stopping, the last state repeats; before, the motion is the nominal one
    np.testing.assert_array_equal(r.trajectories[:, -1], r.trajectories[:, t_exact])
    np.testing.assert_allclose(r.trajectories[0], r.nominal_trajectory, atol=1e-12)
    assert r.trajectories[0, t_exact, 1] >= 3.0 > r.trajectories[0, t_exact - 1, 1]
    assert r.input_index.shape == (3, 300) and (r.input_index[:, :t_exact] >= 0).all()
    assert (r.input_index[:, t_exact:] == -1).all()


def test_seed_determinism_and_batching():
    sys_ = turtlebot()
    c = Const(sys_, north_spec(), [1.0, 0.0])
    a = rollout(c, tb_sim(), X0, n_rollouts=40, horizon=150, seed=7)
    b = rollout(c, tb_sim(), X0, n_rollouts=40, horizon=150, seed=7)
    d = rollout(c, tb_sim(), X0, n_rollouts=40, horizon=150, seed=8)
    np.testing.assert_array_equal(a.trajectories, b.trajectories)
    assert not np.array_equal(a.trajectories, d.trajectories)
    # rollouts differ from each other (noise is per rollout)
    assert np.ptp(a.trajectories[:, 50, 0]) > 1e-3
    # one at a time gives exactly the batched rows
    s = rollout(c, tb_sim(), X0, n_rollouts=40, horizon=150, seed=7, batched=False)
    np.testing.assert_array_equal(a.trajectories, s.trajectories)
    np.testing.assert_array_equal(a.outcome, s.outcome)
    # an explicit generator works too
    g = rollout(c, tb_sim(), X0, n_rollouts=40, horizon=150, rng=np.random.default_rng(7))
    np.testing.assert_array_equal(a.trajectories, g.trajectories)


def test_collision_with_an_obstacle_is_a_failure():
    """A wall across the path at y in [2.5, 2.6]: every rollout hits it before the target."""
    sys_ = turtlebot()
    wall = Box([2.0, 2.5, -INF], [4.0, 2.6, INF])
    r = rollout(Const(sys_, north_spec([wall]), [1.0, 0.0]), tb_sim(), X0, n_rollouts=50, horizon=300, seed=1)
    assert r.n_failures == 50
    assert (r.outcome == OUTCOMES.index("violation")).all() and (r.reach_time == -1).all()
    assert r.to_dict()["violation_kinds"]["obstacle"] == 50
    # first violation: the first state with y >= 2.5 (about 51 steps at ~1 m/s)
    y = r.trajectories[np.arange(50), r.violation_time, 1]
    y_prev = r.trajectories[np.arange(50), r.violation_time - 1, 1]
    assert (y >= 2.5).all() and (y_prev < 2.5).all()
    assert 45 <= r.violation_time.min() and r.violation_time.max() <= 60
    assert r.nominal["outcome"] == "violation" and r.nominal["violation_kind"] == "obstacle"
    assert not r.rollout_average_verdict["satisfied"] and r.mean_map["outcome"] == "violation"


def test_partial_failures_are_counted_per_rollout():
    """A narrow obstacle right of the nominal path: only noisy rollouts that drift into it fail."""
    sys_ = turtlebot()
    post = Box([3.57, 2.6, -INF], [3.75, 2.7, INF])  # nominal x is about 3.545 there
    r = rollout(Const(sys_, north_spec([post]), [1.0, 0.0]), tb_sim(std=(0.0, 0.5)), X0,
                n_rollouts=400, horizon=300, seed=3)
    fail = r.outcome != 0
    assert 0 < fail.sum() < 400
    assert r.n_failures == int(fail.sum())
    # failing rollouts were inside the post at their violation time, the others reached the target
    xv = r.trajectories[fail][np.arange(fail.sum()), r.violation_time[fail]]
    assert post.contains(xv).all()
    assert (r.reach_time[~fail] > 0).all() and (r.violation_time[~fail] == -1).all()
    assert r.nominal["outcome"] == "success"


def test_leaving_X_is_a_violation_and_timeout_without_target():
    sys_ = turtlebot()
    far = Spec("reach_avoid", target=Box([0.0, 0.0, -INF], [0.5, 0.5, INF]))
    r = rollout(Const(sys_, far, [1.0, 0.0]), tb_sim(std=(0, 0)), X0, n_rollouts=2, horizon=400, seed=0)
    assert (r.violation_kind == 2).all() and r.to_dict()["violation_kinds"]["outside_X"] == 2
    assert r.trajectories[0, r.violation_time[0], 1] > 4.0
    r = rollout(Const(sys_, far, [0.0, 0.0]), tb_sim(std=(0, 0)), X0, n_rollouts=2, horizon=20, seed=0)
    assert (r.outcome == OUTCOMES.index("timeout")).all() and r.n_failures == 2
    assert (r.lengths == 20).all()


def test_invariance_failure_and_success():
    sys_ = pendulum()
    safe = Spec("invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    sim = make_simulator({"kind": "numpy", "system": "pendulum", "noise": {"actuation_std": 0.2}})
    # zero torque: gravity pulls the pendulum out of the safe set
    r = rollout(Const(sys_, safe, [0.0]), sim, [0.1, 0.0], n_rollouts=20, horizon=400, seed=0)
    assert r.n_failures == 20 and (r.violation_time > 0).all()
    xv = r.trajectories[np.arange(20), r.violation_time]
    assert (~safe.safe.contains(xv)).all()
    assert r.to_dict()["violation_kinds"]["unsafe"] + r.to_dict()["violation_kinds"]["outside_X"] == 20
    # a stabilizing feedback around 0.1 stays in [0, 0.2] x [-0.5, 0.5]
    ctrl = PendulumFeedback(sys_, safe)
    ctrl.input_index = (lambda f: lambda x: f(np.atleast_2d(x) - [0.1, 0.0]))(ctrl.input_index)
    r = rollout(ctrl, sim, [0.1, 0.0], n_rollouts=50, horizon=400, seed=0)
    assert r.n_failures == 0 and (r.violation_time == -1).all() and (r.lengths == 400).all()
    assert r.nominal["satisfied"] and r.rollout_average_verdict["satisfied"] and r.mean_map["satisfied"]


def test_progress_callback_and_cancel():
    sys_ = turtlebot()
    seen = []
    rollout(Const(sys_, north_spec(), [1.0, 0.0]), tb_sim(), X0, n_rollouts=5, horizon=300, seed=0,
            progress=lambda t, T: seen.append((t, T)))
    assert seen[0] == (1, 300) and seen[-1][0] >= 95 and all(T == 300 for _, T in seen)

    class Cancelled(Exception):
        pass

    def cancel(t, T):
        if t == 10:
            raise Cancelled

    with pytest.raises(Cancelled):
        rollout(Const(sys_, north_spec(), [1.0, 0.0]), tb_sim(), X0, n_rollouts=5, horizon=300, progress=cancel)


def test_hold_and_steps():
    sys_ = turtlebot()
    c = Const(sys_, north_spec(), [1.0, 0.0], hold=5)
    assert resolve_hold(c, tb_sim()) == 5
    r = rollout(c, tb_sim(), X0, n_rollouts=4, horizon=30, seed=0)
    assert r.hold == 5 and c.calls == 1 + 6 + 6 + 6  # x0 check, 6 queries each: rollouts, nominal run, mean map
    # controller on a system with steps=10, simulator stepping 5 base periods: hold 2
    c10 = Const(sys_.with_steps(10), north_spec(), [1.0, 0.0])
    assert resolve_hold(c10, tb_sim(steps=5)) == 2
    r = rollout(c10, tb_sim(steps=5), X0, n_rollouts=2, horizon=50, seed=0)
    assert r.tau == pytest.approx(0.05) and r.reach_time[0] == int(np.ceil(101 / 5))
    with pytest.raises(SimgapError, match="not a multiple"):
        resolve_hold(Const(sys_.with_steps(3), north_spec(), [1, 0]), tb_sim(steps=2))


def test_leaving_the_winning_domain():
    sys_ = turtlebot()
    dom = Box([3.0, 0.0, -INF], [4.0, 2.5, INF])  # the "winning domain" ends at y = 2.5
    c = Const(sys_, north_spec(), [1.0, 0.0], domain=dom)
    r = rollout(c, tb_sim(std=(0, 0)), X0, n_rollouts=3, horizon=300, seed=0)  # fallback: keep last input
    assert (r.left_domain_time > 0).all() and r.n_failures == 0 and r.to_dict()["left_domain"] == 3
    assert r.trajectories[0, r.left_domain_time[0], 1] > 2.5 >= r.trajectories[0, r.left_domain_time[0] - 1, 1]
    r = rollout(c, tb_sim(std=(0, 0)), X0, n_rollouts=3, horizon=300, seed=0, on_exit="stop")
    assert (r.outcome == OUTCOMES.index("left_domain")).all() and r.n_failures == 3
    assert (r.lengths == r.left_domain_time).all()


def test_bad_inputs():
    sys_ = turtlebot()
    c = Const(sys_, north_spec([Box([3.0, 1.0, -INF], [4.0, 1.5, INF])]), [1.0, 0.0],
              domain=Box([0, 0, -INF], [3.8, 4, INF]))
    with pytest.raises(SimgapError, match="outside X"):
        rollout(c, tb_sim(), [5.0, 2.0, 0.0], n_rollouts=2)
    with pytest.raises(SimgapError, match="violates the specification"):
        rollout(c, tb_sim(), [3.5, 1.2, 0.0], n_rollouts=2)
    with pytest.raises(SimgapError, match="winning domain"):
        rollout(c, tb_sim(), [3.9, 2.0, 0.0], n_rollouts=2)
    with pytest.raises(SimgapError, match="does not match"):
        rollout(c, make_simulator({"kind": "numpy", "system": "pendulum"}), [0.0, 0.0])
    with pytest.raises(SimgapError, match="n_rollouts"):
        rollout(c, tb_sim(), X0, n_rollouts=0)
    with pytest.raises(SimgapError, match="horizon"):
        rollout(c, tb_sim(), X0, horizon=-3)
    with pytest.raises(SimgapError, match="on_exit"):
        rollout(c, tb_sim(), X0, on_exit="maybe")


def test_json_and_npz_round_trip(tmp_path):
    sys_ = turtlebot()
    r = rollout(Const(sys_, north_spec(), [1.0, 0.0]), tb_sim(), X0, n_rollouts=30, horizon=200, seed=5)
    d = json.loads(json.dumps(r.to_dict(), allow_nan=False))
    assert d["n_rollouts"] == 30 and d["failures"] == r.n_failures and len(d["per_rollout"]["outcome"]) == 30
    assert d["spec"]["target"]["lo"][2] == "-inf"
    assert Spec.from_dict(d["spec"]).target.lo[2] == -np.inf
    r.save_json(tmp_path / "r.json")
    assert json.loads((tmp_path / "r.json").read_text())["seed"] == 5
    r.save_npz(tmp_path / "r.npz")
    q = load_rollout(tmp_path / "r.npz")
    np.testing.assert_array_equal(q.trajectories, r.trajectories)
    np.testing.assert_array_equal(q.reach_time, r.reach_time)
    assert q.to_dict() == r.to_dict()
    assert [p.name for p in tmp_path.iterdir()] and not any(p.name.startswith(".tmp") for p in tmp_path.iterdir())
    with pytest.raises(SimgapError, match="cannot read"):
        load_rollout(tmp_path / "r.json")


def test_mean_trajectory_uses_circular_mean():
    sys_ = turtlebot()
    spec = Spec("invariance", safe=Box([0, 0, -INF], [4, 4, INF]))
    # heading near +-pi: a plain mean would give about 0
    r = rollout(Const(sys_, spec, [0.0, 0.0]), tb_sim(std=(0, 0), proc=[0, 0, 0.02]), [2.0, 2.0, np.pi - 0.01],
                n_rollouts=200, horizon=50, seed=0)
    assert abs(abs(r.mean_trajectory[-1, 2]) - np.pi) < 0.05

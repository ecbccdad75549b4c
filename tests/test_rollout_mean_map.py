"""The mean map m+ = E fhat(m, u(m)) (what the guarantee is about) against the rollout average."""

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.rollout import load_rollout, rollout
from simgap.simulators.base import make_simulator
from simgap.synthesis.spec import Box, Spec
from simgap.systems import turtlebot

INF = np.inf
OPEN = Spec("invariance", safe=Box([0, 0, -INF], [4, 4, INF]))


class Const:
    """Stand-in controller: always the input nearest to u."""

    def __init__(self, system, spec, u):
        self.system, self.spec, self.hold = system, spec, 1
        self.k = int(np.argmin(((system.inputs - np.asarray(u, float)) ** 2).sum(1)))

    def input_index(self, x):
        return np.full(len(np.atleast_2d(x)), self.k)


def test_mean_map_matches_the_exact_mean_with_additive_noise():
    """Additive zero-mean noise and a drift: E fhat(m, u) = mean_next(m, u) exactly, so the
    Monte Carlo mean map must follow the iterated exact mean within its standard errors."""
    sys_ = turtlebot()
    sim = make_simulator({"kind": "numpy", "system": "turtlebot", "noise": {"process_std": [0.01, 0.01, 0.0]},
                          "effects": {"bias": [0.05, -0.03, 0.0]}})
    x0, T = np.array([1.0, 2.0, 0.7]), 60
    r = rollout(Const(sys_, OPEN, [0.5, 0.0]), sim, x0, n_rollouts=10, horizon=T, seed=2, mean_map_runs=400)
    exact = [x0]
    for _ in range(T):
        exact.append(sim.mean_next(exact[-1][None], np.array([[0.5, 0.0]]))[0])
    exact = np.array(exact)
    se = np.array(r.mean_map["max_std_error"])
    assert se[0] > 1e-4 and r.mean_map["runs_per_step"] == 400 and r.mean_map["satisfied"]
    # the estimate's error accumulates like a sum of independent per-step errors
    k = np.arange(T + 1)[:, None]
    assert np.all(np.abs(r.mean_map_trajectory - exact) <= 6 * se * np.sqrt(np.maximum(k, 1)) + 1e-12)


def test_mean_map_is_not_the_rollout_average():
    """Heading noise: each rollout's heading wanders, so the rollout average advances by
    sum_t tau E cos(theta_t) < T tau cos(theta0); the mean map restarts every step from the mean
    heading and advances by tau cos(theta0) per step. The two differ by far more than their errors."""
    sys_ = turtlebot()
    sim = make_simulator({"kind": "numpy", "system": "turtlebot", "noise": {"process_std": [0.0, 0.0, 0.1]}})
    x0, T = np.array([0.5, 2.0, 0.0]), 100
    r = rollout(Const(sys_, OPEN, [1.0, 0.0]), sim, x0, n_rollouts=1000, horizon=T, seed=0, mean_map_runs=1000)
    mm, avg = r.mean_map_trajectory[-1, 0], r.mean_trajectory[-1, 0]
    assert mm == pytest.approx(x0[0] + T * 0.01, abs=0.005)  # cos(estimated mean heading ~ 0) ~ 1
    want_avg = x0[0] + 0.01 * np.exp(-0.005 * np.arange(T)).sum()      # E cos(theta_t) = exp(-0.01 t / 2)
    assert avg == pytest.approx(want_avg, abs=0.01) and mm - avg > 0.15
    text = "\n".join(r.summary_lines())
    assert "mean map        success" in text and "the sequence the guarantee is about" in text
    assert "rollout average satisfies the spec" in text and "not what the guarantee is about" in text
    d = r.to_dict()
    assert d["mean_map"]["satisfied"] and d["rollout_average"]["satisfied"]


def test_mean_map_has_its_own_stream_and_round_trips(tmp_path):
    sys_ = turtlebot()
    sim = make_simulator({"kind": "numpy", "system": "turtlebot", "noise": {"actuation_std": [0.05, 0.3]}})
    c = Const(sys_, OPEN, [0.5, 0.2])
    a = rollout(c, sim, [1.0, 1.0, 0.0], n_rollouts=20, horizon=40, seed=3, mean_map_runs=0)
    b = rollout(c, sim, [1.0, 1.0, 0.0], n_rollouts=20, horizon=40, seed=3, mean_map_runs=50)
    np.testing.assert_array_equal(a.trajectories, b.trajectories)  # the mean map does not shift the draws
    assert a.mean_map is None and "mean map        not computed" in "\n".join(a.summary_lines())
    b.save_npz(tmp_path / "r.npz")
    q = load_rollout(tmp_path / "r.npz")
    np.testing.assert_array_equal(q.mean_map_trajectory, b.mean_map_trajectory)
    assert q.mean_map == b.to_dict()["mean_map"]
    with pytest.raises(SimgapError, match="mean_map_runs"):
        rollout(c, sim, [1.0, 1.0, 0.0], n_rollouts=2, horizon=5, mean_map_runs=1)


def test_mean_map_standard_error_covers_the_propagated_spread():
    """Across independent repetitions the mean map's m_t spreads by the error every step inherits (a random
    walk here: sqrt(t) times the one-step error). The reported (propagated) standard error must match that
    spread; the one-step conditional standard error, the number reported before, is ~sqrt(40) too small."""
    from simgap.rollout.mean_map import mean_map

    sys_ = turtlebot()
    sim = make_simulator({"kind": "numpy", "system": "turtlebot", "noise": {"process_std": [0.01, 0.01, 0.0]}})
    c = Const(sys_, OPEN, [0.5, 0.0])
    x0, T, reps = np.array([1.0, 2.0, 0.7]), 40, 120
    ends, se, se1 = [], [], []
    for r in range(reps):
        mm = mean_map(c, sim, OPEN, x0, 100, T, 1, np.random.default_rng([r, 9]))
        ends.append(mm.trajectory[T, :2])
        se.append(mm.std_error[T, :2])
        se1.append(mm.step_std_error[T, :2])
        assert mm.groups == 10
    ends, se, se1 = np.array(ends), np.array(se), np.array(se1)
    spread = ends.std(axis=0, ddof=1)
    rms = np.sqrt((se ** 2).mean(axis=0))
    assert np.all((rms > 0.75 * spread) & (rms < 1.33 * spread)), (rms, spread)
    # per repetition: within 3 reported standard errors of the repetitions' mean in >= 90 % of them
    cover = np.abs(ends - ends.mean(axis=0)) <= 3 * se
    assert cover.mean(axis=0).min() >= 0.9
    # the one-step conditional SE does not cover the spread (what the mean map reported before)
    assert np.all(np.sqrt((se1 ** 2).mean(axis=0)) < 0.3 * spread)
    assert (np.abs(ends - ends.mean(axis=0)) <= 3 * se1).mean() < 0.6


def test_mean_map_says_which_rows_theorem_1_is_about():
    from simgap.rollout.mean_map import mean_map
    from simgap.synthesis.abstraction import COMPOSED_HOLD_LABEL

    sys_ = turtlebot()
    sim = make_simulator({"kind": "numpy", "system": "turtlebot", "noise": {"process_std": [0.01, 0.01, 0.0]}})
    c = Const(sys_, OPEN, [0.5, 0.0])
    one = mean_map(c, sim, OPEN, [1.0, 2.0, 0.7], 8, 6, 1, np.random.default_rng(0)).to_dict()
    assert one["theorem1_rows"].startswith("every row") and one["groups"] == 4
    held = mean_map(c, sim, OPEN, [1.0, 2.0, 0.7], 8, 6, 3, np.random.default_rng(0)).to_dict()
    assert "multiples of the hold (3" in held["theorem1_rows"] and "outside Theorem 1" in held["theorem1_rows"]
    c.meta = {"hold_mode": COMPOSED_HOLD_LABEL}
    comp = mean_map(c, sim, OPEN, [1.0, 2.0, 0.7], 8, 6, 3, np.random.default_rng(0)).to_dict()
    assert comp["theorem1_rows"].startswith("none") and "compose_hold" in comp["theorem1_rows"]
    with pytest.raises(SimgapError, match=">= 4"):
        mean_map(c, sim, OPEN, [1.0, 2.0, 0.7], 3, 6, 1, np.random.default_rng(0))

"""Epsilon-cover: every x in X within epsilon of a cover point (incl. the angle seam), sizes, bad input."""

import numpy as np
import pytest

from simgap.cover import CoverSpec, calibrate_rate, estimate_cost, make_cover
from simgap.errors import SimgapError
from simgap.simulators.base import SimulatorConfig, make_simulator
from simgap.systems import get_system


def brute_force_distance(system, cover, x):
    """Distance from each x to its nearest cover point over the covered dims, by exhaustive search."""
    cov = list(cover.covered)
    best = np.full(len(x), np.inf)
    for s in range(0, len(x), 500):
        d = system.diff(x[s:s + 500, None, :], cover.points[None, :, :])[..., cov]
        best[s:s + 500] = np.sqrt((d ** 2).sum(-1)).min(axis=1)
    return best


def random_states(system, rng, n):
    return system.x_lo + rng.random((n, system.n)) * (system.x_hi - system.x_lo)


@pytest.mark.parametrize("eps", [0.05, 0.013])
def test_every_state_within_epsilon_pendulum(eps, rng):
    s = get_system("pendulum")
    cover = make_cover(s, eps)
    x = random_states(s, rng, 4000)
    # the corners of X are the hardest points
    corners = np.array([[lo0, lo1] for lo0 in (s.x_lo[0], s.x_hi[0]) for lo1 in (s.x_lo[1], s.x_hi[1])])
    x = np.vstack([x, corners])
    d = brute_force_distance(s, cover, x)
    assert d.max() <= eps
    # the cover is not trivially dense: some state is close to the worst case
    assert d.max() > 0.8 * eps
    assert cover.radius <= eps
    # locate() finds a cover point within epsilon, consistent with the brute force
    assert np.all(cover.distance(x) <= eps + 1e-15)
    s.check_states(cover.points)


def test_turtlebot_heading_cover_across_the_seam(rng):
    s = get_system("turtlebot")
    cover = make_cover(s, CoverSpec(0.017, invariant_dims=("x", "y"), fixed={"x": 2.0, "y": 2.0}))
    assert cover.N == 185  # ceil(2 pi / 0.034), the paper's TurtleBot cover
    assert np.all(cover.points[:, :2] == 2.0)
    assert cover.periodic == (True,)
    th = np.concatenate([rng.uniform(-np.pi, np.pi, 3000),
                         [-np.pi, np.pi, np.pi - 1e-12, -np.pi + 1e-12, np.nextafter(np.pi, 0)]])
    x = np.column_stack([rng.uniform(0, 4, th.size), rng.uniform(0, 4, th.size), th])
    d = brute_force_distance(s, cover, x)
    assert d.max() <= 0.017
    assert np.all(cover.distance(x) <= 0.017 + 1e-15)
    assert "declared invariance" in cover.summary() and "x=2" in cover.summary()
    desc = cover.describe()
    assert desc["invariant_dims"] == ["x", "y"] and desc["fixed"] == {"x": 2.0, "y": 2.0}


def test_full_3d_turtlebot_cover_periodic(rng):
    s = get_system("turtlebot")
    cover = make_cover(s, 0.6)
    x = random_states(s, rng, 3000)
    x[:200, 2] = rng.choice([-np.pi, np.pi], 200)
    assert brute_force_distance(s, cover, x).max() <= 0.6


def test_paper_pendulum_cover_size_and_cost():
    s = get_system("pendulum")
    cover = make_cover(s, 0.004)
    assert cover.N == 71 * 177 == 12567
    est = estimate_cost(cover, 1000, rate_per_worker=1e6, workers=2)
    assert est.n_pairs == 263907 and est.sim_steps == 263907000
    assert est.seconds == pytest.approx(263907000 / 2e6)
    # k = 5 base periods per sampling period: five physics periods per run
    est5 = estimate_cost(make_cover(s.with_steps(5), 0.004), 1000)
    assert est5.sim_steps == 5 * 263907000 and est5.seconds is None


def test_per_dimension_spacing(rng):
    s = get_system("pendulum")
    cover = make_cover(s, CoverSpec(0.05, spacing=(0.02, 0.09)))
    assert list(cover.counts) == [20, 12]
    assert brute_force_distance(s, cover, random_states(s, rng, 3000)).max() <= cover.radius <= 0.05
    with pytest.raises(SimgapError, match="radius"):
        make_cover(s, CoverSpec(0.01, spacing=(0.02, 0.09)))
    with pytest.raises(SimgapError, match="spacing"):
        make_cover(s, CoverSpec(0.05, spacing=(0.02,)))
    with pytest.raises(SimgapError, match="spacing"):
        make_cover(s, CoverSpec(0.05, spacing=(0.02, -1.0)))


@pytest.mark.parametrize("eps", [0, -0.1, float("nan"), float("inf"), "abc", None])
def test_bad_epsilon(eps):
    with pytest.raises(SimgapError, match="epsilon"):
        make_cover(get_system("pendulum"), eps)


def test_bad_invariance():
    s = get_system("turtlebot")
    with pytest.raises(SimgapError, match="outside X"):
        make_cover(s, CoverSpec(0.1, invariant_dims=("x", "y"), fixed={"x": 5.0}))
    with pytest.raises(SimgapError, match="unknown state dimension"):
        make_cover(s, CoverSpec(0.1, invariant_dims=("z",)))
    with pytest.raises(SimgapError, match="not an invariant"):
        make_cover(s, CoverSpec(0.1, invariant_dims=("x",), fixed={"y": 1.0}))
    with pytest.raises(SimgapError, match="nothing left"):
        make_cover(s, CoverSpec(0.1, invariant_dims=("x", "y", "theta")))
    with pytest.raises(SimgapError, match="too many"):
        make_cover(s, 1e-4)
    # positional names work too
    assert make_cover(s, CoverSpec(0.1, invariant_dims=("x1", "x2"))).covered == (2,)


def test_calibrate_rate_positive():
    sim = make_simulator(SimulatorConfig("numpy", "pendulum", noise={"actuation_std": 0.05}))
    assert calibrate_rate(sim, n_runs=512, budget=0.05) > 0

"""PyBullet pendulum and TurtleBot simulators: physics against the nominal models, exact
effect sizes, batched == one-at-a-time (bit-identical), seeded determinism, bad input."""

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.simulators import make_simulator
from simgap.systems import get_system

pytest.importorskip("pybullet")

PEND = {"kind": "pybullet_pendulum", "system": "pendulum"}
TB = {"kind": "pybullet_turtlebot", "system": "turtlebot"}
G, M, L, TAU = 9.81, 1.0, 1.0, 0.005
I_PIVOT = M * L * L / 3.0  # rod about its end [kg m^2]


def sim(base, **sections):
    return make_simulator({**base, **sections})


def rows(noise, i, j):
    return {k: v[i:j] for k, v in noise.items()}


def pendulum_samples(rng, B):
    s = get_system("pendulum")
    return rng.uniform(s.x_lo, s.x_hi, (B, 2)), s.inputs[rng.integers(0, len(s.inputs), B)]


# ----------------------------------------------------------------------------------------
# pendulum
# ----------------------------------------------------------------------------------------

def test_pendulum_noise_free_matches_nominal_to_tau_squared(rng):
    """Bullet is semi-implicit Euler: omega+ equals the nominal x2+ exactly, theta+ differs from
    the nominal x1 + tau x2 by tau^2 * theta'' (<= tau^2 (3g/2l sin 0.2 + 3/(m l^2)))."""
    s = get_system("pendulum")
    x, u = pendulum_samples(rng, 500)
    with sim(PEND) as p:
        y = p.step(x, u, rng)
    f = s.f(x, u)
    np.testing.assert_allclose(y[:, 1], f[:, 1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(y[:, 0], x[:, 0] + TAU * f[:, 1], rtol=0, atol=1e-12)
    bound = TAU ** 2 * (1.5 * G / L * np.sin(0.2) + 3.0 / (M * L * L))
    err = np.abs(y[:, 0] - f[:, 0])
    assert err.max() <= bound * (1 + 1e-9)
    assert err.max() > 0.3 * bound  # the O(tau^2) term is really there, not hidden


def test_pendulum_several_steps_and_substeps(rng):
    """steps=k holds u for k base periods; with substeps the same physics at a finer dt."""
    x, u = pendulum_samples(rng, 50)
    s3 = get_system("pendulum", steps=3)
    with sim(PEND, steps=3) as p:
        y = p.step(x, u, rng)
    z = x.copy()
    for _ in range(3):  # semi-implicit Euler, the integrator Bullet uses
        w = z[:, 1] - 1.5 * G / L * TAU * np.sin(z[:, 0]) + 3 * TAU * u[:, 0] / (M * L * L)
        z = np.column_stack([z[:, 0] + TAU * w, w])
    np.testing.assert_allclose(y, z, rtol=0, atol=1e-12)
    assert np.abs(y - s3.f(x, u)).max() < 3 * 3 * TAU ** 2 * 6.0
    with sim(PEND, options={"substeps": 4}) as p:
        y4 = p.step(x, u, rng)
    assert np.abs(y4 - get_system("pendulum").f(x, u)).max() < TAU ** 2 * 6.0


def test_pendulum_single_urdf_body_agrees_with_branches(rng):
    """The batched multibody is the URDF pendulum: a loadURDF'ed single pendulum gives the
    same next states."""
    import pybullet as pb
    from pybullet_utils.bullet_client import BulletClient
    from simgap.simulators._bullet import urdf_path

    x, u = pendulum_samples(rng, 20)
    with sim(PEND) as p:
        y = p.step(x, u, rng)
    c = BulletClient(connection_mode=pb.DIRECT)
    try:
        c.setGravity(0, 0, -G)
        c.setPhysicsEngineParameter(fixedTimeStep=TAU, numSubSteps=0)
        body = c.loadURDF(str(urdf_path("pendulum.urdf")), useFixedBase=True, flags=pb.URDF_USE_INERTIA_FROM_FILE)
        c.changeDynamics(body, -1, linearDamping=0, angularDamping=0)
        c.changeDynamics(body, 0, linearDamping=0, angularDamping=0)
        c.setJointMotorControl2(body, 0, pb.VELOCITY_CONTROL, force=0)
        single = []
        for xi, ui in zip(x, u):
            c.resetJointState(body, 0, xi[0], xi[1])
            c.setJointMotorControl2(body, 0, pb.TORQUE_CONTROL, force=ui[0])
            c.stepSimulation()
            single.append(c.getJointState(body, 0)[:2])
    finally:
        c.disconnect()
    np.testing.assert_allclose(y, np.array(single), rtol=0, atol=1e-14)


FULL_PEND = dict(noise={"actuation_std": 0.2, "sensor_std": [0.001, 0.002]},
                 randomize={"mass": 0.1, "length": 0.05},
                 effects={"joint_damping": 0.2, "coulomb_friction": 0.05, "actuator_gain": 0.9})


@pytest.mark.parametrize("sections", [{}, FULL_PEND], ids=["plain", "all-keys"])
def test_pendulum_batched_equals_one_at_a_time(sections, rng):
    x, u = pendulum_samples(rng, 131)  # not a multiple of the branch count
    with sim(PEND, options={"branches": 25}, **sections) as p:
        noise = p.draw_noise(len(x), np.random.default_rng(7))
        batched = p.step_with_noise(x, u, noise)
        single = np.concatenate([p.step_with_noise(x[i:i + 1], u[i:i + 1], rows(noise, i, i + 1))
                                 for i in range(len(x))])
        # also a different split of the batch
        split = np.concatenate([p.step_with_noise(x[i:i + 40], u[i:i + 40], rows(noise, i, i + 40))
                                for i in range(0, len(x), 40)])
    assert np.array_equal(batched, single)
    assert np.array_equal(batched, split)
    with sim(PEND, options={"branches": 7}, **sections) as p:
        assert np.array_equal(p.step_with_noise(x, u, noise), batched)


def test_pendulum_seeded_determinism(rng):
    x, u = pendulum_samples(rng, 60)
    with sim(PEND, **FULL_PEND) as p:
        a = p.step(x, u, np.random.default_rng(3))
        b = p.step(x, u, np.random.default_rng(3))
        c = p.step(x, u, np.random.default_rng(4))
    assert np.array_equal(a, b)
    assert not np.any(a == c)


def test_pendulum_joint_damping_exact_and_mean_shift(rng):
    """Damping c adds the torque -c omega: omega+ shifts by -tau c omega / (m l^2/3) per run,
    so the mean over noisy runs moves against the velocity by that amount."""
    c = 0.3
    x = np.tile([[0.1, 0.5]], (2000, 1))
    u = np.tile([[0.2]], (2000, 1))
    noise_cfg = {"actuation_std": 0.3, "sensor_std": 0.01}
    with sim(PEND, noise=noise_cfg) as p0, sim(PEND, noise=noise_cfg, effects={"joint_damping": c}) as p1:
        noise = p0.draw_noise(len(x), rng)
        d = p1.step_with_noise(x, u, noise) - p0.step_with_noise(x, u, noise)
        expected = -TAU * c * 0.5 / I_PIVOT
        np.testing.assert_allclose(d[:, 1], expected, rtol=1e-9, atol=0)
        np.testing.assert_allclose(d[:, 0], TAU * expected, rtol=1e-6)
        # independent draws: the mean shift is still visible and of the right size
        m0 = p0.step(x, u, np.random.default_rng(1)).mean(axis=0)
        m1 = p1.step(x, u, np.random.default_rng(2)).mean(axis=0)
    se = np.sqrt(2 * ((3 * TAU * 0.3) ** 2 + 0.01 ** 2) / len(x))
    assert abs((m1[1] - m0[1]) - expected) < 4 * se
    assert m1[1] - m0[1] < 0


def test_pendulum_actuator_gain_and_coulomb_friction(rng):
    x, u = pendulum_samples(rng, 40)
    with sim(PEND) as p0, sim(PEND, effects={"actuator_gain": 1.2}) as p1:
        d = p1.step(x, u, rng) - p0.step(x, u, rng)
    np.testing.assert_allclose(d[:, 1], 3 * TAU * 0.2 * u[:, 0] / (M * L * L), atol=1e-12)
    mu = 0.5
    with sim(PEND, effects={"coulomb_friction": mu}) as p:
        # at rest at theta=0 with |u| < mu: stuck; moving: friction opposes the motion
        stuck = p.step([[0.0, 0.0], [0.0, 0.0]], [[0.3], [-0.4]], rng)
        moving = p.step([[0.0, 0.4]], [[0.0]], rng)
    np.testing.assert_allclose(stuck, 0.0, atol=1e-12)
    np.testing.assert_allclose(moving[0, 1], 0.4 - TAU * mu / I_PIVOT, atol=1e-9)


def test_pendulum_randomized_parameters_follow_the_model(rng):
    """Per-run m and l: each run follows x2+ = -(3 g tau / 2 l) sin x1 + x2 + 3 tau u / (m l^2)."""
    x, u = pendulum_samples(rng, 300)
    with sim(PEND, randomize={"mass": 0.2, "length": 0.08}) as p:
        noise = p.draw_noise(len(x), rng)
        y = p.step_with_noise(x, u, noise)
    m, l = M * noise["mass"], L * noise["length"]
    assert noise["mass"].std() > 0.1 and noise["length"].std() > 0.04
    x2 = -(1.5 * G * TAU / l) * np.sin(x[:, 0]) + x[:, 1] + 3 * TAU * u[:, 0] / (m * l * l)
    np.testing.assert_allclose(y[:, 1], x2, rtol=0, atol=1e-12)


@pytest.mark.parametrize("sections, match", [
    ({"noise": {"process_std": 0.1}}, "unknown noise keys"),
    ({"randomize": {"friction": 0.1}}, "unknown randomize keys"),
    ({"effects": {"bias": 1.0}}, "unknown effects keys"),
    ({"noise": {"actuation_std": -1}}, "actuation_std"),
    ({"noise": {"sensor_std": [0.1, 0.1, 0.1]}}, "sensor_std"),
    ({"randomize": {"length": 0.2}}, "randomize.length"),
    ({"effects": {"joint_damping": "much"}}, "joint_damping"),
    ({"options": {"branches": 0}}, "branches"),
    ({"options": {"branches": 500}}, "branches"),
    ({"options": {"substeps": 1.5}}, "substeps"),
    ({"options": {"urdf": "missing.urdf"}}, "URDF file not found"),
    ({"system": "turtlebot"}, "2 states and 1 input"),
])
def test_pendulum_bad_config(sections, match):
    with pytest.raises(SimgapError, match=match):
        make_simulator({**PEND, **sections})


def test_pendulum_nan_is_reported(rng):
    with sim(PEND) as p:
        with pytest.raises(SimgapError, match="NaN"):
            p.step([[np.nan, 0.0], [0.1, 0.0]], [[0.0], [0.0]], rng)
        with pytest.raises(SimgapError, match="need x"):
            p.step([[0.1, 0.0, 0.0]], [[0.0]], rng)


# ----------------------------------------------------------------------------------------
# TurtleBot
# ----------------------------------------------------------------------------------------

def test_turtlebot_drives_straight_and_turns(rng):
    """v = 1 for tau = 0.01 moves about v tau along the heading; omega = 1 turns about omega tau."""
    with sim(TB) as t:
        x0 = np.array([[1.0, 1.0, 0.0], [2.0, 1.0, np.pi / 2], [1.0, 3.0, -2.5]])
        y = t.step(x0, np.tile([[1.0, 0.0]], (3, 1)), rng)
        d = y - x0
        heading = np.column_stack([np.cos(x0[:, 2]), np.sin(x0[:, 2])])
        along = (d[:, :2] * heading).sum(axis=1)
        across = d[:, 0] * -heading[:, 1] + d[:, 1] * heading[:, 0]
        np.testing.assert_allclose(along, 0.01, rtol=0.05)
        assert np.abs(across).max() < 1e-4 and np.abs(d[:, 2]).max() < 1e-4
        turn = t.step([[1.0, 1.0, 0.3]], [[0.0, 1.0]], rng) - [[1.0, 1.0, 0.3]]
        back = t.step([[1.0, 1.0, 0.3]], [[-1.0, -1.0]], rng) - [[1.0, 1.0, 0.3]]
    np.testing.assert_allclose(turn[0, 2], 0.01, rtol=0.15)
    assert np.abs(turn[0, :2]).max() < 1e-4
    assert back[0, 2] < -0.008 and back[0, 0] < -0.009


def test_turtlebot_noise_free_close_to_unicycle(rng):
    """The physical robot is not a unicycle (wheel scrub, tilt), but per 0.01 s step it stays
    within ~5 % of the motion of the nominal model."""
    s = get_system("turtlebot")
    x = rng.uniform(s.x_lo, s.x_hi, (100, 3))
    u = s.inputs[rng.integers(0, len(s.inputs), 100)]
    with sim(TB) as t:
        y = t.step(x, u, rng)
    d = s.diff(y, s.f(x, u))
    assert np.abs(d[:, :2]).max() < 5e-4
    assert np.abs(d[:, 2]).max() < 2e-3
    assert np.all((y[:, 2] >= -np.pi) & (y[:, 2] < np.pi))


FULL_TB = dict(noise={"actuation_std": [0.05, 0.1], "sensor_std": 0.001},
               randomize={"wheel_radius": 0.02, "mass": 0.05, "friction": 0.1},
               effects={"actuator_gain": [1.05, 0.95], "wheel_radius_error": [0.01, -0.01]})


def test_turtlebot_batched_equals_one_at_a_time(rng):
    s = get_system("turtlebot")
    x = rng.uniform(s.x_lo, s.x_hi, (23, 3))
    u = s.inputs[rng.integers(0, len(s.inputs), 23)]
    with sim(TB, options={"robots": 3}, **FULL_TB) as t:
        noise = t.draw_noise(len(x), np.random.default_rng(9))
        batched = t.step_with_noise(x, u, noise)
        single = np.concatenate([t.step_with_noise(x[i:i + 1], u[i:i + 1], rows(noise, i, i + 1))
                                 for i in range(len(x))])
    assert np.array_equal(batched, single)
    with sim(TB, **FULL_TB) as t:  # one robot per world: the same numbers
        assert np.array_equal(t.step_with_noise(x, u, noise), batched)


def test_turtlebot_seeded_determinism(rng):
    x = np.tile([[1.0, 1.0, 0.2]], (8, 1))
    u = np.tile([[0.5, 0.5]], (8, 1))
    with sim(TB, **FULL_TB) as t:
        a = t.step(x, u, np.random.default_rng(1))
        b = t.step(x, u, np.random.default_rng(1))
        c = t.step(x, u, np.random.default_rng(2))
    assert np.array_equal(a, b)
    assert not np.any(a == c)
    assert a.std(axis=0).min() > 0  # runs from the same (x, u) differ


def test_turtlebot_undeclared_effects(rng):
    """Unequal wheel radii r(1 + eL), r(1 + eR) curve the path: omega = v (eR - eL) / b;
    an actuator gain k scales the speed."""
    x = [[1.0, 1.0, 0.0]]
    with sim(TB, effects={"wheel_radius_error": [0.02, -0.02]}) as t:
        d = t.step(x, [[1.0, 0.0]], rng) - x
    np.testing.assert_allclose(d[0, 2], 0.01 * 1.0 * (-0.04) / 0.16, rtol=0.2)
    with sim(TB, effects={"actuator_gain": [1.2, 1.0]}) as t:
        d = t.step(x, [[1.0, 0.0]], rng) - x
    np.testing.assert_allclose(d[0, 0], 0.012, rtol=0.05)


def test_turtlebot_obstacle_blocks_and_angle_wraps(rng):
    x = [[1.0, 1.0, 0.0]]
    u = [[1.0, 0.0]]
    with sim(TB, steps=20) as t:
        free = t.step(x, u, rng) - x
    with sim(TB, steps=20, options={"obstacles": [[1.1, 1.5, 0.5, 1.5]]}) as t:
        blocked = t.step(x, u, rng) - x
    assert free[0, 0] > 0.18
    assert blocked[0, 0] < 0.05
    with sim(TB) as t:
        y = t.step([[1.0, 1.0, np.pi - 0.002]], [[0.0, 1.0]], rng)
    assert -np.pi <= y[0, 2] < -np.pi + 0.02


@pytest.mark.parametrize("sections, match", [
    ({"noise": {"process_std": 0.1}}, "unknown noise keys"),
    ({"effects": {"joint_damping": 0.1}}, "unknown effects keys"),
    ({"effects": {"wheel_radius_error": 0.2}}, "wheel_radius_error"),
    ({"noise": {"actuation_std": [0.1, 0.1, 0.1]}}, "actuation_std"),
    ({"options": {"robots": 0}}, "robots"),
    ({"options": {"obstacles": [[1, 0, 0, 1]]}}, "obstacles"),
    ({"options": {"obstacles": "walls"}}, "obstacles"),
    ({"options": {"motor_force": 0}}, "motor_force"),
    ({"system": "pendulum"}, "3 states"),
])
def test_turtlebot_bad_config(sections, match):
    with pytest.raises(SimgapError, match=match):
        make_simulator({**TB, **sections})


def test_turtlebot_nan_is_reported(rng):
    with sim(TB) as t:
        with pytest.raises(SimgapError, match="NaN"):
            t.step([[np.nan, 1.0, 0.0]], [[0.5, 0.0]], rng)


# ----------------------------------------------------------------------------------------
# batches served by several processes; repeated rows simulated once
# ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("base, sections", [(TB, FULL_TB), (PEND, {"noise": {"actuation_std": 0.05}})])
def test_parallel_simulator_gives_the_same_numbers(rng, base, sections):
    s = get_system(base["system"])
    x = rng.uniform(s.x_lo, s.x_hi, (37, s.n))
    u = s.inputs[rng.integers(0, len(s.inputs), 37)]
    with sim(base, **sections) as one:
        want = one.step(x, u, np.random.default_rng(5))
        want5 = one.step(x[:5], u[:5], np.random.default_rng(5))
    with make_simulator({**base, **sections}, workers=3) as par:
        assert type(par).__name__ == "ParallelSimulator" and par.workers == 3
        got = par.step(x, u, np.random.default_rng(5))
        assert par._pool is not None  # the helpers really ran
        assert np.array_equal(par.step(x[:5], u[:5], np.random.default_rng(5)), want5)  # small: not split
    assert np.array_equal(got, want)


def test_parallel_simulator_remembers_large_batches(rng, monkeypatch):
    """A repeated large batch (the second audit) is a lookup with the same numbers; any change
    of x, u or a draw is a new batch."""
    import simgap.simulators.parallel as par_mod
    monkeypatch.setattr(par_mod, "MEMO_ROWS", 16)
    s = get_system("turtlebot")
    x = rng.uniform(s.x_lo, s.x_hi, (20, 3))
    u = s.inputs[rng.integers(0, len(s.inputs), 20)]
    with make_simulator({**TB, **FULL_TB}, workers=2) as par:
        calls = []
        step = par._step
        monkeypatch.setattr(par, "_step", lambda *a: calls.append(1) or step(*a))
        first = par.step(x, u, np.random.default_rng(1))
        first[:] = 0.0  # the caller's copy, not the remembered one
        again = par.step(x, u, np.random.default_rng(1))
        assert len(calls) == 1
        other = par.step(x, u, np.random.default_rng(2))
        assert len(calls) == 2 and not np.array_equal(other, again)
    with sim(TB, **FULL_TB) as one:
        assert np.array_equal(again, one.step(x, u, np.random.default_rng(1)))


def test_simulator_workers_validated():
    with pytest.raises(SimgapError, match="workers"):
        make_simulator(TB, workers=-2)


def test_turtlebot_repeated_rows_simulated_once(rng, monkeypatch):
    """Rows with the same x, u and physics draws are simulated once (a noise-free simulator
    repeats every pair N1hat times); sensor noise still differs per row."""
    x = np.repeat([[1.0, 1.0, 0.3], [2.0, 1.0, -2.0]], 6, axis=0)
    u = np.repeat([[0.5, 0.5], [1.0, -1.0]], 6, axis=0)
    with sim(TB, noise={"sensor_std": 0.001}) as t:
        calls = []
        inner = t._simulate
        monkeypatch.setattr(t, "_simulate", lambda *a: calls.append(len(a[0])) or inner(*a))
        noise = t.draw_noise(len(x), rng)
        y = t.step_with_noise(x, u, noise)
        assert calls == [2]
        assert np.array_equal(y, np.concatenate([t.step_with_noise(x[i:i + 1], u[i:i + 1], rows(noise, i, i + 1))
                                                 for i in range(len(x))]))
        assert len(np.unique(y[:, 0])) == 12  # per-row sensor noise
        calls.clear()
        noise["act"][3, 0] += 1e-3  # a different draw is a different run
        t.step_with_noise(x, u, noise)
        assert calls == [3]


# ----------------------------------------------------------------------------------------
# Gazebo-like stochasticity: intermittent wheel slip, actuation jitter within the hold
# ----------------------------------------------------------------------------------------

GAZEBO_TB = dict(noise={"actuation_std": [0.01, 0.02], "wheel_slip": [0.3, 0.5], "actuation_jitter": [0.05, 0.1]},
                 randomize={"wheel_radius": 0.02, "friction": 0.2})


def test_turtlebot_gazebo_keys_batched_equals_one_at_a_time_and_parallel(rng):
    s = get_system("turtlebot", steps=3)
    x = rng.uniform(s.x_lo, s.x_hi, (19, 3))
    u = s.inputs[rng.integers(0, len(s.inputs), 19)]
    with sim(TB, steps=3, options={"robots": 3}, **GAZEBO_TB) as t:
        noise = t.draw_noise(len(x), np.random.default_rng(4))
        assert noise["slip"].shape == (19, 2) and noise["jitter"].shape == (19, 3, 2)
        batched = t.step_with_noise(x, u, noise)
        single = np.concatenate([t.step_with_noise(x[i:i + 1], u[i:i + 1], rows(noise, i, i + 1))
                                 for i in range(len(x))])
    assert np.array_equal(batched, single)
    with make_simulator({**TB, "steps": 3, **GAZEBO_TB}, workers=2) as par:
        assert np.array_equal(par.step_with_noise(x, u, noise), batched)


def test_turtlebot_wheel_slip_draws_and_turn():
    """Each wheel slips with probability p, keeping 1 - s V of its speed (V ~ U(0,1)); a slipping
    wheel turns the robot by tau v (f_R - f_L) / b."""
    with sim(TB, noise={"wheel_slip": [0.3, 0.5]}) as t:
        f = t.draw_noise(20000, np.random.default_rng(0))["slip"]
    slipped = f < 1.0
    se = np.sqrt(0.3 * 0.7 / f.size)
    assert abs(slipped.mean() - 0.3) < 4 * se
    assert f.min() >= 0.5 and abs(f[slipped].mean() - 0.75) < 0.01  # 1 - 0.5 E[V]
    x, u = np.array([[1.0, 1.0, 0.0]]), np.array([[1.0, 0.0]])
    with sim(TB, steps=10, options={"friction": 0.5}, noise={"wheel_slip": [1.0, 0.2]}) as t:
        noise = t.draw_noise(1, np.random.default_rng(0))
        noise["slip"][:] = [[0.9, 1.0]]  # the left wheel keeps 90 %: a left turn
        y = t.step_with_noise(x, u, noise)
    np.testing.assert_allclose(y[0, 2], 0.1 * 1.0 * 0.95 * 0.1 / 0.16 / 0.95, rtol=0.15)


def test_turtlebot_actuation_jitter_applied_every_base_period():
    """Jitter changes the wheel targets every base period, in order: a speed-up in the first half
    of the hold moves the robot further than the same speed-up in the second half (the robot
    accelerates at most mu g, so neither reaches the commanded extra 0.025 m); a constant jitter
    equals the held actuation noise."""
    x, u = np.array([[1.0, 1.0, 0.0]]), np.array([[0.5, 0.0]])
    with sim(TB, steps=10, options={"friction": 0.5}, noise={"actuation_jitter": 0.1}) as t:
        noise = t.draw_noise(1, np.random.default_rng(0))
        noise["jitter"][:] = 0.0
        plain = t.step_with_noise(x, u, noise)[0, 0] - 1.0
        noise["jitter"][0, 5:, 0] = 0.5
        later = t.step_with_noise(x, u, noise)[0, 0] - 1.0
        noise["jitter"][0, :, 0] = 0.0
        noise["jitter"][0, 1:6, 0] = 0.5
        early = t.step_with_noise(x, u, noise)[0, 0] - 1.0
        noise["jitter"][0, :, 0] = 0.2
        const = t.step_with_noise(x, u, noise)
    np.testing.assert_allclose(plain, 0.05, rtol=0.05)
    assert 0.002 < later - plain < early - plain < 0.025
    with sim(TB, steps=10, options={"friction": 0.5}, noise={"actuation_std": 0.1}) as t:
        held = t.draw_noise(1, np.random.default_rng(0))
        held["act"][:] = [[0.2, 0.0]]
        assert np.array_equal(t.step_with_noise(x, u, held), const)


def test_turtlebot_gazebo_keys_leave_other_streams_alone():
    """The new draws come last and only when configured: data sets without them are unchanged."""
    with sim(TB, noise={"actuation_std": 0.1}) as a, sim(TB, noise={"actuation_std": 0.1, "wheel_slip": [0.0, 0.5]}) as b:
        na, nb = a.draw_noise(50, np.random.default_rng(3)), b.draw_noise(50, np.random.default_rng(3))
    assert set(na) == set(nb) and all(np.array_equal(na[k], nb[k]) for k in na)


@pytest.mark.parametrize("noise, match", [
    ({"wheel_slip": 0.1}, "wheel_slip"), ({"wheel_slip": [0.1, 1.5]}, "wheel_slip"),
    ({"wheel_slip": [-0.1, 0.5]}, "wheel_slip"), ({"actuation_jitter": -0.1}, "actuation_jitter"),
    ({"actuation_jitter": [0.1, 0.1, 0.1]}, "actuation_jitter")])
def test_turtlebot_gazebo_keys_bad_values(noise, match):
    with pytest.raises(SimgapError, match=match):
        sim(TB, noise=noise)


def test_turtlebot_gazebo_profile_simulator_and_its_noise_free_baseline(rng):
    """The experiment's `gazebo_stress` profile builds; its baseline (the deterministic method's data)
    drops slip and jitter with the rest of the noise; slip makes single runs far off while the
    mean moves little."""
    from simgap.config import load_experiment
    from simgap.pipeline import baseline_experiment

    exp = load_experiment("turtlebot", "gazebo_stress")
    assert {"wheel_slip", "actuation_jitter"} <= set(exp.simulator.noise)
    base = baseline_experiment(exp).simulator
    assert base.noise == {} and base.randomize == {}
    x, u = np.tile([[2.0, 2.0, 0.0]], (32, 1)), np.tile([[1.0, 0.0]], (32, 1))
    with make_simulator(exp.simulator) as g, make_simulator(base) as b:
        noise = g.draw_noise(32, rng)
        assert {"slip", "jitter"} <= set(noise) and not {"slip", "jitter"} & set(b.draw_noise(2, rng))
        y = g.step_with_noise(x, u, noise)
        y0 = b.step(x[:1], u[:1], rng)
    slipped = (noise["slip"] < 1).any(axis=1)
    dth = np.abs(get_system("turtlebot").diff(y, y0)[:, 2])
    assert slipped.any() and (~slipped).any()
    assert dth[slipped].max() > 3 * dth[~slipped].max()  # a slipping wheel turns the robot

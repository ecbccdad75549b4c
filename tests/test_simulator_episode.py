"""Persistent randomization (``randomize.per = "episode"``): per-run parameters drawn once per rollout,
seeded and batch-identical, used by the per-run validation and the closed-loop rollouts."""

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.perrun.validation import success_counts
from simgap.simulators.base import Simulator, SimulatorConfig, make_simulator
from simgap.synthesis.spec import Box, Spec
from simgap.systems import System, input_grid


def _walk_step(x, u, dt):
    return x + dt * u


WALK = System(name="walk", state_names=("p",), input_names=("a",), x_lo=(-1,), x_hi=(1,),
              inputs=input_grid([-1], [1], [3]), base_tau=0.1, step=_walk_step)


class GainWalk(Simulator):
    """x+ = x + 0.1 g u + small noise; g ~ N(1, std^2) a per-run parameter (randomize.gain)."""

    RANDOMIZE_KEYS = ("gain",)
    PARAMETER_DRAWS = ("gain",)

    def draw_noise(self, B, rng):
        return {"gain": 1 + self.config.randomize.get("gain", 0.0) * rng.standard_normal(B),
                "proc": 0.002 * rng.standard_normal((B, 1))}

    def step_with_noise(self, x, u, noise):
        return x + 0.1 * u * noise["gain"][:, None] + noise["proc"]


def _sim(per):
    return GainWalk(SimulatorConfig("gainwalk", "walk", randomize={"gain": 0.5, "per": per}), system=WALK)


def test_episode_parameters_are_held_and_the_rest_is_unchanged():
    per, epi = _sim("period"), _sim("episode")
    assert per.draw_episode(5, np.random.default_rng(0)) == {} and not per.per_episode
    ep = epi.draw_episode(6, np.random.default_rng(0))
    assert set(ep) == {"gain"} and ep["gain"].shape == (6,)
    # the episode's draws are draw_noise's own (same order and count), keyed by PARAMETER_DRAWS only
    np.testing.assert_array_equal(ep["gain"], epi.draw_noise(6, np.random.default_rng(0))["gain"])
    x, u = np.zeros((6, 1)), np.ones((6, 1))
    ra, rb = np.random.default_rng(1), np.random.default_rng(1)
    steps = []
    for _ in range(5):
        y = epi.step(x, u, ra, ep)
        steps.append(y - x)
        x = y
    steps = np.array(steps)[:, :, 0]
    # every period of one rollout uses the same gain: the increments differ only by the process noise
    assert np.all(steps.std(axis=0) < 0.005) and steps.mean(axis=0).std() > 0.01
    np.testing.assert_allclose(steps.mean(axis=0), 0.1 * ep["gain"], atol=0.003)
    # the other draws are those of the period mode (the period's gain is drawn and replaced)
    noise = per.draw_noise(6, rb)
    np.testing.assert_allclose(steps[0], 0.1 * ep["gain"] + noise["proc"][:, 0])


def test_episode_steps_are_batch_identical_on_pybullet():
    cfg = {"kind": "pybullet_pendulum", "system": "pendulum", "noise": {"actuation_std": 0.1},
           "randomize": {"mass": 0.1, "length": 0.05, "per": "episode"}}
    with make_simulator(cfg) as sim:
        assert sim.per_episode and set(sim.draw_episode(3, np.random.default_rng(0))) == {"mass", "length"}
        ep = sim.draw_episode(3, np.random.default_rng(4))
        x = np.array([[0.1, 0.0], [0.2, 0.1], [-0.1, 0.3]])
        u = np.array([[0.5], [0.0], [-0.5]])
        batch = sim.step(x, u, np.random.default_rng(5), ep)
        noise = sim.draw_noise(3, np.random.default_rng(5))
        rows = [sim.step_with_noise(x[i:i + 1], u[i:i + 1], {k: v[i:i + 1] for k, v in {**noise, **ep}.items()})
                for i in range(3)]
        np.testing.assert_array_equal(batch, np.concatenate(rows))
        # the held parameters change the result (the episode's mass, not the period's)
        assert not np.array_equal(batch, sim.step(x, u, np.random.default_rng(5)))


def test_persistent_parameters_change_single_run_success_and_are_seeded():
    """Stay below 0.45 for 40 periods from 0 with u = +1 (0.1 g per period): only a run with a small gain
    succeeds. Redrawn every period the gains average out (the walk reaches 4 +- 0.3: no run succeeds);
    held for the episode, P(-1 <= 4 g <= 0.45) = Phi(-1.775) - Phi(-2.5) = 0.032."""
    spec = Spec("invariance", safe=Box([-1.0], [0.45]))
    H, R = 40, 2000
    go = lambda x, t: np.full(len(x), 2)   # noqa: E731 (u = +1)
    k_per = success_counts(go, 1, _sim("period"), spec, np.zeros((1, 1)), R, H, seed=3)[0]
    k_epi = success_counts(go, 1, _sim("episode"), spec, np.zeros((1, 1)), R, H, seed=3)[0]
    assert k_per == 0
    assert 0.020 < k_epi / R < 0.044            # 0.032 +- 3 SE (SE 0.0039)
    assert k_epi == success_counts(go, 1, _sim("episode"), spec, np.zeros((1, 1)), R, H, seed=3)[0]   # seeded


def test_bad_mode_is_refused():
    with pytest.raises(SimgapError, match="randomize.per must be one of"):
        _sim("rollout")
    with pytest.raises(SimgapError, match="no per-run parameters"):
        make_simulator({"kind": "numpy", "system": "pendulum", "randomize": {"per": "episode"}})


def test_closed_loop_rollouts_hold_the_episode_parameters():
    from simgap.rollout import rollout

    class Right:
        system, hold, meta = WALK, 1, {}

        def input_index(self, x):
            return np.full(len(np.atleast_2d(x)), 2)

    spec = Spec("invariance", safe=Box([-1.0], [1.0]))
    for per, held in (("episode", True), ("period", False)):
        r = rollout(Right(), _sim(per), [0.0], spec=spec, n_rollouts=50, horizon=4, seed=0, mean_map_runs=0)
        inc = np.diff(r.trajectories[:, :, 0], axis=1)          # (R, T)
        assert (inc.std(axis=1).max() < 0.01) == held and inc.mean(axis=1).std() > 0.005

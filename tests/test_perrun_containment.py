"""The Lipschitz assumption of the interval MDP, probed: secants at several distances and the containment check.

Two simulators the single-distance Wood-Zhang estimate is blind to (issue 22, item 5): a 1-D walk with
a 0.2 mm hole (a state in it falls out of X) and a walk with a ripple of period eta / 2."""

import numpy as np
import pytest

import simgap.perrun.imdp as imdp_mod
from simgap.perrun.containment import check_containment
from simgap.perrun.imdp import IMDPOptions, trajectory_lipschitz
from simgap.perrun.sampling import build_imdp
from simgap.simulators.base import SimulatorConfig
from simgap.simulators.numpy_sim import NumpySimulator
from simgap.synthesis.spec import Box, Spec
from simgap.systems import System, input_grid


def _walk_step(x, u, dt):
    return x + dt * u


WALK = System(name="walk", state_names=("p",), input_names=("a",), x_lo=(-1,), x_hi=(1,),
              inputs=input_grid([-1], [1], [3]), base_tau=0.1, step=_walk_step)
SPEC = Spec("invariance", safe=Box([-0.8], [0.8]))
CONFIG = SimulatorConfig("numpy", "walk", noise={"process_std": 0.01})
HOLE = (0.0150, 0.0152)              # inside the cell [0.01, 0.03] of eta = 0.02
RIPPLE_PERIOD = 0.01                 # eta / 2: the single secant distance
RIPPLE_AMPLITUDE = 3.1 * RIPPLE_PERIOD / (2 * np.pi)   # true Lipschitz constant 1 + 3.1 = 4.1


class HoleWalk(NumpySimulator):
    """The walk, except that from a state in HOLE the next state is 5 (outside X = [-1, 1])."""

    def step_with_noise(self, x, u, noise):
        y = super().step_with_noise(x, u, noise)
        return np.where((x >= HOLE[0]) & (x <= HOLE[1]), 5.0, y)


class RippleWalk(NumpySimulator):
    """x+ = x + 0.1 u + a sin(2 pi x / p) + noise, p = eta / 2: Lipschitz constant 1 + 2 pi a / p = 4.1."""

    def step_with_noise(self, x, u, noise):
        return super().step_with_noise(x, u, noise) + RIPPLE_AMPLITUDE * np.sin(2 * np.pi * x / RIPPLE_PERIOD)


def test_secants_at_several_distances_see_a_ripple_one_distance_cannot(monkeypatch):
    sim = RippleWalk(CONFIG, system=WALK)
    half = np.array([0.01])
    L, how = trajectory_lipschitz(sim, 1, half, np.random.default_rng(0))
    assert 3.9 <= L[0, 0] <= 4.2                     # true constant 4.1
    monkeypatch.setattr(imdp_mod, "SECANT_SPREAD", 1.0)   # the old estimate: every secant at eta / 2
    L1, _ = trajectory_lipschitz(sim, 1, half, np.random.default_rng(0))
    assert L1[0, 0] < 1.01                           # blind: the ripple cancels at its own period


def _caught(sim, seed, n_states=64, hold=1):
    im = build_imdp(sim, SPEC, IMDPOptions(eta=[0.02], hold=hold, n_runs=300, pilot_runs=50, seed=seed))
    rep = check_containment(sim, SPEC, im, n_states=n_states, seed=seed)
    return im.meta["lipschitz"][0][0], rep


def test_containment_check_or_secants_catch_a_hole_in_most_seeds():
    """One abstract step of one period: the secants at sampled pairs rarely straddle a 0.2 mm hole (1 %
    of a cell); 64 fresh states per (cell, input) in every cell do, with probability 1 - 0.99^192 = 0.85."""
    sim = HoleWalk(CONFIG, system=WALK)
    caught, by_check = 0, 0
    for seed in range(10):
        L, rep = _caught(sim, seed)
        if not rep.passed:
            by_check += 1
            # the failures are reported in the hole's cell, as unaccounted runs (unsafe, reference run safe)
            assert {f["cell"] for f in rep.failures} == {51} and rep.unaccounted >= 1 and rep.cells_failed == 1
            assert rep.failures[0]["center"] == pytest.approx([0.02])
        caught += (L > 1.5) or not rep.passed
    assert caught >= 8 and by_check >= 6              # measured: 18 of 20 seeds (docs/per-run.md)


def test_containment_check_passes_without_a_hole_and_with_shared_runs():
    sim = NumpySimulator(CONFIG, system=WALK)
    for seed in range(3):
        L, rep = _caught(sim, seed, hold=3)
        assert rep.passed and rep.runs == rep.rows_checked * 64 and rep.construction == "per cell"
    im = build_imdp(sim, SPEC, IMDPOptions(eta=[0.02], hold=3, n_runs=300, pilot_runs=50, seed=1, share=5))
    rep = check_containment(sim, SPEC, im, n_states=64, seed=1)
    assert rep.construction == "shared" and rep.passed
    hole = HoleWalk(CONFIG, system=WALK)
    im = build_imdp(hole, SPEC, IMDPOptions(eta=[0.02], hold=1, n_runs=300, pilot_runs=50, seed=1, share=5))
    rep = check_containment(hole, SPEC, im, n_states=256, seed=1)
    assert not rep.passed and 51 in {f["cell"] for f in rep.failures}


def test_a_too_small_widening_is_caught_everywhere():
    """Given constants half the true ones (the walk's L = 1), fresh runs leave their boxes in most rows."""
    sim = NumpySimulator(CONFIG, system=WALK)
    im = build_imdp(sim, SPEC, IMDPOptions(eta=[0.02], hold=2, n_runs=300, pilot_runs=50, seed=0, lipschitz=[[0.5]]))
    rep = check_containment(sim, SPEC, im, n_states=16, seed=0)
    assert not rep.passed and rep.outside_box > rep.runs / 4 and rep.cells_failed > 0.9 * im.live.sum()
    im = build_imdp(sim, SPEC, IMDPOptions(eta=[0.02], hold=2, n_runs=300, pilot_runs=50, seed=0, lipschitz=[[1.0]]))
    assert check_containment(sim, SPEC, im, n_states=16, seed=0).passed

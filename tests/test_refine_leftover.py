"""Refine flags what its library cannot explain, and names no extra effect on small data (issue 57).

Generated cases with a known truth (simgap.refine.cases): four effects outside the library must
leave their state flagged, whatever library terms stand beside them; small data sets with one
planted library effect must name it alone (or nothing) and flag nothing; the held-out thresholds
grow as the held-out data shrink.
"""

import numpy as np
import pytest

from simgap.refine.cases import make_case, verdict
from simgap.refine.report import refine
from simgap.refine.selection import SelectionOptions
from simgap.refine.structure import critical, gain_z


def _run(name, K, seed=0):
    c = make_case(name, K, seed)
    return c, refine(c.system, c.data, options=SelectionOptions(seed=seed, n_boot=5)).report


@pytest.mark.parametrize("name", ["friction_dead_zone", "position_friction", "backlash", "delayed_coupling"])
@pytest.mark.parametrize("seed", [0, 2])
def test_effect_outside_the_library_is_flagged_not_called_a_mix(name, seed):
    c, rep = _run(name, 2000, seed)
    ok, desc = verdict(c, rep)
    assert ok, desc
    assert rep["unexplained"] is True
    (st,) = [s for s in rep["states"] if s["state_name"] == "omega"]
    assert st["unexplained"] and st["unexplained_fraction"] > 0.03, st


@pytest.mark.parametrize("seed", [0, 1])
def test_backlash_is_seen_as_memory_with_a_note(seed):
    """A residual that follows its own past (hysteresis) is flagged by the memory test, and the named
    lag terms beside it are said to be the library's nearest reading."""
    c, rep = _run("backlash", 2000, seed)
    (st,) = [s for s in rep["states"] if s["state_name"] == "omega"]
    assert st["memory_r2"] is not None and st["memory_r2"] > 0.2, st
    assert any("follows its own past" in n for n in st["notes"]), st["notes"]


@pytest.mark.parametrize("name", ["noise_series", "actuator_lag", "delay1"])
def test_memory_test_is_quiet_when_nothing_is_left(name):
    """White noise after the right terms: no memory, no flag (a memory test that always fires fails here)."""
    c, rep = _run(name, 2000, 1)
    assert verdict(c, rep)[0], verdict(c, rep)[1]
    assert all(s["memory_r2"] is None for s in rep["states"]), rep["states"]


@pytest.mark.parametrize("name", ["viscous", "input_gain", "coulomb_viscous", "heading_bias", "noise", "hetero_noise"])
@pytest.mark.parametrize("K", [150, 300])
def test_small_data_name_no_extra_effect_and_flag_nothing(name, K):
    for seed in range(4):
        c, rep = _run(name, K, seed)
        found = {(e["name"], e["state_name"]) for e in rep["effects"]}
        assert found <= set(c.expect["effects"]), (seed, found)
        assert rep["unexplained"] is False, (seed, verdict(c, rep)[1])


def test_threshold_grows_as_the_held_out_data_shrink():
    assert critical(3.0, 10_000) == pytest.approx(3.0, abs=0.01)
    assert 3.2 < critical(3.0, 30) < 3.35 and critical(3.0, 4) > 6
    # the paired statistic: a fit that predicts half of a signal is significant with many rows,
    # not with a handful; white noise in blocks gives the number of blocks less one as dof
    rng = np.random.default_rng(0)
    sig = rng.standard_normal(4000)
    e = sig + rng.standard_normal(4000)
    z, dof = gain_z(e, e - 0.5 * sig)
    assert z > 10 and dof == 3999
    z, dof = gain_z(e[:12], e[:12] - 0.5 * sig[:12])
    assert dof == 11 and z < critical(3.0, dof)
    _, dof = gain_z(e, e - 0.5 * sig, block=40)
    assert dof == 99


def test_heading_turned_by_the_speed_is_named_as_an_input_coupling():
    """The unicycle routes v into x, y only; a heading turned by the speed is named input_coupling
    theta:v with its rate, and the error bar covers the truth."""
    c, rep = _run("heading_speed", 4000)
    assert verdict(c, rep)[0], verdict(c, rep)[1]
    (e,) = rep["effects"]
    assert e["input"] == "v" and abs(e["coefficient"] - 0.06) <= 3 * e["stderr"] + 1e-4, e


def test_weighted_pair_means_count_each_pair_by_its_standard_error():
    """Pair means whose runs scatter 50 times more at speed: weighting by 1 / se recovers the turn-rate
    loss with a much smaller error bar than the unweighted fit; off by default."""
    from simgap.refine.data import make_transitions
    from simgap.systems import get_system

    s = get_system("turtlebot")
    rng = np.random.default_rng(3)
    K = 3000
    x = s.x_lo + rng.random((K, s.n)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, len(s.inputs), K)]
    se = np.repeat((1e-4 + 5e-3 * np.abs(u[:, [0]])), 3, axis=1)
    xn = s.f(x, u) + s.tau * np.column_stack([0 * u[:, 0], 0 * u[:, 0], -0.1 * u[:, 1]]) \
        + se * rng.standard_normal(x.shape)
    d = make_transitions(x, u, xn, s.tau, system=s)
    d.se = se
    out = {}
    for w in (False, True):
        rep = refine(s, d, options=SelectionOptions(weighted=w, n_boot=20)).report
        assert rep["weighted"] is w
        (e,) = [e for e in rep["effects"] if e["state_name"] == "theta"]
        assert e["name"] == "input_gain" and abs(e["coefficient"] + 0.1) <= 3 * e["stderr"], e
        out[w] = e["stderr"]
    assert out[True] < out[False] / 3, out

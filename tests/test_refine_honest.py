"""An honest refinement loop: flag what the library cannot explain, name delays, carry misfit in
error bars, gate on multi-step error, iterate on refined models (generated cases with a known truth)."""

from pathlib import Path

import numpy as np
import pytest

from simgap.refine.cases import CASES, make_case, verdict
from simgap.refine.data import make_transitions
from simgap.refine.report import refine
from simgap.refine.selection import SelectionOptions
from simgap.systems import get_system


def _run(name, K=20000, seed=0, **kw):
    c = make_case(name, K, seed)
    return c, refine(c.system, c.data, **kw).report


@pytest.mark.parametrize("name", ["slip", "ripple", "terrain"])
def test_out_of_library_residual_is_flagged_with_share_above_floor(name):
    c, rep = _run(name)
    ok, desc = verdict(c, rep)
    assert ok, desc
    st = {s["state_name"]: s for s in rep["states"]}[c.expect["flag"]]
    # the model-free floor matches the planted noise, and the share above it is reported
    s = get_system(c.system)
    i = s.state_names.index(c.expect["flag"])
    r = (c.data.x_next[:, i] - s.f(c.data.x, c.data.u)[:, i]) / s.tau
    true_floor = (CASES[name]["std"] / s.tau) ** 2 / np.mean(r ** 2)
    # (nearest-neighbour differences also pick up some structure: the floor errs on the high side)
    assert 0.85 * true_floor < st["noise_floor_fraction"] < true_floor + 0.2, (st, true_floor)
    assert st["unexplained_fraction"] == pytest.approx(st["remaining_fraction"] - st["noise_floor_fraction"])
    assert st["unexplained_fraction"] > 0.15, st


@pytest.mark.parametrize("name,seed", [("noise", 1), ("noise", 2), ("hetero_noise", 1), ("hetero_noise", 2),
                                       ("noise_series", 1)])
def test_noise_is_not_flagged(name, seed):
    c, rep = _run(name, K=12000, seed=seed)
    assert rep["effects"] == [] and rep["unexplained"] is False, verdict(c, rep)[1]
    for s in rep["states"]:
        # the floor accounts for (almost) all of the residual: nothing structured is left
        assert 0.8 < s["noise_floor_fraction"] < 1.2, s


@pytest.mark.parametrize("name", ["viscous", "input_gain", "coulomb_viscous", "heading_bias"])
def test_in_library_effects_are_named(name):
    c, rep = _run(name, K=12000)
    ok, desc = verdict(c, rep)
    assert ok, desc


def test_refining_a_refined_model_drops_collinear_candidates_with_a_note():
    """EMPS has no drift: on a refined EMPS (bias + friction), 'gravity' is the refined drift itself."""
    s = get_system("emps")
    rng = np.random.default_rng(3)

    def rows(K):
        x = s.x_lo + rng.random((K, 2)) * (s.x_hi - s.x_lo)
        u = s.inputs[rng.integers(0, len(s.inputs), K)]
        xn = s.f(x, u)
        xn[:, 1] += s.tau * (0.05 - 2.0 * x[:, 1] - 0.2 * np.sign(x[:, 1])) + 1e-6 * rng.standard_normal(K)
        return make_transitions(x, u, xn, s.tau, system=s)

    first = refine("emps", rows(12000))
    assert {e["name"] for e in first.report["effects"]} >= {"bias", "viscous_friction", "coulomb_friction"}
    second = refine(first.refined, rows(12000))      # no --effects: must not fail as rank-deficient
    notes = " ".join(n for st in second.report["states"] for n in st["notes"])
    assert "gravity:qd" in notes and "collinear" in notes
    assert second.report["effects"] == [] and second.report["unexplained"] is False


EMPS_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "emps"


@pytest.mark.skipif(not (EMPS_DIR / "DATA_EMPS_PULSES.mat").exists(), reason=f"EMPS records not in {EMPS_DIR}")
def test_emps_refined_model_refines_again_on_the_second_record():
    from simgap.refine.trajectory import from_trajectory_file
    first = refine("emps", from_trajectory_file(EMPS_DIR / "DATA_EMPS.mat", preset="emps"),
                   options=SelectionOptions(n_boot=20))
    second = refine(first.refined, from_trajectory_file(EMPS_DIR / "DATA_EMPS_PULSES.mat", preset="emps"),
                    options=SelectionOptions(n_boot=20))
    notes = " ".join(n for st in second.report["states"] for n in st["notes"])
    assert "collinear" in notes


def test_generator_has_the_promised_variety():
    shapes = {c["shape"] for c in CASES.values()}
    assert len(CASES) >= 10
    assert sum(s.startswith("outside") for s in shapes) >= 3
    assert any("delay" in s for s in shapes) and any("heteroscedastic" in s for s in shapes)

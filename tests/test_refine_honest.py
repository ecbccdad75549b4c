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
    # (slip: input_gain + input_cross_abs, v |omega|, carry 86 % of the step in |omega|; what is
    # left above the floor is the step's misfit, about 5 %)
    assert st["unexplained_fraction"] > (0.03 if name == "slip" else 0.15), st


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


@pytest.mark.parametrize("name,periods", [("delay1", 1), ("delay2", 2)])
def test_input_delay_is_named_as_a_delay_with_its_length(name, periods):
    c, rep = _run(name)
    ok, desc = verdict(c, rep)
    assert ok, desc
    (d,) = [e for e in rep["effects"] if e["name"] == "input_delay"]
    assert d["periods"] == periods and d["input"] == "torque"
    assert d["coefficient"] == pytest.approx(1.0, abs=0.05)      # the whole input arrives late
    assert d["physical"]["value"] == pytest.approx(periods * 0.005)   # seconds
    assert not any(e["name"] == "input_gain" for e in rep["effects"])


def test_multistep_gate_withdraws_a_fix_that_predicts_worse():
    """Without history candidates the delay looks like an input gain; its multi-step error is worse."""
    c, rep = _run("delay1", effects=["bias", "viscous_friction", "input_gain", "gravity"])
    assert not any(e["name"] == "input_gain" for e in rep["effects"]), rep["effects"]
    (w,) = [e for e in rep["withdrawn"] if e["name"] == "input_gain" and e["state_name"] == "omega"]
    assert f"{w['horizon']}-step" in w["reason"] and w["horizon"] in (10, 100)
    for k in ("10", "100"):
        ms = rep["multistep"][k]
        assert np.all(np.asarray(ms["rms_after"]) <= np.asarray(ms["rms_before"]) * 1.0001)
    assert rep["unexplained"] is True         # what remains is not explained, and the report says so


def test_dead_zone_error_bar_includes_misfit():
    c, rep = _run("dead_zone")
    (d,) = [e for e in rep["effects"] if e["name"] == "deadband"]
    width, se = -d["coefficient"], d["stderr"]
    # a wrong-shaped term must not look precise: the interval covers the true width 0.2
    assert abs(width - 0.2) <= 2 * se, (width, se)
    assert d["stderr_misfit"] > d["stderr_statistical"]
    # an exact-shaped term keeps a tight error bar
    _, rep2 = _run("viscous", K=12000)
    (v,) = rep2["effects"]
    assert v["stderr_misfit"] < 3 * v["stderr_statistical"] + 1e-12
    assert abs(v["coefficient"] + 0.5) < 0.01


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


def test_cli_iterates_on_a_saved_refined_model_and_validates_on_a_second_record(tmp_path, capsys):
    from simgap.cli import main
    import json
    files = []
    for seed in (0, 1):
        c = make_case("coulomb_viscous", 6000, seed)
        p = tmp_path / f"d{seed}.npz"
        c.data.save_npz(p)
        files.append(str(p))
    rep, sysf, rep2 = tmp_path / "r.json", tmp_path / "ref.json", tmp_path / "r2.json"
    assert main(["refine", "--system", "pendulum", "--data", files[0], "--validate", files[1], "--quiet",
                 "--bootstrap", "20", "--out", str(rep), "--save-system", str(sysf)]) == 0
    v = json.loads(rep.read_text())["validation"]
    assert v["samples"] == 6000 and v["data"] == files[1]
    assert v["rms_after"][1] < v["rms_before"][1] / 5          # the fix carries over to the unseen record
    # iterate: the refined model on the second record, no --effects: nothing left to add, no error
    assert main(["refine", "--system", str(sysf), "--data", files[1], "--quiet", "--bootstrap", "20",
                 "--out", str(rep2)]) == 0
    r2 = json.loads(rep2.read_text())
    assert r2["effects"] == [] and r2["unexplained"] is False
    capsys.readouterr()
    assert main(["refine", "--system", "emps", "--data", str(tmp_path / "rec.mat")]) == 2
    assert "needs --preset" in capsys.readouterr().err


def test_user_term_with_lagged_input_on_time_ordered_data():
    from simgap.refine.effects import user_effect
    c = make_case("delay1", 12000)
    s = get_system("pendulum")
    late = user_effect(s, "late_torque", "omega", "3*(torque[k-1] - torque)", max_lag=3)
    rep = refine(s, c.data, effects=["bias", "viscous_friction"], user_terms=[late]).report
    (e,) = rep["effects"]
    assert e["name"] == "late_torque" and e["in_refined_system"] is False
    # the model's torque gain is 3 / (m l^2) = 3: the term is exactly the delayed torque's effect
    assert e["coefficient"] == pytest.approx(1.0, rel=0.02)
    rows = make_transitions(c.data.x, c.data.u, c.data.x_next, c.data.tau, system=s)   # no time order
    from simgap.errors import SimgapError
    with pytest.raises(SimgapError, match="no time order"):
        refine(s, rows, user_terms=[late])
    with pytest.raises(SimgapError, match="input_delay needs time-ordered data"):
        refine(s, rows, effects=["input_delay"])


def test_structure_test_on_tiny_data_sets():
    """Fewer train rows than the largest k of the kNN fit still give a report, not an IndexError."""
    c = make_case("viscous", 40)
    rep = refine("pendulum", c.data, effects=["viscous_friction"]).report
    assert [e["name"] for e in rep["effects"]] == ["viscous_friction"]
    assert all(np.isfinite(s["structure_r2"]) for s in rep["states"])

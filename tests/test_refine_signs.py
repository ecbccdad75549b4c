"""Impossible signs are never reported as found physics: refused with the reason (and flagged)."""

import numpy as np
import pytest

from simgap.refine.cases import make_case, verdict
from simgap.refine.effects import candidate_effects, sign_check
from simgap.refine.refined import refined_system
from simgap.refine.report import format_table, refine
from simgap.systems import get_system

from tests.test_refine import sample


def test_saturation_is_not_a_dead_zone_of_negative_width():
    c = make_case("saturation", 12000)
    rep = refine(c.system, c.data).report
    assert not any(e["name"] == "deadband" for e in rep["effects"]), rep["effects"]
    (r,) = [r for r in rep["refused"] if r["key"].startswith("deadband")]
    assert r["coefficient"] > 0 and "negative width" in r["reason"] and r["state_name"] == "omega"
    assert verdict(c, rep)[0]                          # omega flagged
    assert "refused deadband" in format_table(rep)


def test_anti_damping_is_refused_but_less_friction_than_the_model_has_is_not():
    s = get_system("pendulum")
    push = sample("pendulum", 6000, 3, extra=lambda x, u: np.stack([0 * x[:, 0], 0.8 * x[:, 1]], 1))
    rep = refine(s, push).report
    assert not any(e["name"] in ("viscous_friction", "drag") and e["coefficient"] > 0 for e in rep["effects"])
    assert any("inject energy" in r["reason"] for r in rep["refused"]), rep["refused"]
    assert rep["states"][1]["unexplained"] is True
    # a model with damping -2.0 on data with -1.2: the correction +0.8 keeps the total dissipative
    (visc,) = candidate_effects(s, ["viscous_friction"])
    damped = refined_system(s, [visc], [-2.0])
    data = sample("pendulum", 6000, 4, extra=lambda x, u: np.stack([0 * x[:, 0], -1.2 * x[:, 1]], 1))
    rep2 = refine(damped, data).report
    (e,) = rep2["effects"]
    assert e["name"] == "viscous_friction" and e["coefficient"] == pytest.approx(0.8, rel=0.03)
    assert rep2["refused"] == [] and rep2["unexplained"] is False


def test_sign_rules_one_by_one():
    s = get_system("pendulum")
    effs = candidate_effects(s, ["viscous_friction", "coulomb_friction", "drag", "deadband", "input_gain",
                                 "input_delay"], max_lag=2)
    x = np.column_stack([np.zeros(5), np.linspace(-0.5, 0.5, 5)])
    check = sign_check(s, [e for e in effs if e.state == 1], x)
    ok = 1e-3
    assert check(["viscous_friction:omega:omega"], [-0.3], [ok]) is None
    k, why, beyond = check(["viscous_friction:omega:omega"], [0.3], [ok])
    assert k == "viscous_friction:omega:omega" and "inject energy" in why and beyond
    # Coulomb dominating a small positive viscous term over the data's speeds still dissipates
    assert check(["coulomb_friction:omega:omega", "viscous_friction:omega:omega"], [-0.5, 0.5], [ok, ok]) is None
    assert check(["coulomb_friction:omega:omega", "viscous_friction:omega:omega"], [-0.1, 0.5], [ok, ok])[0] \
        == "viscous_friction:omega:omega"
    assert check(["drag:omega:omega"], [0.2], [ok])[0] == "drag:omega:omega"
    assert check(["deadband:omega:torque"], [0.05], [ok])[1].startswith("a dead zone of negative width")
    assert check(["deadband:omega:torque"], [-0.05], [ok]) is None
    assert check(["input_delay:omega:torque:1"], [-0.2], [ok])[1].startswith("a negative fraction")
    assert check(["input_delay:omega:torque:1"], [1.001], [ok]) is None       # the whole input, within 2 se
    assert check(["input_delay:omega:torque:2"], [1.5], [ok])[2] is True
    assert check(["input_gain:omega:torque"], [-1.4], [ok]) is not None
    assert check(["input_gain:omega:torque"], [-0.4], [ok]) is None
    # a term merely on the wrong side of zero within its error bar is refused without a flag
    assert check(["deadband:omega:torque"], [0.01], [0.02])[2] is False


@pytest.mark.parametrize("seed", [0, 1])
def test_small_effect_next_to_a_large_one_is_named_in_a_second_round(seed):
    """Coulomb friction 20x below an input-gain error (2x the noise): 0.2 % of the nominal residual."""
    from simgap.refine.selection import SelectionOptions
    c = make_case("small_coulomb", 20000, seed)
    rep = refine(c.system, c.data, options=SelectionOptions(n_boot=20)).report
    assert verdict(c, rep)[0], verdict(c, rep)[1]
    (cf,) = [e for e in rep["effects"] if e["name"] == "coulomb_friction"]
    assert abs(cf["coefficient"] - c.truth["coulomb"]) < max(3 * cf["stderr"], 0.002)
    assert rep["states"][1]["rounds"] == 2 and rep["states"][0]["rounds"] == 1
    # one round with thresholds relative to the nominal residual misses it, but the flag (relative
    # to what is left) still says that structure remains
    one = refine(c.system, c.data, options=SelectionOptions(n_boot=5, max_rounds=1)).report
    assert [e["name"] for e in one["effects"]] == ["input_gain"]
    assert one["states"][1]["unexplained"] is True

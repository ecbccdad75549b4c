"""Consistent corrections on a semi-implicit user model: a cubic spring named from the library, and a
correction of the velocity update carried into the position that integrates it."""

from pathlib import Path

import numpy as np
import pytest

from simgap.refine.data import make_transitions
from simgap.refine.effects import candidate_effects, carry_matrix
from simgap.refine.refined import load_system, refined_system, save_refined
from simgap.refine.report import refine
from simgap.refine.selection import SelectionOptions
from simgap.systems import get_system

SB = Path(__file__).resolve().parents[1] / "examples" / "silverbox" / "silverbox_linear.toml"
K3 = -5.0e5          # hardening cubic spring [V/s^2 per V^3], as on the real Silverbox


def _duffing_log(K=12000, seed=0, runs=20):
    """Episodes of the semi-implicit model with a cubic spring the model lacks (and process noise)."""
    s = load_system(str(SB))
    rng = np.random.default_rng(seed)
    dt = s.tau
    T = K // runs
    u = rng.uniform(-0.12, 0.12, (runs, T))
    u = np.repeat(u[:, ::8], 8, axis=1)[:, :T]             # held for 8 periods
    x = np.zeros((runs, 2))
    X, XN = [], []
    for k in range(T):
        a = K3 * x[:, 0] ** 3
        xn = s.f(x, u[:, k:k + 1])
        xn[:, 1] += dt * a                                   # velocity update ...
        xn[:, 0] += dt * dt * a                              # ... and the position that uses it
        xn += rng.normal(0, [1e-6, 1e-4], xn.shape)
        X.append(x), XN.append(xn)
        x = xn
    X, XN = (np.stack(a, axis=1).reshape(-1, 2) for a in (X, XN))
    t = (np.arange(runs)[:, None] * (T + 10) + np.arange(T)[None, :]).reshape(-1) * dt
    return s, make_transitions(X, u.reshape(-1, 1), XN, dt, t, system=s)


def test_carry_factors_follow_the_discretisation():
    assert not np.any(carry_matrix(get_system("pendulum")))        # explicit Euler: nothing carried
    assert not np.any(carry_matrix(get_system("emps")))
    s = load_system(str(SB))
    K = carry_matrix(s)
    assert K[0, 1] == pytest.approx(s.tau, rel=1e-6) and K[1, 0] == 0 and K[0, 0] == 0


def test_cubic_spring_is_named_and_carried_into_the_position(tmp_path):
    s, data = _duffing_log()
    rep = refine(s, data, options=SelectionOptions(n_boot=10)).report
    (e,) = [e for e in rep["effects"] if e["state_name"] == "v"]
    assert e["name"] == "cubic_stiffness" and e["variable"] == "y"
    assert e["coefficient"] == pytest.approx(K3, rel=0.05)
    # the position needs nothing of its own: the carried correction is the whole story
    assert not [e for e in rep["effects"] if e["state_name"] == "y"], rep["effects"]
    assert rep["unexplained"] is False
    # the refined model equals the truth on both updates, so its free run follows the record
    (cubic,) = [c for c in candidate_effects(s, ["cubic_stiffness"])]
    ref = refined_system(s, [cubic], [K3])
    x = data.x[:50]
    truth = s.f(x, data.u[:50])
    truth[:, 1] += s.tau * K3 * x[:, 0] ** 3
    truth[:, 0] += s.tau ** 2 * K3 * x[:, 0] ** 3
    np.testing.assert_allclose(ref.f(x, data.u[:50]), truth, rtol=1e-12, atol=1e-15)
    # saved on the file base, loadable without the file
    from simgap.refine.report import refine as _r
    res = _r(s, data, options=SelectionOptions(n_boot=5))
    p = save_refined(res.refined, tmp_path / "sb.json")
    back = load_system(str(p))
    np.testing.assert_allclose(back.f(x, data.u[:50]), res.refined.f(x, data.u[:50]), rtol=1e-12)


def test_free_run_check_says_when_the_refined_model_diverges_where_the_nominal_does_not():
    from simgap.refine.cases import make_case
    from simgap.refine.report import free_run_check
    from simgap.refine.selection import split_heldout
    c = make_case("noise_series", 4000, 0)
    s = get_system("pendulum")
    held = split_heldout(c.data.K, c.data.t, SelectionOptions())
    (visc,) = candidate_effects(s, ["viscous_friction"])
    fine = free_run_check(s, refined_system(s, [visc], [-0.5]), c.data, held)
    assert fine["diverged_before"] == 0 and fine["diverged_after"] == 0 and fine["stretches"] >= 5
    bad = free_run_check(s, refined_system(s, [visc], [400.0]), c.data, held)     # anti-damping, 2 1/tau
    assert bad["diverged_before"] == 0 and bad["diverged_after"] == bad["stretches"]

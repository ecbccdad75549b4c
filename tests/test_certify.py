"""Gap certification: formulas, basis parsing and interval bounds, scenario LP, Lipschitz, certificate."""

import json

import numpy as np
import pytest

from simgap.certify import BoundOptions, beta_from_delta, certify, confidences, delta_from_beta, \
    joint_from_per_dimension, load
from simgap.certify.basis import Basis, monomial_names, parse_term
from simgap.certify.bounds import required_runs
from simgap.certify.lipschitz import l2_analytic, wood_zhang
from simgap.certify.scp import solve_scp
from simgap.certify.synthetic import grid_cover, synthetic_dataset
from simgap.certify.variance import variance_bound
from simgap.errors import SimgapError
from simgap.systems import pendulum, turtlebot

PEND_CFG = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 0.002},
            "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]], "bias": [0.0, 0.01]}}


@pytest.fixture(scope="module")
def pend_ds():
    return synthetic_dataset(PEND_CFG, epsilon=0.02, n_runs=100, seed=3)


@pytest.fixture(scope="module")
def pend_cert(pend_ds):
    return certify(pend_ds, terms={1: ["sin(theta)"]})


# ----- formulas ---------------------------------------------------------------------------

def test_chebyshev_formulas_hand_computed():
    # Lemma 1: M/(d^2 N); Lemma 2: 2M/(d^2 N)
    b1, b2 = beta_from_delta([0.007, 0.0101], 0.05, 0.05, 1000)
    assert b1 == pytest.approx([0.0028, 0.0101 / 2.5], rel=1e-12)
    assert b2 == pytest.approx([0.0056, 2 * 0.0101 / 2.5], rel=1e-12)
    # the paper's printed beta_1,1 = 0.0028 follows from delta = 0.05, not the printed 0.01
    assert beta_from_delta([0.007], 0.01, 0.01, 1000)[0][0] == pytest.approx(0.07)
    # ... and the printed beta_1,3 = 0.0079 follows from Mhat_3 = 0.0101 at none of the printed deltas
    for d in (0.01, 0.05):
        assert beta_from_delta([0.0101], d, d, 1000)[0][0] != pytest.approx(0.0079, rel=0.05)
    # general Lemma 2 (4 Mhat)
    assert beta_from_delta([0.007], 0.05, 0.05, 1000, opts=BoundOptions(lemma2_factor=4.0))[1][0] \
        == pytest.approx(0.0112)
    # inverse: smallest delta for a target beta, delta = sqrt(M / (beta N)) and sqrt(2M / (beta N))
    d1, d2 = delta_from_beta([0.007], 0.0028, 0.0056, 1000)
    assert d1[0] == pytest.approx(0.05) and d2[0] == pytest.approx(0.05)
    # uniform mode divides beta_1 by K
    d1u, _ = delta_from_beta([0.007], 0.0028, 0.0056, 1000, K=100, opts=BoundOptions(uniform=True))
    assert d1u[0] == pytest.approx(0.5)


def test_paper_confidence_composition_table():
    # TurtleBot: betas (0.0028, 0.0056), (0.0028, 0.0056), (0.0079, 0.0158)
    per, joint = confidences([0.0028, 0.0028, 0.0079], [0.0056, 0.0056, 0.0158])
    assert per == pytest.approx([0.9916, 0.9916, 0.9763], abs=1e-12)
    assert round(100 * joint, 2) == 95.95
    assert round(100 * joint_from_per_dimension([0.9916, 0.9916, 0.9763]), 2) == 95.95
    # pendulum: 0.973 and 0.9649 -> 93.8 %
    assert round(100 * joint_from_per_dimension([0.973, 0.9649]), 1) == 93.8


@pytest.mark.parametrize("opts", [BoundOptions(), BoundOptions(concentration="subgaussian"),
                                  BoundOptions(concentration="bernstein", value_range=0.5),
                                  BoundOptions(uniform=True, lemma2_factor=4.0)])
def test_delta_beta_roundtrip(opts):
    M = np.array([1e-4, 3e-3])
    d1, d2 = delta_from_beta(M, 0.01, 0.02, 500, K=1000, opts=opts)
    b1, b2 = beta_from_delta(M, d1, d2, 500, K=1000, opts=opts)
    assert b1 == pytest.approx([0.01, 0.01], rel=1e-6) and b2 == pytest.approx([0.02, 0.02], rel=1e-6)
    # smaller delta -> larger beta (the delta is the smallest one)
    b1s, _ = beta_from_delta(M, 0.99 * d1, d2, 500, K=1000, opts=opts)
    assert np.all(b1s > 0.01)


def test_exponential_bounds_tighter_than_chebyshev_at_small_beta():
    M = [0.007]
    dc = delta_from_beta(M, 0.001, 0.001, 1000)[0][0]
    ds = delta_from_beta(M, 0.001, 0.001, 1000, opts=BoundOptions(concentration="subgaussian"))[0][0]
    assert ds < dc / 3


def test_required_runs():
    N = required_runs([0.007], 0.05, 0.05, 0.0028, 0.0056)
    assert N == 1000
    assert np.all(np.concatenate(beta_from_delta([0.007], 0.05, 0.05, N)) <= [0.0028, 0.0056])


def test_variance_bounds():
    var = np.array([[1e-4, 2e-4], [3e-4, 1e-5]])
    vb = variance_bound(var, 100)
    assert vb.M == pytest.approx([3e-3, 2e-3])
    mp = variance_bound(var, 100, method="maurer_pontil", value_range=0.1, beta_v=0.01)
    expect = (np.sqrt([3e-4, 2e-4]) + 0.1 * np.sqrt(2 * np.log(2 / 0.01) / 99)) ** 2
    assert mp.M == pytest.approx(expect)
    with pytest.raises(SimgapError, match="N1hat >= 2"):
        variance_bound(var, 1)
    with pytest.raises(SimgapError, match="range"):
        variance_bound(var, 100, method="maurer_pontil")


# ----- basis ------------------------------------------------------------------------------

def test_monomials_and_names():
    s = pendulum()
    names = monomial_names(s, 2)
    assert len(names) == 10 and names[0] == "1" and "x1*u1" in names and "x2^2" in names
    assert len(monomial_names(turtlebot(), 1)) == 6
    b = Basis.polynomial(s, 1, ["cos(theta)", "omega^2*torque", "x2*u1"])
    x = np.array([[0.1, -0.3], [0.0, 0.2]])
    u = np.array([[0.5], [-1.0]])
    P = b.design(x, u)
    assert P[0] == pytest.approx([1, 0.1, -0.3, 0.5, np.cos(0.1), 0.09 * 0.5, -0.15])


@pytest.mark.parametrize("bad, match", [
    ("cos(x3)", "unknown variable 'x3'"), ("foo(x1)", "function 'foo'"), ("x1**x2", "integer"),
    ("__import__('os').system('true')", "not allowed"), ("x1.real", "Attribute"), ("x1 +", "does not parse"),
    ("", "empty"), ("x1 if x2 else 1", "IfExp"), ("sin(x1, x2)", "one argument"), ("'a'", "not a number")])
def test_bad_terms(bad, match):
    with pytest.raises(SimgapError, match=match):
        parse_term(bad, pendulum())


def test_interval_bounds_are_sound_against_dense_sampling():
    s = pendulum()
    b = Basis.polynomial(s, 2, ["cos(theta)", "sin(3*x1)/(2+x2)", "sqrt(abs(x1))", "tanh(x2)*exp(u1)",
                                "sign(x1)*x2", "tan(x1)", "x2^3 - x1^-1*0"])
    rng = np.random.default_rng(0)
    B = 64
    c = rng.uniform(-0.3, 0.3, (B, 3))
    w = rng.uniform(0, 0.1, (B, 3))
    lo, hi = c - w, c + w
    S = 3000
    Z = lo + rng.random((S, B, 3)) * (hi - lo)
    Zf = Z.reshape(-1, 3)
    P = b.design(Zf[:, :2], Zf[:, 2:]).reshape(S, B, -1)
    plo, phi = b.value_bounds(lo, hi)
    assert np.all(plo <= P.min(axis=0) + 1e-12) and np.all(phi >= P.max(axis=0) - 1e-12)
    q = rng.normal(size=len(b))
    assert np.all(b.upper_box(q, lo, hi) >= (P @ q).max(axis=0) - 1e-12)
    # gradient bound vs central differences
    g = b.grad_x_bound(q, lo, hi)
    h = 1e-6
    inner = np.clip(Z[:200], lo + 2 * h, hi - 2 * h).reshape(-1, 3)
    for j in range(2):
        e = np.zeros(3)
        e[j] = h
        fd = (b.design((inner + e)[:, :2], inner[:, 2:]) @ q - b.design((inner - e)[:, :2], inner[:, 2:]) @ q) / (2 * h)
        fd = np.abs(fd).reshape(200, B)
        ok = np.isfinite(fd)
        assert np.all(fd[ok] <= np.broadcast_to(g[:, j], fd.shape)[ok] * (1 + 1e-6) + 1e-6)


def test_design_rejects_nan_terms():
    b = Basis(pendulum(), ["1", "1/x1"])
    with pytest.raises(SimgapError, match="1/x1"):
        b.design(np.array([[0.0, 0.1]]), np.array([[0.0]]))


# ----- scenario program --------------------------------------------------------------------

def test_scp_small_hand_case():
    # p = [1, x]; gaps g = |x| on x in [-1, 1]: min eta forces eta = 1 + delta, the secondary
    # objective (min mean fit) with q0 + q1 x >= |x| + delta and fit <= eta: q = [1 + delta, 0]... or tilted
    x = np.linspace(-1, 1, 201)
    P = np.stack([np.ones_like(x), x], axis=1)
    g = np.abs(x)
    r = solve_scp(P, g, 0.1)
    assert r.eta_star == pytest.approx(1.1, abs=1e-6)
    fit = P @ r.q
    assert np.all(fit >= g + 0.1 - 1e-9) and fit.max() <= 1.1 + 1e-5
    assert r.q[1] == pytest.approx(0.0, abs=1e-5)   # symmetric data -> flat fit is the unique 2nd-stage optimum
    assert r.status.startswith("optimal")


@pytest.mark.parametrize("solver", ["CLARABEL", "HIGHS"])
def test_constraint_generation_equals_full_lp(pend_ds, solver):
    P = Basis.polynomial(pend_ds.system, 2).design(pend_ds.x, pend_ds.u)
    g = pend_ds.gap()[:, 1]
    a = solve_scp(P, g, 0.001, solver=solver)
    b = solve_scp(P, g, 0.001, method="full", solver=solver)
    assert a.rounds > 2 and a.n_rows_used < pend_ds.K / 2
    assert a.eta_star == pytest.approx(b.eta_star, rel=1e-6)
    assert (P @ a.q).mean() == pytest.approx((P @ b.q).mean(), rel=1e-5)
    assert np.allclose(a.q, b.q, atol=1e-6 * np.abs(b.q).max())
    # stage 1 solved as an LP gives the closed-form optimum max(g + delta1)
    c = solve_scp(P, g, 0.001, solver=solver, closed_form=False)
    assert c.stages["stage1"]["rounds"] >= 1
    assert c.eta_star == pytest.approx(a.eta_star, rel=1e-6) == pytest.approx(g.max() + 0.001, rel=1e-9)
    assert (P @ c.q).mean() == pytest.approx((P @ a.q).mean(), rel=1e-5)


def test_scp_infeasible_basis_is_an_error(pend_ds):
    with pytest.raises(SimgapError, match="infeasible"):
        certify(pend_ds, degree=-1, terms={-1: ["x1"]})


def test_scp_bad_inputs():
    P = np.ones((5, 2))
    with pytest.raises(SimgapError, match="linearly dependent"):
        solve_scp(P, np.zeros(5))
    with pytest.raises(SimgapError, match="NaN"):
        solve_scp(np.array([[1.0], [np.nan]]), np.zeros(2))
    with pytest.raises(SimgapError, match="solver"):
        solve_scp(np.ones((2, 1)), np.zeros(2), solver="GUROBI")


# ----- Lipschitz ---------------------------------------------------------------------------

def test_wood_zhang_recovers_known_constant():
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 2, 20000)
    b = a + rng.uniform(1e-3, 1e-2, a.size)
    slopes = np.abs(np.sin(3 * a) - np.sin(3 * b)) / np.abs(a - b)
    est = wood_zhang(slopes, np.random.default_rng(2))
    assert 2.9 <= est.estimate <= 3.3 and est.estimate >= est.max_slope


def test_l2_analytic_bounds_gradient():
    s = pendulum()
    b = Basis.polynomial(s, 2)
    q = np.array([0.0, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # x1 + 2 x1^2: |grad| <= 1 + 4*0.2
    L = l2_analytic(b, q, s)
    assert L == pytest.approx(1.8, abs=1e-9)  # attained at x1 = 0.2: the bound is exact here


# ----- end to end: known true gap -------------------------------------------------------------

def test_certificate_bounds_true_gap(pend_ds, pend_cert):
    from simgap.simulators.base import make_simulator
    sim = make_simulator(pend_ds.manifest["simulator"])
    rng = np.random.default_rng(7)
    s = pend_ds.system
    x = s.x_lo + rng.random((5000, 2)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, len(s.inputs), 5000)]
    true_gap = np.abs(s.diff(sim.mean_next(x, u), s.f(x, u)))
    gam = pend_cert.gamma(x, u)
    assert np.all(true_gap <= gam)
    assert pend_cert.joint_confidence == pytest.approx(0.96)
    # sanity: the gap is not trivial (bias 0.01 * tau, damping) and gamma is not absurdly large
    assert true_gap[:, 1].max() > 1e-4 and gam.max() < 0.1


def test_gamma_upper_box_sound(pend_cert):
    rng = np.random.default_rng(3)
    s = pendulum()
    B = 40
    c = s.x_lo + rng.random((B, 2)) * (s.x_hi - s.x_lo)
    w = rng.uniform(0, 0.05, (B, 2))
    lo, hi = np.maximum(c - w, s.x_lo), np.minimum(c + w, s.x_hi)
    u = s.inputs[rng.integers(0, 21, B)]
    ub = pend_cert.gamma_upper_box(lo, hi, u)
    S = 2000
    X = lo + rng.random((S, B, 2)) * (hi - lo)
    G = pend_cert.gamma(X.reshape(-1, 2), np.tile(u, (S, 1))).reshape(S, B, 2)
    assert np.all(ub >= G.max(axis=0) - 1e-12)
    assert np.all(ub - G.max(axis=0) < 0.01)  # not vacuous
    # a degenerate box gives gamma itself
    assert pend_cert.gamma_upper_box(c, c, u) == pytest.approx(pend_cert.gamma(c, u), abs=1e-12)


def test_certificate_json_roundtrip_and_hash(tmp_path, pend_ds, pend_cert):
    p = pend_cert.save(tmp_path / "cert.json")
    d = json.loads(p.read_text())
    assert d["provenance"]["dataset_hash"] == pend_ds.hash and "cvxpy" in d["provenance"]["versions"]
    assert d["dims"][1]["terms"][-1] == "sin(theta)" and d["method"] == "stochastic"
    assert "L_fhat" in d["dims"][0]["lipschitz_how"]
    c2 = load(p, dataset=pend_ds)
    x = np.array([[0.05, -0.2], [0.1, 0.3]])
    u = np.array([[0.5], [-1.0]])
    assert c2.gamma(x, u) == pytest.approx(pend_cert.gamma(x, u), rel=1e-14)
    assert c2.system_name == "pendulum" and c2.n == 2 and c2.steps == 1
    assert np.array_equal(c2.inputs, pend_cert.inputs) and c2.inputs.shape == (21, 1)
    c2.check_system(pendulum())
    with pytest.raises(SimgapError, match="not 'pendulum'"):
        c2.check_system(pendulum().with_steps(2))
    other = synthetic_dataset(PEND_CFG, epsilon=0.05, n_runs=5, seed=4)
    with pytest.raises(SimgapError, match="hash"):
        load(p, dataset=other)
    (tmp_path / "bad.json").write_text("{]")
    with pytest.raises(SimgapError, match="JSON"):
        load(tmp_path / "bad.json")
    assert not list(tmp_path.glob("*.tmp"))


# ----- bad inputs ------------------------------------------------------------------------------

def test_certify_bad_inputs(pend_ds):
    with pytest.raises(SimgapError, match="delta must be > 0"):
        certify(pend_ds, delta1=0.0)
    with pytest.raises(SimgapError, match="too small for beta"):
        certify(pend_ds, delta1=0.0005, delta2=0.0005, beta1=0.01, beta2=0.01)
    with pytest.raises(SimgapError, match="no confidence"):
        certify(pend_ds, delta1=1e-5)
    with pytest.raises(SimgapError, match=r"beta_1 must be in \(0, 1\)"):
        certify(pend_ds, beta1=1.5)
    with pytest.raises(SimgapError, match="unknown variable"):
        certify(pend_ds, terms={0: ["x7"]})
    with pytest.raises(SimgapError, match="deterministic baseline has no delta"):
        certify(pend_ds, method="deterministic", delta1=0.01)
    with pytest.raises(SimgapError, match="state dimension 3"):
        certify(pend_ds, terms={2: ["x1"]})
    with pytest.raises(SimgapError, match="bernstein"):
        certify(pend_ds, bounds=BoundOptions(concentration="bernstein"))
    one = synthetic_dataset(PEND_CFG, epsilon=0.05, n_runs=1, seed=4)
    with pytest.raises(SimgapError, match="N1hat >= 2"):
        certify(one)
    import copy
    bad = copy.deepcopy(pend_ds)
    bad.mean[5, 1] = np.nan
    with pytest.raises(SimgapError, match="NaN"):
        certify(bad)
    bad = copy.deepcopy(pend_ds)
    bad.f_nom[0, 0] = np.inf
    with pytest.raises(SimgapError, match="NaN or inf"):
        certify(bad)


def test_grid_cover_is_an_epsilon_cover():
    C = grid_cover([-0.2, -0.5], [0.2, 0.5], 0.004)
    assert 12_000 <= len(C) <= 13_000   # the paper's pendulum cover, about 12.6k points
    from scipy.spatial import cKDTree
    rng = np.random.default_rng(0)
    x = np.array([-0.2, -0.5]) + rng.random((20000, 2)) * np.array([0.4, 1.0])
    assert cKDTree(C).query(x)[0].max() <= 0.004 + 1e-12


def test_lhat_from_simulator_with_common_random_numbers(pend_ds):
    # increments: theta: tau * omega -> 0.005; omega: tau * (-(3g/2l) cos(theta) , -0.5) -> ~0.0736
    c_data = certify(pend_ds, l2="estimated")
    c_sim = certify(pend_ds, lhat="simulator", lhat_pairs=500, lhat_runs=50)
    exact = [0.005, np.hypot(0.005 * 1.5 * 9.81, 0.005 * 0.5)]
    for i in range(2):
        assert exact[i] * 0.95 <= c_sim.dims[i].L_fhat <= exact[i] * 1.1
        assert c_data.dims[i].L_fhat >= c_sim.dims[i].L_fhat  # independent draws only add slope noise
        assert "common random numbers" in c_sim.dims[i].lipschitz_how["L_fhat"]["how"]
    # L_f of the increment, estimated from f on the cover, matches the analytic values
    assert c_data.dims[0].L_f == pytest.approx(0.005, rel=0.02)
    assert c_data.dims[1].L_f == pytest.approx(0.005 * 1.5 * 9.81, rel=0.05)
    with pytest.raises(SimgapError, match="lhat"):
        certify(pend_ds, lhat="oracle")


def test_lhat_from_noisy_means_is_flagged_with_its_remedy():
    """Lhat_fhat from slopes between empirical means of few runs estimates their noise: the certificate
    says so (share of the largest slope noise alone gives) and names lhat = "simulator", whose common
    random numbers give a smaller constant; data with many runs per row are not flagged."""
    from simgap.certify.pipeline import CertifyOptions, certify
    from simgap.certify.synthetic import synthetic_dataset
    cfg = {"kind": "numpy", "system": "pendulum", "noise": {"actuation_std": 0.5},
           "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]]}}
    few = synthetic_dataset(cfg, epsilon=0.03, n_runs=20, seed=1)
    c = certify(few, CertifyOptions(method="stochastic", degree=1))
    share = c.dims[1].lipschitz_how["L_fhat"]["noise_share"]
    assert share > 0.5 and any("Lhat_fhat[omega]" in n and "simulator" in n for n in c.options["notes"])
    assert [w for w in c.options["warnings"] if "Lhat_fhat[omega]" in w]   # `simgap run` shows warnings
    crn = certify(few, CertifyOptions(method="stochastic", degree=1, lhat="simulator", lhat_pairs=200, lhat_runs=20))
    assert not any("Lhat_fhat" in n for n in crn.options["notes"]) and not crn.options["warnings"]
    assert crn.dims[1].L_fhat < 0.5 * c.dims[1].L_fhat
    # noise's share of a slope between means ~ 1 / (epsilon sqrt(N1hat)): 0.06 and 1,250 runs give
    # the share of 0.03 and 5,000 (0.18 both) on a sixteenth of the runs
    many = synthetic_dataset(cfg, epsilon=0.06, n_runs=1250, seed=1)
    cm = certify(many, CertifyOptions(method="stochastic", degree=1))
    assert cm.dims[1].lipschitz_how["L_fhat"]["noise_share"] < 0.5
    assert not any("Lhat_fhat" in n for n in cm.options["notes"])

"""Issue 11 items 5-10: simultaneous confidence, Lhat along covered dimensions, beyond-the-paper
labels, content hashes of data chunks, digests of certificates and controllers."""

import json

import numpy as np
import pytest

from simgap.certify import BoundOptions, beta_from_delta, certify, delta_from_beta, load
from simgap.certify.lipschitz import fhat_slopes_crn
from simgap.certify.synthetic import synthetic_dataset
from simgap.cli import main
from simgap.collect import CollectionPlan, collect, load_store, store_status
from simgap.cover import CoverSpec, make_cover
from simgap.dataset import load_dataset
from simgap.errors import SimgapError
from simgap.simulators.base import SimulatorConfig, make_simulator
from simgap.synthesis.controller import Controller, synthesize
from simgap.synthesis.spec import Box, Spec
from simgap.systems import get_system

PEND_CFG = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 0.002},
            "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]]}}


@pytest.fixture(scope="module")
def pend_ds():
    return synthetic_dataset(PEND_CFG, epsilon=0.05, n_runs=40, seed=3)


@pytest.fixture(scope="module")
def pend_cert(pend_ds):
    return certify(pend_ds, degree=1)


# ----- item 5: pointwise vs simultaneous ----------------------------------------------------

def test_uniform_mode_union_bounds_lemma_1_and_lemma_2():
    M, N, K = np.array([0.01, 0.04]), 100, 500
    d1, d2 = np.array([0.3, 0.5]), np.array([0.4, 0.7])
    b1, b2 = beta_from_delta(M, d1, d2, N, K, BoundOptions(uniform=True))
    # Chebyshev by hand: K * M / (d^2 N) and K * 2 M / (d^2 N)
    assert b1 == pytest.approx(K * M / (d1 ** 2 * N))
    assert b2 == pytest.approx(K * 2 * M / (d2 ** 2 * N))
    e1, e2 = delta_from_beta(M, 0.01, 0.01, N, K, BoundOptions(uniform=True))
    assert e1 == pytest.approx(np.sqrt(K * M / (0.01 * N)))
    assert e2 == pytest.approx(np.sqrt(K * 2 * M / (0.01 * N)))


def test_certificate_states_both_confidences(pend_ds, pend_cert):
    K = pend_ds.K
    b = np.array([d.beta1 + d.beta2 for d in pend_cert.dims])
    d = pend_cert.to_dict()
    assert d["confidence_scope"] == "pointwise"
    assert d["pointwise_joint_confidence"] == pytest.approx(1 - b.sum())
    assert d["simultaneous_joint_confidence"] == pytest.approx(1 - K * b.sum())
    assert "pointwise" in pend_cert.summary() and "simultaneous" in pend_cert.summary()
    uni = certify(pend_ds, degree=1, bounds=BoundOptions(uniform=True))
    du = uni.to_dict()
    bu = np.array([x.beta1 + x.beta2 for x in uni.dims])
    assert du["confidence_scope"] == "simultaneous"
    assert du["simultaneous_joint_confidence"] == pytest.approx(uni.joint_confidence) == pytest.approx(0.96)
    assert du["pointwise_joint_confidence"] == pytest.approx(1 - bu.sum() / K)
    # the simultaneous statement pays in both margins: delta_2 grows too (sqrt(K) for Chebyshev)
    for a, p in zip(uni.dims, pend_cert.dims):
        assert a.delta2 == pytest.approx(p.delta2 * np.sqrt(K))
        assert a.delta1 == pytest.approx(p.delta1 * np.sqrt(K))
    assert any("Lemma 2" in s for s in du["options"]["beyond_paper"])


# ----- item 6: Lhat with common random numbers along the covered dimensions ------------------

TB_CFG = {"kind": "numpy", "system": "turtlebot", "steps": 30, "noise": {"process_std": 0.001}}


def test_lhat_simulator_pairs_move_only_covered_dims():
    sim = make_simulator(TB_CFG)
    seen = []
    orig = sim.step_with_noise

    def spy(X, U, noise):
        seen.append(X.copy())
        return orig(X, U, noise)

    sim.step_with_noise = spy
    fhat_slopes_crn(sim, np.random.default_rng(0), h=0.2, n_pairs=50, runs=2, dims=[2])
    X = seen[0].reshape(2, 50, 2, 3)[:, :, 0]
    step = X[1] - X[0]
    assert np.all(step[:, :2] == 0) and np.allclose(np.abs(step[:, 2]), 0.2)


def test_lhat_simulator_matches_the_true_lipschitz_constant():
    """TurtleBot held 0.3 s, position declared invariant: the increment tau u1 cos(theta) has Lipschitz
    constant 0.3 in theta (chord slope at distance eps = 0.2: 0.3 * sin(0.1) / 0.1 = 0.29950).
    Directions drawn in all three dimensions measured 0.254-0.295 here."""
    sysm = get_system("turtlebot", steps=30)
    U = np.array([[-1.0, 0.0], [0.0, 0.0], [1.0, 0.0], [1.0, 0.5]])
    ds = synthetic_dataset(TB_CFG, epsilon=0.2, n_runs=10, seed=0, inputs=U, fixed={0: 2.0, 1: 2.0})
    assert ds.system.name == sysm.name
    true = 0.3 * np.sin(0.1) / 0.1
    for seed in (0, 1, 2):
        c = certify(ds, degree=1, lhat="simulator", lhat_pairs=2000, lhat_runs=3, seed=seed)
        for i in (0, 1):
            assert true - 0.004 <= c.dims[i].L_fhat <= 0.305, (seed, i, c.dims[i].L_fhat)


# ----- item 7: labels beyond the paper --------------------------------------------------------

def test_beyond_paper_labels(pend_ds, pend_cert):
    assert pend_cert.options["beyond_paper"] == []
    c = certify(pend_ds, degree=1, safety=1.0)
    assert any("safety factor 1" in s for s in c.options["beyond_paper"])
    c = certify(pend_ds, degree=1, bounds=BoundOptions(concentration="subgaussian"))
    assert any("sub-Gaussian" in s and "variance proxy" in s for s in c.options["beyond_paper"])
    c = certify(pend_ds, degree=1, variance="maurer_pontil", value_range=0.1)
    assert any("cover rows" in s and "not over all of X" in s for s in c.options["beyond_paper"])
    assert "safety factor" in certify(pend_ds, degree=1, safety=1.0).summary()


# ----- item 9: content hashes of data ----------------------------------------------------------

def _plan(seed=5):
    s = get_system("pendulum")
    cover = make_cover(s, CoverSpec(epsilon=0.2))
    return CollectionPlan(system=s, simulator=SimulatorConfig.from_dict(PEND_CFG), cover=cover, n_runs=20,
                          seed=seed, chunk_size=100)


def _forge(path, **changes):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(changes)
    np.savez(path, **arrays)


def _collected(tmp_path):
    """(plan, store, dataset, certificate) of a small numpy pendulum collection."""
    plan = _plan()
    store = tmp_path / "s"
    collect(plan, store, executor="serial")
    ds = load_store(store)
    return plan, store, ds, certify(ds, degree=1)


def test_forged_chunk_is_refused_and_resume_recomputes_it(tmp_path):
    plan, store, ds, cert = _collected(tmp_path)
    cert.save(tmp_path / "c.json")
    chunk = store / "chunks" / "c000001.npz"
    with np.load(chunk) as z:
        forged = z["mean"] * 0.5  # means halved: the gap looks different
    _forge(chunk, mean=forged)
    with pytest.raises(SimgapError, match=r"c000001.npz.*'mean' does not match its digest"):
        load_store(store)
    assert store_status(store)["done"] == plan.n_chunks - 1
    res = collect(plan, store, executor="serial")  # resume: the broken chunk is recomputed, not trusted
    assert res.computed == 1 and res.complete
    again = load_store(store)
    assert np.array_equal(again.mean, ds.mean) and again.hash == ds.hash
    load(tmp_path / "c.json", dataset=again)


def test_dataset_hash_is_a_content_hash(tmp_path):
    _, store, ds, cert = _collected(tmp_path)
    assert cert.provenance["dataset_hash"] == ds.hash != ds.config_hash
    # a forger who also rewrites the chunk's digests gets a store that loads, but another data set
    chunk = store / "chunks" / "c000001.npz"
    from simgap.collect import _chunk_digests
    with np.load(chunk) as z:
        arrays = {k: z[k] for k in z.files if k not in ("chunk", "hash", "digest", "digests")}
    arrays["mean"] = arrays["mean"] + 1e-3
    per, dig = _chunk_digests(1, ds.config_hash, arrays)
    _forge(chunk, mean=arrays["mean"], digests=np.array(json.dumps(per)), digest=np.array(dig))
    forged = load_store(store)
    assert forged.config_hash == ds.config_hash and forged.hash != ds.hash
    cert.save(tmp_path / "c.json")
    with pytest.raises(SimgapError, match="was made from data set"):
        load(tmp_path / "c.json", dataset=forged)
    # the single-file form carries its content hash too
    p = ds.save_npz(tmp_path / "d.npz")
    assert load_dataset(p).hash == ds.hash
    _forge(p, mean=ds.mean * 0.5)
    with pytest.raises(SimgapError, match="modified after it was written"):
        load_dataset(p)


# ----- item 10: digests of certificates and controllers ----------------------------------------

def _edit(path, fn):
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))


def test_edited_certificate_is_refused(tmp_path, pend_ds, pend_cert, capsys):
    p = pend_cert.save(tmp_path / "c.json")
    assert load(p).digest == pend_cert.digest == json.loads(p.read_text())["digest"]

    def zero_gamma(d):
        for e in d["dims"]:
            e["q"] = [0.0] * len(e["q"])
            e["delta2"] = e["L_f"] = e["L_fhat"] = e["L_2"] = 0.0
        d["gamma_constant"] = [0.0] * len(d["dims"])
        d["joint_confidence"] = 0.999999

    bad = tmp_path / "bad.json"
    bad.write_text(p.read_text())
    _edit(bad, zero_gamma)
    with pytest.raises(SimgapError, match=r"modified after it was written.*joint_confidence.*digest"):
        load(bad)
    rc = main(["synthesize", "--system", "pendulum", "--cert", str(bad), "--safe=-0.5,0.5,-1,1",
               "--eta", "0.05,0.1", "--out", str(tmp_path / "ctrl.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and "modified after it was written" in err and "joint_confidence" in err
    assert not (tmp_path / "ctrl.npz").exists()
    # an edit that keeps every derived field consistent is caught by the digest alone
    _edit(bad, lambda d: d.update(json.loads(p.read_text())))
    _edit(bad, lambda d: d["dims"][0]["q"].__setitem__(0, d["dims"][0]["q"][0] - 1e-4))
    with pytest.raises(SimgapError, match="content digest"):
        load(bad)
    data = pend_ds.save_npz(tmp_path / "d.npz")
    assert main(["audit", str(p), "--data", str(data), "--points", "5", "--runs", "50"]) == 0
    capsys.readouterr()
    rc = main(["audit", str(bad), "--data", str(data), "--points", "5", "--runs", "50"])
    assert rc == 2 and "content digest" in capsys.readouterr().err


def test_edited_controller_is_refused(tmp_path):
    s = get_system("pendulum")
    spec = Spec("invariance", safe=Box(np.array([-0.5, -1.0]), np.array([0.5, 1.0])))
    ctrl = synthesize(s, spec, [0.05, 0.1]).controller
    p = ctrl.save(tmp_path / "k.npz")
    assert Controller.load(p).size == ctrl.size
    with np.load(p, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["steps"] = np.where(arrays["steps"] < 0, 0, arrays["steps"])  # every cell "winning"
    np.savez_compressed(p, **arrays)
    with pytest.raises(SimgapError, match="modified after it was written"):
        Controller.load(p)


# ----- item 8: the audit's multiplicity correction and power -------------------------------------

def test_holm_by_hand():
    from simgap.certify.audit import holm
    p = np.array([0.001, 0.04, 0.012, 0.5])  # thresholds 0.05/4, 0.05/3, 0.05/2, 0.05
    assert holm(p, 0.05).tolist() == [True, False, True, False]
    assert holm(np.array([0.03, 0.04]), 0.05).tolist() == [False, False]  # first step 0.025 fails
    assert holm(np.array([0.02, 0.025]), 0.05).tolist() == [True, True]


def _boundary_cert(pend_cert, sim, shrink=None):
    """The pendulum certificate with gamma replaced by the TRUE gap (every null at its boundary);
    ``shrink(x)`` (optional) is subtracted: a planted violation."""
    import copy
    c = copy.copy(pend_cert)
    s = sim.system

    def gamma(x, u):
        g = np.abs(s.diff(sim.mean_next(x, u), s.f(x, u)))
        return g if shrink is None else g - shrink(x)[:, None]

    c.gamma = gamma
    return c


def test_audit_false_alarm_rate_is_controlled(pend_cert):
    """A certificate that holds with equality everywhere: 3 SE per test without correction raises a false
    alarm in about 42 % of audits of 200 points x 2 dims; Holm keeps it at or below alpha = 0.05."""
    from simgap.certify.audit import audit
    sim = make_simulator(PEND_CFG)
    c = _boundary_cert(pend_cert, sim)
    A = 60
    fails = sum(not audit(c, sim, points=200, runs=100, seed=s)["passed"] for s in range(A))
    rate, se = fails / A, np.sqrt(0.05 * 0.95 / A)
    assert rate <= 0.05 + 3 * se, (fails, A)


def test_audit_power_is_what_it_reports(pend_cert):
    """Gamma violated by far more than the detectable size on a band of theta holding a fraction rho of X:
    the audit fails at least as often as its reported power (Monte Carlo over 40 audits)."""
    from simgap.certify.audit import audit, report_table
    sim = make_simulator(PEND_CFG)
    s = sim.system
    lo, hi = s.x_lo[0], s.x_hi[0]
    rho = 0.02
    band = lo + rho * (hi - lo)
    c = _boundary_cert(pend_cert, sim, shrink=lambda x: 0.05 * (x[:, 0] < band))
    reps = [audit(c, sim, points=100, runs=100, seed=s, power_fraction=rho) for s in range(40)]
    p = reps[0]["power"]["probability"]
    assert p == pytest.approx(1 - (1 - 0.95 * rho) ** 100)
    assert all(r["power"]["detectable_violation"]["omega"] < 0.05 for r in reps)
    rate = np.mean([not r["passed"] for r in reps])
    assert rate >= p - 3 * np.sqrt(p * (1 - p) / 40), (rate, p)
    text = report_table(reps[0])
    assert "tested:" in text and "Holm" in text and "power:" in text and "not tested" in text
    assert "stated conf" not in text


def test_uniform_deltas_hold_at_all_rows_at_once_monte_carlo():
    """Lemma 1 and Lemma 2 events at K rows at once, Gaussian variables (sub-Gaussian with proxy = variance):
    with the uniform deltas every row holds in >= 1 - beta of 2000 replications (3 standard errors);
    the pointwise deltas fail at some row almost always, so they do not carry a simultaneous statement."""
    K, N, R, M, beta = 200, 20, 2000, 0.04, 0.1
    rng = np.random.default_rng(7)
    bo_u = BoundOptions(concentration="subgaussian", uniform=True)
    bo_p = BoundOptions(concentration="subgaussian")
    d_u = delta_from_beta(np.array([M]), beta, beta, N, K, bo_u)
    d_p = delta_from_beta(np.array([M]), beta, beta, N, K, bo_p)
    for lemma, var in ((0, M), (1, 2 * M)):  # Lemma 2: the increment at (x, x_r) has variance <= 2 Mhat
        dev = np.abs(rng.standard_normal((R, K, N)).mean(axis=2)) * np.sqrt(var)  # |empirical mean - E|
        fail_u = (dev > d_u[lemma][0]).any(axis=1).mean()
        fail_p = (dev > d_p[lemma][0]).any(axis=1).mean()
        assert fail_u <= beta + 3 * np.sqrt(beta * (1 - beta) / R), (lemma, fail_u)
        assert fail_p > 0.9, (lemma, fail_p)

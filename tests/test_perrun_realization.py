"""Run-level gap gamma^alpha: order statistics in the store, the binomial bound, coverage audits that can fail."""

import json

import numpy as np
import pytest

from simgap.certify import certify, load
from simgap.certify.synthetic import synthetic_dataset
from simgap.cli import main
from simgap.collect import CollectionPlan, collect, load_samples, load_store
from simgap.cover import make_cover
from simgap.errors import SimgapError
from simgap.perrun.orderstats import alpha_min, order_index
from simgap.perrun.realization import certify_run, smallest_alpha
from simgap.perrun.run_audit import audit_run
from simgap.simulators.base import SimulatorConfig, make_simulator
from simgap.systems import get_system

CFG = {"kind": "numpy", "system": "pendulum", "noise": {"actuation_std": 0.3, "process_std": 0.002},
       "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]]}}


@pytest.fixture(scope="module")
def data():
    return synthetic_dataset(CFG, 0.04, 300, seed=1)


def test_store_keeps_the_largest_deviations(tmp_path):
    s = get_system("pendulum")
    sim = SimulatorConfig("numpy", "pendulum", noise={"actuation_std": 0.1})
    plan = CollectionPlan(system=s, simulator=sim, cover=make_cover(s, 0.1), n_runs=40, seed=3, keep_samples=True)
    collect(plan, tmp_path / "s", executor="serial")
    ds = load_store(tmp_path / "s")
    Y = load_samples(tmp_path / "s")
    want = -np.sort(-np.abs(Y - ds.f_nom[:, None, :]), axis=1)[:, :32]
    np.testing.assert_array_equal(ds.absdev_top, want)


def test_order_statistic_bound_holds_and_is_not_loose():
    """P(D_(N-j) < q*) <= beta by Monte Carlo (exponential: q* known), and j is the largest such index."""
    rng = np.random.default_rng(0)
    N, alpha, beta = 200, 0.1, 0.05
    j = order_index(N, alpha, beta)
    q = -np.log(alpha)
    D = np.sort(rng.exponential(size=(40000, N)), axis=1)
    miss = (D[:, N - 1 - j] < q).mean()
    se = np.sqrt(beta * (1 - beta) / 40000)
    assert miss <= beta + 3 * se
    assert (D[:, N - 2 - j] < q).mean() > beta          # one more exceedance allowed would break it
    assert alpha_min(400, 1e-3) == pytest.approx(1 - 1e-3 ** (1 / 400))
    with pytest.raises(SimgapError, match="smallest supported alpha is 0.01"):
        order_index(400, 0.01, 1e-3)


def test_run_certificate_covers_fresh_points_and_mean_gap_does_not(data):
    sim = make_simulator(CFG)
    cert = certify_run(data, alpha=0.1, lhat_pairs=300, lhat_runs=10)
    assert cert.method == "run" and cert.options["alpha"] == 0.1 and cert.joint_confidence == pytest.approx(0.99)
    rep = audit_run(cert, sim, points=40, runs=2000, seed=3)
    assert rep["passed"], rep["per_dim"]
    assert all(d["coverage_min"] >= 0.9 for d in rep["per_dim"].values())
    # the paper's mean-gap certificate read as a per-run bound fails the same audit
    mean_cert = certify(data, method="deterministic")
    mean_cert.method, mean_cert.options = "run", dict(mean_cert.options, alpha=0.1)
    bad = audit_run(mean_cert, sim, points=40, runs=2000, seed=3)
    assert not bad["passed"] and bad["n_violated"] > 20, bad["per_dim"]


def test_run_certificate_follows_its_stated_construction(data):
    """gamma^alpha recomputed here from the kept order statistics: the index j from the exact binomial
    at beta / (n K) (Bonferroni over pairs AND dimensions), the fit above D_(N - j) at every cover
    pair, and a Lipschitz term at least the largest per-run slope seen here (common random numbers)
    times eps. Fails for Bonferroni over K only, an order statistic one too low, or no extension."""
    from scipy import stats

    from simgap.perrun.realization import per_run_slopes

    alpha, beta = 0.1, 0.01
    cert = certify_run(data, alpha=alpha, beta=beta, lhat_pairs=300, lhat_runs=10)
    N, K, n = int(data.n_runs), data.K, data.system.n
    b1 = beta / (n * K)
    j = int(np.flatnonzero(stats.binom.cdf(np.arange(N), N, alpha) <= b1)[-1])
    assert cert.options["per_pair_beta"] == pytest.approx(b1, rel=1e-12) and cert.options["order_index"] == j
    assert cert.options["alpha_min"] == pytest.approx(1 - b1 ** (1 / N), rel=1e-9)
    D = data.absdev_top[:, min(j, data.absdev_top.shape[1] - 1), :]
    fit = cert.fit(data.x, data.u) + np.array([d.repair for d in cert.dims])
    assert np.all(fit >= D - 1e-7), float((D - fit).max())
    slope = per_run_slopes(make_simulator(CFG), np.random.default_rng(5), data.epsilon, 50, 5).max(axis=0)
    lip = cert.constant() - np.array([d.repair for d in cert.dims])
    assert np.all(lip >= slope * data.epsilon), (lip, slope * data.epsilon)


def test_audit_catches_a_bound_forty_percent_too_small(data):
    """The audit has power: the run certificate with fit scaled by 0.6 and no Lipschitz term is refused."""
    cert = certify_run(data, alpha=0.1, lhat_pairs=300, lhat_runs=10)
    for d in cert.dims:
        d.q = d.q * 0.6
        d.L_f = d.L_fhat = d.L_2 = 0.0
    rep = audit_run(cert, make_simulator(CFG), points=40, runs=2000, seed=3)
    assert not rep["passed"]


def test_cli_run_level(tmp_path, data, capsys):
    path = tmp_path / "d.npz"
    data.save_npz(path)
    out = tmp_path / "c.json"
    assert main(["certify", str(path), "--level", "run", "--alpha", "0.1", "--out", str(out)]) == 0
    txt = capsys.readouterr().out
    assert "smallest alpha these data support" in txt
    cert = load(out)
    assert cert.method == "run" and json.loads(out.read_text())["options"]["order_index"] >= 0
    assert main(["audit", str(out), "--data", str(path), "--points", "10", "--runs", "500"]) == 0
    a_min = smallest_alpha(data)
    for bad, msg in ((["--alpha", "1.5"], "--alpha: must be in (0, 1)"), (["--alpha", "0"], "--alpha: must be in"),
                     (["--alpha", f"{a_min / 2}"], f"smallest supported alpha is {a_min:.4g}"), ([], "needs --alpha")):
        o2 = tmp_path / "x.json"
        try:
            rc = main(["certify", str(path), "--level", "run", *bad, "--out", str(o2)])
        except SystemExit as e:  # a value outside (0, 1) is refused by the argument parser itself
            rc = e.code
        assert rc == 2
        assert msg in capsys.readouterr().err and not o2.exists()

"""A local certificate (issue 42 item 3): ``[collect] region`` covers a sub-box of X; the
certificate records it, is stated with the uniform (all-rows) confidence, and every consumer that
takes gamma's sup over a set refuses a set leaving it. Confidences are never printed negative."""

import json

import numpy as np
import pytest

from simgap.certify import BoundOptions, certify, delta_from_beta, load
from simgap.certify.bounds import scope_confidences
from simgap.certify.certificate import confidence_text
from simgap.collect import CollectionPlan, collect, load_store
from simgap.cover import CoverSpec, make_cover
from simgap.errors import SimgapError
from simgap.simulators.base import SimulatorConfig
from simgap.synthesis.controller import synthesize
from simgap.synthesis.invariant_set import gap_bound, synthesize_invariant_set
from simgap.synthesis.spec import Box, Spec
from simgap.systems import get_system

PEND_CFG = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 0.002},
            "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]]}}
REGION = {"theta": [-0.1, 0.1], "omega": [-0.2, 0.2]}


def _collect(tmp, region, seed=5):
    s = get_system("pendulum")
    cover = make_cover(s, CoverSpec(epsilon=0.05, region=region))
    plan = CollectionPlan(system=s, simulator=SimulatorConfig.from_dict(PEND_CFG), cover=cover, n_runs=20,
                          seed=seed, chunk_size=500)
    collect(plan, tmp, executor="serial")
    return load_store(tmp)


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    ds = _collect(tmp_path_factory.mktemp("local"), REGION)
    # uniform is not asked for: the region makes it so
    return ds, certify(ds, degree=1, bounds=BoundOptions(concentration="subgaussian"))


def test_cover_and_data_stay_in_the_region(local):
    """The cover points lie in the region (not X); the manifest records it; a region leaving X or
    with lo >= hi is refused naming the dimension."""
    ds, _ = local
    assert np.all(np.abs(ds.x[:, 0]) <= 0.1) and np.all(np.abs(ds.x[:, 1]) <= 0.2)
    assert ds.manifest["cover"]["region"] == {"theta": [-0.1, 0.1], "omega": [-0.2, 0.2]}
    s = get_system("pendulum")
    with pytest.raises(SimgapError, match=r"region: omega = \[-0.2, 0.9\] leaves X"):
        make_cover(s, CoverSpec(epsilon=0.05, region={"omega": [-0.2, 0.9]}))
    with pytest.raises(SimgapError, match=r"region: theta .* needs finite lo < hi"):
        make_cover(s, CoverSpec(epsilon=0.05, region={"theta": [0.1, 0.1]}))
    # without a region the cover spec (and so the configuration hash of a collection over X) is unchanged
    assert "region" not in CoverSpec(epsilon=0.05).to_dict()


def test_certificate_records_region_and_is_uniform(local, tmp_path):
    """The certificate records the region, round-trips it through JSON, is stated with the uniform
    confidence (the all-rows reading is the stated 0.96, not vacuous) and says so in its summary."""
    ds, cert = local
    assert np.allclose(cert.region[0], [-0.1, -0.2]) and np.allclose(cert.region[1], [0.1, 0.2])
    assert np.allclose(cert.x_lo, [-0.2, -0.5])      # X itself is kept: the region is a separate statement
    assert cert.scope == "simultaneous"
    assert cert.sup_confidence() == pytest.approx(0.96)
    assert "region (local certificate)" in cert.summary() and "theta [-0.1, 0.1]" in cert.summary()
    cert.save(tmp_path / "c.json")
    back = load(tmp_path / "c.json")
    assert np.allclose(back.region[0], cert.region[0]) and back.sup_confidence() == pytest.approx(0.96)
    d = json.loads((tmp_path / "c.json").read_text())
    d["region"] = [[-0.2, -0.5], [0.2, 0.5]]          # widening the region after the fact is refused
    (tmp_path / "c.json").write_text(json.dumps(d))
    with pytest.raises(SimgapError, match="modified"):
        load(tmp_path / "c.json")


def test_consumers_refuse_sets_leaving_the_region(local):
    """gap_bound over a box leaving the region, the invariant-set synthesis with a safe set leaving it,
    the grid synthesis over X and gamma_upper_box / gamma_sup over such a box are all refused with a
    message naming the set and the region; inside the region gamma is used."""
    ds, cert = local
    s = get_system("pendulum")
    n = s.n
    with pytest.raises(SimgapError, match=r"invariant set's bounding box .* leaves the certificate's region "
                                          r"\[theta \[-0.1, 0.1\] x omega \[-0.2, 0.2\]\] in omega"):
        gap_bound(cert, n, [-0.05, -0.3], [0.05, 0.1], [0.0], [0.0])
    w, _ = gap_bound(cert, n, [-0.05, -0.1], [0.05, 0.1], [-0.5], [0.5])
    assert np.all(np.isfinite(w)) and np.all(w > 0)
    with pytest.raises(SimgapError, match=r"safe set .* leaves the certificate's region"):
        synthesize_invariant_set(s, Spec("invariance", safe=Box(s.x_lo, s.x_hi)), cert, x_star=[0.0, 0.0],
                                 u_star=[0.0])
    with pytest.raises(SimgapError, match=r"grid synthesis's domain X .* leaves the certificate's region"):
        synthesize(s, Spec("invariance", safe=Box(s.x_lo, s.x_hi)), [0.01, 0.02], gap=cert)
    with pytest.raises(SimgapError, match="leaves the certificate's region"):
        cert.gamma_upper_box(np.array([[-0.15, 0.0]]), np.array([[0.0, 0.1]]), s.inputs[:1])
    with pytest.raises(SimgapError, match="leaves the certificate's region"):
        cert.gamma_sup(np.array([0.0, 0.0]), np.array([0.0, 0.3]), np.array([0.0]), np.array([0.0]))


def test_local_gamma_is_smaller_than_over_x(local, tmp_path):
    """The point of a local certificate: the same simulator over X gives a larger gamma sup on the
    region than the local certificate (estimates over the region only), both uniform."""
    ds, cert = local
    full = _collect(tmp_path / "x", {})
    cx = certify(full, degree=1, bounds=BoundOptions(concentration="subgaussian", uniform=True))
    lo, hi = cert.region
    u = np.array([0.0])
    g_loc = cert.gamma_upper_box(lo[None], hi[None], u[None])[0]
    g_x = cx.gamma_upper_box(lo[None], hi[None], u[None])[0]
    assert g_loc[1] < g_x[1], (g_loc, g_x)


def test_no_negative_confidence_is_printed():
    """A pointwise certificate over many rows has an all-rows reading <= 0: it is shown as "vacuous"
    with the reason, never as a negative number (statement, summary table)."""
    from simgap.pipeline import _simultaneous
    c = scope_confidences([0.01, 0.01], [0.01, 0.01], [0.0, 0.0], 5000, False)
    assert c["simultaneous"] < 0
    txt = confidence_text(c["simultaneous"], 5000)
    assert txt.startswith("vacuous") and "-" not in txt.split("(")[0] and "uniform" in txt
    assert _simultaneous(c["simultaneous"]) == "vacuous"
    assert confidence_text(0.96) == "0.9600"


def test_sup_statement_uses_the_all_rows_confidence_monte_carlo():
    """Mutation check: the confidence a sup statement carries (Certificate.sup_confidence, from
    scope_confidences' simultaneous reading) must not exceed the Monte Carlo frequency with which
    the margins hold at ALL K rows at once. Gaussian rows (sub-Gaussian with proxy = variance), 1000
    replications. With the pointwise deltas the all-rows event almost never holds, so a sup
    confidence taken from the pointwise reading (0.8) fails this test; the all-rows reading says
    vacuous (nothing to check) and, with uniform deltas, 0.8 <= the observed frequency."""
    from simgap.certify.certificate import Certificate

    K, N, R, M, beta = 200, 20, 1000, 0.04, 0.1
    rng = np.random.default_rng(11)
    for uniform in (False, True):
        bo = BoundOptions(concentration="subgaussian", uniform=uniform)
        d1, d2 = delta_from_beta(np.array([M]), beta, beta, N, K, bo)
        # the claimed confidence of a sup statement, through the certificate's own method
        fake = Certificate.__new__(Certificate)
        fake.method, fake.options, fake.K = "stochastic", {"bounds": {"uniform": uniform}}, K
        fake.dims = [type("D", (), {"beta1": beta, "beta2": beta, "beta_v": 0.0, "confidence": 1 - 2 * beta})()]
        claimed = fake.sup_confidence()
        dev1 = np.abs(rng.standard_normal((R, K, N)).mean(axis=2)) * np.sqrt(M)
        dev2 = np.abs(rng.standard_normal((R, K, N)).mean(axis=2)) * np.sqrt(2 * M)
        holds = ((dev1 <= d1[0]) & (dev2 <= d2[0])).all(axis=1).mean()
        if claimed is not None:
            assert claimed <= holds + 3 * np.sqrt(claimed * (1 - claimed) / R), (uniform, claimed, holds)
        else:
            assert not uniform and holds < 0.1   # vacuous, and rightly so: the event nearly never holds
    # the pointwise reading of the same pointwise certificate would claim 0.8 for an event seen < 10 %
    assert scope_confidences([beta], [beta], [0.0], K, False)["pointwise"] == pytest.approx(0.8)


def test_run_level_certificate_records_the_region(local):
    """The realization-level certificate (certify --level run) of region data records the region too,
    so its consumers refuse sets leaving it as well."""
    from simgap.perrun.realization import certify_run

    ds, _ = local
    rc = certify_run(ds, alpha=0.5, beta=0.05)
    assert rc.region is not None and np.allclose(rc.region[1], [0.1, 0.2])
    with pytest.raises(SimgapError, match="leaves the certificate's region"):
        rc.gamma_upper_box(np.array([[-0.2, 0.0]]), np.array([[0.0, 0.1]]), np.array([[0.0]]))


@pytest.mark.parametrize("region,match", [
    ('{ omega = [-0.2, 0.9] }', r"region: omega = \[-0.2, 0.9\] leaves X's \[-0.5, 0.5\]"),
    ('{ omega = [0.2, -0.2] }', r"region: omega = \[0.2, -0.2\] needs finite lo < hi"),
    ('{ speed = [0.0, 0.1] }', r"unknown state dimension 'speed'"),
    ('{ omega = [0.1] }', r"\[collect\] region"),
])
def test_bad_region_is_refused_before_any_work(tmp_path, capsys, region, match):
    """`simgap collect` with a bad [collect] region: exit 2, the key named, no traceback, no store."""
    import re

    from simgap.cli import main
    p = tmp_path / "exp.toml"
    p.write_text('[system]\nname = "pendulum"\n[simulator]\nkind = "numpy"\n[collect]\nepsilon = 0.1\nn_runs = 4\n'
                 f"region = {region}\n")
    out = tmp_path / "store"
    rc = main(["collect", str(p), "--profile", "base", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error:") and "Traceback" not in err, err
    assert re.search(match, err), err
    assert not out.exists()


def test_proof_confidence_names_its_kind(local, tmp_path):
    """What `simgap synthesize` prints beside a proof: the all-rows number when there is one (the
    uniform local certificate), and for a pointwise certificate over X (K in the thousands) no number
    for the proof, the pointwise one named as such beside it; the deterministic baseline states none."""
    _, cert = local
    assert cert.proof_confidence_text() == (f"all rows {cert.sup_confidence():.4g} (the all-rows reading a sup of "
                                            "gamma over a set needs)")
    full = _collect(tmp_path / "x", {})
    pw = certify(full, degree=1, bounds=BoundOptions(concentration="subgaussian"))
    assert pw.scope == "pointwise" and pw.sup_confidence() is None and pw.K > 1000
    txt = pw.proof_confidence_text()
    point = pw.scope_confidences()["pointwise"]
    assert txt.startswith(f"none: the all-rows reading over K = {pw.K} rows is vacuous") and "all rows 0" not in txt
    assert f"the pointwise {point:.4g} is about one (x, u) at a time" in txt
    det = certify(full, method="deterministic", degree=1)
    assert det.proof_confidence_text().startswith("none stated")

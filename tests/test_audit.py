"""Audit against ground truth; the deterministic baseline vs the stochastic certificate; the CLIs."""

import json

import numpy as np
import pytest

from simgap.certify import certify, load
from simgap.certify.audit import audit, report_table
from simgap.certify.synthetic import synthetic_dataset
from simgap.cli import main
from simgap.errors import SimgapError
from simgap.simulators.base import SimulatorConfig
from simgap.simulators.numpy_sim import NumpySimulator
from simgap.systems import System, input_grid

PEND_CFG = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 0.002},
            "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]], "bias": [0.0, 0.01]}}


def cart():
    """A user system whose input enters nonlinearly: zero-mean actuation noise shifts the mean
    next state (E cos(3(u + a)) = cos(3u) exp(-9 s^2 / 2)), which a deterministic simulator
    (the predecessor's setting) never shows."""

    def step(x, u, dt):
        return np.stack([x[:, 0] + dt * x[:, 1], x[:, 1] + dt * 2.0 * np.cos(3.0 * u[:, 0])], axis=1)

    return System(name="cart", state_names=("p", "v"), input_names=("a",), x_lo=(-1, -1), x_hi=(1, 1),
                  inputs=input_grid([-1], [1], [11]), base_tau=0.1, step=step)


def cart_sims():
    s = cart()
    effects = {"linear": [[0.0, 0.0], [0.0, -0.5]]}  # undeclared damping: a real, known gap
    noisy = NumpySimulator(SimulatorConfig("numpy", "cart", noise={"actuation_std": 0.4, "process_std": 0.01},
                                           effects=effects), system=s)
    quiet = NumpySimulator(SimulatorConfig("numpy", "cart", effects=effects), system=s)
    return s, noisy, quiet


def dataset_from(sim, epsilon, n_runs, seed):
    return synthetic_dataset(sim, epsilon, n_runs, seed)


def test_stochastic_passes_and_deterministic_baseline_is_tighter_but_fails():
    s, noisy, quiet = cart_sims()
    ds = dataset_from(noisy, 0.1, 200, seed=1)
    ds_det = dataset_from(quiet, 0.1, 1, seed=1)   # one run per sample of a deterministic simulator
    cs = certify(ds)
    cd = certify(ds_det, method="deterministic")
    assert cd.joint_confidence is None and all(d.delta1 == 0 and d.delta2 == 0 for d in cd.dims)
    xs = np.random.default_rng(0).uniform(-1, 1, (500, 2))
    us = s.inputs[np.random.default_rng(1).integers(0, 11, 500)]
    assert np.all(cd.gamma(xs, us) < cs.gamma(xs, us))           # the baseline is tighter
    rs = audit(cs, noisy, points=150, runs=2000, seed=5)
    rd = audit(cd, noisy, points=150, runs=2000, seed=5)
    assert rs["passed"] and rs["joint"]["fraction_holds"] == 1.0
    assert not rd["passed"]
    assert rd["per_dim"]["v"]["fraction_violated"] > 0.3 and rd["per_dim"]["v"]["worst_violation"] > 0.02
    # the noise-free simulator itself is bounded by the baseline (it is sound for what it saw)
    rq = audit(cd, quiet, points=150, runs=2, seed=5)
    assert rq["passed"]
    assert "FAILED" in report_table(rd) and "PASSED" in report_table(rs)


def test_audit_report_contents_and_mc_error():
    ds = synthetic_dataset(PEND_CFG, epsilon=0.03, n_runs=50, seed=2)
    c = certify(ds)
    r = audit(c, ds.manifest["simulator"], points=60, runs=400, seed=9, dataset=ds)
    d = r["per_dim"]["omega"]
    assert r["passed"] and d["fraction_holds"] == 1.0
    # MC standard error of the audit: process noise 0.002 / sqrt(400) = 1e-4
    assert d["mc_standard_error"]["median"] == pytest.approx(1e-4, rel=0.2)
    assert set(d["margin_quantiles"]) == {"0.0", "0.01", "0.05", "0.5", "0.95", "1.0"}
    assert len(d["margins"]) == 60 and min(d["margins"]) == pytest.approx(d["margin_quantiles"]["0.0"])
    assert r["exact"]["joint_fraction_holds"] == 1.0
    assert 0 < r["distance_to_cover"]["min"] and r["distance_to_cover"]["max"] <= ds.epsilon + 1e-12
    with pytest.raises(SimgapError, match="runs >= 2"):
        audit(c, ds.manifest["simulator"], points=5, runs=1)
    other = dict(PEND_CFG, system="turtlebot", effects={})
    with pytest.raises(SimgapError, match="certificate is for system"):
        audit(c, other, points=5, runs=10)


def test_cli_certify_and_audit(tmp_path, capsys):
    ds = synthetic_dataset(PEND_CFG, epsilon=0.03, n_runs=50, seed=2)
    data = ds.save_npz(tmp_path / "d.npz")
    cert = tmp_path / "c.json"
    assert main(["certify", str(data), "--beta", "0.01", "--term", "omega:sin(theta)", "--out", str(cert)]) == 0
    out = capsys.readouterr().out
    assert "joint confidence (Theorem 2): 0.9600" in out and "sin(theta)" in out
    c = load(cert, dataset=ds)
    assert c.dims[1].terms[-1] == "sin(theta)" and c.dims[0].terms[-1] != "sin(theta)"
    rep = tmp_path / "a.json"
    assert main(["audit", str(cert), "--data", str(data), "--points", "30", "--runs", "200", "--out", str(rep)]) == 0
    assert json.loads(rep.read_text())["passed"] is True
    assert "PASSED" in capsys.readouterr().out
    # per-dimension degrees, the certified variance bound and an option beyond the paper
    c3 = tmp_path / "c3.json"
    assert main(["certify", str(data), "--degree", "1,2", "--variance", "maurer_pontil", "--range", "0.05",
                 "--concentration", "bernstein", "--out", str(c3)]) == 0
    d3 = json.loads(c3.read_text())
    assert len(d3["dims"][0]["terms"]) == 4 and len(d3["dims"][1]["terms"]) == 10
    assert d3["dims"][0]["beta_v"] == 0.001 and "concentration=bernstein" in d3["options"]["beyond_paper"]
    assert "options beyond the paper" in capsys.readouterr().out
    # comparison table
    assert main(["certify", str(data), "--compare"]) == 0
    out = capsys.readouterr().out
    assert "sub-Gaussian" in out and "uniform" in out
    # bad inputs -> exit 2 with a message
    for argv, msg in [(["certify", str(data), "--term", "2:cos(x3)"], "unknown variable"),
                      (["certify", str(data), "--term", "9:x1"], "is not 1..2"),
                      (["certify", str(data), "--delta", "0"], "delta must be > 0"),
                      (["certify", str(data), "--delta", "0.0001", "--beta", "0.01"], "too small"),
                      (["certify", str(tmp_path / "missing.npz")], "does not exist"),
                      (["certify", str(data), "--concentration", "bernstein"], "range")]:
        assert main(argv) == 2, argv
        assert msg in capsys.readouterr().err
    other = synthetic_dataset(PEND_CFG, epsilon=0.05, n_runs=5, seed=4).save_npz(tmp_path / "o.npz")
    assert main(["audit", str(cert), "--data", str(other)]) == 2
    assert "hash" in capsys.readouterr().err


def test_cli_audit_against_another_simulator(tmp_path, capsys):
    # the predecessor's setting: certify on a noise-free simulator (one run suffices), audit on the noisy one
    quiet = dict(PEND_CFG, noise={})
    d_det = synthetic_dataset(quiet, epsilon=0.03, n_runs=1, seed=2).save_npz(tmp_path / "det.npz")
    d_noisy = synthetic_dataset(PEND_CFG, epsilon=0.03, n_runs=20, seed=2).save_npz(tmp_path / "noisy.npz")
    cert = tmp_path / "det.json"
    assert main(["certify", str(d_det), "--method", "deterministic", "--out", str(cert)]) == 0
    rep = tmp_path / "a.json"
    rc = main(["audit", str(cert), "--data", str(d_det), "--against", str(d_noisy), "--points", "20",
               "--runs", "100", "--out", str(rep)])
    r = json.loads(rep.read_text())
    assert r["simulator"]["noise"] == PEND_CFG["noise"] and r["simulator_source"] == str(d_noisy)
    assert rc == (0 if r["passed"] else 1)


def test_declared_invariance_turtlebot():
    # heading-only cover (x, y declared invariant, as the TurtleBot experiment does); a heading bias
    # and a speed-dependent drift that do not depend on the position
    cfg = {"kind": "numpy", "system": "turtlebot", "noise": {"process_std": 0.001},
           "effects": {"bias": [0.01, -0.02, 0.05]}}
    U = np.array([[v, w] for v in (-1.0, 0.0, 1.0) for w in (-1.0, 0.0, 1.0)])
    ds = synthetic_dataset(cfg, epsilon=0.1, n_runs=30, seed=1, inputs=U, fixed={0: 2.0, 1: 2.0})
    assert np.all(ds.x[:, :2] == 2.0)
    c = certify(ds, degree=2)
    assert c.inputs.shape == (9, 2)   # certified for the inputs the data covered; the audit draws from them
    assert not any("x1" in t or "x2" in t for d in c.dims for t in d.terms)
    assert "declared invariant" in " ".join(c.options["notes"])
    with pytest.raises(SimgapError, match="declared invariant"):
        certify(ds, terms={0: ["x1*u1"]})
    # audit over the whole X (positions anywhere) with the same inputs
    from simgap.simulators.base import make_simulator
    sim = make_simulator(cfg)
    rep = audit(c, sim, points=100, runs=200, seed=3, dataset=ds)
    assert rep["passed"] and rep["distance_to_cover"]["dims"] == ["theta"]
    assert rep["distance_to_cover"]["max"] <= 0.1 + 1e-9

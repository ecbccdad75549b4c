"""The certificate at tight margins: gamma recomputed from its parts, and the scenario
constraints met with equality somewhere. A gamma that is merely far above the true gap (the
old test passed with delta_1 = 0, no delta_2 and no L_x * epsilon term) fails here;
``bench/mutations.py`` checks that each of those mutations is caught."""

import numpy as np
import pytest

from simgap.certify.pipeline import certify
from simgap.certify.synthetic import synthetic_dataset

PEND_CFG = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 0.002},
            "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]], "bias": [0.0, 0.01]}}


@pytest.fixture(scope="module")
def ds():
    return synthetic_dataset(PEND_CFG, epsilon=0.04, n_runs=100, seed=3)


@pytest.fixture(scope="module")
def cert(ds):
    return certify(ds, terms={1: ["sin(theta)"]})


def chebyshev_deltas(e, N):
    """Paper, Sec. IV: beta_1 = Mhat / (delta_1^2 N), beta_2 = 2 Mhat / (delta_2^2 N)."""
    return np.sqrt(e["Mhat"] / (e["beta1"] * N)), np.sqrt(2 * e["Mhat"] / (e["beta2"] * N))


def test_gamma_recomputed_from_its_parts(ds, cert):
    """gamma_i = (L_f + Lhat_fhat + L_2) eps + q_i^T p_i(x, u) + delta_2i (+ repair_i), with
    every part read from the certificate's JSON, the deltas recomputed from Mhat and the betas."""
    d = cert.to_dict()
    rng = np.random.default_rng(4)
    s = ds.system
    x = s.x_lo + rng.random((500, 2)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, len(s.inputs), 500)]
    for i, e in enumerate(d["dims"]):
        d1, d2 = chebyshev_deltas(e, d["n_runs"])
        assert e["delta1"] == pytest.approx(d1, rel=1e-9) and e["delta2"] == pytest.approx(d2, rel=1e-9)
        Lx = e["L_f"] + e["L_fhat"] + e["L_2"]
        assert Lx > 0 and Lx * d["epsilon"] > 1e-5  # the Lipschitz term is not negligible here
        fit = cert.dims[i].basis.design(x, u) @ np.asarray(e["q"])
        want = Lx * d["epsilon"] + fit + d2 + e["repair"]
        np.testing.assert_allclose(cert.gamma(x, u)[:, i], want, rtol=1e-12, atol=1e-15)
        # the box bound of a point box is gamma itself
        np.testing.assert_allclose(cert.gamma_upper_box(x, x, u)[:, i], want, rtol=1e-12, atol=1e-15)


def test_scenario_constraints_tight_at_the_data(ds, cert):
    """At every cover row gamma - g >= delta_1 + delta_2 + L_x eps (Theorem 1's constraint
    q^T p >= g + delta_1 plus the constant terms), with equality at some row of each dimension:
    a gamma missing delta_1, delta_2 or L_x eps fails the first, an inflated one the second."""
    g = ds.gap()
    gam = cert.gamma(ds.x, ds.u)
    for i, (dim, e) in enumerate(zip(cert.dims, cert.to_dict()["dims"])):
        d1, d2 = chebyshev_deltas(e, cert.n_runs)
        floor = d1 + d2 + dim.L_x * cert.epsilon + dim.repair
        slack = gam[:, i] - g[:, i] - floor
        assert slack.min() >= -1e-7, f"dim {i}: a scenario constraint is violated by {-slack.min():.3g}"
        assert slack.min() <= 1e-6, f"dim {i}: no constraint is active (gamma inflated by {slack.min():.3g})"

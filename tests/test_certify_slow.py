"""Paper-scale certification (SIMGAP_SLOW=1): the pendulum case-study LP and a full certificate."""

import numpy as np
import pytest

from simgap.certify import certify
from simgap.certify.basis import Basis
from simgap.certify.scp import solve_scp
from simgap.certify.synthetic import synthetic_dataset

CFG = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 0.002, "actuation_std": 0.05},
       "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]], "bias": [0.0, 0.02]}}


@pytest.mark.slow
def test_paper_scale_lp_constraint_generation_equals_full_and_certificate_holds():
    ds = synthetic_dataset(CFG, epsilon=0.004, n_runs=20, seed=1)
    assert ds.K > 260_000
    P = Basis.polynomial(ds.system, 2).design(ds.x, ds.u)
    g = ds.gap()
    for i in range(2):
        a = solve_scp(P, g[:, i], 0.001, solver="HIGHS")
        b = solve_scp(P, g[:, i], 0.001, solver="HIGHS", method="full")
        assert a.eta_star == pytest.approx(b.eta_star, rel=1e-6)
        assert (P @ a.q).mean() == pytest.approx((P @ b.q).mean(), rel=1e-5)
        assert a.n_rows_used < 5000
    cert = certify(ds)
    from simgap.simulators.base import make_simulator
    sim = make_simulator(CFG)
    rng = np.random.default_rng(0)
    s = ds.system
    x = s.x_lo + rng.random((20000, 2)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, 21, 20000)]
    assert np.all(np.abs(s.diff(sim.mean_next(x, u), s.f(x, u))) <= cert.gamma(x, u))

"""False-alarm rate of `simgap audit` at the boundary: the numpy pendulum with gamma set to the exact
true gap (every null hypothesis holds with equality), 200 points x 100 runs per audit.

    python bench/audit_false_alarm.py [AUDITS]     (default 200; compare with alpha = 0.05)
"""
import numpy as np, copy, sys
from simgap.certify.synthetic import synthetic_dataset
from simgap.certify import certify
from simgap.certify.audit import audit
from simgap.simulators.base import make_simulator
PEND_CFG = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 0.002},
            "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]]}}
ds = synthetic_dataset(PEND_CFG, epsilon=0.05, n_runs=40, seed=3)
cert = certify(ds, degree=1)
sim = make_simulator(PEND_CFG); s = sim.system
c = copy.copy(cert)
c.gamma = lambda x, u: np.abs(s.diff(sim.mean_next(x, u), s.f(x, u)))
A = int(sys.argv[1]) if len(sys.argv) > 1 else 200
fails = sum(not audit(c, sim, points=200, runs=100, seed=k)["passed"] for k in range(A))
print(f"{fails} of {A} audits failed: {fails/A:.3f} +- {np.sqrt(fails/A*(1-fails/A)/A):.3f}")

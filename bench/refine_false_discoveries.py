"""False discoveries of the refinement loop on pure-noise data (the nominal model is exact).

    python bench/refine_false_discoveries.py [--seeds 100]

For each system and sample size, draws K transitions from the numpy simulator with process noise
only (std 1e-3) and counts the seeds for which any effect is reported, and those flagged
unexplained. Expected: 0 of 100 everywhere (docs/refine.md).
"""

import argparse
import collections

import numpy as np

from simgap.refine import make_transitions, refine
from simgap.refine.selection import SelectionOptions
from simgap.simulators.base import make_simulator
from simgap.systems import get_system


def pure_noise(sysname, K, seed):
    s = get_system(sysname)
    rng = np.random.default_rng(seed)
    x = s.x_lo + rng.random((K, s.n)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, len(s.inputs), K)]
    with make_simulator({"kind": "numpy", "system": sysname, "noise": {"process_std": 1e-3}}) as sim:
        xn = sim.step(x, u, rng)
    return make_transitions(x, u, xn, s.tau, system=s)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=100)
    args = ap.parse_args()
    for sysname in ("pendulum", "turtlebot"):
        for K in (1000, 20000):
            found, unexplained, names = 0, 0, collections.Counter()
            for seed in range(args.seeds):
                rep = refine(sysname, pure_noise(sysname, K, 1000 + seed),
                             options=SelectionOptions(seed=seed, n_boot=5)).report
                found += bool(rep["effects"])
                unexplained += rep["unexplained"]
                names.update(e["name"] for e in rep["effects"])
            print(f"{sysname:10s} K={K:6d}: effects reported for {found}/{args.seeds} seeds {dict(names)}, "
                  f"unexplained {unexplained}/{args.seeds}")


if __name__ == "__main__":
    main()

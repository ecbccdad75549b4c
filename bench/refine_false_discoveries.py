"""False discoveries and missed flags of the refinement loop (run by hand; docs/refine.md).

    python bench/refine_false_discoveries.py [--seeds 100] [--case-seeds 20]

1. Pure noise (the nominal model is exact): for each system and sample size, K transitions from
   the numpy simulator with process noise only (std 1e-3); the seeds for which any effect is
   reported, and those flagged unexplained. Expected: none.
2. Small data sets with one library effect (generated cases, :mod:`simgap.refine.cases`): the
   seeds where an effect beside the planted ones is named (extra), where a state is flagged
   though the planted effects explain everything (false flag), and where the verdict is right.
3. Effects outside the library (generated cases): the seeds where the right state is flagged, and
   where library effects are named with nothing flagged (a mix called the answer).
"""

import argparse
import collections

import numpy as np

from simgap.refine import make_transitions, refine
from simgap.refine.cases import make_case, verdict
from simgap.refine.selection import SelectionOptions
from simgap.simulators.base import make_simulator
from simgap.systems import get_system

SMALL = ("viscous", "input_gain", "coulomb_viscous", "heading_bias")
OUTSIDE = ("friction_dead_zone", "position_friction", "backlash", "delayed_coupling")


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
    ap.add_argument("--case-seeds", type=int, default=20)
    args = ap.parse_args()
    print("1. pure noise")
    for sysname in ("pendulum", "turtlebot"):
        for K in (200, 1000, 20000):
            found, unexplained, names = 0, 0, collections.Counter()
            for seed in range(args.seeds):
                rep = refine(sysname, pure_noise(sysname, K, 1000 + seed),
                             options=SelectionOptions(seed=seed, n_boot=5)).report
                found += bool(rep["effects"])
                unexplained += rep["unexplained"]
                names.update(e["name"] for e in rep["effects"])
            print(f"{sysname:10s} K={K:6d}: effects reported for {found}/{args.seeds} seeds {dict(names)}, "
                  f"unexplained {unexplained}/{args.seeds}", flush=True)
    n = args.case_seeds
    print("2. small data, one library effect planted")
    for name in SMALL:
        for K in (150, 300):
            extra = flag = right = 0
            for seed in range(n):
                c = make_case(name, K, seed)
                rep = refine(c.system, c.data, options=SelectionOptions(seed=seed, n_boot=5)).report
                found = {(e["name"], e["state_name"]) for e in rep["effects"]}
                extra += bool(found - set(c.expect["effects"]))
                flag += bool(rep["unexplained"])
                right += verdict(c, rep)[0]
            print(f"{name:20s} K={K:5d}: extra effect {extra}/{n}, false flag {flag}/{n}, right {right}/{n}",
                  flush=True)
    print("3. outside the library")
    for name in OUTSIDE:
        for K in (2000, 20000):
            m = n if K <= 2000 else max(1, n // 4)
            flagged = mix = 0
            for seed in range(m):
                c = make_case(name, K, seed)
                rep = refine(c.system, c.data, options=SelectionOptions(seed=seed, n_boot=5)).report
                ok = verdict(c, rep)[0]
                flagged += ok
                mix += bool(rep["effects"]) and not rep["unexplained"]
            print(f"{name:20s} K={K:5d}: flagged {flagged}/{m}, named with nothing flagged {mix}/{m}", flush=True)


if __name__ == "__main__":
    main()

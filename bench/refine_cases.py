"""Refinement on the generated cases (simgap.refine.cases): right name or right flag, time per case.

    PYTHONPATH=. python bench/refine_cases.py [K]
    PYTHONPATH=. python bench/refine_cases.py --seeds 20 [--cases periodic,drift,...] [--K 20000]

With --seeds N: per case, over seeds 0..N-1, how often the verdict is right (right names, or the
right state flagged), how often a time-series refinement predicts worse than the nominal over 10
or 100 steps (mean squared ratio over the states > 1.01), and how many named effects have an
impossible sign (friction on its own > 0, dead-zone width < 0, fraction delayed or lagged < 0).
"""
import argparse
import sys
import time

import numpy as np

from simgap.refine.cases import CASES, make_case, verdict
from simgap.refine.report import refine


def main(K=20000):
    print(f"{'case':<16}{'shape':<46}{'ok':<5}{'s':>6}  found")
    for name in CASES:
        c = make_case(name, K)
        t0 = time.perf_counter()
        rep = refine(c.system, c.data).report
        dt = time.perf_counter() - t0
        ok, desc = verdict(c, rep)
        extra = ""
        for e in rep["effects"]:
            if e["name"] == "deadband":
                extra = f"  width {-e['coefficient']:.4f} +- {e['stderr']:.4f}"
        st = [s for s in rep["states"] if s["unexplained"]]
        if st:
            extra += "  " + "; ".join(f"{s['state_name']}: {100 * s['unexplained_fraction']:.0f}% above floor"
                                      for s in st)
        print(f"{name:<16}{c.shape:<46}{'yes' if ok else 'NO':<5}{dt:>6.2f}  {desc}{extra}")


def impossible(e) -> bool:
    return ((e["name"] in ("viscous_friction", "coulomb_friction", "drag") and e["coefficient"] > 0)
            or (e["name"] == "deadband" and e["coefficient"] > 0)
            or (e["name"] in ("input_delay", "actuator_lag") and e["coefficient"] < 0))


def seeds(n, names, K):
    from simgap.refine.selection import SelectionOptions
    print(f"{'case':<22}{'right':>8}{'worse 10/100-step':>20}{'impossible signs':>18}{'s/seed':>8}")
    for name in names:
        right = worse = bad = 0
        t0 = time.perf_counter()
        for seed in range(n):
            c = make_case(name, K, seed)
            rep = refine(c.system, c.data, options=SelectionOptions(seed=seed, n_boot=20)).report
            right += verdict(c, rep)[0]
            bad += sum(impossible(e) for e in rep["effects"])
            ms = rep.get("multistep", {})
            worse += any(np.mean((np.asarray(m["rms_after"]) / np.asarray(m["rms_before"])) ** 2) > 1.01
                         for m in ms.values())
        print(f"{name:<22}{right:>5}/{n:<2}{worse:>17}/{n:<2}{bad:>18}{(time.perf_counter() - t0) / n:>8.1f}",
              flush=True)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1].startswith("--"):
        ap = argparse.ArgumentParser()
        ap.add_argument("--seeds", type=int, default=20)
        ap.add_argument("--cases", default=",".join(CASES))
        ap.add_argument("--K", type=int, default=20000)
        a = ap.parse_args()
        seeds(a.seeds, [c for c in a.cases.split(",") if c], a.K)
    else:
        main(int(sys.argv[1]) if len(sys.argv) > 1 else 20000)

"""Refinement on the generated cases (simgap.refine.cases): right name or right flag, time per case.

    PYTHONPATH=. python bench/refine_cases.py [K]
"""
import sys
import time

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


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 20000)

"""Benchmark: invariant-set synthesis time and memory against the state dimension (issue 33).

    python bench/bench_invariant_set.py [--dims 2,4,6,8,12] [--seed 0]

For each n a random stabilizable system written as a system file (a discrete map, so that its
formulas go through the interval proof like a user's): x+ = A x + B u + 0.01 sin(x_{i+1}) per
state, A = I + 0.05 G with G Gaussian (seeded; typically unstable), B Gaussian with m = max(1, n // 4)
inputs, X = [-1, 1]^n, inputs in [-2, 2]; safe set X; no gap (the nominal proof) and a constant gap
of 1e-4 per state. Each (n, gap) runs once in a fresh process: the wall time of
``synthesize_invariant_set`` (design: LQR, the cvxpy programs, the proof of every candidate scale),
the number of candidates, whether a set was proved, and the process's peak RSS (interpreter,
numpy, scipy and cvxpy included). Imports are done before the clock starts.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCRIPT = r"""
import json, resource, sys, time
import numpy as np
sys.path.insert(0, sys.argv[1])
n, seed, gap, path = int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), sys.argv[5]
rng = np.random.default_rng(seed + n)
m = max(1, n // 4)
A = np.eye(n) + 0.05 * rng.normal(size=(n, n))
B = rng.normal(size=(n, m))
st = [f"s{i}" for i in range(n)]
ins = [f"a{j}" for j in range(m)]
fmt = lambda v: repr(float(v))
rows = []
for i in range(n):
    terms = [f"{fmt(A[i, j])}*{st[j]}" for j in range(n)] + [f"{fmt(B[i, j])}*{ins[j]}" for j in range(m)]
    terms.append(f"0.01*sin({st[(i + 1) % n]})")
    rows.append(f'{st[i]} = "' + " + ".join(terms) + '"')
text = "\n".join([
    'format = "simgap-system"', f'name = "rand{n}"', f"states = {json.dumps(st)}", f"inputs = {json.dumps(ins)}",
    f"x_lo = {[-1.0] * n}", f"x_hi = {[1.0] * n}", "tau = 0.1",
    f"input_grid = {{lo = {[-2.0] * m}, hi = {[2.0] * m}, counts = {[3] * m}}}",
    "[dynamics]", 'kind = "discrete"'] + rows) + "\n"
open(path, "w").write(text)
from simgap.system_file import load_system_file
from simgap.synthesis import Box, Spec
from simgap.synthesis.invariant_set import synthesize_invariant_set
import cvxpy, scipy.linalg, scipy.optimize  # imported before the clock starts (about 2-15 s here, by load)
s = load_system_file(path)
spec = Spec(kind="invariance", safe=Box(s.x_lo, s.x_hi))
t0 = time.perf_counter()
res = synthesize_invariant_set(s, spec, gap=None if gap == 0 else np.full(n, gap))
dt = time.perf_counter() - t0
print(json.dumps({"n": n, "m": m, "gap": gap, "seconds": dt, "candidates": res.stats["candidates"],
                  "proved": not res.empty, "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "min_half_width": min(res.stats["half_widths"]), "gap_scale": res.stats["gap_scale"]}))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dims", default="2,4,6,8,12")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in [int(v) for v in a.dims.split(",")]:
            for gap in (0.0, 1e-4):
                out = subprocess.run([sys.executable, "-c", SCRIPT, ROOT, str(n), str(a.seed), str(gap),
                                      os.path.join(tmp, f"rand{n}.toml")], capture_output=True, text=True)
                if out.returncode:
                    print(out.stderr, file=sys.stderr)
                    return 1
                rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
                r = rows[-1]
                print(f"n = {r['n']:2d}, m = {r['m']}, gap {r['gap']:g}: {r['seconds']:.2f} s, {r['rss_mb']:.0f} MB", file=sys.stderr)
    print("| n | m | gap per state | synthesis [s] | candidates | proved | smallest half-width | gap margin s | peak RSS [MB] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        s = "-" if r["gap_scale"] is None else f"{r['gap_scale']:.3g}"
        print(f"| {r['n']} | {r['m']} | {r['gap']:g} | {r['seconds']:.2f} | {r['candidates']} | {r['proved']} | "
              f"{r['min_half_width']:.3g} | {s} | {r['rss_mb']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

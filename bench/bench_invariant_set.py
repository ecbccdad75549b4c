"""Benchmark: invariant-set and box-tube synthesis time and memory against the state dimension
(issues 33 and 42).

    python bench/bench_invariant_set.py [--dims 2,4,6,8,12] [--seed 0] [--method ellipsoid|box_tube|both]

For each n a random stabilizable system written as a system file (a discrete map, so that its
formulas go through the interval proof like a user's): x+ = A x + B u + 0.01 sin(x_{i+1}) per
state, A = I + 0.05 G with G Gaussian (seeded; typically unstable), B Gaussian with m = max(1, n // 4)
inputs, X = [-1, 1]^n, inputs in [-2, 2]; safe set X; no gap (the nominal proof) and a constant gap
of 1e-4 per state. Each (n, gap) runs once in a fresh process: the wall time of
``synthesize_invariant_set`` (design: LQR, the cvxpy programs, the proof of every candidate scale),
the number of candidates, whether a set was proved, and the process's peak RSS (interpreter,
numpy, scipy and cvxpy included). Imports are done before the clock starts.

The box tube (``--method box_tube``) on a chain of n / 2 double integrators (positions p_i,
velocities v_i, one force each; Euler steps of 0.1 s as a discrete system file): v_i+ = v_i + 0.1
(-(p_i - p_{i-1}) - (p_i - p_{i+1}) + 0.3 sin(p_i) - 0.1 v_i + u_i) (p_0 = p_{n/2+1} = 0), X = [-1, 1]^n,
forces in [-2, 2]; from x0 = (0.3 each position, 0 each velocity) to a box around the origin, the design and its proof (``synthesize_box_tube`` with ``margin_search=False``)
timed apart from the tolerable-gap search (a bisection of whole proofs), with the plan's length T0,
the terminal box's smallest half-width and the tolerable factor.

The real plan (``--real CERT``, e.g. the reacher's ``cert_stochastic.json`` written by ``simgap run
reacher``): ``python -m simgap synthesize --spec reacher --cert CERT`` as a user runs it (design,
proof, tolerable scale, noise tube), once per ``SIMGAP_JIT`` mode (``--jit 0,auto``: the numpy
interval path against the compiled kernels of simgap.compile), the modes interleaved ``--repeat``
times, each in a fresh process: the process's CPU seconds (user + system), its wall time, the
synthesis's own ``time`` line, the peak RSS and the margin printed (the outputs must agree).
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
m = max(1, n // 4) if sys.argv[6] != "box_tube" else n // 2
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
if sys.argv[6] == "box_tube":  # a chain of double integrators, one force per mass
    k = n // 2
    st = [f"p{i}" for i in range(k)] + [f"v{i}" for i in range(k)]
    ins = [f"a{i}" for i in range(k)]
    rows = [f'p{i} = "p{i} + 0.1*v{i}"' for i in range(k)]
    for i in range(k):
        nb = " ".join(f"- (p{i} - p{j})" for j in (i - 1, i + 1) if 0 <= j < k)
        wall = " - p{i}".format(i=i) * (2 - sum(0 <= j < k for j in (i - 1, i + 1)))
        rows.append(f'v{i} = "v{i} + 0.1*({nb}{wall} + 0.3*sin(p{i}) - 0.1*v{i} + a{i})"')
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
g = None if gap == 0 else np.full(n, gap)
if sys.argv[6] == "box_tube":
    from simgap.synthesis import box_tube as bt
    from simgap.synthesis.interval_map import IntervalMap
    x0 = np.concatenate([np.full(n // 2, 0.3), np.zeros(n // 2)])
    res = bt.synthesize_box_tube(s, spec, g, x0=x0, x_star=np.zeros(n), u_star=np.zeros(m),
                                 margin_search=False)
    dt = time.perf_counter() - t0
    scale, ds = None, 0.0
    if not res.empty and g is not None:
        c = res.controller
        plan = bt.TubePlan(c.x_nom, c.u_nom, c.K, c.x_star, c.u_star, c.H.copy())
        t1 = time.perf_counter()
        scale = bt.tolerable_scale(s, plan, s.x_lo, s.x_hi, np.full(m, -2.0), np.full(m, 2.0), g, IntervalMap(s),
                                   bt.SHELLS)
        ds = time.perf_counter() - t1
    print(json.dumps({"n": n, "m": m, "gap": gap, "seconds": dt, "search_seconds": ds, "T0": res.stats["T0"],
                      "proved": not res.empty, "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                      "min_H": min(res.stats["H_min"]), "max_H": max(res.stats["H"]), "gap_scale": scale}))
    sys.exit(0)
res = synthesize_invariant_set(s, spec, gap=g)
dt = time.perf_counter() - t0
print(json.dumps({"n": n, "m": m, "gap": gap, "seconds": dt, "candidates": res.stats["candidates"],
                  "proved": not res.empty, "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "min_half_width": min(res.stats["half_widths"]), "gap_scale": res.stats["gap_scale"]}))
"""


def real_plan(cert: str, spec: str, modes, repeat: int, horizon=None) -> int:
    """The module docstring's ``--real``: one fresh process per mode and repeat, interleaved."""
    import re
    import resource
    import time
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(repeat):
            for mode in modes:
                env = {key: v for key, v in os.environ.items() if key != "SIMGAP_JIT"}
                env.update(SIMGAP_JIT=mode, PYTHONPATH=ROOT)
                r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                t0 = time.perf_counter()
                out = subprocess.run([sys.executable, "-m", "simgap", "synthesize", "--spec", spec, "--cert", cert,
                                      "--out", os.path.join(tmp, f"ctrl_{mode}_{k}.npz")]
                                     + ([] if horizon is None else ["--horizon", str(horizon)]),
                                     capture_output=True, text=True, env=env)
                wall = time.perf_counter() - t0
                r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                if out.returncode:
                    print(out.stdout, out.stderr, file=sys.stderr)
                    return 1
                t = re.search(r"^time\s+([0-9.]+) s, peak memory ([0-9]+) MB", out.stdout, re.M)
                margin = re.search(r"^margin\s+(.*)$", out.stdout, re.M)
                rows.append({"mode": mode, "cpu": (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime),
                             "wall": wall, "synthesis": float(t.group(1)), "rss": int(t.group(2)),
                             "margin": margin.group(1) if margin else "-", "load": os.getloadavg()[0]})
                print(f"SIMGAP_JIT={mode}: {rows[-1]['cpu']:.1f} s CPU, {wall:.1f} s wall", file=sys.stderr)
    print("| SIMGAP_JIT | process CPU [s] | wall [s] | synthesis (its time line) [s] | peak RSS [MB] | load (1 min) "
          "| margin |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['mode']} | {r['cpu']:.1f} | {r['wall']:.1f} | {r['synthesis']:.1f} | {r['rss']} | "
              f"{r['load']:.1f} | {r['margin']} |")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", metavar="CERT", help="the real plan: synthesize --spec SPEC --cert CERT per mode")
    ap.add_argument("--spec", default="reacher", help="--real: the experiment (default reacher)")
    ap.add_argument("--jit", default="0,auto", help="--real: SIMGAP_JIT modes, interleaved (default 0,auto)")
    ap.add_argument("--repeat", type=int, default=1, help="--real: rounds of the modes (default 1)")
    ap.add_argument("--horizon", type=int, help="--real: the per-run statement's horizon (as simgap run passes its "
                    "[rollout] horizon; default synthesize's 2 T0 + 1)")
    ap.add_argument("--dims", default="2,4,6,8,12")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--method", choices=["ellipsoid", "box_tube", "both"], default="both")
    a = ap.parse_args()
    if a.real:
        return real_plan(os.path.abspath(a.real), a.spec, a.jit.split(","), a.repeat, a.horizon)
    methods = ["ellipsoid", "box_tube"] if a.method == "both" else [a.method]
    rows = {k: [] for k in methods}
    with tempfile.TemporaryDirectory() as tmp:
        for meth in methods:
            for n in [int(v) for v in a.dims.split(",")]:
                for gap in (0.0, 1e-4):
                    out = subprocess.run([sys.executable, "-c", SCRIPT, ROOT, str(n), str(a.seed), str(gap),
                                          os.path.join(tmp, f"rand{n}.toml"), meth], capture_output=True, text=True)
                    if out.returncode:
                        print(out.stderr, file=sys.stderr)
                        return 1
                    r = json.loads(out.stdout.strip().splitlines()[-1])
                    rows[meth].append(r)
                    print(f"{meth}: n = {r['n']:2d}, m = {r['m']}, gap {r['gap']:g}: {r['seconds']:.2f} s, "
                          f"{r['rss_mb']:.0f} MB", file=sys.stderr)
    if "ellipsoid" in rows:
        print("| n | m | gap per state | synthesis [s] | candidates | proved | smallest half-width | gap margin s | peak RSS [MB] |")
        print("|---|---|---|---|---|---|---|---|---|")
        for r in rows["ellipsoid"]:
            s = "-" if r["gap_scale"] is None else f"{r['gap_scale']:.3g}"
            print(f"| {r['n']} | {r['m']} | {r['gap']:g} | {r['seconds']:.2f} | {r['candidates']} | {r['proved']} | "
                  f"{r['min_half_width']:.3g} | {s} | {r['rss_mb']:.0f} |")
    if "box_tube" in rows:
        print("| n | m | gap per state | design + proof [s] | T0 | proved | smallest H (min over states) | terminal box used (max) | tolerable factor | search [s] | peak RSS [MB] |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows["box_tube"]:
            s = "-" if r["gap_scale"] is None else f"{r['gap_scale']:.3g}"
            print(f"| {r['n']} | {r['m']} | {r['gap']:g} | {r['seconds']:.2f} | {r['T0']} | {r['proved']} | "
                  f"{r['min_H']:.3g} | {r['max_H']:.3g} | {s} | {r['search_seconds']:.1f} | {r['rss_mb']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

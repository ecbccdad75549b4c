"""Benchmark: the size of a collection along a box tube against a grid over X, at 4, 6 and 14 states
(issue 52 item 5).

    python bench/bench_tube_cover.py [--dims 4,6,14] [--epsilon 0.1] [--gap 1e-4] [--run DIR ...]

The system is bench/bench_invariant_set.py's chain of n / 2 double integrators (Euler steps of 0.1 s
as a discrete system file, X = [-1, 1]^n, forces in [-2, 2]), the tube its box tube from x0 = (0.3
each position, 0 each velocity) to a box around the origin under a constant gap ``--gap`` per state
(``synthesize_box_tube``, no margin search, no per-run statement). The cover along the tube
(:mod:`simgap.tube_cover`) covers the boxes x_nom(t) +- (h_t + margin) and the smallest proved terminal box
x* +- (H_min + margin) (the largest one the synthesis reports by default may be most of X: a tube cover
asks for the smallest, ``terminal = "smallest"``) at the cover radius ``--epsilon`` (default spacing 2 eps / sqrt(n)), for two margins: eps /
(2 sqrt(n)) (a box narrower than the spacing: one point per period where h_t is small) and a fixed
0.05. Printed per n: the plan's periods, the boxes kept, the points along the tube, the points of the
grid over X and of the grid over the tube's hull at the same epsilon (the two routes without the
tube), and the seconds the tube cover took to build. Pairs = points x the input grid (3 values per
input here: 3^(n/2) inputs); the table gives points, the quantity that depends on the cover.

``--run DIR`` (a ``simgap run`` folder whose data were collected along a tube, e.g. ``simgap run kuka``'s)
adds the collection that run actually made, read from its store's manifest: the system's n, the boxes,
the points along the tube, the grid over X at the run's cover spacing, the inputs per point, N1hat and
the simulator runs.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCRIPT = r"""
import json, sys, time
import numpy as np
sys.path.insert(0, sys.argv[1])
n, eps, gap, path = int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4]), sys.argv[5]
k = n // 2
st = [f"p{i}" for i in range(k)] + [f"v{i}" for i in range(k)]
rows = [f'p{i} = "p{i} + 0.1*v{i}"' for i in range(k)]
for i in range(k):
    nb = " ".join(f"- (p{i} - p{j})" for j in (i - 1, i + 1) if 0 <= j < k)
    wall = " - p{i}".format(i=i) * (2 - sum(0 <= j < k for j in (i - 1, i + 1)))
    rows.append(f'v{i} = "v{i} + 0.1*({nb}{wall} + 0.3*sin(p{i}) - 0.1*v{i} + a{i})"')
text = "\n".join(['format = "simgap-system"', f'name = "chain{n}"', f"states = {json.dumps(st)}",
                  f"inputs = {json.dumps([f'a{i}' for i in range(k)])}", f"x_lo = {[-1.0] * n}", f"x_hi = {[1.0] * n}",
                  "tau = 0.1", f"input_grid = {{lo = {[-2.0] * k}, hi = {[2.0] * k}, counts = {[3] * k}}}",
                  "[dynamics]", 'kind = "discrete"'] + rows) + "\n"
open(path, "w").write(text)
from simgap.system_file import load_system_file
from simgap.synthesis import Box, Spec
from simgap.synthesis.box_tube import synthesize_box_tube
from simgap.cover import CoverSpec, make_cover
from simgap.tube_cover import default_spacing, grid_size, tube_boxes
s = load_system_file(path)
spec = Spec(kind="invariance", safe=Box(s.x_lo, s.x_hi))
x0 = np.concatenate([np.full(k, 0.3), np.zeros(k)])
t0 = time.perf_counter()
res = synthesize_box_tube(s, spec, np.full(n, gap), x0=x0, x_star=np.zeros(n), u_star=np.zeros(k),
                          margin_search=False, per_run=False)
t_syn = time.perf_counter() - t0
c = res.controller
h = default_spacing(eps, n)
out = {"n": n, "T0": int(c.T0), "proved": not res.empty, "synthesis_s": t_syn, "max_h": float(c.radii.max()),
       "grid_X": grid_size(s.x_hi - s.x_lo, h), "inputs": int(s.inputs.shape[0]), "rows": []}
for margin in (eps / (2 * np.sqrt(n)), 0.05):
    t1 = time.perf_counter()
    H_min = np.asarray(res.stats["H_min"], float)
    lo, hi = tube_boxes(s.x_lo, s.x_hi, c.x_nom, c.radii, margin, terminal=(c.x_star, H_min))
    cov = make_cover(s, CoverSpec(epsilon=eps, boxes=tuple(zip(lo.tolist(), hi.tolist()))))
    dt = time.perf_counter() - t1
    out["rows"].append({"margin": float(margin), "boxes": int(len(lo)), "points": int(cov.N), "seconds": dt,
                        "radius": cov.radius, "grid_hull": grid_size(hi.max(0) - lo.min(0), h),
                        "H_min": float(H_min.max())})
print(json.dumps(out))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dims", default="4,6,14")
    ap.add_argument("--epsilon", type=float, default=0.1)
    ap.add_argument("--gap", type=float, default=1e-4)
    ap.add_argument("--run", nargs="*", default=[], help="simgap run folders collected along a tube")
    a = ap.parse_args()
    if a.run:
        print_runs(a.run)
    res = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in [int(v) for v in a.dims.split(",")]:
            out = subprocess.run([sys.executable, "-c", SCRIPT, ROOT, str(n), str(a.epsilon), str(a.gap),
                                  os.path.join(tmp, f"chain{n}.toml")], capture_output=True, text=True)
            if out.returncode:
                print(out.stderr, file=sys.stderr)
                return 1
            r = json.loads(out.stdout.strip().splitlines()[-1])
            res.append(r)
            print(f"n = {n}: T0 {r['T0']}, synthesis {r['synthesis_s']:.1f} s", file=sys.stderr)
    print(f"epsilon {a.epsilon:g}, gap {a.gap:g} per state")
    print("| n | plan periods T0 | tube max h_t | margin | boxes | points along the tube | points per period | "
          "grid over the tube's hull | grid over X | inputs | build [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in res:
        for row in r["rows"]:
            print(f"| {r['n']} | {r['T0']} | {r['max_h']:.3g} | {row['margin']:.3g} | {row['boxes']} | "
                  f"{row['points']:,} | {row['points'] / (r['T0'] + 1):.1f} | {row['grid_hull']:.3g} | "
                  f"{r['grid_X']:.3g} | {r['inputs']} | {row['seconds']:.2f} |")
    return 0


def run_row(folder: str) -> dict:
    """The collection a ``simgap run`` made along its tube, from its store's manifest (the first round's)."""
    sys.path.insert(0, ROOT)
    import numpy as np
    from simgap.tube_cover import grid_size

    man = json.load(open(os.path.join(folder, "data", "manifest.json")))["config"]
    cv, s = man["cover"], man["system"]
    if cv.get("type") != "boxes":
        raise SystemExit(f"{folder}: its data were not collected along a tube (cover type {cv.get('type')!r})")
    cov = [s["state_names"].index(d) for d in cv["covered_dims"]]
    L = (np.asarray(s["x_hi"], float) - np.asarray(s["x_lo"], float))[cov]
    h = np.full(len(cov), 2.0 * float(cv["epsilon"]) / math.sqrt(len(cov)))  # the default spacing
    boxes = json.loads(cv["boxes"]) if isinstance(cv["boxes"], str) else cv["boxes"]
    m = man["n_pairs"] // cv["n_points"]
    return {"name": os.path.basename(os.path.normpath(folder)), "n": len(s["state_names"]), "boxes": len(boxes),
            "points": cv["n_points"], "grid_X": grid_size(L, h), "inputs": m,
            "pairs": man["n_pairs"], "n_runs": man["n_runs"], "runs": man["n_pairs"] * man["n_runs"],
            "epsilon": cv["epsilon"]}


def print_runs(folders) -> None:
    print("| run | n | cover radius eps | boxes | points along the tube | grid over X | inputs per point | pairs | "
          "N1hat | simulator runs |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for f in folders:
        r = run_row(f)
        print(f"| {r['name']} | {r['n']} | {r['epsilon']:g} | {r['boxes']} | {r['points']:,} | {r['grid_X']:.3g} | "
              f"{r['inputs']:,} | {r['pairs']:,} | {r['n_runs']} | {r['runs']:,} |")
    print()


if __name__ == "__main__":
    sys.exit(main())

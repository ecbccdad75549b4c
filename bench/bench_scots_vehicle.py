"""Benchmark: the SCOTS v2 vehicle example (parity and speed against SCOTS on this machine).

    python bench/bench_scots_vehicle.py [--repeat 5] [--tracemalloc]

Each repetition runs in a fresh process (so peak RSS is per run) and prints labels, abstraction,
game and total times (wall and CPU), the transitions count and winning domain (to check parity:
35,772,302 and 48,018), and the peak resident memory (ru_maxrss, including the Python
interpreter and numpy). With --tracemalloc, one more run reports the peak of traced allocations
(numpy arrays included), which excludes the interpreter baseline.

SCOTS v2 (g++ -O3) on this machine: abstraction 3.7 s, game 0.21 s, peak RSS 266 MB.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CHILD = r"""
import json, resource, sys, time
t_import = time.perf_counter()
import numpy as np
from simgap.synthesis.controller import synthesize
from simgap.synthesis.examples import VEHICLE_ETA, vehicle_growth, vehicle_spec, vehicle_system
base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
trace = sys.argv[1] == "1"
if trace:
    import tracemalloc
    tracemalloc.start()
c0 = time.process_time()
w0 = time.perf_counter()
res = synthesize(vehicle_system(), vehicle_spec(), VEHICLE_ETA, growth=vehicle_growth, strict_domain=False)
wall = time.perf_counter() - w0
cpu = time.process_time() - c0
out = {"wall": wall, "cpu": cpu, "seconds": res.stats["seconds"], "transitions": res.stats["transitions"],
       "winning": res.stats["winning"], "winning_with_target": res.stats["winning_with_target"],
       "boxes": res.stats["boxes"], "iterations": res.stats["iterations"],
       "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "import_rss_mb": base_rss}
if trace:
    out["traced_peak_mb"] = tracemalloc.get_traced_memory()[1] / 2**20
print(json.dumps(out))
"""


def run_child(trace: bool) -> dict:
    p = subprocess.run([sys.executable, "-c", CHILD, "1" if trace else "0"], capture_output=True, text=True,
                       check=True)
    return json.loads(p.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--tracemalloc", action="store_true")
    a = ap.parse_args()
    runs = [run_child(False) for _ in range(a.repeat)]
    print(f"{'run':>4} {'abstr s':>8} {'game s':>8} {'total s':>8} {'cpu s':>7} {'peak RSS MB':>12} "
          f"{'transitions':>12} {'winning':>8}")
    for i, r in enumerate(runs):
        s = r["seconds"]
        print(f"{i:>4} {s['abstraction']:>8.3f} {s['game']:>8.3f} {s['total']:>8.3f} {r['cpu']:>7.3f} "
              f"{r['peak_rss_mb']:>12.1f} {r['transitions']:>12,} {r['winning']:>8,}")

    def med(key, sub=None):
        v = sorted((r[sub][key] if sub else r[key]) for r in runs)
        return v[len(v) // 2]
    print(f"median: abstraction {med('abstraction', 'seconds'):.3f} s (labels {med('labels', 'seconds'):.3f} s), "
          f"game {med('game', 'seconds'):.3f} s, total {med('total', 'seconds'):.3f} s wall / "
          f"{med('cpu'):.3f} s CPU, peak RSS {med('peak_rss_mb'):.1f} MB "
          f"(after imports: {med('import_rss_mb'):.1f} MB)")
    ok = all(r["winning"] == 48018 and r["transitions"] == 35_772_302 for r in runs)
    print(f"parity with SCOTS (48,018 winning cells, 35,772,302 transitions): {'yes' if ok else 'NO'}")
    print(f"game iterations {runs[0]['iterations']}, valid boxes {runs[0]['boxes']:,}")
    if a.tracemalloc:
        t = run_child(True)
        print(f"tracemalloc peak of traced allocations: {t['traced_peak_mb']:.1f} MB "
              f"(run under tracing: total {t['seconds']['total']:.3f} s)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark: synthesis cost per (cell, input) pair as the grid grows (issue 24: linear in pairs).

    python bench/bench_synthesis_scaling.py [--sizes 401,801,1601] [--repeat 3]

Pendulum invariance (safe set [0, 0.2] x [-0.5, 0.5], the README's case), n x n cells over the
pendulum's state box, its 21 inputs, a constant gap (1e-4, 1e-3): the user script of
``bench_vs_previous.py``'s ``pendulum801`` at other resolutions. Every run is a fresh process;
the sizes alternate (401, 801, 1601, 401, ...) so that all see the same machine load. Reported per
size: median whole-process CPU time (user + system from ``wait4``: interpreter and imports
included), that time per pair in nanoseconds, the ratio of the per-pair cost to the smallest
size's, peak RSS, the game method and the winning cells.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCRIPT = """
import sys
sys.path.insert(0, sys.argv[2])
from simgap.synthesis import Box, Spec, synthesize
from simgap.systems import get_system
n = int(sys.argv[1]) - 1
s = get_system("pendulum")
spec = Spec(kind="invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
res = synthesize(s, spec, eta=(0.4 / n, 1.0 / n), gap=[1e-4, 1e-3])
st = res.stats
print(st["cells"], st["inputs"], st["game_method"], st["winning"], st["transitions"])
"""


def run(size: int, tree: str):
    env = dict(os.environ, PYTHONPATH=tree)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        p = subprocess.Popen([sys.executable, "-c", SCRIPT, str(size), tree], stdout=out, stderr=err,
                             env=env, cwd=tree)
        _, status, ru = os.wait4(p.pid, 0)
        out.seek(0)
        err.seek(0)
        if status:
            raise SystemExit(f"size {size} failed:\n{err.read().decode()[-3000:]}")
        cells, inputs, method, winning, trans = out.read().decode().split()[-5:]
    return ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024, int(cells) * int(inputs), method, int(winning), int(trans)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="401,801,1601")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--tree", default=ROOT, help="the simgap tree to run (default: this checkout)")
    a = ap.parse_args()
    sizes = [int(s) for s in a.sizes.split(",")]
    run(sizes[0], a.tree)  # warm-up: bytecode caches
    res = {s: [] for s in sizes}
    for _ in range(a.repeat):
        for s in sizes:
            res[s].append(run(s, a.tree))
    med = lambda v: sorted(v)[len(v) // 2]  # noqa: E731
    base = None
    print(f"{'cells':>12} {'pairs':>11} {'CPU s':>8} {'ns/pair':>8} {'vs first':>8} {'peak MB':>8} "
          f"{'method':>9} {'winning':>9}  (median of {a.repeat} interleaved fresh processes)")
    for s in sizes:
        cpu, mb = med([r[0] for r in res[s]]), med([r[1] for r in res[s]])
        pairs, method, win = res[s][0][2], res[s][0][3], res[s][0][4]
        per = 1e9 * cpu / pairs
        base = base or per
        print(f"{s}x{s:<7} {pairs:>11,} {cpu:>8.2f} {per:>8.1f} {per / base:>8.2f} {mb:>8.0f} {method:>9} {win:>9,}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

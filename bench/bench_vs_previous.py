"""Whole-process CPU and peak memory of this tree against a previous simgap, interleaved.

    python bench/bench_vs_previous.py --previous /tmp/simgap_prev [--repeat 5] [--only dcdc,vehicle_cells,...]

``--previous`` is a checkout of the earlier release (e.g. ``git worktree add /tmp/simgap_prev
<commit>`` or ``git archive <commit> | tar -x -C /tmp/simgap_prev``). Every run is a fresh
Python process whose ``sys.path`` starts with the tree under test; the runs of the two trees
alternate (previous, this, previous, this, ...), so both see the same machine load. Reported per
case: the median over the repetitions of the child's CPU time (user + system, from ``wait4``, so
the interpreter start and every import are included), its peak RSS, and the ratios this /
previous. On a machine shared with other jobs, CPU times inflate too; the ratios of interleaved
runs are what to compare.

Cases (each a user script through the public API):

* ``import``: ``import simgap.synthesis`` and nothing else.
* ``dcdc``: the boost DC-DC converter, 801 x 801 cells, 2 inputs, invariance, ``rk4_step`` +
  ``rk4_growth`` (``simgap.synthesis.examples``); checks 593,089 winning cells.
* ``vehicle_cells``: the SCOTS vehicle with every cell integrated (``invariant_dims=()``);
  checks 48,018 winning cells and 35,772,302 transitions.
* ``vehicle``: the SCOTS vehicle with shared boxes (simgap's default); same checks.
* ``pendulum801``: pendulum invariance at 801 x 801 cells, 21 inputs, constant gap.
* ``turtlebot_gap``: TurtleBot arena reach-avoid, eta 0.08 (205k cells), 441 inputs, hold 10,
  a constant gap (5e-4, 5e-4, 1e-3) per period composed (``bench_synthesis_cases.py``'s case).
* ``vi150``: value iteration on the interval MDP of ``bench_perrun.py vi --succ 150`` (1.28e8
  entries, ``bench/synthetic_imdp.py`` of this checkout, built the same way for both trees), each
  tree's ``synthesize_imdp``; also prints the largest p_cert difference and the policy entries
  that differ (minutes; the earlier version needs about 5 GB).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

SCRIPTS = {
    "import": "import simgap.synthesis\nprint('ok')\n",
    "dcdc": """
from simgap.synthesis import synthesize
from simgap.synthesis import examples as ex
res = synthesize(ex.dcdc_system(), ex.dcdc_spec(), ex.DCDC_ETA, growth=ex.dcdc_growth(), invariant_dims=())
assert res.stats["winning"] == 593089, res.stats["winning"]
print(res.stats["winning"])
""",
    "vehicle_cells": """
from simgap.synthesis import synthesize
from simgap.synthesis import examples as ex
res = synthesize(ex.vehicle_system(), ex.vehicle_spec(), ex.VEHICLE_ETA, growth=ex.vehicle_growth,
                 strict_domain=False, invariant_dims=())
assert res.stats["winning"] == 48018 and res.stats["transitions"] == 35772302, res.stats
print(res.stats["winning"])
""",
    "vehicle": """
from simgap.synthesis import synthesize
from simgap.synthesis import examples as ex
res = synthesize(ex.vehicle_system(), ex.vehicle_spec(), ex.VEHICLE_ETA, growth=ex.vehicle_growth,
                 strict_domain=False)
assert res.stats["winning"] == 48018 and res.stats["transitions"] == 35772302, res.stats
print(res.stats["winning"])
""",
    "pendulum801": """
from simgap.synthesis import Box, Spec, synthesize
from simgap.systems import get_system
s = get_system("pendulum")
spec = Spec(kind="invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
res = synthesize(s, spec, eta=(0.4 / 800, 1.0 / 800), gap=[1e-4, 1e-3])
print(res.stats["winning"])
""",
    # the interval MDP of bench/synthetic_imdp.py (this checkout's) solved by each tree's value
    # iteration; p_cert and the policy are saved, the last line is their digest-free summary
    "vi150": f"""
import inspect, time, numpy as np
sys.path.insert(1, {HERE!r})
from synthetic_imdp import synthetic_imdp
from simgap.perrun.value_iteration import synthesize_imdp
im = synthetic_imdp(150)
kw = ["invariance"] if "kind" in inspect.signature(synthesize_imdp).parameters else []
ctl = synthesize_imdp(im, 400, *kw)
np.savez(sys.argv[1], p_cert=ctl.p_cert, policy=ctl.policy)
print("saved")
""",
    "turtlebot_gap": """
from simgap.maps import load_map
from simgap.synthesis import synthesize
from simgap.systems import get_system
s = get_system("turtlebot")
res = synthesize(s, load_map("arena").spec(s), 0.08, gap=[5e-4, 5e-4, 1e-3], hold=10, compose_hold=True)
print(res.stats["winning"], res.stats["transitions"])
""",
}


def run(tree: str, case: str, save: str = "") -> tuple[float, float, str]:
    """(CPU seconds user + system, peak RSS MB, last output line) of one fresh process."""
    env = dict(os.environ, PYTHONPATH=tree)
    # compiled bytecode cached as after a regular install (a warm-up run writes it): without the
    # cache every process compiles simgap's modules again (about 40-60 ms)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    argv = [sys.executable, "-c", f"import sys; sys.path.insert(0, {tree!r})\n" + SCRIPTS[case], save]
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        p = subprocess.Popen(argv, stdout=out, stderr=err, env=env, cwd=tree)
        _, status, ru = os.wait4(p.pid, 0)
        out.seek(0)
        err.seek(0)
        if status:
            raise SystemExit(f"{case} in {tree} failed:\n{err.read().decode()[-3000:]}")
        last = (out.read().decode().strip().splitlines() or [""])[-1]
    return ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024, last


def _med(v):
    v = sorted(v)
    return v[len(v) // 2]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--previous", required=True, help="a checkout of the earlier simgap")
    ap.add_argument("--current", default=ROOT, help="the tree under test (default: this checkout)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--only", default="import,dcdc,vehicle_cells,vehicle,pendulum801,turtlebot_gap",
                    help="comma-separated cases (vi150 only when named)")
    a = ap.parse_args()
    trees = {"previous": os.path.abspath(a.previous), "current": os.path.abspath(a.current)}
    print(f"{'case':<14} {'prev CPU s':>10} {'new CPU s':>10} {'CPU ratio':>9} {'prev MB':>8} {'new MB':>8} "
          f"{'MB ratio':>8}  (median of {a.repeat} interleaved fresh processes)")
    for case in a.only.split(","):
        if case != "vi150":
            for tree in trees.values():
                run(tree, case)  # warm-up: bytecode caches, file cache
        res = {k: [] for k in trees}
        saved = {k: os.path.join(tempfile.gettempdir(), f"bench_vs_previous_{os.getpid()}_{k}.npz") for k in trees}
        for _ in range(a.repeat):
            for k, tree in trees.items():
                res[k].append(run(tree, case, saved[k]))
        outs = {k: {r[2] for r in v} for k, v in res.items()}
        cp, cn = _med([r[0] for r in res["previous"]]), _med([r[0] for r in res["current"]])
        mp, mn = _med([r[1] for r in res["previous"]]), _med([r[1] for r in res["current"]])
        same = "" if outs["previous"] == outs["current"] else f"  OUTPUT DIFFERS {outs}"
        print(f"{case:<14} {cp:>10.3f} {cn:>10.3f} {cn / cp:>9.2f} {mp:>8.1f} {mn:>8.1f} {mn / mp:>8.2f}{same}",
              flush=True)
        if case == "vi150":
            import numpy as np
            p, n = np.load(saved["previous"]), np.load(saved["current"])
            print(f"{'':<14} p_cert max |difference| {np.abs(p['p_cert'] - n['p_cert']).max():.2e}, policy entries "
                  f"that differ: {int((p['policy'] != n['policy']).sum())} of {p['policy'].size}", flush=True)
            for f in saved.values():
                os.remove(f)
    return 0


if __name__ == "__main__":
    sys.exit(main())

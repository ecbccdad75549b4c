"""Printed estimates against measured wall times, per stage of `simgap run` (run by hand).

    python bench/bench_estimates.py RESULTS_FOLDER [RESULTS_FOLDER ...]   # finished runs' summaries
    python bench/bench_estimates.py --run EXPERIMENT [--profile P] [--out DIR]

For every stage that prints an estimate before it starts (collection, the simulator Lipschitz runs
of certify, audit, rollouts with the mean map) the table gives the estimate, the measured wall time
and their ratio (measured / estimate; within 2x means 0.5-2). A run records both in summary.json
(``estimated_seconds`` and ``seconds``); runs made before ``estimated_seconds`` existed have no
estimates to compare. The estimates come from a rate measured at the start of the stage in the
command's own process; the machine may be shared, so the load average is printed with the table.
What each estimate covers: collection, audit and rollouts their simulator runs (the stage's other
work, e.g. writing the store or a worker pool's start, is not in it: on runs of a few seconds the
ratio is large and says nothing); certify only its simulator Lipschitz runs, not the linear
programs, so a certify ratio above 1 is expected.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def table(summary: dict, name: str) -> list:
    est = summary.get("estimated_seconds") or {}
    secs = summary.get("seconds") or {}
    rows = []
    for stage, e in est.items():
        m = secs.get(stage)
        if e is None or m is None:
            continue
        ratio = m / e if e > 0 else float("inf")
        rows.append((name, stage, e, m, ratio, 0.5 <= ratio <= 2.0))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="*", help="results folders of finished runs (summary.json)")
    p.add_argument("--run", default=None, help="run this experiment first (simgap run), then report it")
    p.add_argument("--profile", default=None)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    folders = [Path(f) for f in a.folders]
    if a.run:
        from simgap.cli import main as simgap
        out = Path(a.out or f"results/bench-estimates-{Path(a.run).stem}")
        args = ["run", a.run, "--out", str(out), "--no-record"] + (["--profile", a.profile] if a.profile else [])
        if simgap(args) != 0:
            return 1
        folders.append(out)
    rows = []
    for f in folders:
        s = json.loads((f / "summary.json").read_text())
        rows += table(s, f"{s['experiment']}-{s.get('profile') or 'base'}")
    if not rows:
        print("no stage with both an estimate and a measured time (runs older than estimated_seconds?)")
        return 1
    print(f"load average {os.getloadavg()[0]:.1f} (now; the runs' own load is not recorded)")
    print(f"{'run':24s} {'stage':28s} {'estimate s':>11s} {'measured s':>11s} {'ratio':>7s}  within 2x")
    for name, stage, e, m, r, ok in rows:
        print(f"{name:24s} {stage:28s} {e:11.1f} {m:11.1f} {r:7.2f}  {'yes' if ok else 'NO'}")
    n_ok = sum(r[-1] for r in rows)
    print(f"{n_ok} of {len(rows)} stages within 2x")
    return 0


if __name__ == "__main__":
    sys.exit(main())

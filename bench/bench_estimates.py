"""Printed estimates against measured wall times, per stage of `simgap run` (run by hand).

    python bench/bench_estimates.py RESULTS_FOLDER [RESULTS_FOLDER ...]   # finished runs' summaries
    python bench/bench_estimates.py --run EXPERIMENT [--profile P] [--out DIR]

For every stage that prints an estimate before it starts (collection, the simulator Lipschitz runs
of certify, audit, rollouts with the mean map) the table gives the estimate, the measured wall time
and their ratio (measured / estimate; within 2x means 0.5-2). A run records both in summary.json
(``estimated_seconds`` and ``seconds``); runs made before ``estimated_seconds`` existed have no
estimates to compare. Only stages whose measured time is at least ``--min-seconds`` (1 s) are
judged: a sub-second stage's ratio is start-up and scheduling noise (printed, marked "-").
What each estimate counts (docs/benchmarks.md, "What the estimates count, and how close they come"):
collection: the pairs' runs and statistics at the rate the executor's workers achieve (timed in
them, with the collection's own settings: the noise-free one has its own), the workers' start and
set-up, a chunk's writing; audit: its runs at the rate of its own simulator at its batch size;
rollouts: R rollouts and the mean map at the rate at their batch size, over the nominal path's
steps to the target for reach-avoid (the horizon is the stated upper bound); certify: only its
simulator Lipschitz runs, not the linear programs. The machine may be shared: the load average is
printed with the table.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


def table(summary: dict, name: str, min_seconds: float = 1.0) -> list:
    """(run, stage, estimate, measured, ratio, verdict) per stage with both; verdict True/False within
    2x, None when the measured time is under ``min_seconds`` (not judged)."""
    est = summary.get("estimated_seconds") or {}
    secs = summary.get("seconds") or {}
    rows = []
    for stage, e in est.items():
        m = secs.get(stage)
        if e is None or m is None:
            continue
        ratio = m / e if e > 0 else float("inf")
        rows.append((name, stage, e, m, ratio, None if m < min_seconds else 0.5 <= ratio <= 2.0))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="*", help="results folders of finished runs (summary.json)")
    p.add_argument("--run", default=None, help="run this experiment first (simgap run), then report it")
    p.add_argument("--profile", default=None)
    p.add_argument("--out", default=None)
    p.add_argument("--min-seconds", type=float, default=1.0, help="judge only stages measured at least this long")
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
        rows += table(s, f"{s['experiment']}-{s.get('profile') or 'base'}", a.min_seconds)
    if not rows:
        print("no stage with both an estimate and a measured time (runs older than estimated_seconds?)")
        return 1
    print(f"load average {os.getloadavg()[0]:.1f} (now; the runs' own load is not recorded)")
    print(f"{'run':24s} {'stage':28s} {'estimate s':>11s} {'measured s':>11s} {'est/meas':>8s} {'ratio':>7s}  within 2x")
    for name, stage, e, m, r, ok in rows:
        mark = "-" if ok is None else ("pass" if ok else "FAIL")
        print(f"{name:24s} {stage:28s} {e:11.1f} {m:11.1f} {e / m if m > 0 else float('inf'):8.2f} {r:7.2f}  {mark}")
    judged = [r for r in rows if r[-1] is not None]
    n_ok = sum(bool(r[-1]) for r in judged)
    print(f"{n_ok} of {len(judged)} stages measured >= {a.min_seconds:g} s within 2x "
          f"({len(rows) - len(judged)} shorter stages not judged)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

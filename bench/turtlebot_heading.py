"""The TurtleBot's level-0.5 data collected alone, for `simgap refine` (run by hand, issue 57).

    nice -n 19 python bench/turtlebot_heading.py --out /tmp/tb-heading --n1hat 200 [--dry-run]

The scan's point (bench/turtlebot_separation.py: the gazebo profile with the simulator noise of
``--level``, N1hat runs per (heading, input) pair) without its certificates, audits and rollouts:
only the collection store ``OUT/noise<level>_n<N1hat>/data``, which `simgap refine --system
turtlebot --data ...` reads. Prints the collection's own time estimate first; resumable.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from turtlebot_separation import experiments, point_name  # noqa: E402


def main() -> int:
    from simgap.collect import collect, printed_collection_estimate
    from simgap.cover import calibrate_rate
    from simgap.executors import make_executor
    from simgap.simulators import make_simulator

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--level", type=float, default=0.5)
    ap.add_argument("--n1hat", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--dry-run", action="store_true")
    a = ap.parse_args()
    exp = experiments(a.level, a.n1hat)["paper"]
    plan = exp.plan()
    store = Path(a.out) / point_name(a.level, a.n1hat) / "data"
    ex = make_executor("local", a.workers, None)
    with make_simulator(exp.simulator, exp.system) as sim:
        rate = calibrate_rate(sim, budget=0.3, work=plan.n_pairs * float(plan.n_runs))
    est = printed_collection_estimate(plan, store, ex, a.workers, None, rate, ex.workers)
    print(est.summary(), flush=True)
    if a.dry_run:
        return 0
    res = collect(plan, store, executor=ex)
    print(f"collected {res.runs:,} runs in {res.seconds:.0f} s into {store}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

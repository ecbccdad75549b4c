"""What a per-run certificate of the TurtleBot from x0 would take (run by hand; docs/per-run.md, "TurtleBot").

    python bench/perrun_turtlebot_limits.py grid 0.05 0.05 0.0982    # noise-free robust game: is x0 won?
    python bench/perrun_turtlebot_limits.py spread                    # one 0.3 s step under the gazebo_stress noise
    python bench/perrun_turtlebot_limits.py spread --profile gazebo   # ... under the Gazebo-sized noise

1. ``grid ETA_X ETA_Y ETA_THETA``: the translation-invariant interval MDP (simgap.perrun.translation)
   of the noise-free numpy unicycle (30 periods of 0.01 s per step, inputs v in {0.5, 1} m/s x
   omega in {-1, -0.5, 0, 0.5, 1} rad/s) in the arena, with every sampled transition certain
   (hi = 1 where a run touched the cell, sink bound 1 or 0): the robust game over the widened
   support, the best any sampling could give on that grid. Prints whether x0 = (3.5, 2, 1.5) is won,
   the entries, the build and value-iteration times and the peak RSS.
2. ``spread [--profile P]``: 2000 PyBullet runs of one 0.3 s step from (2, 2, 0) under the experiment's
   gazebo_stress profile (or profile P, e.g. gazebo), per input: quantiles of the end state and the 90 % / 99 % ranges in cells of
   0.05 m x 0.05 m x pi/32 (the grid of 1. that wins x0), i.e. how many successor cells a row of
   that grid's interval MDP has under this noise.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from simgap.config import load_experiment  # noqa: E402
from simgap.maps import load_map  # noqa: E402
from simgap.perrun.imdp import IMDPOptions  # noqa: E402
from simgap.perrun.translation import build_imdp_translation  # noqa: E402
from simgap.perrun.value_iteration import synthesize_imdp  # noqa: E402
from simgap.simulators import make_simulator  # noqa: E402
from simgap.systems import get_system  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
INPUTS = np.array([[v, w] for v in (0.5, 1.0) for w in (-1.0, -0.5, 0.0, 0.5, 1.0)])
X0 = np.array([[3.5, 2.0, 1.5]])


def grid(eta, horizon: int) -> dict:
    s = dataclasses.replace(get_system("turtlebot"), inputs=INPUTS)
    sim = make_simulator({"kind": "numpy", "system": "turtlebot", "steps": 30}, system=s)
    t0 = time.perf_counter()
    im = build_imdp_translation(sim, load_map("arena").spec(s), IMDPOptions(eta=eta, hold=1, n_runs=10, pilot_runs=10,
                                                                            seed=3))
    t_build = time.perf_counter() - t0
    sink = im.col == im.C
    im.hi[:] = np.where(im.k_hi > 0, 1.0, 0.0)     # noise-free: what a run touched is possible, nothing else
    im.lo[:] = 0
    ctl = synthesize_imdp(im, horizon, im.meta["spec"]["kind"])
    won = ctl.p_cert >= 1 - 1e-9
    return {"eta": list(eta), "x0_won": bool(ctl.certified(X0)[0] >= 1 - 1e-9), "won_cells": int(won.sum()),
            "live_cells": int(im.live.sum()), "rows": int(im.live.sum()) * len(INPUTS), "entries": im.nnz,
            "sink_entries": int(sink.sum()), "rho": np.round(im.meta["rho"], 4).tolist(),
            "seconds_build": round(t_build, 1), "seconds_vi": round(ctl.meta["seconds_vi"], 1),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}


def spread(runs: int, profile: str = "gazebo_stress") -> dict:
    exp = load_experiment(ROOT / "assets/experiments/turtlebot.toml", profile)
    s = dataclasses.replace(exp.system, inputs=INPUTS)
    cells = np.array([0.05, 0.05, np.pi / 32])
    out = {}
    with make_simulator(exp.simulator.to_dict(), system=s, workers=1) as sim:
        rng = np.random.default_rng(0)
        for u in INPUTS:
            y = sim.step(np.tile([2.0, 2.0, 0.0], (runs, 1)), np.tile(u, (runs, 1)), rng)
            q = np.percentile(y, [0.5, 5, 50, 95, 99.5], axis=0)
            out[f"v={u[0]:g},omega={u[1]:g}"] = {"median": np.round(q[2], 3).tolist(),
                                                 "cells_90": np.round((q[3] - q[1]) / cells, 1).tolist(),
                                                 "cells_99": np.round((q[4] - q[0]) / cells, 1).tolist()}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    g = sub.add_parser("grid")
    g.add_argument("eta", type=float, nargs=3)
    g.add_argument("--horizon", type=int, default=60, help="0.3 s steps")
    sp = sub.add_parser("spread")
    sp.add_argument("--runs", type=int, default=2000)
    sp.add_argument("--profile", default="gazebo_stress", help="the TurtleBot experiment's profile (its simulator)")
    a = ap.parse_args()
    res = grid(a.eta, a.horizon) if a.what == "grid" else spread(a.runs, a.profile)
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()

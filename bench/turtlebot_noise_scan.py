"""How much per-step noise the TurtleBot's deterministic-gap controller rides out (run by hand).

    python bench/turtlebot_noise_scan.py results/turtlebot-gazebo --scales 2 4 --n 1000

Loads ``controller_deterministic.npz`` of a `simgap run turtlebot --profile gazebo` folder and rolls
it out from the arena's x0 in the gazebo profile's simulator with the held actuation noise
(``noise.actuation_std``) multiplied by each scale; prints collisions out of n and the closest
approach to the grown obstacles (:func:`simgap.pipeline.closest_approach`). A characterization of
the margin (docs/case-studies.md), not a profile: the gazebo profile's sizes come from Gazebo's
models (docs/simulators.md).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from simgap.config import load_experiment
from simgap.experiment_spec import experiment_spec
from simgap.pipeline import closest_approach
from simgap.rollout import rollout
from simgap.simulators import make_simulator
from simgap.synthesis.controller import Controller


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a `simgap run turtlebot --profile gazebo` folder")
    ap.add_argument("--scales", type=float, nargs="+", default=[2.0, 4.0])
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--method", default="deterministic", choices=["deterministic", "stochastic"])
    a = ap.parse_args()
    exp = load_experiment("turtlebot", "gazebo")
    spec, x0, arena = experiment_spec(exp)
    ro = exp.section("rollout")
    ctrl = Controller.load(Path(a.run) / f"controller_{a.method}.npz", exp.system)
    base = exp.simulator.to_dict()
    for s in a.scales:
        cfg = {**base, "noise": {**base["noise"],
                                 "actuation_std": (np.asarray(base["noise"]["actuation_std"]) * s).tolist()}}
        t0 = time.perf_counter()
        with make_simulator(cfg, exp.system, workers=a.workers) as sim:
            rr = rollout(ctrl, sim, x0, n_rollouts=a.n, horizon=ro.get("horizon"), seed=int(ro.get("seed", 11)))
        ca = closest_approach(arena, rr)
        print(f"{a.method}, actuation_std x {s:g} = {cfg['noise']['actuation_std']}: {rr.n_failures} / {rr.n_rollouts} "
              f"fail; closest approach min {ca['min']:.3f} m, 5 % {ca['q05']:.3f} m, median {ca['median']:.3f} m "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()

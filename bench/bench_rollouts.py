"""Benchmark: closed-loop rollouts in PyBullet, batched versus one rollout at a time.

    python bench/bench_rollouts.py                       # TurtleBot (arena) and pendulum, 1000 rollouts
    python bench/bench_rollouts.py --system turtlebot --n 1000 --n-seq 1000
    python bench/bench_rollouts.py --controller ctrl.npz --system turtlebot

Reports robot-steps per second (one robot-step = one rollout advanced by one simulator step of
tau, controller queries included) for the batched rollout (one ``step_with_noise`` call per time
step for all active rollouts) and for one rollout at a time (one call per rollout per step), in
the same process, and their ratio. Both modes use the same noise draws, so they also give the same
outcomes (checked).

Without ``--controller`` the TurtleBot runs a stand-in waypoint-following feedback on the arena
(heading P-control snapped to the 441-input grid; not a synthesized controller), and the pendulum
a saturated linear state feedback snapped to the 21 torques; the simulator cost, which dominates,
does not depend on which controller picks the inputs.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

from simgap.maps import load_map
from simgap.simulators.base import make_simulator
from simgap.synthesis.rollout import rollout
from simgap.synthesis.spec import Box, Spec
from simgap.systems import pendulum, turtlebot, wrap_angle


class ArenaWaypoints:
    """Stand-in controller for the arena: steer to the next waypoint of a fixed route (a function of x)."""

    def __init__(self, system, amap, hold=1):
        self.system, self.spec, self.hold = system, amap.spec(system), hold
        self.x0 = amap.x0(system)

    def input_index(self, x):
        x = np.atleast_2d(x)
        px, py, th = x[:, 0], x[:, 1], x[:, 2]
        # route: north along x = 3.4, west along y = 3.05, south along x = 1.25, west to the target
        right = (py < 2.95) & (px > 2.45)
        top = (py >= 2.95) & (px > 1.3)
        left = ~right & ~top & (py >= 0.75)
        gx = np.select([right, top, left], [3.4, 1.2, 1.25], 0.55)
        gy = np.select([right, top, left], [3.1, 3.05, 0.55], 0.55)
        e = wrap_angle(np.arctan2(gy - py, gx - px) - th)
        v = np.clip(1.0 - 1.5 * np.abs(e), 0.0, 1.0)
        w = np.clip(3.0 * e, -1.0, 1.0)
        U = self.system.inputs
        iv = np.rint((v + 1) / 0.1).astype(int)
        iw = np.rint((w + 1) / 0.1).astype(int)
        idx = iv * 21 + iw  # input_grid: last dimension fastest
        assert np.allclose(U[idx], np.stack([np.rint(v * 10) / 10, np.rint(w * 10) / 10], 1), atol=1e-9)
        return idx


class PendulumFeedback:
    """Stand-in controller: u = sat(-K (x - x_ref)) snapped to the 21 torques, invariance in [0, 0.2] x [-0.5, 0.5]."""

    def __init__(self, system, K=(30.0, 8.0), x_ref=(0.1, 0.0)):
        self.system, self.K, self.x_ref = system, np.asarray(K), np.asarray(x_ref)
        self.spec = Spec("invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
        self.hold = 1

    def input_index(self, x):
        u = np.clip(-((np.atleast_2d(x) - self.x_ref) @ self.K), -1, 1)
        return np.abs(self.system.inputs[:, 0][None] - u[:, None]).argmin(1)


def load_controller(path):
    from simgap.cli.rollout import load_controller as load
    return load(path)


def bench(name, ctrl, cfg, x0, n, n_seq, horizon, seed):
    rows = {}
    for batched, R in ((True, n), (False, n_seq)):
        sim = make_simulator(cfg)
        try:
            res = rollout(ctrl, sim, x0, n_rollouts=R, horizon=horizon, seed=seed, batched=batched)
        finally:
            sim.close()
        t = res.timing
        rows["batched" if batched else "one_at_a_time"] = {
            "rollouts": R, "robot_steps": t["robot_steps"], "wall_s": round(t["wall_s"], 3),
            "simulator_s": round(t["simulator_s"], 3), "controller_s": round(t["controller_s"], 3),
            "robot_steps_per_s": round(t["robot_steps_per_s"]), "failures": res.n_failures,
            "outcomes": res.to_dict(per_rollout=False)["outcomes"], "_res": res}
    b, s = rows["batched"], rows["one_at_a_time"]
    m = min(b["rollouts"], s["rollouts"])
    # one-at-a-time and batched get the same noise only when R is the same (draw_noise(R) per step)
    same = None
    if b["rollouts"] == s["rollouts"]:
        same = bool(np.array_equal(b["_res"].outcome[:m], s["_res"].outcome[:m])
                    and np.allclose(b["_res"].trajectories[:m], s["_res"].trajectories[:m], atol=1e-9))
    out = {"case": name, "simulator": cfg, "horizon": horizon, "hold": b["_res"].hold, "tau": b["_res"].tau,
           "nominal": b["_res"].nominal["outcome"],
           "batched": {k: v for k, v in b.items() if k != "_res"},
           "one_at_a_time": {k: v for k, v in s.items() if k != "_res"},
           "speedup": round(b["robot_steps_per_s"] / max(s["robot_steps_per_s"], 1e-9), 2),
           "same_results": same}
    print(f"{name}: batched {b['robot_steps_per_s']:,} robot-steps/s ({b['rollouts']} rollouts, {b['wall_s']} s, "
          f"{b['failures']} failures); one at a time {s['robot_steps_per_s']:,} robot-steps/s "
          f"({s['rollouts']} rollouts, {s['wall_s']} s); ratio {out['speedup']}x; identical results: {same}")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--system", choices=("turtlebot", "pendulum", "both"), default="both")
    ap.add_argument("--n", type=int, default=1000, help="rollouts, batched")
    ap.add_argument("--n-seq", type=int, default=None, help="rollouts one at a time (default: --n)")
    ap.add_argument("--horizon", type=int, default=None, help="simulator steps (default 1200 TurtleBot, 400 pendulum)")
    ap.add_argument("--controller", default=None, help="synthesized controller file (default: a stand-in feedback)")
    ap.add_argument("--simulator", default=None, help="JSON SimulatorConfig overriding the default")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write the results here")
    a = ap.parse_args(argv)
    n_seq = a.n_seq or a.n
    results = []
    amap = load_map("arena")
    if a.system in ("turtlebot", "both"):
        cfg = {"kind": "pybullet_turtlebot", "system": "turtlebot", "steps": 1,
               "noise": {"actuation_std": [0.05, 0.1]}, "options": amap.simulator_options()}
        if a.simulator:
            cfg = json.loads(open(a.simulator).read()) if a.simulator.endswith(".json") else json.loads(a.simulator)
        ctrl = load_controller(a.controller) if a.controller and a.system == "turtlebot" else ArenaWaypoints(turtlebot(), amap)
        results.append(bench("turtlebot", ctrl, cfg, amap.x0(turtlebot()), a.n, n_seq, a.horizon or 1200, a.seed))
    if a.system in ("pendulum", "both"):
        cfg = {"kind": "pybullet_pendulum", "system": "pendulum", "steps": 1, "noise": {"actuation_std": 0.05}}
        if a.simulator and a.system == "pendulum":
            cfg = json.loads(open(a.simulator).read()) if a.simulator.endswith(".json") else json.loads(a.simulator)
        ctrl = load_controller(a.controller) if a.controller and a.system == "pendulum" else PendulumFeedback(pendulum())
        results.append(bench("pendulum", ctrl, cfg, [0.1, 0.0], a.n, n_seq, a.horizon or 400, a.seed))
    meta = {"python": sys.version.split()[0], "machine": platform.machine(), "cpus": os.cpu_count(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"meta": meta, "results": results}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

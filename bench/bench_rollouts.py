"""Benchmark: closed-loop rollouts in PyBullet, batched versus one rollout at a time.

    python bench/bench_rollouts.py                       # TurtleBot (arena) and pendulum, 1000 rollouts
    python bench/bench_rollouts.py --system turtlebot --n 1000 --n-seq 1000
    python bench/bench_rollouts.py --controller ctrl.npz --system turtlebot
    python bench/bench_rollouts.py --gap-demo            # gap vs no gap under a drift (numpy simulator)

Reports robot-steps per second (one robot-step = one rollout advanced by one simulator step of
tau, controller queries included) for the batched rollout (one ``step_with_noise`` call per time
step for all active rollouts) and for one rollout at a time (one call per rollout per step), in
the same process, and their ratio. Both modes use the same noise draws, so they also give the same
outcomes (checked).

Without ``--controller`` the controllers are synthesized first (not timed): the TurtleBot
reach-avoid controller on the arena map (441 inputs, input held 30 x 0.01 s, eta = 0.1, 0.1,
0.2, no gap) and the pendulum invariance controller for [0, 0.2] x [-0.5, 0.5] (eta = 0.005,
0.01, no gap). The simulators step with their base period (0.01 s, 0.005 s), so the
specification is checked every base period.
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
from simgap.rollout import rollout
from simgap.synthesis.spec import Box, Spec
from simgap.synthesis.controller import synthesize
from simgap.systems import pendulum, turtlebot


def arena_controller(k=30, eta=(0.1, 0.1, 0.2), gap=None):
    """The arena reach-avoid controller: TurtleBot with 441 inputs at tau = k * 0.01 s."""
    amap = load_map("arena")
    system = turtlebot().with_steps(k)
    t = time.perf_counter()
    res = synthesize(system, amap.spec(system), list(eta), gap=gap, x0=amap.x0(system))
    print(f"synthesized the arena controller in {time.perf_counter() - t:.1f} s: "
          f"{res.stats['winning']:,} winning cells, hold {k} x 0.01 s")
    return res.controller


def pendulum_controller(eta=(0.005, 0.01)):
    """Invariance in [0, 0.2] x [-0.5, 0.5] for the pendulum (tau = 0.005 s), no gap."""
    spec = Spec("invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    res = synthesize(pendulum(), spec, list(eta))
    print(f"synthesized the pendulum controller: {res.stats['winning']:,} of {res.stats['safe_cells']:,} safe cells")
    return res.controller


def gap_demo(n=1000, seed=0):
    """Controllers with and without a gap against an unmodeled drift (numpy simulator, 25 inputs)."""
    from simgap.systems import input_grid
    amap = load_map("arena")
    system = turtlebot(inputs=input_grid([-1, -1], [1, 1], [5, 5])).with_steps(30)
    sim_cfg = {"kind": "numpy", "system": "turtlebot", "noise": {"actuation_std": [0.2, 0.3]},
               "effects": {"bias": [-0.1, 0.1, 0.0]}}  # 0.1 m/s per axis: 0.03 m per 0.3 s step
    out = []
    for gap in (None, [0.01, 0.01, 0.0], [0.02, 0.02, 0.0]):
        ctrl = synthesize(system, amap.spec(system), [0.1, 0.1, 0.2], gap=gap).controller
        res = rollout(ctrl, make_simulator(sim_cfg, system), amap.x0(system), n_rollouts=n, seed=seed)
        d = res.to_dict(per_rollout=False)
        print(f"gap {gap}: winning {ctrl.size:,} cells, failures {d['failures']}/{n} "
              f"(obstacle {d['violation_kinds']['obstacle']}), left domain {d['left_domain']}, "
              f"nominal {d['nominal']['outcome']}", flush=True)
        out.append({"gap": gap, "winning": ctrl.size, "failures": d["failures"], "left_domain": d["left_domain"]})
    return out


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
            "robot_steps_per_s": round(t["robot_steps_per_s"]), "cpu_s": round(t["cpu_s"], 3),
            "robot_steps_per_cpu_s": round(t["robot_steps_per_cpu_s"]), "failures": res.n_failures,
            "outcomes": res.to_dict(per_rollout=False)["outcomes"], "_res": res}
    b, s = rows["batched"], rows["one_at_a_time"]
    m = min(b["rollouts"], s["rollouts"])
    # one-at-a-time and batched get the same noise only when R is the same (draw_noise(R) per step)
    same = None
    if b["rollouts"] == s["rollouts"]:
        same = bool(np.array_equal(b["_res"].outcome[:m], s["_res"].outcome[:m])
                    and np.allclose(b["_res"].trajectories[:m], s["_res"].trajectories[:m], atol=1e-9))
    out = {"case": name, "simulator": cfg, "horizon": b["_res"].horizon, "hold": b["_res"].hold, "tau": b["_res"].tau,
           "nominal": b["_res"].nominal["outcome"],
           "batched": {k: v for k, v in b.items() if k != "_res"},
           "one_at_a_time": {k: v for k, v in s.items() if k != "_res"},
           "speedup": round(b["robot_steps_per_s"] / max(s["robot_steps_per_s"], 1e-9), 2),
           "speedup_cpu": round(b["robot_steps_per_cpu_s"] / max(s["robot_steps_per_cpu_s"], 1e-9), 2),
           "same_results": same}
    print(f"{name}: batched {b['robot_steps_per_s']:,} robot-steps/s ({b['rollouts']} rollouts, {b['wall_s']} s, "
          f"{b['failures']} failures); one at a time {s['robot_steps_per_s']:,} robot-steps/s "
          f"({s['rollouts']} rollouts, {s['wall_s']} s); ratio {out['speedup']}x (per CPU second: batched "
          f"{b['robot_steps_per_cpu_s']:,}, one at a time {s['robot_steps_per_cpu_s']:,}, ratio {out['speedup_cpu']}x); "
          f"identical results: {same}", flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--system", choices=("turtlebot", "pendulum", "both"), default="both")
    ap.add_argument("--n", type=int, default=1000, help="rollouts, batched")
    ap.add_argument("--n-seq", type=int, default=None, help="rollouts one at a time (default: --n)")
    ap.add_argument("--horizon", type=int, default=None, help="simulator steps (default: TurtleBot from the controller's steps-to-go, pendulum 1000)")
    ap.add_argument("--controller", default=None, help="synthesized controller file (default: a stand-in feedback)")
    ap.add_argument("--simulator", default=None, help="JSON SimulatorConfig overriding the default")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--gap-demo", action="store_true",
                    help="instead: failures of controllers with and without a gap under an unmodeled drift")
    a = ap.parse_args(argv)
    if a.gap_demo:
        gap_demo(a.n, a.seed)
        return 0
    n_seq = a.n_seq or a.n
    results = []
    amap = load_map("arena")
    if a.system in ("turtlebot", "both"):
        cfg = {"kind": "pybullet_turtlebot", "system": "turtlebot", "steps": 1,
               "noise": {"actuation_std": [0.05, 0.1]}, "options": amap.simulator_options()}
        if a.simulator:
            cfg = json.loads(open(a.simulator).read()) if a.simulator.endswith(".json") else json.loads(a.simulator)
        ctrl = load_controller(a.controller) if a.controller and a.system == "turtlebot" else arena_controller()
        results.append(bench("turtlebot", ctrl, cfg, amap.x0(turtlebot()), a.n, n_seq, a.horizon, a.seed))
    if a.system in ("pendulum", "both"):
        cfg = {"kind": "pybullet_pendulum", "system": "pendulum", "steps": 1, "noise": {"actuation_std": 0.05}}
        if a.simulator and a.system == "pendulum":
            cfg = json.loads(open(a.simulator).read()) if a.simulator.endswith(".json") else json.loads(a.simulator)
        ctrl = load_controller(a.controller) if a.controller and a.system == "pendulum" else pendulum_controller()
        results.append(bench("pendulum", ctrl, cfg, [0.1, 0.0], a.n, n_seq, a.horizon or 1000, a.seed))
    meta = {"python": sys.version.split()[0], "machine": platform.machine(), "cpus": os.cpu_count(),
            "load_average_at_end": os.getloadavg(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"meta": meta, "results": results}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())

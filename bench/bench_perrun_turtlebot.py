"""Per-run controller on the gazebo-like TurtleBot: interval MDP from PyBullet samples, p_cert vs p_emp (run by hand).

    python bench/bench_perrun_turtlebot.py                                   # the small grid (defaults)
    python bench/bench_perrun_turtlebot.py --n-runs 2000 --pilot 200 --rollouts 10000

The simulator is the experiment's ``gazebo_stress`` profile (assets/experiments/turtlebot.toml: per-run
wheel radius and friction randomization, wheel slip, actuation jitter; 30 periods of 0.01 s per
0.3 s step, 2 physics substeps), the specification the arena's reach-avoid task from
x0 = (3.5, 2, 1.5). The interval MDP is sampled once per (heading cell, input) and shifted to every
position cell (:mod:`simgap.perrun.translation`: the floor is uniform, the declared invariance of
the collection), so the simulator cost is headings x inputs x (N + N0) x k steps, whatever the
number of position cells.

Reported: robot-steps (0.01 s periods) simulated, wall and CPU seconds per phase (this process
plus the simulator helper processes, from getrusage), the interval MDP's size, value iteration
time, p_cert(x0), and R batched rollouts from x0 and ``--states`` initial states in the domain
(p_cert > 0, target cells excluded): p_emp with its 95 % Clopper-Pearson interval, soundness p_emp >= p_cert - 3 SE per
state, tightness p_emp - p_cert at x0. The machine may be shared: the load average is reported.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from simgap.config import load_experiment  # noqa: E402
from simgap.perrun.imdp import IMDPOptions  # noqa: E402
from simgap.perrun.translation import build_imdp_translation  # noqa: E402
from simgap.perrun.validation import empirical, sample_in_cells, success_counts  # noqa: E402
from simgap.perrun.value_iteration import synthesize_imdp  # noqa: E402
from simgap.pipeline import experiment_spec  # noqa: E402
from simgap.simulators import make_simulator  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def cpu_now() -> float:
    """CPU seconds of this process and its reaped children (the simulator helpers, once closed)."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--profile", default="gazebo_stress")
    ap.add_argument("--eta", type=float, nargs=3, default=[0.1, 0.1, np.pi / 16])
    ap.add_argument("--v", type=float, nargs="+", default=[0.5, 1.0], help="speeds of the input set [m/s]")
    ap.add_argument("--omega", type=float, nargs="+", default=[-1.0, -0.5, 0.0, 0.5, 1.0], help="turn rates [rad/s]")
    ap.add_argument("--hold", type=int, default=1, help="0.3 s steps per abstract step")
    ap.add_argument("--n-runs", type=int, default=500)
    ap.add_argument("--pilot", type=int, default=50)
    ap.add_argument("--beta", type=float, default=0.01)
    ap.add_argument("--horizon", type=int, default=60, help="0.3 s steps (the rollouts' too)")
    ap.add_argument("--rollouts", type=int, default=1000)
    ap.add_argument("--states", type=int, default=10)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=None, help="write the JSON report here too")
    a = ap.parse_args()

    exp = load_experiment(ROOT / "assets/experiments/turtlebot.toml", a.profile)
    spec, x0, _ = experiment_spec(exp)
    inputs = np.array([[v, w] for v in a.v for w in a.omega])
    system = dataclasses.replace(exp.system, inputs=inputs)
    cfg = exp.simulator.to_dict()
    periods = system.steps                         # 0.01 s robot-steps per 0.3 s step
    load0 = os.getloadavg()

    # ----- interval MDP + value iteration (the "small grid" target) -------------------------------
    w0, c0 = time.perf_counter(), cpu_now()
    opts = IMDPOptions(eta=a.eta, hold=a.hold, n_runs=a.n_runs, pilot_runs=a.pilot, beta=a.beta, seed=a.seed)
    with make_simulator(cfg, system=system, workers=a.workers) as sim:
        im = build_imdp_translation(sim, spec, opts, log=print)
    w_build, c_build = time.perf_counter() - w0, cpu_now() - c0
    w1, c1 = time.perf_counter(), cpu_now()
    ctl = synthesize_imdp(im, a.horizon, spec.kind)
    w_vi, c_vi = time.perf_counter() - w1, cpu_now() - c1
    lip_steps = 100 * 20 * 2 * a.hold             # the heading column's common-random-number pairs
    steps = im.meta["samples"] + lip_steps
    p0 = float(ctl.certified(x0[None])[0])
    print(f"interval MDP: {im.C} cells ({int(im.live.sum())} live), {im.M} inputs, {im.nnz} entries; "
          f"{steps} steps = {steps * periods:.3g} robot-steps; build {w_build:.1f} s wall / {c_build:.1f} s CPU, "
          f"value iteration {w_vi:.1f} s wall / {c_vi:.1f} s CPU; p_cert(x0) = {p0:.4f}", flush=True)

    # ----- validation: batched rollouts -----------------------------------------------------------
    rng = np.random.default_rng([a.seed, 5])
    dom = np.flatnonzero((ctl.p_cert > 0) & im.live)            # target cells (p_cert = 1) are not drawn
    xs = np.concatenate([x0[None], sample_in_cells(im.grid, dom, a.states, rng)])
    w2, c2 = time.perf_counter(), cpu_now()
    with make_simulator(cfg, system=system, workers=a.workers) as sim:
        k = success_counts(lambda x, t: ctl.input_index(x, t), ctl.hold, sim, spec, xs, a.rollouts, a.horizon,
                           seed=a.seed + 9)
    w_roll, c_roll = time.perf_counter() - w2, cpu_now() - c2
    e = empirical(k, a.rollouts)
    pc = ctl.certified(xs)
    pe, se = np.array(e["p_emp"]), np.maximum(np.array(e["se"]), 1 / a.rollouts)
    sound = pe >= pc - 3 * se
    rows = [{"x0": np.round(x, 4).tolist(), "p_cert": round(float(c), 4), "p_emp": round(float(p), 4),
             "ci95": np.round(ci, 4).tolist(), "sound": bool(ok)} for x, c, p, ci, ok in zip(xs, pc, pe, e["ci95"], sound)]
    rep = {"profile": a.profile, "eta": im.grid.eta.tolist(), "hold": a.hold, "inputs": inputs.tolist(),
           "n_runs": a.n_runs, "pilot_runs": a.pilot, "beta": a.beta, "horizon": a.horizon,
           "abstract_steps": ctl.steps, "cells": im.C, "live_cells": int(im.live.sum()), "classes": im.meta["classes"],
           "nnz": im.nnz, "bytes_imdp": im.nbytes(), "bounds": im.meta["bounds"], "rho": np.round(im.meta["rho"], 4).tolist(),
           "lipschitz": np.round(im.meta["lipschitz"], 4).tolist(),
           "sim_steps": steps, "robot_steps": steps * periods,
           "build": {"wall_s": round(w_build, 1), "cpu_s": round(c_build, 1),
                     "phases_wall_s": {k_: round(v, 1) for k_, v in im.meta["seconds"].items()}},
           "vi": {"wall_s": round(w_vi, 1), "cpu_s": round(c_vi, 1)},
           "build_plus_vi": {"wall_s": round(w_build + w_vi, 1), "cpu_s": round(c_build + c_vi, 1)},
           "robot_steps_per_cpu_s": round(steps * periods / max(c_build, 1e-9)),
           "live_cells_p_cert_pos": int(dom.size), "target_cells": int(im.target.sum()), "p_cert_x0": round(p0, 4),
           "rollouts": {"per_state": a.rollouts, "states": len(xs), "wall_s": round(w_roll, 1), "cpu_s": round(c_roll, 1)},
           "sound_states": int(sound.sum()), "p_emp_x0": rows[0]["p_emp"],
           "tightness_x0": round(float(pe[0] - pc[0]), 4), "peak_rss_mb": round(resource.getrusage(
               resource.RUSAGE_SELF).ru_maxrss / 1024), "loadavg_start": load0, "loadavg_end": os.getloadavg(),
           "table": rows}
    text = json.dumps(rep, indent=1)
    print(text)
    if a.out:
        Path(a.out).write_text(text)


if __name__ == "__main__":
    main()

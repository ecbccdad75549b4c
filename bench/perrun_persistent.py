"""Persistent randomization against the per-run certificate: p_emp with parameters per period and per episode (run by hand).

    python bench/perrun_persistent.py --out /tmp/persistent.json

The simulator is the TurtleBot experiment's ``perrun`` profile (the gazebo-like PyBullet robot:
per-run wheel radius 3 % and friction 30 % randomization, wheel slip, actuation jitter; 10 inputs,
0.3 s steps) on an open piece of floor small enough for a loaded 2-core machine: X = [0, 2.5] m x
[0, 2] m x all headings, reach-avoid into the box [1.6, 2.2] x [0.6, 1.4] m (any heading) without
leaving X, from x0 = (0.4, 1.0, 0) and ``--states`` states drawn where p_cert > 0. The interval MDP
is sampled once per (heading cell, input) (translation invariance, :mod:`simgap.perrun.translation`)
with the simulator's parameters redrawn every period, its Markov assumption. The same controller is
then validated twice with the same seeds: ``randomize.per = "period"`` (what the certificate
assumes) and ``randomize.per = "episode"`` (each rollout keeps its wheel radius and friction for the
whole run, as a real robot does). Reported: p_cert, both p_emp with 95 % Clopper-Pearson intervals,
and p_emp >= p_cert - 3 SE per state and mode.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from simgap.config import load_experiment  # noqa: E402
from simgap.perrun.containment import check_containment  # noqa: E402
from simgap.perrun.imdp import IMDPOptions  # noqa: E402
from simgap.perrun.translation import build_imdp_translation  # noqa: E402
from simgap.perrun.validation import empirical, sample_in_cells, success_counts  # noqa: E402
from simgap.perrun.value_iteration import PerRunController, synthesize_imdp  # noqa: E402
from simgap.simulators import make_simulator  # noqa: E402
from simgap.synthesis.spec import Box, Spec  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--eta", type=float, nargs=3, default=[0.1, 0.1, np.pi / 8])
    ap.add_argument("--n-runs", type=int, default=200)
    ap.add_argument("--pilot", type=int, default=20)
    ap.add_argument("--horizon", type=int, default=12, help="0.3 s steps")
    ap.add_argument("--rollouts", type=int, default=500)
    ap.add_argument("--states", type=int, default=4)
    ap.add_argument("--check-states", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=None)
    ap.add_argument("--controller", default=None, help="save the per-run controller here, or load it if it exists "
                                                       "(skips the build: same seeds, same controller)")
    a = ap.parse_args()

    exp = load_experiment(ROOT / "assets/experiments/turtlebot.toml", "perrun")
    system = dataclasses.replace(exp.system, x_lo=np.array([0.0, 0.0, -np.pi]), x_hi=np.array([2.5, 2.0, np.pi]))
    spec = Spec("reach_avoid", target=Box([1.6, 0.6, -np.pi], [2.2, 1.4, np.pi]))
    x0 = np.array([0.4, 1.0, 0.0])
    cfg = exp.simulator.to_dict()
    load0 = os.getloadavg()

    t0 = time.perf_counter()
    if a.controller and Path(a.controller).exists():
        ctl = PerRunController.load(a.controller)
        info = {k: ctl.meta[k] for k in ("nnz", "lipschitz", "containment")}
    else:
        opts = IMDPOptions(eta=a.eta, hold=1, n_runs=a.n_runs, pilot_runs=a.pilot, seed=a.seed)
        with make_simulator(cfg, system=system, workers=a.workers) as sim:
            im = build_imdp_translation(sim, spec, opts, log=print)
            rep = check_containment(sim, spec, im, a.check_states, seed=a.seed)
        ctl = synthesize_imdp(im, a.horizon, spec.kind)
        info = {"nnz": im.nnz, "lipschitz": np.round(im.meta["lipschitz"], 4).tolist(), "containment": rep.to_dict()}
        ctl.meta.update(info)
        if a.controller:
            ctl.save(a.controller)
    t_build = time.perf_counter() - t0
    print(f"interval MDP {info['nnz']} entries, {t_build:.0f} s; containment passed: {info['containment']['passed']}; "
          f"p_cert(x0) = {float(ctl.certified(x0[None])[0]):.4f}", flush=True)

    rng = np.random.default_rng([a.seed, 5])
    live = (ctl.p_cert > 0) & ~ctl.target
    xs = np.concatenate([x0[None], sample_in_cells(ctl.grid, np.flatnonzero(live), a.states, rng)])
    pc = ctl.certified(xs)
    modes = {}
    for per in ("period", "episode"):
        c = dict(cfg, randomize=dict(cfg["randomize"], per=per))
        t1 = time.perf_counter()
        with make_simulator(c, system=system, workers=a.workers) as sim:
            k = success_counts(lambda x, t: ctl.input_index(x, t), ctl.hold, sim, spec, xs, a.rollouts, a.horizon,
                               seed=a.seed + 9)
        e = empirical(k, a.rollouts)
        pe, se = np.array(e["p_emp"]), np.maximum(np.array(e["se"]), 1 / a.rollouts)
        modes[per] = {"p_emp": pe.round(4).tolist(), "ci95": np.round(e["ci95"], 4).tolist(),
                      "sound": (pe >= pc - 3 * se).tolist(), "seconds": round(time.perf_counter() - t1, 1)}
        print(per, modes[per], flush=True)
    out = {"x0s": np.round(xs, 4).tolist(), "p_cert": pc.round(4).tolist(), "modes": modes,
           "eta": list(a.eta), "n_runs": a.n_runs, "pilot": a.pilot, "horizon": a.horizon, "rollouts": a.rollouts,
           **info,
           "build_s": round(t_build, 1), "loadavg_start": load0, "loadavg_end": os.getloadavg()}
    text = json.dumps(out, indent=1)
    print(text)
    if a.out:
        Path(a.out).write_text(text)


if __name__ == "__main__":
    main()

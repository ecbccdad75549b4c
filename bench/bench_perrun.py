"""Per-run guarantees: interval-MDP cost, and p_cert next to p_emp from batched rollouts (run by hand).

    python bench/bench_perrun.py vi                      # value iteration at the pendulum target size
    python bench/bench_perrun.py validate                # numpy noisy pendulum, 10^4 rollouts x 21 states
    python bench/bench_perrun.py validate --sim pybullet --inputs 5 --n-runs 500 --rollouts 2000

1. ``vi``: value iteration alone on an interval MDP of the pendulum target size (201 x 201 cells,
   21 inputs, horizon 400 periods at hold k = 20: 20 abstract steps) with a synthetic sparse
   structure (``--succ`` successor cells per row + the sink, random valid intervals); wall time
   per step and in total, peak RSS (after the synthetic build and in all). Sampling the simulator
   is not part of this number (see 2). The synthetic interval MDP: ``bench/synthetic_imdp.py``.
   The noisy pendulum's real support at this grid and hold is about 150 cells per row (measured,
   docs/per-run.md): ``--succ 150`` is the honest size, the default 18 a small-support case.
2. ``validate``: the noisy pendulum (actuation std 0.5 N m, joint damping as an undeclared
   effect, invariance in X, x0 = (0.05, 0.1)): interval MDP from simulator samples (time per
   phase, samples, entries, bytes), value iteration, then R rollouts of the per-run controller
   from x0 and ``--states`` initial states in its domain: p_cert, p_emp (95 % Clopper-Pearson),
   soundness p_emp >= p_cert - 3 SE per state, tightness p_emp - p_cert at x0, and p_cert(x0)
   from the same counts with the uniform Bonferroni split (every bound at beta / all bounds).
3. ``sample``: the interval-MDP sampling rate at the 201 x 201 pendulum (``--cells 201``, the noisy
   PyBullet pendulum of ``simgap run pendulum --profile perrun``, 21 inputs, hold 20, N = 4000,
   N0 = 400) in one worker process: the secants of the Lipschitz phase as the sampling draws them
   (``simgap.perrun.sampling``), then ``--pairs`` (cell, input) pairs spread over the grid through
   ``count_pairs`` (one chunk's work, bookkeeping included): CPU seconds per simulator step, support
   entries per row, the worker's peak RSS, and the driver's bytes per entry while it assembles the
   interval MDP (tracemalloc over the assembly of the sampled chunk). From these: the projection for
   1, 16 and 256 cores (docs/per-run.md, "Beyond one machine").
The machine may be shared: the report states wall times and the load average.
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
sys.path.insert(1, str(Path(__file__).resolve().parent))

from simgap.perrun.imdp import IMDPOptions, reallocate  # noqa: E402
from simgap.perrun.sampling import build_imdp  # noqa: E402
from simgap.perrun.validation import empirical, sample_in_cells, success_counts  # noqa: E402
from simgap.perrun.value_iteration import synthesize_imdp  # noqa: E402
from simgap.simulators.base import make_simulator  # noqa: E402
from simgap.synthesis.spec import Box, Spec  # noqa: E402
from simgap.systems import get_system, input_grid  # noqa: E402
from synthetic_imdp import synthetic_imdp  # noqa: E402


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def bench_vi(a) -> dict:
    t0 = time.perf_counter()
    im = synthetic_imdp(a.succ)
    t_build = time.perf_counter() - t0
    rss_build = peak_rss_mb()
    c0 = time.process_time()
    ctl = synthesize_imdp(im, 400, "invariance")
    cpu = time.process_time() - c0
    out = {"cpu_seconds_vi": round(cpu, 2), "cells": im.C, "inputs": im.M, "nnz": im.nnz, "bytes_imdp": im.nbytes(),
           "steps": ctl.steps, "seconds_synthetic_build": round(t_build, 2), "seconds_vi": round(ctl.meta["seconds_vi"], 2),
           "seconds_per_step": round(ctl.meta["seconds_vi"] / ctl.steps, 3), "peak_rss_mb_build": round(rss_build),
           "peak_rss_mb": round(peak_rss_mb()), "cpu_seconds_process": round(time.process_time(), 2),
           "p_cert_mean": float(ctl.p_cert.mean()), "p_cert_max": float(ctl.p_cert.max())}
    if a.save:
        np.savez(a.save, p_cert=ctl.p_cert, policy=ctl.policy)
    return out


def bench_validate(a) -> dict:
    s = get_system("pendulum")
    if a.inputs != 21:
        s = dataclasses.replace(s, inputs=input_grid([-1], [1], [a.inputs]))
    if a.sim == "numpy":
        cfg = {"kind": "numpy", "system": "pendulum", "noise": {"actuation_std": 0.5},
               "effects": {"linear": [[0.0, 0.0], [0.0, -0.3]]}}
    else:
        cfg = {"kind": "pybullet_pendulum", "system": "pendulum", "noise": {"actuation_std": 0.5, "sensor_std": 1e-4},
               "effects": {"joint_damping": 0.1}, "options": {"branches": 25}}
    sim = make_simulator(cfg, system=s)
    spec = Spec("invariance", safe=Box(s.x_lo, s.x_hi))
    x0 = np.array([0.05, 0.1])
    t0 = time.perf_counter()
    opts = IMDPOptions(eta=a.eta, hold=a.hold, n_runs=a.n_runs, pilot_runs=a.pilot, seed=a.seed,
                       **({"split": tuple(a.split)} if a.split else {}), share=a.share)
    c0 = time.process_time()
    im = build_imdp(sim, spec, opts, log=print)
    cpu_build = time.process_time() - c0
    t_build = time.perf_counter() - t0
    ctl = synthesize_imdp(im, a.horizon, spec.kind)
    # ablation on the same counts: the uniform Bonferroni split (every bound at beta / all bounds)
    n_sink = int((im.col == im.C).sum())
    n_sup = im.nnz - n_sink
    uniform = reallocate(im, im.meta["beta"], np.array([n_sink, n_sup, n_sup]) / (n_sink + 2 * n_sup))
    p_uniform = float(synthesize_imdp(uniform, a.horizon, spec.kind).certified(x0[None])[0])
    rng = np.random.default_rng(5)
    xs = np.concatenate([x0[None], sample_in_cells(im.grid, np.flatnonzero(ctl.p_cert > 0), a.states, rng)])
    t1, c1 = time.perf_counter(), time.process_time()
    k = success_counts(lambda x, t: ctl.input_index(x, t), ctl.hold, sim, spec, xs, a.rollouts, a.horizon, seed=9)
    t_roll, cpu_roll = time.perf_counter() - t1, time.process_time() - c1
    e = empirical(k, a.rollouts)
    pc = ctl.certified(xs)
    pe, se = np.array(e["p_emp"]), np.maximum(np.array(e["se"]), 1 / a.rollouts)
    sound = pe >= pc - 3 * se
    rows = [{"x0": np.round(x, 4).tolist(), "p_cert": round(float(c), 4), "p_emp": round(float(p), 4),
             "ci95": np.round(ci, 4).tolist(), "se": round(float(sd), 5)}
            for x, c, p, ci, sd in zip(xs, pc, pe, e["ci95"], e["se"])]
    sim.close()
    return {"simulator": a.sim, "eta": a.eta, "hold": a.hold, "inputs": a.inputs, "n_runs": a.n_runs,
            "pilot_runs": a.pilot, "horizon": a.horizon, "abstract_steps": ctl.steps, "cells": im.C,
            "live_cells": int(im.live.sum()), "nnz": im.nnz, "bytes_imdp": im.nbytes(), "samples": im.meta["samples"],
            "seconds": {k: round(v, 2) for k, v in im.meta["seconds"].items()}, "seconds_build": round(t_build, 2), "cpu_seconds_total": round(time.process_time(), 2),
            "cpu_seconds_build": round(cpu_build, 2), "cpu_seconds_rollouts": round(cpu_roll, 2),
            "split": im.meta["split"], "levels": im.meta["levels"], "share": im.meta.get("share"),
            "anchors": im.meta.get("anchors"), "rho": im.meta["rho"], "bounds": im.meta["bounds"], "seed": a.seed,
            "seconds_vi": round(ctl.meta["seconds_vi"], 2), "seconds_rollouts": round(t_roll, 2),
            "rollouts_per_state": a.rollouts, "states": len(xs), "sound_states": int(sound.sum()),
            "p_cert_x0": rows[0]["p_cert"], "p_emp_x0": rows[0]["p_emp"],
            "p_cert_x0_uniform_split": round(p_uniform, 4),
            "tightness_x0": round(float(pe[0] - pc[0]), 4), "peak_rss_mb": round(peak_rss_mb()), "table": rows}


def bench_sample(a) -> dict:
    import tracemalloc

    from simgap.perrun.imdp import count_pairs, layout, lipschitz_from_slopes, secant_slopes
    from simgap.perrun.sampling import SECANT_PAIRS, SECANT_RUNS, _assemble, chunk_rng, runs_config
    s = get_system("pendulum")
    cfg = ({"kind": "numpy", "system": "pendulum", "noise": {"actuation_std": 0.5},
            "effects": {"linear": [[0.0, 0.0], [0.0, -0.3]]}} if a.sim == "numpy" else
           {"kind": "pybullet_pendulum", "system": "pendulum", "noise": {"actuation_std": 0.5, "sensor_std": 1e-4},
            "effects": {"joint_damping": 0.1}, "options": {"branches": 25}})
    sim = make_simulator(cfg, system=s)
    spec = Spec("invariance", safe=Box(s.x_lo, s.x_hi))
    eta = ((s.x_hi - s.x_lo) / a.cells).tolist()
    o = IMDPOptions(eta=eta, hold=a.hold, n_runs=a.n_runs, pilot_runs=a.pilot, seed=a.seed)
    lay = layout(s, spec, o)
    half = lay.grid.eta / 2
    c0 = time.process_time()
    slopes = {j: secant_slopes(sim, a.hold, j, half[j], chunk_rng(a.seed, 1, j), SECANT_PAIRS, SECANT_RUNS)
              for j in range(s.n)}
    cpu_lip = time.process_time() - c0
    L, how = lipschitz_from_slopes(s, slopes)
    widening = {"rho": (L @ half).tolist()}
    pp = lay.order[np.linspace(0, lay.P - 1, a.pairs).astype(np.int64)]
    c0 = time.process_time()
    part = count_pairs(sim, spec, lay, widening, pp, o, chunk_rng(a.seed, 2, 0), chunk_rng(a.seed, 3, 0))
    cpu_runs = time.process_time() - c0
    steps = len(pp) * (a.n_runs + a.pilot) * a.hold
    rate = steps / cpu_runs
    entries_per_row = (part["key"].size + len(pp)) / len(pp)                 # support + the sink
    # the driver's bytes per entry: tracemalloc over the assembly of synthetic interval MDPs on 41 x 41 and
    # 81 x 81 grids with the measured entries per row, in chunks as sampled (the sizes, not the numbers, set
    # the memory); the slope between the two is the cost per entry, the rest a constant (one block of bounds)
    per_row = max(1, int(round(entries_per_row)) - 1)
    measured = []
    for g in (41, 81):
        small = layout(s, spec, dataclasses.replace(o, eta=((s.x_hi - s.x_lo) / g).tolist()))
        rng = np.random.default_rng(0)
        Ps, Cs = small.P, small.C
        key = (np.arange(Ps)[:, None] * (Cs + 1) + np.sort(rng.integers(0, Cs, (Ps, per_row)), axis=1)).ravel()
        n_hit = rng.integers(0, a.n_runs, key.size).astype(np.int32)
        S = o.units_per_chunk(Ps)                                             # pairs per chunk, as sampled
        bounds = np.arange(0, Ps + S, S).clip(max=Ps)
        n_sink = rng.integers(0, a.n_runs, Ps).astype(np.int32)
        parts = [{"key": key[b0 * per_row:b1 * per_row], "n_hit": n_hit[b0 * per_row:b1 * per_row],
                  "n_in": n_hit[b0 * per_row:b1 * per_row] // 2, "pairs": np.arange(b0, b1), "n_sink": n_sink[b0:b1],
                  "single_seen": np.bool_(True), "simulated": np.int64(0)} for b0, b1 in zip(bounds[:-1], bounds[1:])]
        full = dict(runs_config(sim, spec, o, small, widening), n_chunks=len(parts))
        tracemalloc.start()
        im = _assemble(sim, spec, o, small, lambda c, names=None: parts[c], widening, L, None, how, full,
                       time.perf_counter(), 0.0, 0.0, None)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        measured.append((im.nnz, peak))
        del im, parts, key, n_hit
    per_entry = (measured[1][1] - measured[0][1]) / (measured[1][0] - measured[0][0])
    fixed = measured[1][1] - per_entry * measured[1][0]
    sim.close()
    P = lay.P
    secant_steps = s.n * 2 * SECANT_PAIRS * SECANT_RUNS * a.hold
    total_steps = P * (a.n_runs + a.pilot) * a.hold + secant_steps
    cpu_h = (P * (a.n_runs + a.pilot) * a.hold / rate + cpu_lip) / 3600
    entries = entries_per_row * P
    imdp_bytes = entries * (4 + 4 + 4 + 4 + 4) + (lay.C * lay.M + 1) * 8     # col, lo, hi, k_lo, k_hi + row_ptr
    return {"simulator": a.sim, "cells": lay.C, "grid": list(lay.grid.shape), "live_cells": int(lay.cells.size),
            "inputs": lay.M, "pairs": P, "hold": a.hold, "n_runs": a.n_runs, "pilot_runs": a.pilot,
            "rho": widening["rho"], "lipschitz": L.tolist(), "sampled_pairs": len(pp),
            "cpu_seconds_secants": round(cpu_lip, 2), "cpu_seconds_pairs": round(cpu_runs, 2),
            "steps_per_cpu_second": round(rate), "entries_per_row": round(entries_per_row, 1),
            "worker_peak_rss_mb": round(peak_rss_mb()),
            "assembly_bytes_per_entry": round(per_entry, 1), "assembly_fixed_bytes": round(fixed),
            "assembly_measured": [{"entries": e, "peak_bytes": b} for e, b in measured],
            "projection": {"simulator_steps": total_steps, "cpu_hours": round(cpu_h, 1), "entries": round(entries),
                           "imdp_bytes": round(imdp_bytes),
                           "driver_peak_bytes": round(per_entry * entries + fixed),
                           "note": "driver_peak_bytes: the assembly reading one chunk at a time, as from the store "
                                   "(the synthetic chunks exist before tracemalloc starts)",
                           "wall_hours": {str(c): round(cpu_h / c, 2) for c in (1, 16, 256)}}}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["vi", "validate", "sample"])
    ap.add_argument("--cells", type=int, default=201, help="sample: cells per dimension")
    ap.add_argument("--pairs", type=int, default=16, help="sample: (cell, input) pairs to sample")
    ap.add_argument("--succ", type=int, default=18, help="vi: successor cells per row")
    ap.add_argument("--sim", choices=["numpy", "pybullet"], default="numpy")
    ap.add_argument("--eta", type=float, nargs=2, default=[0.02, 0.05])
    ap.add_argument("--hold", type=int, default=20)
    ap.add_argument("--inputs", type=int, default=11)
    ap.add_argument("--n-runs", type=int, default=4000)
    ap.add_argument("--pilot", type=int, default=400)
    ap.add_argument("--horizon", type=int, default=400)
    ap.add_argument("--rollouts", type=int, default=10000)
    ap.add_argument("--states", type=int, default=20)
    ap.add_argument("--seed", type=int, default=1, help="validate: sampling seed of the interval MDP")
    ap.add_argument("--split", type=float, nargs=3, default=None, metavar=("SINK", "LO", "HI"),
                    help="validate: shares of beta for the three bound families (default: IMDPOptions.split)")
    ap.add_argument("--share", type=int, nargs="+", default=None,
                    help="validate: cells per block sharing one anchor's runs (one, or one per dimension)")
    ap.add_argument("--save", default=None, help="vi: write p_cert and the policy to this .npz (to compare runs)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    if a.what == "sample" and "--inputs" not in sys.argv:
        a.inputs = 21
    rep = {"vi": bench_vi, "validate": bench_validate, "sample": bench_sample}[a.what](a)
    rep["load_average"] = os.getloadavg()
    rep["command"] = " ".join(["python"] + sys.argv)
    print(json.dumps(rep, indent=1))
    if a.json:
        Path(a.json).write_text(json.dumps(rep, indent=1))


if __name__ == "__main__":
    main()

"""The TurtleBot case study's cost: simulator settings, processes, and `simgap run turtlebot` end to end.

    python bench/bench_turtlebot.py            # simulator table (~2 min), then the whole small profile
    python bench/bench_turtlebot.py --no-run   # the simulator table only
    python bench/bench_turtlebot.py --no-table # the whole run only

(1) Robot-steps (0.01 s base periods) per CPU second of one process on a collection-like batch
    (x = (2, 2, theta), theta uniform, the small profile's 25 inputs, tau_k = 0.3 s), for
    physics substeps, solver iterations and robots per world; next to each the largest and the
    rms deviation of the noise-free next state from a converged reference (16 substeps, 200
    solver iterations) and the largest noise-free gap |fhat - f| to the unicycle model, which is
    what the settings may change. CPU seconds are not inflated by other jobs on the machine.
(2) The same batch with every row repeated 60 times and no noise (what the deterministic
    baseline's collection and Lhat estimate ask for): repeated rows simulated once vs every row.
(3) A ParallelSimulator with 2 processes vs one process: wall time of the same batch (on a
    loaded machine the ratio says how much of a second core this process got).
(4) `python -m simgap run turtlebot` (small profile, with the recording) in a fresh folder:
    wall time, CPU time of the run and all its processes, and the wall time of each stage.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from simgap.simulators import make_simulator
from simgap.systems import get_system

ROOT = Path(__file__).resolve().parents[1]
STEPS = 30  # the experiment's k: tau_k = 0.3 s
CFG = {"kind": "pybullet_turtlebot", "system": "turtlebot", "steps": STEPS,
       "effects": {"wheel_radius_error": [0.005, -0.005]}}


def batch(B: int, seed: int = 0):
    s = get_system("turtlebot", steps=STEPS)
    rng = np.random.default_rng(seed)
    x = np.column_stack([np.full(B, 2.0), np.full(B, 2.0), rng.uniform(-np.pi, np.pi, B)])
    grid = np.linspace(-1.0, 1.0, 5)
    U = np.array([[a, b] for a in grid for b in grid])
    return s, x, U[rng.integers(0, len(U), B)]


def options(substeps, iterations, robots):
    return {"friction": 0.5, "substeps": substeps, "solver_iterations": iterations, "robots": robots}


def timed_step(cfg, x, u, workers=1):
    """(next states, CPU s of this process, wall s) of one noise-free batch."""
    with make_simulator(cfg, workers=workers) as sim:
        noise = sim.draw_noise(len(x), np.random.default_rng(1))
        if workers > 1:
            sim.step_with_noise(x[:64], u[:64], {k: v[:64] for k, v in noise.items()})  # start the helpers
        c0, t0 = time.process_time(), time.perf_counter()
        y = sim.step_with_noise(x, u, noise)
        return y, time.process_time() - c0, time.perf_counter() - t0


def simulator_table(B: int) -> None:
    s, x, u = batch(B)
    f = s.f(x, u)
    ref, _, _ = timed_step({**CFG, "options": options(16, 200, 1)}, x, u)
    print(f"(1) {B} runs of tau_k = {STEPS * 0.01:.1f} s; deviation from 16 substeps / 200 iterations; "
          f"gap = max |fhat - f| without noise")
    print(f"{'substeps':>8} {'iters':>5} {'robots':>6} {'steps/CPU s':>12} {'speed-up':>8}  "
          f"{'dev max x,y [mm]':>16} {'dev rms x,y [mm]':>16} {'dev max th [mrad]':>17}  {'gap max x,y,th':>22}")
    base = None
    for sub, it, rob in [(4, 50, 1), (4, 50, 4), (2, 50, 1), (2, 50, 4), (1, 50, 1), (1, 100, 1), (2, 20, 1),
                         (4, 10, 1)]:
        y, cpu, _ = timed_step({**CFG, "options": options(sub, it, rob)}, x, u)
        rate = B * STEPS / cpu
        base = base or rate
        d = np.abs(s.diff(y, ref))
        g = np.abs(s.diff(y, f)).max(axis=0)
        print(f"{sub:8d} {it:5d} {rob:6d} {rate:12,.0f} {rate / base:7.2f}x  {1e3 * d[:, :2].max():16.2f} "
              f"{1e3 * np.sqrt((d[:, :2] ** 2).mean()):16.2f} {1e3 * d[:, 2].max():17.2f}  "
              f"{g[0]:7.4f} {g[1]:7.4f} {g[2]:6.4f}", flush=True)

    cfg = {**CFG, "options": options(2, 50, 1)}
    xr, ur = np.repeat(x[:B // 60 + 1], 60, axis=0), np.repeat(u[:B // 60 + 1], 60, axis=0)
    with make_simulator(cfg) as sim:
        noise = sim.draw_noise(len(xr), np.random.default_rng(1))
        c0 = time.process_time()
        once = sim.step_with_noise(xr, ur, noise)
        c_once = time.process_time() - c0
        c0 = time.process_time()
        every = sim._simulate(xr, ur, noise) + noise["sens"]
        c_every = time.process_time() - c0
    same = np.array_equal(once[:, :2], every[:, :2])
    print(f"(2) {len(xr)} noise-free runs, each (x, u) 60 times: {c_once:.2f} CPU s simulated once vs "
          f"{c_every:.2f} CPU s every row ({c_every / c_once:.0f}x; positions identical: {same})")

    _, _, w1 = timed_step(cfg, x, u)
    y2, _, w2 = timed_step(cfg, x, u, workers=2)
    y1, _, _ = timed_step(cfg, x, u)
    print(f"(3) {B} runs, wall: 1 process {w1:.2f} s, 2 processes {w2:.2f} s ({w1 / w2:.2f}x; "
          f"identical results: {np.array_equal(y1, y2)})", flush=True)


def tree_cpu(proc, seen: dict) -> None:
    """Record the CPU seconds of ``proc`` and all its descendants (pid -> largest value seen).

    Polled, because collection and simulator pools are started by a forkserver whose children
    are never waited for by the run, so RUSAGE_CHILDREN does not see them."""
    import psutil
    try:
        root = psutil.Process(proc.pid)
        procs = [root] + root.children(recursive=True)
    except psutil.Error:
        return
    for p in procs:
        try:
            t = p.cpu_times()
            seen[p.pid] = max(seen.get(p.pid, 0.0), t.user + t.system)
        except psutil.Error:
            pass


def whole_run(profile: str) -> None:
    with tempfile.TemporaryDirectory(prefix="simgap_bench_tb_") as tmp:
        cmd = [sys.executable, "-m", "simgap", "run", "turtlebot", "--profile", profile, "--out", tmp]
        print(f"(4) {' '.join(cmd[1:])}", flush=True)
        t0 = time.perf_counter()
        seen: dict = {}
        with open(Path(tmp) / "log.txt", "w+") as log:
            proc = subprocess.Popen(cmd, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, text=True)
            while proc.poll() is None:
                tree_cpu(proc, seen)
                time.sleep(0.5)
            wall = time.perf_counter() - t0
            log.seek(0)
            out = log.read()
        if proc.returncode != 0:
            print(out[-3000:])
            raise SystemExit(f"simgap run failed ({proc.returncode})")
        cpu = sum(seen.values())
        print(out)
        stages = re.findall(r"\[([\w/]+)\] done in ([\d.]+) s", out)
        if stages:
            print("stage wall times: " + ", ".join(f"{k} {float(v):.1f} s" for k, v in stages))
        print(f"whole run: {wall:.1f} s wall ({wall / 60:.2f} min), {cpu:.1f} CPU s in {len(seen)} processes "
              f"({cpu / wall:.2f} cores busy on average; polled every 0.5 s)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=400, help="batch size of the simulator table")
    ap.add_argument("--no-run", action="store_true", help="skip the whole `simgap run turtlebot`")
    ap.add_argument("--no-table", action="store_true", help="skip the simulator table")
    ap.add_argument("--profile", default="small")
    a = ap.parse_args()
    if not a.no_table:
        simulator_table(a.runs)
    if not a.no_run:
        whole_run(a.profile)


if __name__ == "__main__":
    main()

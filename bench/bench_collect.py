"""Collection throughput and memory (run by hand; prints a report).

    python bench/bench_collect.py                  # ~2-3 minutes on 2 cores
    python bench/bench_collect.py --fraction 0.1   # a larger share of the case study
    python bench/bench_collect.py --full           # the whole pendulum case study (2.64e8 steps)

1. Plain loop (one pendulum body, resetJointState / TORQUE_CONTROL / stepSimulation /
   getJointState per sample): one-step samples per second on one core.
2. The collector on the pendulum case study (assets/experiments/pendulum.toml, profile paper:
   epsilon 0.004, N1hat 1000, 21 inputs = 263,907 pairs, 2.64e8 simulator steps): every k-th
   chunk (a uniform ``--fraction`` of the work) with the local process pool, wall-clock time
   including pool start-up and one simulator build per worker, extrapolated to the full set;
   samples/s per core and the ratio to (1) measured in the same run.
3. TurtleBot: the same for the TurtleBot case study (185 headings x 441 inputs x 1000 runs),
   ``--tb-chunks`` chunks of 262 pairs x 1000 runs, robot-steps per second.

The machine may be shared: besides wall-clock rates the report gives rates per CPU-second
(the workers' user + system time from getrusage, the plain loop's process_time), which do not
depend on how many other processes compete for the cores; the idle-machine estimates use them.
4. Peak memory of a pendulum-scale collection: the full 263,907-pair, N1hat = 1000 store
   collected with the numpy simulator (same chunking and statistics; PyBullet would add only
   its per-worker client), then loaded as one Dataset. Peak RSS of the collecting process and
   of the largest worker (getrusage) and the tracemalloc peak of loading the store.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time


sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_simulators import plain_loop  # noqa: E402  (the same baseline loop as the simulator bench)


def collector_fraction(experiment: str, fraction: float, workers: int):
    """Collect every k-th chunk of the paper profile; return (plan, chunks run, seconds, runs)."""
    from simgap.collect import collect
    from simgap.config import load_experiment

    exp = load_experiment(experiment, "paper")
    plan = exp.plan()
    k = max(1, int(round(1 / fraction)))
    ids = list(range(0, plan.n_chunks, k))
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        res = collect(plan, os.path.join(d, "s"), executor="local", workers=workers, chunk_ids=ids)
        wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)  # the pool's workers, joined by collect()
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    collector_fraction.worker_rss_mb = r1.ru_maxrss / 1024  # largest child so far
    return plan, len(ids), wall, cpu, res.runs


def memory_child(workers: int) -> None:
    """(4), run in a fresh process so that its getrusage numbers are its own."""
    import tracemalloc

    from simgap.collect import collect, load_store
    from simgap.config import load_experiment
    from simgap.simulators.base import SimulatorConfig

    exp = load_experiment("pendulum", "paper")
    exp.simulator = SimulatorConfig("numpy", "pendulum", noise={"actuation_std": 0.05, "sensor_std": 1e-4})
    plan = exp.plan()
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        collect(plan, os.path.join(d, "s"), executor="local", workers=workers)
        t_collect = time.perf_counter() - t0
        rss_collect = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        # traced after the pool is gone (forked workers would inherit the tracing)
        tracemalloc.start()
        ds = load_store(os.path.join(d, "s"))
        _, peak_load = tracemalloc.get_traced_memory()
        store_mb = sum(os.path.getsize(os.path.join(r, f)) for r, _, fs in os.walk(d) for f in fs) / 1e6
    tracemalloc.stop()
    data_mb = sum(getattr(ds, k).nbytes for k in ("x", "u", "f_nom", "mean", "var", "lo", "hi",
                                                  "cover_index", "input_index")) / 1e6
    print(json.dumps({
        "pairs": ds.K, "runs": ds.K * ds.n_runs, "chunks": plan.n_chunks, "collect_s": t_collect,
        "self_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "worker_maxrss_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
        "self_maxrss_collect_mb": rss_collect, "tracemalloc_load_mb": peak_load / 1e6,
        "dataset_mb": data_mb, "store_mb": store_mb}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fraction", type=float, default=0.05, help="share of the pendulum case study to run")
    ap.add_argument("--tb-chunks", type=int, default=2, help="TurtleBot case-study chunks to run (of 312)")
    ap.add_argument("--workers", type=int, default=os.cpu_count())
    ap.add_argument("--full", action="store_true", help="run the whole pendulum case study")
    ap.add_argument("--skip-memory", action="store_true")
    ap.add_argument("--skip-turtlebot", action="store_true")
    ap.add_argument("--memory-child", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.memory_child:
        memory_child(a.workers)
        return
    W = a.workers
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at start; workers = {W}")

    plain_cpu, plain = plain_loop(20000, 3, wall=True)
    print(f"(1) plain loop, one pendulum body: {plain:,.0f} samples/s wall-clock (best of 3), "
          f"{plain_cpu:,.0f} samples per CPU-second")

    frac = 1.0 if a.full else a.fraction
    plan, n, wall, cpu, runs = collector_fraction("pendulum", frac, W)
    rate = runs / wall
    total = plan.n_pairs * plan.n_runs
    print(f"(2) collector, pendulum case study: {n} of {plan.n_chunks} chunks ({runs:,} runs) in {wall:.1f} s "
          f"wall-clock, {cpu:.1f} CPU-s in {W} workers")
    print(f"    wall-clock: {rate:,.0f} samples/s total, {rate / W:,.0f} per core = {rate / W / plain:.1f}x "
          f"the plain loop; full case study {'measured' if a.full else 'extrapolated'} "
          f"{wall * plan.n_chunks / n / 60:.1f} min")
    print(f"    CPU time: {runs / cpu:,.0f} samples per CPU-second = {runs / cpu / plain_cpu:.1f}x the plain loop; "
          f"full case study ({total:,} steps) on {W} otherwise idle cores: {total / (runs / cpu) / W / 60:.1f} min")
    print(f"    peak RSS of the largest PyBullet worker: {collector_fraction.worker_rss_mb:.0f} MB; "
          f"collecting process {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")

    if not a.skip_turtlebot:
        tb_frac = a.tb_chunks / 312
        plan, n, wall, cpu, runs = collector_fraction("turtlebot", tb_frac, W)
        total = plan.n_pairs * plan.n_runs
        k = plan.system.steps  # robot-steps (periods of base tau) per run
        print(f"(3) collector, TurtleBot case study (k = {k} periods of {plan.system.base_tau:g} s per run): {n} of "
              f"{plan.n_chunks} chunks ({runs:,} runs) in {wall:.1f} s wall-clock, {cpu:.1f} CPU-s; "
              f"{runs * k / wall:,.0f} robot-steps/s total, {runs * k / cpu:,.0f} per CPU-second; "
              f"full set ({total:,} runs) on {W} idle cores: {total / (runs / cpu) / W / 3600:.2f} h")

    if not a.skip_memory:
        out = subprocess.run([sys.executable, __file__, "--memory-child", "--workers", str(W)],
                             capture_output=True, text=True, check=True)
        m = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"(4) memory, pendulum-scale store ({m['pairs']:,} pairs, {m['runs']:,} runs, {m['chunks']} chunks, "
              f"numpy simulator, {m['collect_s']:.0f} s):")
        print(f"    peak RSS: collecting process {m['self_maxrss_collect_mb']:.0f} MB during collection, "
              f"{m['self_maxrss_mb']:.0f} MB after loading the dataset; largest worker {m['worker_maxrss_mb']:.0f} MB")
        print(f"    load_store tracemalloc peak {m['tracemalloc_load_mb']:.1f} MB; dataset arrays "
              f"{m['dataset_mb']:.1f} MB; store on disk {m['store_mb']:.1f} MB")
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()

"""Throughput of the PyBullet simulators (run by hand; prints a table).

    python bench/bench_simulators.py            # ~1 minute on 2 cores
    python bench/bench_simulators.py --quick    # a few seconds, smaller samples

Pendulum, one-step samples per second per core (tau = 0.005 s, random (x, u) in X x U, a fresh
state every sample, which is what collection does):
  (a) plain loop: one pendulum body loaded from assets/urdf/pendulum.urdf;
      per sample resetJointState / setJointMotorControl2(TORQUE) / stepSimulation / getJointState;
  (b) simgap's PendulumSimulator.step (one multibody, ``branches`` independent pendulums,
      array calls), including noise draws, for several branch counts, with and without
      per-run parameter randomization;
  (c) two processes running (b) at once (the 2-core machine's real throughput).
TurtleBot robot-steps per second (tau = 0.01 s, 4 physics substeps): one step() call per
sample vs one batched call, with 1 and several robots per world.
The last lines estimate the full pendulum case-study collection (2.65e8 steps) on 2 cores.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import time

import numpy as np

from simgap.simulators import make_simulator
from simgap.systems import get_system

PAPER_PENDULUM_STEPS = 2.65e8


def best_times(fn, repeat: int) -> tuple:
    """Smallest (CPU time of this process, wall-clock time) [s] over ``repeat`` runs."""
    cpu, wall = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - t0)
    return min(cpu), min(wall)


def best_time(fn, repeat: int) -> float:
    """Smallest CPU time of this process [s] over ``repeat`` runs.

    CPU seconds, not wall-clock seconds: rates are per core, and CPU time is not inflated when
    other processes share the cores (wall-clock rates are, by the load factor)."""
    return best_times(fn, repeat)[0]


def pendulum_samples(n: int, seed: int = 0):
    s = get_system("pendulum")
    rng = np.random.default_rng(seed)
    return rng.uniform(s.x_lo, s.x_hi, (n, 2)), s.inputs[rng.integers(0, len(s.inputs), n)]


def plain_loop(n: int, repeat: int, bullet_client_methods: bool = False, wall: bool = False):
    """(a): samples per CPU second of a per-sample loop over one URDF pendulum (with ``wall``:
    also samples per wall-clock second, as a pair (cpu_rate, wall_rate)).

    Raw ``pybullet.f(..., physicsClientId=cid)`` calls (the fastest call style, the one
    simgap uses), or with ``bullet_client_methods`` the common ``client.f(...)`` idiom of
    ``BulletClient`` (which wraps every call in a functools.partial)."""
    import pybullet as pb
    from pybullet_utils.bullet_client import BulletClient
    from simgap.simulators._bullet import urdf_path

    x, u = pendulum_samples(n)
    c = BulletClient(connection_mode=pb.DIRECT)
    c.setGravity(0, 0, -9.81)
    c.setPhysicsEngineParameter(fixedTimeStep=0.005, numSubSteps=0)
    body = c.loadURDF(str(urdf_path("pendulum.urdf")), useFixedBase=True, flags=pb.URDF_USE_INERTIA_FROM_FILE)
    c.changeDynamics(body, -1, linearDamping=0, angularDamping=0)
    c.changeDynamics(body, 0, linearDamping=0, angularDamping=0)
    c.setJointMotorControl2(body, 0, pb.VELOCITY_CONTROL, force=0)
    cid = c._client
    q, qd, tq = x[:, 0].tolist(), x[:, 1].tolist(), u[:, 0].tolist()

    def run_methods():
        out = np.empty((n, 2))
        for i in range(n):
            c.resetJointState(body, 0, q[i], qd[i])
            c.setJointMotorControl2(body, 0, pb.TORQUE_CONTROL, force=tq[i])
            c.stepSimulation()
            out[i] = c.getJointState(body, 0)[:2]
        return out

    def run():
        out = np.empty((n, 2))
        for i in range(n):
            pb.resetJointState(body, 0, q[i], qd[i], physicsClientId=cid)
            pb.setJointMotorControl2(body, 0, pb.TORQUE_CONTROL, force=tq[i], physicsClientId=cid)
            pb.stepSimulation(physicsClientId=cid)
            out[i] = pb.getJointState(body, 0, physicsClientId=cid)[:2]
        return out

    t_cpu, t_wall = best_times(run_methods if bullet_client_methods else run, repeat)
    c.disconnect()
    return (n / t_cpu, n / t_wall) if wall else n / t_cpu


def batched(n: int, repeat: int, branches: int, randomize: bool = False) -> float:
    """(b): samples/s of PendulumSimulator.step (with actuation and sensor noise)."""
    x, u = pendulum_samples(n)
    cfg = {"kind": "pybullet_pendulum", "system": "pendulum", "options": {"branches": branches},
           "noise": {"actuation_std": 0.05, "sensor_std": 1e-4}}
    if randomize:
        cfg["randomize"] = {"mass": 0.05, "length": 0.02}
    with make_simulator(cfg) as sim:
        rng = np.random.default_rng(1)
        t = best_time(lambda: sim.step(x, u, rng), repeat)
    return n / t


def _worker(args):
    n, branches = args
    x, u = pendulum_samples(n, seed=n)
    with make_simulator({"kind": "pybullet_pendulum", "system": "pendulum", "options": {"branches": branches},
                         "noise": {"actuation_std": 0.05, "sensor_std": 1e-4}}) as sim:
        sim.step(x[:1000], u[:1000], np.random.default_rng(0))  # warm up
        t0, c0 = time.perf_counter(), time.process_time()
        sim.step(x, u, np.random.default_rng(1))
        return time.perf_counter() - t0, time.process_time() - c0


def two_processes(n: int, branches: int):
    """(c): two processes stepping n samples each at the same time: (total samples per
    wall-clock second, total samples per CPU second per core)."""
    with mp.get_context("spawn").Pool(2) as pool:
        res = pool.map(_worker, [(n, branches)] * 2)
    wall = max(r[0] for r in res)
    cpu = max(r[1] for r in res)
    return 2 * n / wall, n / cpu


def turtlebot(n: int, repeat: int, robots: int, one_at_a_time: bool) -> float:
    """Robot-steps/s of TurtlebotSimulator (actuation + sensor noise, mass/friction randomized)."""
    s = get_system("turtlebot")
    rng = np.random.default_rng(0)
    x = rng.uniform(s.x_lo, s.x_hi, (n, 3))
    u = s.inputs[rng.integers(0, len(s.inputs), n)]
    cfg = {"kind": "pybullet_turtlebot", "system": "turtlebot", "options": {"robots": robots},
           "noise": {"actuation_std": 0.05, "sensor_std": 1e-3}, "randomize": {"mass": 0.05, "friction": 0.1}}
    with make_simulator(cfg) as sim:
        g = np.random.default_rng(1)
        if one_at_a_time:
            t = best_time(lambda: [sim.step(x[i:i + 1], u[i:i + 1], g) for i in range(n)], repeat)
        else:
            t = best_time(lambda: sim.step(x, u, g), repeat)
    return n / t


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small samples (a few seconds)")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    n = 20_000 if args.quick else 200_000
    n_tb = 200 if args.quick else 2_000
    rep = 1 if args.quick else args.repeat

    load0 = os.getloadavg()
    rows = []
    a = plain_loop(n, rep)
    rows.append(("pendulum (a) plain loop, one URDF body", a, 1.0))
    a2 = plain_loop(n, rep, bullet_client_methods=True)
    rows.append(("pendulum (a') same loop via BulletClient methods", a2, a2 / a))
    best = 0.0
    for nb in (25, 50, 100):
        r = batched(n, rep, nb)
        best = max(best, r)
        rows.append((f"pendulum (b) batched, {nb} branches", r, r / a))
    r = batched(n, rep, 50, randomize=True)
    rows.append(("pendulum (b) batched, 50 branches, m/l randomized", r, r / a))
    two, two_cpu = two_processes(n, 50)
    rows.append(("pendulum (c) 2 processes x batched 50, per core", two_cpu, two_cpu / a))
    rows.append(("pendulum (c) 2 processes x batched 50, total wall-clock", two, two / a))
    t1 = turtlebot(n_tb, rep, 1, one_at_a_time=True)
    rows.append(("turtlebot one step() call per sample", t1, 1.0))
    for robots in (1, 4, 8):
        r = turtlebot(n_tb, rep, robots, one_at_a_time=False)
        rows.append((f"turtlebot batched, {robots} robot(s) per world", r, r / t1))

    load = os.getloadavg()
    print(f"load average before/after: {load0[0]:.2f} / {load[0]:.2f} (cores: {os.cpu_count()}; "
          "other processes on the machine slow every row)")
    print("rates are steps per CPU second of one process (= per core) unless marked wall-clock")
    print(f"{'benchmark':55s} {'steps/s':>12s} {'ratio':>7s}")
    for name, rate, ratio in rows:
        print(f"{name:55s} {rate:12,.0f} {ratio:7.2f}")
    print(f"\n(b) best batched / (a') BulletClient-method loop: {best / a2:.2f}x")
    print(f"full pendulum case study ({PAPER_PENDULUM_STEPS:.3g} steps):")
    print(f"  at 2 x best single-process batched rate ({best:,.0f}/s): "
          f"{PAPER_PENDULUM_STEPS / (2 * best) / 60:.1f} min")
    print(f"  at 2 x the per-core rate measured with 2 processes ({two_cpu:,.0f}/s): "
          f"{PAPER_PENDULUM_STEPS / (2 * two_cpu) / 60:.1f} min")
    print(f"  at the wall-clock 2-process rate of this run ({two:,.0f}/s, load-dependent): "
          f"{PAPER_PENDULUM_STEPS / two / 60:.1f} min")


if __name__ == "__main__":
    main()

"""MuJoCo batched vs PyBullet batched on the same pendulum, one run, one process (run by hand).

    python bench/bench_mujoco.py            # about a minute on 2 cores
    python bench/bench_mujoco.py --quick    # a few seconds

The pendulum is the rod of assets/urdf/pendulum.urdf; MuJoCo gets the same rod as
assets/urdf/pendulum.xml (Euler integrator, semi-implicit like Bullet's: the two simulators agree
to 1e-12, printed). Every row calls ``Simulator.step`` (noise draws included: actuation noise
0.05 N m) on a fresh random (x, u) in X x U per run, as collection does, with the input held for
``steps`` physics steps of 0.005 s. Rates are physics steps per **CPU second** of this process
(all its threads: MuJoCo's rollout threads count), the best of ``--repeat`` runs after one
untimed warm-up batch (MuJoCo's per-run model copies are made once, about 0.2 ms each); the
wall-clock rate is printed next to it (it depends on the machine's load). Rows:

* ``pybullet_pendulum``: the built-in batched pendulum (one multibody, 50 branches);
* ``pybullet_urdf``: the generic URDF backend (16 copies of the URDF per world);
* ``mujoco``: the generic MJCF backend through ``mujoco.rollout`` with 1 and 2 threads;
* the same with per-run mass randomization (``randomize.mass = 0.05``: one model per run);
* Gymnasium's cart-pole (assets/experiments/cartpole/inverted_pendulum.xml, RK4, 2 steps of 0.02 s).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path

import numpy as np

from simgap.simulators import make_simulator
from simgap.systems import get_system

REPO = Path(__file__).resolve().parents[1]
URDF = str(REPO / "assets" / "urdf" / "pendulum.urdf")
MJCF = str(REPO / "assets" / "urdf" / "pendulum.xml")
CARTPOLE = str(REPO / "assets" / "experiments" / "cartpole" / "inverted_pendulum.xml")
NOISE = {"actuation_std": 0.05}


def rate(sim, x, u, steps_per_row: int, repeat: int):
    """(physics steps per CPU second, per wall-clock second), best of ``repeat`` batches."""
    cpu, wall = [], []
    sim.step(x, u, np.random.default_rng(99))  # warm-up: MuJoCo's pool of per-run models is built once
    for r in range(repeat):
        rng = np.random.default_rng(r)
        t0, c0 = time.perf_counter(), time.process_time()
        sim.step(x, u, rng)
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - t0)
    n = len(x) * steps_per_row
    return n / min(cpu), n / min(wall)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small batches (a few seconds)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    B = 2000 if a.quick else 20000
    s = get_system("pendulum")
    rng = np.random.default_rng(0)
    x = rng.uniform(s.x_lo, s.x_hi, (B, 2))
    u = s.inputs[rng.integers(0, len(s.inputs), B)]
    pend = {"kind": "pybullet_pendulum", "system": "pendulum", "noise": NOISE, "options": {"branches": 50}}
    urdf = {"kind": "pybullet_urdf", "system": "pendulum", "noise": NOISE,
            "options": {"urdf": URDF, "positions": ["hinge"], "velocities": ["hinge"], "inputs": ["hinge"],
                        "copies": 16}}
    mj = {"kind": "mujoco", "system": "pendulum", "noise": NOISE,
          "options": {"model": MJCF, "positions": ["hinge"], "velocities": ["hinge"], "inputs": ["torque"]}}

    def with_(cfg, **kw):
        out = {**cfg, **{k: v for k, v in kw.items() if k != "options"}}
        out["options"] = {**cfg["options"], **kw.get("options", {})}
        return out

    print(f"load average before: {os.getloadavg()[0]:.2f} (cores: {os.cpu_count()}); batch {B} runs, "
          f"best of {a.repeat}")
    for steps in (1, 20):
        with make_simulator(with_(pend, steps=steps)) as p, make_simulator(with_(mj, steps=steps)) as m:
            noise = p.draw_noise(B, np.random.default_rng(9))
            nm = m.draw_noise(B, np.random.default_rng(9))
            nm["act"] = noise["act"]
            dev = np.max(np.abs(p.step_with_noise(x, u, noise) - m.step_with_noise(x, u, nm)))
        print(f"\nsteps per run: {steps} (tau = {0.005 * steps:g} s); max |MuJoCo - PyBullet| on the batch: {dev:.1e}")
        print(f"{'simulator':58s} {'steps/CPU s':>12s} {'steps/wall s':>13s} {'ratio (CPU)':>12s}")
        rows = [("pybullet_pendulum batched (50 branches)", with_(pend, steps=steps)),
                ("pybullet_urdf batched (16 copies)", with_(urdf, steps=steps)),
                ("mujoco rollout, 1 thread", with_(mj, steps=steps, options={"threads": 1})),
                ("mujoco rollout, 2 threads", with_(mj, steps=steps, options={"threads": 2})),
                ("pybullet_pendulum, mass randomized per run", with_(pend, steps=steps, randomize={"mass": 0.05})),
                ("mujoco, 1 thread, mass randomized per run",
                 with_(mj, steps=steps, randomize={"mass": 0.05}, options={"threads": 1}))]
        base = None
        for name, cfg in rows:
            n = B if "urdf" not in name else B // 4  # the generic URDF loop is slower: fewer runs
            with make_simulator(cfg) as sim:
                c, w = rate(sim, x[:n], u[:n], steps, a.repeat)
            base = base or c
            print(f"{name:58s} {c:12,.0f} {w:13,.0f} {c / base:12.2f}")
    # the cart-pole case study's simulator: 4 states, RK4, 2 steps of 0.02 s per period
    cp = dataclasses.replace(s, name="cartpole", state_names=("p", "th", "pd", "thd"), x_lo=np.full(4, -0.2),
                             x_hi=np.full(4, 0.2), base_tau=0.04, inputs=np.array([[0.0]]))
    xc = rng.uniform(-0.2, 0.2, (B, 4))
    uc = rng.uniform(-3, 3, (B, 1))
    print("\nGymnasium cart-pole (inverted_pendulum.xml, RK4, 2 x 0.02 s per run)")
    for name, extra in (("mujoco rollout, 2 threads", {}),
                        ("mujoco, 2 threads, mass and damping randomized", {"randomize": {"mass": 0.05, "damping": 0.2}})):
        cfg = {"kind": "mujoco", "system": "cartpole", "noise": {"actuation_std": 0.05}, **extra,
               "options": {"model": CARTPOLE, "positions": ["slider", "hinge"], "velocities": ["slider", "hinge"],
                           "inputs": ["slide"], "threads": 2}}
        with make_simulator(cfg, cp) as sim:
            c, w = rate(sim, xc, uc, 2, a.repeat)
        print(f"{name:58s} {c:12,.0f} {w:13,.0f}")
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()

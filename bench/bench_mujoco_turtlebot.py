"""What a MuJoCo differential drive would cost per robot-step against the PyBullet TurtleBot (run by hand).

    python bench/bench_mujoco_turtlebot.py            # about a minute on 2 cores
    python bench/bench_mujoco_turtlebot.py --quick    # a few seconds

Both simulators step the same collection-like batch: x = (2, 2, theta) with theta uniform, the
gazebo profile's 25 inputs (v, omega) in {-1, -0.5, 0, 0.5, 1}^2, tau_k = 30 base periods of
0.01 s, the gazebo profile's noise (held actuation noise 0.03 m/s and 0.03 rad/s, 0.5 mm pose
noise). Rows:

* ``pybullet_turtlebot`` (assets/urdf/diffbot.urdf), 4 robots per world, friction 0.5, with 1
  physics step per base period (the TurtleBot profiles' setting) and with 4 (the default);
* ``mujoco`` (the generic MJCF backend) on assets/urdf/diffbot.xml, the same robot's dimensions
  with a planar base and the unicycle inputs as velocity servos on wheel tendons, with 1 and 5
  MuJoCo steps per base period, 1 and 2 rollout threads.

Rates are robot-steps (0.01 s base periods) per **CPU second** of this process (all its threads:
MuJoCo's rollout threads count), the best of ``--repeat`` batches after one untimed warm-up, with
the wall-clock rate next to it (it depends on the machine's load). Next to each, the noise-free
gap to the unicycle model, max and rms of |fhat - f| per (x, y, theta) on the same batch: what
the model would cost in certified gamma. The MuJoCo backend starts every period at rest (its
runs do not depend on anything but (x, u, noise)), while the PyBullet robot starts at the
commanded velocity, so the MuJoCo robot loses up to v^2 / (2 mu g) = 0.05 m of travel per step
to the acceleration; its gap says so, and is not a property of MuJoCo's contacts.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from bench_mujoco import rate          # the same timing (best of repeat batches after a warm-up)
from bench_turtlebot import batch     # the same collection-like batch as the PyBullet bench
from simgap.simulators import make_simulator

ROOT = Path(__file__).resolve().parents[1]
STEPS = 30  # the experiment's k: tau_k = 0.3 s
NOISE = {"actuation_std": [0.03, 0.03], "sensor_std": 0.0005}  # the gazebo profile's
PYBULLET = {"kind": "pybullet_turtlebot", "system": "turtlebot", "steps": STEPS, "noise": NOISE,
            }
MUJOCO = {"kind": "mujoco", "system": "turtlebot", "steps": STEPS, "noise": NOISE}
MJ_OPTIONS = {"model": str(ROOT / "assets" / "urdf" / "diffbot.xml"), "positions": ["root_x", "root_y", "root_yaw"],
              "velocities": [], "inputs": ["v", "omega"]}


def quiet(noise: dict) -> dict:
    """The same draws with the additive noises zeroed and every relative factor 1 (noise-free)."""
    factors = ("radius", "mass", "friction", "damping", "slip")
    return {k: (np.ones_like(v) if k in factors else np.zeros_like(v)) for k, v in noise.items()}


def measure(cfg, s, x, u, repeat: int):
    """(robot-steps per CPU s, per wall s, max |fhat - f| (3,), rms (3,)) of one simulator."""
    with make_simulator(cfg, s) as sim:
        cpu_rate, wall_rate = rate(sim, x, u, STEPS, repeat)
        y = sim.step_with_noise(x, u, quiet(sim.draw_noise(len(x), np.random.default_rng(0))))
    d = np.abs(s.diff(y, s.f(x, u)))
    return cpu_rate, wall_rate, d.max(axis=0), np.sqrt((d ** 2).mean(axis=0))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small batches (a few seconds)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    B = 400 if a.quick else 4000
    s, x, u = batch(B)
    rows = [("pybullet_turtlebot, 1 physics step per 0.01 s (profiles)",
             {**PYBULLET, "options": {"robots": 4, "friction": 0.5, "substeps": 1}}),
            ("pybullet_turtlebot, 4 physics steps per 0.01 s (default)",
             {**PYBULLET, "options": {"robots": 4, "friction": 0.5, "substeps": 4}}),
            ("mujoco diffbot.xml, 1 step per 0.01 s, 1 thread", {**MUJOCO, "options": {**MJ_OPTIONS, "substeps": 1,
                                                                                     "threads": 1}}),
            ("mujoco diffbot.xml, 1 step per 0.01 s, 2 threads", {**MUJOCO, "options": {**MJ_OPTIONS, "substeps": 1,
                                                                                      "threads": 2}}),
            ("mujoco diffbot.xml, 5 steps per 0.01 s, 1 thread", {**MUJOCO, "options": {**MJ_OPTIONS, "substeps": 5,
                                                                                      "threads": 1}})]
    print(f"load average before: {os.getloadavg()[0]:.2f} (cores: {os.cpu_count()}); batch {B} runs of "
          f"tau_k = {STEPS * 0.01:.1f} s, best of {a.repeat}")
    print(f"{'simulator':56s} {'steps/CPU s':>12s} {'steps/wall s':>13s} {'vs first':>8s}  "
          f"{'gap max x, y [m], th [rad]':>28s}  {'gap rms x, y, th':>22s}")
    base = None
    for name, cfg in rows:
        c, w, gmax, grms = measure(cfg, s, x, u, a.repeat)
        base = base or c
        print(f"{name:56s} {c:12,.0f} {w:13,.0f} {c / base:7.2f}x  "
              f"{gmax[0]:8.4f} {gmax[1]:8.4f} {gmax[2]:8.4f}    {grms[0]:6.4f} {grms[1]:6.4f} {grms[2]:6.4f}",
              flush=True)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()

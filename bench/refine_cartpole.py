"""The cart-pole's missing damping, named by `simgap refine` from logs of many MuJoCo episodes.

    PYTHONPATH=. python bench/refine_cartpole.py [--episodes 100] [--steps 250] [--out DIR]

Logs: the cart-pole experiment's own simulator (assets/experiments/cartpole.toml: Gymnasium's MJCF
in the generic `mujoco` backend, actuation noise, per-run masses and damping), E episodes of T
periods of 0.02 s, each from rest with the pole tilted by up to 0.05 rad, its clock from 0. The
ctrl keeps the pole up: a discrete LQR of the textbook model (LQR_GAIN, Q = diag(1, 10, 1, 1),
R = 1 at 0.02 s) plus an offset redrawn uniformly in [-0.5, 0.5] every 10 periods, clipped to
[-3, 3]; the ctrl actually applied is what the log records as u. Saved as `logs.npz` (x, u, x_next,
tau, t, episode), then `simgap refine --system assets/experiments/cartpole/cartpole.toml --data
logs.npz` writes report.json and refined.json into --out.

What the MJCF has and the system file leaves out: slider damping b = 1 N s/m and hinge damping
c = 1 N m s/rad. Through the mass matrix they enter the rates as
    v'     += -(I + m l^2) / D * b v + m l cos(theta) / D * c omega
    omega' +=  m l cos(theta) / D * b v - (M + m) / D * c omega,
D = (M + m)(I + m l^2) - (m l cos theta)^2. `expected()` gives these coefficients from the system
file's parameters (near theta = 0); the script prints them beside what refine names.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SYSTEM_FILE = ROOT / "assets" / "experiments" / "cartpole" / "cartpole.toml"
LQR_GAIN = np.array([0.749, 8.156, 1.255, 1.723])  # ctrl = offset + LQR_GAIN . (p, theta, v, omega)


def mujoco_episodes(episodes: int, steps: int, seed: int = 5) -> dict:
    """Transition arrays of ``episodes`` x ``steps`` periods of the cart-pole experiment's MuJoCo
    simulator (rows episode by episode, each episode's clock t from 0)."""
    from simgap.config import load_experiment
    from simgap.simulators import make_simulator

    exp = load_experiment("cartpole", profile=None)
    rng = np.random.default_rng(seed)
    x = np.zeros((episodes, 4))
    x[:, 1] = rng.uniform(-0.05, 0.05, episodes)
    xs, us, xn = (np.empty((episodes, steps, k)) for k in (4, 1, 4))
    offset = np.zeros(episodes)
    with make_simulator(exp.simulator, exp.system) as sim:
        for k in range(steps):
            if k % 10 == 0:
                offset = rng.uniform(-0.5, 0.5, episodes)
            u = np.clip(offset + x @ LQR_GAIN, -3.0, 3.0)[:, None]
            nxt = sim.step(x, u, rng)
            xs[:, k], us[:, k], xn[:, k] = x, u, nxt
            x = nxt
    tau = exp.system.base_tau
    return {"x": xs.reshape(-1, 4), "u": us.reshape(-1, 1), "x_next": xn.reshape(-1, 4), "tau": tau,
            "t": np.tile(np.arange(steps) * tau, episodes), "episode": np.repeat(np.arange(episodes), steps)}


def expected(params: dict, b: float = 1.0, c: float = 1.0) -> dict:
    """Rate coefficients [1/s] of the MJCF's damping near theta = 0 (module docstring)."""
    M, m, l, I = params["M"], params["m"], params["l"], params["I"]
    D = (M + m) * (I + m * l * l) - (m * l) ** 2
    return {("v", "v"): -(I + m * l * l) / D * b, ("v", "omega"): m * l / D * c,
            ("omega", "v"): m * l / D * b, ("omega", "omega"): -(M + m) / D * c}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--steps", type=int, default=250)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--out", default="results/refine-cartpole")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    data = mujoco_episodes(a.episodes, a.steps, a.seed)
    np.savez(out / "logs.npz", **data)
    t1 = time.perf_counter()
    print(f"{a.episodes} episodes x {a.steps} periods of MuJoCo in {t1 - t0:.1f} s; max |theta| "
          f"{np.abs(data['x'][:, 1]).max():.3f} rad, max |p| {np.abs(data['x'][:, 0]).max():.3f} m")
    cmd = [sys.executable, "-m", "simgap", "refine", "--system", str(SYSTEM_FILE), "--data", str(out / "logs.npz"),
           "--out", str(out / "report.json"), "--save-system", str(out / "refined.json"), "--seed", str(a.seed)]
    print("$ " + " ".join(cmd[1:]))
    subprocess.run(cmd, check=True)
    from simgap.system_file import load_system_file

    want = expected(load_system_file(SYSTEM_FILE).params)
    report = json.loads((out / "report.json").read_text())
    print("\nMJCF damping near theta = 0 (rates, 1/s):  " + ", ".join(f"{s}' from {v}: {c:+.4f}"
                                                                   for (s, v), c in want.items()))
    for e in report["effects"]:
        key = (e["state_name"], e.get("variable"))
        print(f"named {e['name']} on {e['state_name']} ({e.get('variable')}): {e['coefficient']:+.4f} +- {e['stderr']:.4f}"
              + (f"  (MJCF: {want[key]:+.4f})" if key in want else ""))
    for h, r in report["multistep"].items():
        print(f"held-out {h}-step RMS (p, theta, v, omega): f " + " ".join(f"{v:.4g}" for v in r["rms_before"])
              + "  f' " + " ".join(f"{v:.4g}" for v in r["rms_after"]))


if __name__ == "__main__":
    main()

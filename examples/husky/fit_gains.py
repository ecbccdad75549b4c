"""Fit the husky system file's gains to the noise-free simulator (a short least-squares fit).

Runs every input of husky.toml from rest at 72 headings with the experiment's simulator, noise
off, and prints the husky.toml gains (kv, kw, kwv, d; husky.toml says what each is), fitted by linear
least squares, with the largest remaining noise-free gap per dimension:

    python examples/husky/fit_gains.py
"""

import dataclasses
import sys
from pathlib import Path

import numpy as np

from simgap.config import load_experiment
from simgap.simulators import make_simulator
from simgap.system_file import system_from_spec


def with_params(system, params: dict):
    """The system file's model with some of its [params] replaced (the formulas fold them in when loaded)."""
    spec = system.params["_system_file"]
    return system_from_spec({**spec, "params": {**spec.get("params", {}), **params}})


def fit(experiment: Path, headings: int = 72):
    """({kv, kw, kwv, d}, largest |gap| per dimension with them) from noise-free periods from rest."""
    exp = load_experiment(experiment, "base")
    s = exp.system
    cfg = dataclasses.replace(exp.simulator, noise={}, randomize={})
    th = np.linspace(-np.pi, np.pi, headings, endpoint=False)
    centre = (s.x_lo[:2] + s.x_hi[:2]) / 2
    x = np.array([[*centre, t] for t in th for _ in s.inputs])
    u = np.tile(s.inputs, (headings, 1))
    with make_simulator(cfg, s) as sim:
        y = sim.step(x, u, np.random.default_rng(0))
    d = y - x
    d[:, 2] = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
    tau, v, w, th0 = s.tau, u[:, 0], u[:, 1], x[:, 2]
    # the turn tau (kw - kwv v) omega: linear in (kw, kwv)
    kw, kwv = np.linalg.lstsq(np.c_[tau * w, -tau * w * v], d[:, 2], rcond=None)[0]
    turn = tau * (kw - kwv * v) * w
    # the displacement kv tau v (cos, sin)(theta + turn / 2) + d ((cos, sin)(theta + turn) - (cos, sin)(theta)):
    # linear in (kv, d), x and y rows stacked
    A = np.r_[np.c_[tau * v * np.cos(th0 + turn / 2), np.cos(th0 + turn) - np.cos(th0)],
              np.c_[tau * v * np.sin(th0 + turn / 2), np.sin(th0 + turn) - np.sin(th0)]]
    kv, r = np.linalg.lstsq(A, np.r_[d[:, 0], d[:, 1]], rcond=None)[0]
    gains = {"kv": float(kv), "kw": float(kw), "kwv": float(kwv), "d": float(r)}
    model = with_params(s, gains)
    gap = y - model.f(x, u)
    gap[:, 2] = (gap[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return gains, np.abs(gap).max(axis=0)


if __name__ == "__main__":
    here = Path(__file__).resolve().parent
    gains, g = fit(Path(sys.argv[1]) if len(sys.argv) > 1 else here / "experiment.toml")
    print("".join(f"{k} = {v:.3f}\n" for k, v in gains.items()) + f"largest noise-free gap: x {g[0]:.4f} m, y {g[1]:.4f} m, theta {g[2]:.4f} rad")

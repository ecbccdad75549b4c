"""Fit the husky system file's gains to the noise-free simulator with simgap's own fit (simgap.fit).

Runs every input of husky.toml from rest at 72 headings (x, y held at the arena's centre) with the
experiment's simulator, noise off, fits the husky.toml gains (kv, kw, kwv, d; husky.toml says what
each is) by least squares, and prints them with the largest remaining noise-free gap per dimension:

    python examples/husky/fit_gains.py

The same fit from the command line, writing the fitted system file:

    simgap fit examples/husky/experiment.toml --profile base --params kv kw kwv d \\
               --fix x=3 y=3 --grid 72 --out husky_fitted.toml
"""

import dataclasses
import sys
from pathlib import Path

import numpy as np

from simgap.config import load_experiment
from simgap.fit import fit_params, sample_states, transitions, with_params  # noqa: F401 (with_params: tests)
from simgap.simulators import make_simulator

GAINS = ["kv", "kw", "kwv", "d"]


def fit(experiment: Path, headings: int = 72):
    """({kv, kw, kwv, d}, largest |gap| per dimension with them) from noise-free periods from rest."""
    exp = load_experiment(experiment, "base")
    s = exp.system
    centre = (s.x_lo[:2] + s.x_hi[:2]) / 2
    rng = np.random.default_rng(0)
    x = sample_states(s, headings, rng, fix={"x": centre[0], "y": centre[1]}, grid=True)
    with make_simulator(dataclasses.replace(exp.simulator, noise={}, randomize={}), s) as sim:
        X, U, Y = transitions(sim, x, s.inputs, rng)
    res = fit_params(s, GAINS, X, U, Y)
    return res.values(), res.max_after


if __name__ == "__main__":
    here = Path(__file__).resolve().parent
    gains, g = fit(Path(sys.argv[1]) if len(sys.argv) > 1 else here / "experiment.toml")
    print("".join(f"{k} = {v:.3f}\n" for k, v in gains.items()) + f"largest noise-free gap: x {g[0]:.4f} m, y {g[1]:.4f} m, theta {g[2]:.4f} rad")

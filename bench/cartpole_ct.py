"""Fit the cart-pole's missing damping (affine continuous-time terms, `simgap refine --effects
affine_ct`) from noise-free MuJoCo one-step transitions and write the refined system file the
box-tube profiles use (assets/experiments/cartpole/cartpole_ct.toml).

    PYTHONPATH=. python bench/cartpole_ct.py --out assets/experiments/cartpole/cartpole_ct.toml

3,000 transitions at seeded random states of X and grid inputs, with no actuation noise and the
nominal masses and damping (the simulator's randomization drawn at its nominal values).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from simgap.cli import main as simgap
from simgap.config import load_experiment
from simgap.simulators import make_simulator


def noise_free(exp, x, u):
    """MuJoCo's next states with no actuation noise and the nominal masses and damping."""
    with make_simulator(exp.simulator, exp.system) as sim:
        noise = sim.draw_noise(len(x), np.random.default_rng(0))
        quiet = {k: (np.ones_like(v) if k in ("mass", "damping") else np.zeros_like(v)) for k, v in noise.items()}
        return sim.step_with_noise(x, u, quiet)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", required=True, help="the refined system file to write (.toml)")
    p.add_argument("--rows", type=int, default=3000)
    p.add_argument("--seed", type=int, default=1)
    a = p.parse_args(argv)
    exp = load_experiment("cartpole", profile=None)
    s = exp.system
    rng = np.random.default_rng(a.seed)
    x = rng.uniform(s.x_lo, s.x_hi, (a.rows, s.n))
    u = s.inputs[rng.integers(0, len(s.inputs), a.rows)]
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "transitions.npz"
        np.savez(data, x=x, u=u, x_next=noise_free(exp, x, u), tau=s.tau)
        sysfile = exp.path.parent / exp.sections["system"]["name"]
        return simgap(["refine", "--system", str(sysfile), "--data", str(data), "--effects", "affine_ct",
                       "--save-system", str(Path(a.out).resolve()), "--name", "cartpole_ct",
                       "--out", str(Path(tmp) / "report.json")])


if __name__ == "__main__":
    sys.exit(main())

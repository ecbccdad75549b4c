"""Benchmark the pendulum case-study scenario program (SCP-N1hat), per state dimension.

Data: the paper's pendulum cover (eps = 0.004, about 12.8k grid points x 21 inputs = 269k
(x_r, u) pairs), synthesized with the numpy simulator (the LP's size and structure do not depend
on N1hat, so a small --runs keeps synthesis fast), or a real data set with --data.
Basis: all monomials of degree <= 2 in (x1, x2, u) (10 terms), as in the paper.

Compares constraint generation vs the whole LP, and HiGHS vs Clarabel (both through cvxpy).

    python bench/bench_lp.py                 # everything (the full LPs take ~10-30 s each)
    python bench/bench_lp.py --skip-full     # constraint generation only
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from simgap.certify.basis import Basis
from simgap.certify.scp import solve_scp
from simgap.certify.synthetic import synthetic_dataset
from simgap.dataset import load_dataset


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="a real data set instead of the synthesized one")
    ap.add_argument("--epsilon", type=float, default=0.004)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--delta", type=float, default=0.001)
    ap.add_argument("--skip-full", action="store_true")
    ap.add_argument("--no-certify", action="store_true", help="skip timing the whole certify()")
    ap.add_argument("--repeat", type=int, default=3, help="constraint-generation repeats (best and median)")
    a = ap.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")

    t = time.perf_counter()
    if a.data:
        ds = load_dataset(a.data)
    else:
        cfg = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 0.002, "actuation_std": 0.05},
               "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]], "bias": [0.0, 0.02]}}
        ds = synthetic_dataset(cfg, a.epsilon, a.runs, seed=1)
    t_data = time.perf_counter() - t
    basis = Basis.polynomial(ds.system, 2)
    t = time.perf_counter()
    P = basis.design(ds.x, ds.u)
    t_design = time.perf_counter() - t
    g = ds.gap()
    print(f"data: K = {ds.K} (x_r,u) pairs, {len(basis)} basis terms, synthesized/loaded in {t_data:.1f} s; "
          f"design matrix {t_design * 1e3:.0f} ms")
    print(f"{'dim':<8}{'method':<8}{'solver':<10}{'seconds':>9}{'(median)':>10}{'cpu s':>8}{'rounds':>8}{'rows used':>11}"
          f"{'eta*':>13}{'mean fit':>13}")
    for i, name in enumerate(ds.system.state_names):
        ref = None
        for method in (["cg"] if a.skip_full else ["cg", "full"]):
            for solver in ("CLARABEL", "HIGHS"):
                reps = a.repeat if method == "cg" else 1
                times, cpus, r = [], [], None
                for _ in range(reps):
                    c0 = time.process_time()
                    r = solve_scp(P, g[:, i], a.delta, method=method, solver=solver)
                    cpus.append(time.process_time() - c0)
                    times.append(r.seconds)
                fit = float((P @ r.q).mean())
                print(f"{name:<8}{method:<8}{solver:<10}{min(times):>9.3f}{np.median(times):>10.3f}{min(cpus):>8.3f}{r.rounds:>8}"
                      f"{r.n_rows_used:>11}{r.eta_star:>13.7g}{fit:>13.7g}")
                if ref is None:
                    ref = (r.eta_star, fit)
                elif abs(r.eta_star - ref[0]) > 1e-6 * abs(ref[0]) or abs(fit - ref[1]) > 1e-5 * abs(ref[1]):
                    print(f"   WARNING: differs from the first solve (eta* {ref[0]:.9g}, mean fit {ref[1]:.9g})")
    if not a.no_certify:
        from simgap.certify import certify
        t, c0 = time.perf_counter(), time.process_time()
        cert = certify(ds) if ds.n_runs >= 2 else certify(ds, method="deterministic")
        print(f"whole certify() (both dimensions: variance, LPs, Lipschitz estimates, L_2 bound): "
              f"{time.perf_counter() - t:.2f} s wall, {time.process_time() - c0:.2f} s cpu")
        print(cert.summary())


if __name__ == "__main__":
    main()

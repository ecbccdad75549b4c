"""Certification time with the paper's Lipschitz term against the gap's own term (beyond the paper).

    python bench/bench_gap_lipschitz.py --data results/pendulum-small/data --repeat 3
    python bench/bench_gap_lipschitz.py --data results/cartpole-small/data --lhat simulator \
        --concentration subgaussian --safety 1 --repeat 2

Interleaved runs in one process (paper, gap, paper, gap, ...), each on a fresh copy of the data
set so that no memoized Lipschitz estimate is shared; the medians and their ratio are printed
(machines are noisy: compare the ratio, not the seconds). Both terms are computed in either
mode; "gap" also estimates the gap's slopes along each covered axis (and, with lhat = simulator,
takes the paper's Lhat_fhat from the same runs instead of a second simulation).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from simgap.certify import BoundOptions, CertifyOptions, certify
from simgap.dataset import load_store


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a collected data store (simgap collect / simgap run)")
    ap.add_argument("--lhat", choices=["data", "simulator"], default="data")
    ap.add_argument("--concentration", default="chebyshev")
    ap.add_argument("--safety", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    ds = load_store(a.data)
    times = {"paper": [], "gap": []}
    gam = {}
    for _ in range(a.repeat):
        for term in ("paper", "gap"):
            o = CertifyOptions(beta1=0.01, beta2=0.01, lhat=a.lhat, safety=a.safety, lipschitz_term=term,
                               bounds=BoundOptions(concentration=a.concentration))
            fresh = dataclasses.replace(ds)  # a new object: the Lipschitz memo is keyed by identity
            t0 = time.perf_counter()
            c = certify(fresh, o)
            times[term].append(time.perf_counter() - t0)
            gam[term] = [d.scp["gamma_range_on_data"][1] for d in c.dims]
    med = {k: float(np.median(v)) for k, v in times.items()}
    print(f"data {a.data}: K = {ds.K} pairs, N1hat = {ds.n_runs}, lhat = {a.lhat}, {a.repeat} interleaved repeats")
    print(f"{'term':<8}{'median s':>10}{'runs':>30}   gamma max per dimension")
    for k in ("paper", "gap"):
        print(f"{k:<8}{med[k]:>10.2f}{' '.join(f'{t:.2f}' for t in times[k]):>30}   "
              + ", ".join(f"{g:.4g}" for g in gam[k]))
    print(f"ratio gap / paper: {med['gap'] / med['paper']:.2f}")


if __name__ == "__main__":
    main()

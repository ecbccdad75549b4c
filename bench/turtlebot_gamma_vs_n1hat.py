"""The stochastic TurtleBot certificate against N1hat: how much of gamma the delta terms are (run by hand).

    python bench/turtlebot_gamma_vs_n1hat.py STORE [STORE ...] [--profile gazebo]
    python bench/turtlebot_gamma_vs_n1hat.py --cert RUN/cert_stochastic.json ...   # certificates already made

Each STORE is a collection of the TurtleBot experiment (``simgap collect turtlebot --profile gazebo
--n-runs N --out STORE``, or a run folder's ``data/``); it is certified with the profile's
``[certify]`` section exactly as ``simgap run`` does (stochastic method, Lhat_fhat from the
simulator with common random numbers). Per certificate and state dimension the table gives
gamma max (the largest gamma over the data's (x_r, u) pairs), its parts delta_1 (the margin added
to every observed mean gap in the scenario program), delta_2 (added to gamma), L_x eps (the
Lipschitz term) and the largest observed mean gap, and the delta share (delta_1 + delta_2) /
gamma max: what more runs per pair could remove at the same confidence.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from simgap.certify.certificate import load as load_certificate  # noqa: E402
from simgap.certify.pipeline import certify  # noqa: E402
from simgap.collect import load_store  # noqa: E402
from simgap.config import load_experiment  # noqa: E402
from simgap.pipeline import certify_options  # noqa: E402
from simgap.simulators import make_simulator  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def rows(cert) -> list:
    """One dict per state dimension: N1hat, gamma max, delta_1, delta_2, L_x eps, max gap, delta share."""
    out = []
    for name, d in zip(cert.state_names, cert.dims):
        gmax = d.scp["gamma_range_on_data"][1]
        out.append({"N1hat": cert.n_runs, "dim": name, "gamma_max": gmax, "delta1": d.delta1, "delta2": d.delta2,
                    "Lx_eps": d.L_x * cert.epsilon, "gap_max": d.gap_max, "share": (d.delta1 + d.delta2) / gmax,
                    "confidence": d.confidence})
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stores", nargs="*", help="collection stores of the TurtleBot experiment")
    ap.add_argument("--cert", nargs="*", default=[], help="stochastic certificate JSON files instead")
    ap.add_argument("--profile", default="gazebo", help="the experiment profile whose [certify] section is used")
    a = ap.parse_args(argv)
    exp = load_experiment(ROOT / "assets" / "experiments" / "turtlebot.toml", a.profile)
    certs = [load_certificate(p) for p in a.cert]
    if a.stores:
        opts = certify_options(exp.section("certify"), "stochastic")
        with make_simulator(exp.simulator.to_dict(), exp.system) as sim:
            for st in a.stores:
                t0 = time.perf_counter()
                certs.append(certify(load_store(st, system=exp.system), opts, simulator=sim))
                print(f"certified {st} in {time.perf_counter() - t0:.1f} s", flush=True)
    print(f"{'N1hat':>6} {'dim':<6} {'gamma max':>10} {'delta1':>9} {'delta2':>9} {'Lx eps':>9} {'gap max':>9} "
          f"{'delta share':>11} {'conf':>6}")
    for c in sorted(certs, key=lambda c: c.n_runs):
        for r in rows(c):
            print(f"{r['N1hat']:6d} {r['dim']:<6} {r['gamma_max']:10.4f} {r['delta1']:9.4f} {r['delta2']:9.4f} "
                  f"{r['Lx_eps']:9.4f} {r['gap_max']:9.4f} {r['share']:11.1%} {r['confidence']:6.3f}")


if __name__ == "__main__":
    main()

"""Benchmark: synthesis for the two case studies at their resolutions, each in a fresh process.

    python bench/bench_synthesis_cases.py [--pendulum-cert P.json] [--turtlebot-cert T.json]
                                          [--turtlebot-steps 10] [--hold 10] [--only pendulum|turtlebot]

* pendulum: invariance, safe set [0, 0.2] x [-0.5, 0.5] (paper), eta = (0.002, 0.005)
  (201 x 201 cells, 21 inputs); gap: the certificate, else a constant (1e-4, 1e-3).
* turtlebot: reach-avoid on assets/maps/arena.toml, eta = 0.08 (51 x 51 x 79 cells, heading
  periodic), 441 inputs; abstract step = 10 periods of 0.01 s, either ``--hold 10`` on the
  one-step system (gap composed 10 times) or ``--turtlebot-steps 10 --hold 1`` with a gap
  certified at 0.1 s. Gap: the certificate, else a constant (5e-4, 5e-4, 1e-3) per period.

Prints wall and CPU time per stage, the kernel (system) share of the CPU time and the minor
page faults, peak RSS (ru_maxrss) and the result sizes.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

CHILD = r"""
import json, resource, sys, time
import numpy as np
from simgap.synthesis.controller import synthesize
from simgap.synthesis.spec import Box, Spec
from simgap.systems import get_system
a = json.loads(sys.argv[1])
gap = None
if a.get("cert"):
    from simgap.certify.certificate import load
    gap = load(a["cert"])
elif a.get("gamma") is not None:
    gap = np.array(a["gamma"])
if a["case"] == "pendulum":
    system = get_system("pendulum", a.get("steps", 1))
    spec = Spec(kind="invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    x0 = None
else:
    from simgap.maps import load_map
    system = get_system("turtlebot", a.get("steps", 1))
    amap = load_map("arena")
    spec, x0 = amap.spec(system), amap.x0(system)
r0 = resource.getrusage(resource.RUSAGE_SELF)
c0 = time.process_time()
res = synthesize(system, spec, a["eta"], gap=gap, hold=a.get("hold", 1), x0=x0,
                 compose_hold=a.get("hold", 1) > 1)  # --hold k on a one-step gap: labelled composed
cpu = time.process_time() - c0
r1 = resource.getrusage(resource.RUSAGE_SELF)
s = res.stats
out = {"cpu": cpu, "sys": r1.ru_stime - r0.ru_stime, "minflt": r1.ru_minflt - r0.ru_minflt, "stats": s, "x0_winning": None if x0 is None else bool(res.controller.winning(x0[None])[0]),
       "x0_steps": None if x0 is None else int(res.controller.steps_to_go(x0[None])[0])}
print(json.dumps(out, default=float))
"""


def run(args: dict) -> dict:
    p = subprocess.run([sys.executable, "-c", CHILD, json.dumps(args)], capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(p.stderr)
    return json.loads(p.stdout.strip().splitlines()[-1])


def show(name: str, r: dict) -> None:
    s = r["stats"]
    t = s["seconds"]
    print(f"== {name}: grid {' x '.join(map(str, s['grid_shape']))} = {s['cells']:,} cells, {s['inputs']} inputs, "
          f"hold {s['hold']}, tau {s['tau']:g} s")
    print(f"   boxes {s['boxes']:,}, transitions {s['transitions']:,}, winning {s['winning']:,}"
          + (f" (+{s['target_cells']:,} target)" if s["spec_kind"] == "reach_avoid" else
             f" of {s['safe_cells']:,} safe cells"))
    print(f"   time: abstraction {t['abstraction']:.2f} s, game {t['game']:.2f} s, total {t['total']:.2f} s wall, "
          f"{r['cpu']:.2f} s CPU; peak RSS {s['peak_rss_mb']:.0f} MB; iterations {s['iterations']}")
    print(f"   kernel time {r['sys']:.2f} s = {100 * r['sys'] / max(r['cpu'], 1e-9):.1f} % of CPU, "
          f"{r['minflt']:,} minor page faults; game method {s.get('game_method')}")
    if r.get("x0_winning") is not None:
        print(f"   x0 winning: {r['x0_winning']}, steps to go {r['x0_steps']}")
    if s.get("diagnosis"):
        print(f"   note: {s['diagnosis']}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pendulum-cert")
    ap.add_argument("--turtlebot-cert")
    ap.add_argument("--turtlebot-steps", type=int, default=1)
    ap.add_argument("--hold", type=int, default=None, help="TurtleBot hold (default 10 / steps)")
    ap.add_argument("--only", choices=["pendulum", "turtlebot"])
    a = ap.parse_args()
    if a.only in (None, "pendulum"):
        args = {"case": "pendulum", "eta": [0.002, 0.005]}
        if a.pendulum_cert:
            args["cert"] = a.pendulum_cert
        else:
            args["gamma"] = [1e-4, 1e-3]
        show("pendulum invariance", run(args))
    if a.only in (None, "turtlebot"):
        steps = a.turtlebot_steps
        hold = a.hold if a.hold is not None else max(1, 10 // steps)
        args = {"case": "turtlebot", "eta": 0.08, "steps": steps, "hold": hold}
        if a.turtlebot_cert:
            args["cert"] = a.turtlebot_cert
        else:
            args["gamma"] = [5e-4, 5e-4, 1e-3]
        show("turtlebot reach-avoid", run(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark: synthesis on systems without translation invariance, and the vehicle against the
previous release's game.

    python bench/bench_synthesis_generic.py [--repeat 3] [--only dcdc|vortex|vehicle|turtlebot] [--reference]

Cases (each repetition in a fresh process, so the peak RSS is per run):

* ``dcdc``: the boost DC-DC converter of SCOTS's examples, a 2-D switched linear system
  (``simgap.synthesis.examples.dcdc_system``), 801 x 801 = 641,601 cells, 2 inputs (modes),
  invariance of [1.15, 1.55] x [5.45, 5.85], RK4 growth bound (``rk4_growth``).
* ``vortex``: a 3-D nonlinear unicycle drifting in a position-dependent vortex
  (``vortex_system``), reach-avoid with two walls, heading periodic, 15 inputs.
* ``vehicle``: the SCOTS vehicle (shared boxes): abstraction once, then the game of this
  release and the previous release's game (``bench/reference_games.py``, kept unchanged)
  alternately in the same process, CPU times compared as a ratio.
* ``turtlebot`` (only with ``--only turtlebot``, minutes): the same comparison on the TurtleBot
  arena (SAT game), with the kernel share of the CPU time and the minor page faults.

Per case: abstraction and game time (wall, the game split into the pass over all pairs, the
predecessor index, the fixed point and the controller; CPU of the abstraction, of the
predecessor index it builds without shared boxes, and of the game measured again on the same
abstraction), transitions, winning cells, iterations and peak RSS of ``synthesize``. With ``--reference`` the dcdc game is also timed with the previous release's
game on the same abstraction (slow: seconds).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))

CHILD = r"""
import json, resource, sys, time
import numpy as np
case, reference = sys.argv[1], sys.argv[2] == "1"
sys.path.insert(0, sys.argv[3])
from simgap.synthesis import synthesize
from simgap.synthesis import examples as ex
rss = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
base = rss()
out = {"import_rss_mb": base}
if case in ("dcdc", "vortex"):
    if case == "dcdc":
        args = (ex.dcdc_system(), ex.dcdc_spec(), ex.DCDC_ETA)
        kw = dict(growth=ex.dcdc_growth(), invariant_dims=())
    else:
        args = (ex.vortex_system(), ex.vortex_spec(), ex.VORTEX_ETA)
        kw = dict(growth=ex.vortex_growth(), invariant_dims=())
    c0 = time.process_time()
    res = synthesize(*args, **kw)
    out["cpu"] = time.process_time() - c0
    out["stats"] = res.stats
    out["peak_rss_mb"] = rss()
    # CPU time of the stages (synthesize reports wall times), then the previous release's game
    import reference_games as ref
    from simgap.synthesis import UniformGrid, build_abstraction, label_cells, solve_invariance, solve_reach
    sysm, spec, eta = args
    grid = UniformGrid(sysm.x_lo, sysm.x_hi, eta, periodic=sysm.angle_dims)
    blocked, cells = label_cells(grid, spec, sysm.x_lo, sysm.x_hi)
    c0 = time.process_time()
    ab = build_abstraction(sysm, grid, **kw)
    out["abstraction_cpu"] = time.process_time() - c0
    from simgap.synthesis.corner_index import CornerIndex
    c0 = time.process_time()
    CornerIndex.build(ab)  # the predecessor index, built inside build_abstraction: its share
    out["index_cpu"] = time.process_time() - c0
    games = [("new", solve_invariance if spec.kind == "invariance" else solve_reach)]
    if reference:
        games.append(("previous", ref.solve_invariance if spec.kind == "invariance" else ref.solve_reach))
    for _ in range(2):  # alternate, so that both see the same load
        for name, fn in games:
            c0 = time.process_time()
            r = fn(ab, cells, blocked)
            out.setdefault(name + "_game_cpu", []).append(time.process_time() - c0)
            out[name + "_winning"] = int((r.winning & ~r.target).sum())
else:
    import reference_games as ref
    from simgap.synthesis import UniformGrid, build_abstraction, label_cells, solve_reach
    if case == "vehicle":
        sysm, spec = ex.vehicle_system(), ex.vehicle_spec()
        grid = UniformGrid(sysm.x_lo, sysm.x_hi, ex.VEHICLE_ETA)
        blocked, cells = label_cells(grid, spec, sysm.x_lo, sysm.x_hi, strict_domain=False)
        ab = build_abstraction(sysm, grid, growth=ex.vehicle_growth, invariant_dims=(0, 1))
        rounds = 3
    else:  # the TurtleBot arena at eta 0.08, 441 inputs held 10 periods, no gap
        from simgap.maps import load_map
        from simgap.systems import get_system
        sysm = get_system("turtlebot")
        spec = load_map("arena").spec(sysm)
        grid = UniformGrid(sysm.x_lo, sysm.x_hi, 0.08, periodic=sysm.angle_dims)
        blocked, cells = label_cells(grid, spec, sysm.x_lo, sysm.x_hi)
        ab = build_abstraction(sysm, grid, hold=10, invariant_dims=(0, 1))
        rounds = 2
    t = {"new": [], "previous": []}
    for _ in range(rounds):  # alternate, so that both see the same load
        for name, fn in (("previous", ref.solve_reach), ("new", solve_reach)):
            r0 = resource.getrusage(resource.RUSAGE_SELF)
            c0, w0 = time.process_time(), time.perf_counter()
            r = fn(ab, cells, blocked)
            r1 = resource.getrusage(resource.RUSAGE_SELF)
            t[name].append((time.process_time() - c0, time.perf_counter() - w0,
                            r1.ru_stime - r0.ru_stime, r1.ru_minflt - r0.ru_minflt))
            out[name + "_winning"] = int((r.winning & ~r.target).sum())
            out[name + "_transitions"] = r.info["transitions"]
            out["method"] = r.info.get("method", out.get("method"))
    out["times"] = t
    out["peak_rss_mb"] = rss()
print(json.dumps(out, default=float))
"""


def run_child(case: str, reference: bool) -> dict:
    p = subprocess.run([sys.executable, "-c", CHILD, case, "1" if reference else "0", HERE],
                       capture_output=True, text=True)
    if p.returncode:
        raise SystemExit(p.stderr)
    return json.loads(p.stdout.strip().splitlines()[-1])


def _med(v):
    v = sorted(v)
    return v[len(v) // 2]


def report_generic(case: str, runs: list) -> None:
    s0 = runs[0]["stats"]
    print(f"\n== {case}: {s0['spec_kind']}, grid {' x '.join(map(str, s0['grid_shape']))} = {s0['cells']:,} cells, "
          f"{s0['inputs']} inputs, game method {s0['game_method']}")
    print(f"{'run':>4} {'abstr s':>8} {'game s':>8} {'(all pairs':>10} {'pre-index':>9} {'fixpoint':>9} "
          f"{'controller)':>11} {'total s':>8} {'cpu s':>7} {'peak RSS MB':>12}")
    for i, r in enumerate(runs):
        s, gs = r["stats"]["seconds"], r["stats"]["game_seconds"]
        print(f"{i:>4} {s['abstraction']:>8.3f} {s['game']:>8.3f} {gs['live_pairs']:>10.3f} {gs['predecessors']:>9.3f} "
              f"{gs['fixed_point']:>9.3f} {gs['controller']:>11.3f} {s['total']:>8.3f} {r['cpu']:>7.3f} "
              f"{r['peak_rss_mb']:>12.1f}")
    med = lambda k: _med([r["stats"]["seconds"][k] for r in runs])  # noqa: E731
    print(f"median: abstraction {med('abstraction'):.3f} s, game {med('game'):.3f} s "
          f"(fixed point {_med([r['stats']['game_seconds']['fixed_point'] for r in runs]):.3f} s), "
          f"total {med('total'):.3f} s wall / {_med([r['cpu'] for r in runs]):.3f} s CPU, "
          f"peak RSS {_med([r['peak_rss_mb'] for r in runs]):.1f} MB (after imports {runs[0]['import_rss_mb']:.1f} MB)")
    w = (f"winning {s0['winning']:,} of {s0['safe_cells']:,} safe cells" if s0["spec_kind"] == "invariance" else
         f"winning {s0['winning']:,} cells (+{s0['target_cells']:,} target)")
    print(f"transitions {s0['transitions']:,} ({s0['boxes']:,} valid boxes), {w}, iterations {s0['iterations']}")
    new = _med([min(r["new_game_cpu"]) for r in runs])
    print(f"CPU: abstraction {_med([r['abstraction_cpu'] for r in runs]):.3f} s (of which the predecessor "
          f"index {_med([r['index_cpu'] for r in runs]):.3f} s), game {new:.3f} s (best of 2 per run, median "
          f"over runs); synthesize in all {_med([r['cpu'] for r in runs]):.3f} s")
    refs = [r for r in runs if "previous_game_cpu" in r]
    if refs:
        old = _med([min(r["previous_game_cpu"]) for r in refs])
        new = _med([min(r["new_game_cpu"]) for r in refs])
        print(f"previous release's game on the same abstraction: {old:.3f} s CPU against {new:.3f} s "
              f"(ratio {new / old:.2f}); winning {refs[0]['previous_winning']:,} "
              f"({'same' if refs[0]['previous_winning'] == s0['winning'] else 'DIFFERENT'})")


def report_pair(case: str, runs: list) -> bool:
    what = ("vehicle (SCOTS v2 example, shared boxes)" if case == "vehicle" else
            "turtlebot arena (205k cells, 441 inputs, hold 10, no gap)")
    print(f"\n== {what}: game of this release ({runs[0]['method']}) vs the previous release's")
    print(f"{'run':>4} {'previous cpu':>13} {'new cpu':>8} {'ratio':>6} {'previous wall':>14} {'new wall':>9} "
          f"{'kernel % prev':>13} {'new':>5} {'page faults prev':>17} {'new':>9}")
    ratios = []
    for i, r in enumerate(runs):
        best = {k: min(v, key=lambda x: x[0]) for k, v in r["times"].items()}
        p, n = best["previous"], best["new"]
        ratios.append(n[0] / p[0])
        print(f"{i:>4} {p[0]:>13.3f} {n[0]:>8.3f} {n[0] / p[0]:>6.2f} {p[1]:>14.3f} {n[1]:>9.3f} "
              f"{100 * p[2] / p[0]:>13.1f} {100 * n[2] / n[0]:>5.1f} {p[3]:>17,} {n[3]:>9,}")
    ok = all(r["new_winning"] == r["previous_winning"] for r in runs)
    if case == "vehicle":
        ok &= all(r["new_winning"] == 48018 and r["new_transitions"] == 35_772_302 for r in runs)
    print(f"median ratio new / previous (CPU, the fastest of the alternating calls per run): {_med(ratios):.2f}; "
          f"same winning domain{' and parity (48,018 winning, 35,772,302 transitions)' if case == 'vehicle' else ''}: "
          f"{'yes' if ok else 'NO'}; peak RSS {_med([r['peak_rss_mb'] for r in runs]):.1f} MB (both games)")
    return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", choices=["dcdc", "vortex", "vehicle", "turtlebot"],
                    help="one case; turtlebot (minutes) runs only when named")
    ap.add_argument("--reference", action="store_true", help="also run the previous release's game on dcdc")
    a = ap.parse_args()
    ok = True
    for case in ("dcdc", "vortex", "vehicle", "turtlebot"):
        if (a.only and case != a.only) or (case == "turtlebot" and a.only != "turtlebot"):
            continue
        runs = [run_child(case, a.reference and case == "dcdc" and i == 0) for i in range(a.repeat)]
        if case in ("vehicle", "turtlebot"):
            ok &= report_pair(case, runs)
        else:
            report_generic(case, runs)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

"""The TurtleBot's level-0.5 data collected alone, for `simgap refine` (run by hand, issue 57).

    nice -n 19 python bench/turtlebot_heading.py --out /tmp/tb-heading --n1hat 200 [--dry-run]
    python bench/turtlebot_heading.py --out /tmp/tb-heading --n1hat 200 --refine results/turtlebot-heading

The scan's point (bench/turtlebot_separation.py: the gazebo profile with the simulator noise of
``--level``, N1hat runs per (heading, input) pair) without its certificates, audits and rollouts:
only the collection store ``OUT/noise<level>_n<N1hat>/data``, which `simgap refine --system
turtlebot --data ...` reads. Prints the collection's own time estimate first; resumable.

``--refine DIR``: `simgap refine` (:func:`simgap.refine.report.refine`, the whole library) on the
pairs of the store's finished chunks (all of them, or the part collected so far: each chunk is
verified by its digests), unweighted and weighted by 1 / the standard error of each pair's mean,
and per state the gap before and after: the mean of (r / se)^2 over the pairs (1 when only sampling
noise is left) and the systematic gap, the residual averaged per input over the headings (the
unicycle's gap does not depend on the heading), its largest magnitude with its standard error.
Writes DIR/heading.json and each refined model as DIR/turtlebot_refined_<mode>.json.

``--certify FILE ...`` (a complete store only): the stochastic certificate of the data against the
textbook model and each system FILE (gap term, the gazebo profile's options; the data do not depend
on the nominal model), its gamma max split into observed gap + delta + Lipschitz, and whether the
gazebo profile's synthesis on that model wins x0; into DIR/certify.json (with --refine's DIR).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from turtlebot_separation import experiments, point_name  # noqa: E402


def main() -> int:
    from simgap.collect import collect, printed_collection_estimate
    from simgap.cover import calibrate_rate
    from simgap.executors import make_executor
    from simgap.simulators import make_simulator

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--level", type=float, default=0.5)
    ap.add_argument("--n1hat", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--dry-run", action="store_true")
    ap.add_argument("--refine", metavar="DIR", help="refine on the collected pairs, write DIR/heading.json")
    ap.add_argument("--certify", nargs="*", metavar="FILE", help="certify the store against the textbook model and "
                                                                  "these system files (into --refine's DIR)")
    a = ap.parse_args()
    exp = experiments(a.level, a.n1hat)["paper"]
    store = Path(a.out) / point_name(a.level, a.n1hat) / "data"
    if a.certify:
        return certify_against(experiments(a.level, a.n1hat)["gap"], store, [Path(f) for f in a.certify],
                               Path(a.refine or "."), a)
    if a.refine:
        return refine_heading(exp, store, Path(a.refine), a)
    plan = exp.plan()
    store = Path(a.out) / point_name(a.level, a.n1hat) / "data"
    ex = make_executor("local", a.workers, None)
    with make_simulator(exp.simulator, exp.system) as sim:
        rate = calibrate_rate(sim, budget=0.3, work=plan.n_pairs * float(plan.n_runs))
    est = printed_collection_estimate(plan, store, ex, a.workers, None, rate, ex.workers)
    print(est.summary(), flush=True)
    if a.dry_run:
        return 0
    res = collect(plan, store, executor=ex)
    print(f"collected {res.runs:,} runs in {res.seconds:.0f} s into {store}")
    return 0


def finished_pairs(store: Path) -> tuple:
    """(x, u, mean, se, chunks read, chunks planned) of the store's finished chunks, each verified."""
    import json

    import numpy as np

    from simgap.store import read_chunk

    man = json.loads((store / "manifest.json").read_text())
    h, cfg = man["hash"], man["config"]
    parts, done = [], 0
    for c in range(int(cfg["n_chunks"])):
        if (store / "chunks" / f"c{c:06d}.npz").exists():
            parts.append(read_chunk(store, c, h, ("x", "u", "mean", "var")))
            done += 1
    x, u, mean, var = (np.concatenate([p[k] for p in parts]) for k in ("x", "u", "mean", "var"))
    return x, u, mean, np.sqrt(var / int(cfg["n_runs"])), done, int(cfg["n_chunks"])


def gap_summary(system, r, se, u, x) -> dict:
    """Per state: mean (r / se)^2 over the pairs, and the largest per-input mean residual (over the
    headings) with its standard error; x and y in the robot's frame (along and across the heading),
    where the unicycle's gap does not depend on the heading."""
    import numpy as np

    c, s_ = np.cos(x[:, 2]), np.sin(x[:, 2])
    r = np.column_stack([c * r[:, 0] + s_ * r[:, 1], -s_ * r[:, 0] + c * r[:, 1], r[:, 2]])
    se = np.column_stack([np.sqrt((c * se[:, 0]) ** 2 + (s_ * se[:, 1]) ** 2),
                          np.sqrt((s_ * se[:, 0]) ** 2 + (c * se[:, 1]) ** 2), se[:, 2]])
    inputs, inv = np.unique(np.round(u, 9), axis=0, return_inverse=True)
    inv = inv.ravel()
    cnt = np.bincount(inv)
    out = {}
    for i, name in enumerate(("along", "across", system.state_names[2])):
        m = np.bincount(inv, r[:, i]) / cnt
        sem = np.sqrt(np.bincount(inv, se[:, i] ** 2)) / cnt
        j = int(np.argmax(np.abs(m)))
        out[name] = {"mean_sq_in_se": float(np.mean((r[:, i] / np.maximum(se[:, i], 1e-12)) ** 2)),
                     "systematic_max": float(m[j]), "systematic_max_se": float(sem[j]),
                     "at_input": inputs[j].tolist(), "pair_max": float(np.abs(r[:, i]).max())}
    return out


def refine_heading(exp, store: Path, out: Path, a) -> int:
    import json
    import time

    from simgap.refine import make_transitions, refine, save_refined
    from simgap.refine.selection import SelectionOptions

    s = exp.system
    x, u, mean, se, done, planned = finished_pairs(store)
    data = make_transitions(x, u, mean, s.tau, system=s, source=str(store))
    data.se = se
    out.mkdir(parents=True, exist_ok=True)
    rows = {"level": a.level, "n1hat": a.n1hat, "pairs": int(data.K), "chunks": [done, planned], "modes": {}}
    for mode in ("unweighted", "weighted"):
        t0 = time.perf_counter()
        res = refine(s, data, options=SelectionOptions(weighted=mode == "weighted"), name=f"turtlebot_refined_{mode}")
        path = save_refined(res.refined, out / f"turtlebot_refined_{mode}.json")
        rep = res.report
        row = {"effects": [{k: e[k] for k in ("name", "state_name", "input", "variable", "coefficient", "stderr", "unit")
                            if k in e} for e in rep["effects"]],
               "flagged": [st["state_name"] for st in rep["states"] if st["unexplained"]],
               "before": gap_summary(s, res.before.r, se, u, x), "after": gap_summary(s, res.after.r, se, u, x),
               "system_file": path.name, "seconds": round(time.perf_counter() - t0, 1)}
        rows["modes"][mode] = row
        named = ", ".join(f"{e['name']}:{e['state_name']}:{e.get('input') or e.get('variable') or ''} {e['coefficient']:+.4f}"
                          for e in row["effects"])
        print(f"{mode}: {named}; flagged {row['flagged']}")
        for name in row["before"]:
            b, f = row["before"][name], row["after"][name]
            print(f"  {name:6s} mean (r/se)^2 {b['mean_sq_in_se']:7.2f} -> {f['mean_sq_in_se']:6.2f};  systematic max "
                  f"{b['systematic_max']:+.4f} +- {b['systematic_max_se']:.4f} at u={b['at_input']} -> "
                  f"{f['systematic_max']:+.4f} +- {f['systematic_max_se']:.4f} at u={f['at_input']}")
    (out / "heading.json").write_text(json.dumps(rows, indent=1))
    print(f"{data.K} pairs from {done} of {planned} chunks; wrote {out / 'heading.json'}")
    return 0


def certify_against(exp, store: Path, files: list, out: Path, a) -> int:
    import hashlib
    import json
    import time

    import numpy as np

    from simgap.certify.pipeline import certify
    from simgap.dataset import load_store
    from simgap.pipeline import certify_options, check_experiment
    from simgap.simulators.factory import make_simulator
    from simgap.synthesis.controller import synthesize
    from simgap.system_ref import resolve_system
    from turtlebot_separation import budget

    c = check_experiment(exp)
    x0 = np.asarray(c["x0"], float)
    rows = []
    for f in [None] + files:
        t0 = time.perf_counter()
        nominal = exp.system if f is None else resolve_system(str(f), steps=exp.system.steps)
        ds = load_store(store, system=exp.system)
        if f is not None:
            ds = ds.with_nominal(nominal)
        sim = make_simulator(exp.simulator.to_dict(), exp.system, workers=a.workers)
        try:
            cert = certify(ds, certify_options(exp.section("certify"), "stochastic", nominal), simulator=sim)
        finally:
            sim.close()
        res = synthesize(nominal, c["spec"], np.asarray(c["eta"], float), gap=cert, hold=c["hold"], x0=x0)
        won = (not res.empty) and bool(res.controller.winning(x0[None])[0])
        d = json.loads(json.dumps(cert.to_dict(), default=float))
        row = {"nominal": "turtlebot (textbook)" if f is None else f.name,
               "system_sha256": None if f is None else hashlib.sha256(f.read_bytes()).hexdigest(),
               "n1hat": a.n1hat, "level": a.level, "budget": budget(d, "gap"),
               "gamma_max": np.max(cert.gamma(ds.x, ds.u), axis=0).tolist(), "x0_won": won,
               "winning_cells": int(res.stats["winning"]), "seconds": round(time.perf_counter() - t0, 1)}
        rows.append(row)
        print(f"{row['nominal']}: gamma max {', '.join(f'{g:.4g}' for g in row['gamma_max'])} (observed "
              f"{', '.join(f'{g:.4g}' for g in row['budget']['gap_max'])}; delta "
              f"{', '.join(f'{g:.4g}' for g in row['budget']['delta'])}), x0 {'won' if won else 'not won'}, "
              f"{row['winning_cells']} winning cells ({row['seconds']} s)", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    (out / "certify.json").write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

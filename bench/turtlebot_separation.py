"""Where the paper's TurtleBot separation lives: collisions and certificates across noise (run by hand).

    python bench/turtlebot_separation.py --out results/turtlebot-separation           # the full scan
    python bench/turtlebot_separation.py --out results/turtlebot-separation --n1hat 100 400 1000
    python bench/turtlebot_separation.py --out results/turtlebot-separation --table-only   # table + figure
    python bench/turtlebot_separation.py --out results/turtlebot-separation --frontier     # gaps that win x0
    python bench/turtlebot_separation.py --out results/turtlebot-separation --levels 0.5 --n1hat 1000 \
        --nominal refined.json      # that point's data against a refined model (`simgap refine`)

The paper's headline is 44 / 1000 collisions of the deterministic-gap controller against 0 / 1000
of the stochastic-gap one. This scan asks at which simulator noise that separation appears for
simgap's TurtleBot. The noise level ``s`` moves every noise setting of the ``gazebo`` profile
(s = 0: command latency at 30 Hz as a held actuation error of 0.03 m/s, 0.03 rad/s) linearly to
the ``gazebo_stress`` profile's (s = 1: held actuation error 0.05 m/s, 0.2 rad/s, actuation
jitter, each wheel slipping in 20 % of the runs for the whole period, per-run wheel radius and friction spread) and
beyond (s > 1: slip probability 0.2 s, the latency terms s times theirs; the per-run parameter
spread stays at gazebo_stress's, the simulator's largest accepted friction spread being 0.3).
Physics, grid, cover, inputs and stage options are the ``gazebo`` profile's (one physics substep
per 0.01 s; gazebo_stress's measured 31 / 1000 was taken with two, so s = 1 is its noise, not its
exact run).

Each (s, N1hat) point is one folder ``OUT/noise<s>_n<N1hat>`` with ``point.json`` (its
configuration) and two `simgap run` result folders made by :func:`simgap.pipeline.run_experiment`:
``paper/`` (the paper's Lipschitz term; it holds the collection stores) and ``gap/`` (``lipschitz_term
= "gap"``, docs/certify.md), which reads ``paper/``'s stores (``stores_from``): one collection serves
both terms. A term whose ``summary.json`` is complete for the point's configuration is skipped; an
interrupted one is run again, its collection resuming from the stores. After every term the table
``OUT/separation.json`` is rewritten from the finished summaries (nothing is recomputed), with the
projections of the points not run (projected over ``--max-hours``); the text table and the figure
``OUT/separation.png`` (and .pdf) are made from that JSON alone.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENT = ROOT / "assets" / "experiments" / "turtlebot.toml"
BASE, STRESS = "gazebo", "gazebo_stress"
LEVELS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5)
TERMS = ("paper", "gap")
METHODS = ("deterministic", "stochastic")
PAPER = {"deterministic": 44, "stochastic": 0}  # collisions out of 1000 Gazebo runs (the paper, Sec. V)
SEPARATION_DET = 0.02  # the deterministic-gap controller collides in >= 20 of 1000 runs ...
# ... while the stochastic certificate wins x0 and its controller collides in 0
IDLE_RUNS_PER_S = 1790.0  # simulator runs (30 physics steps each) per second on 2 idle cores (docs/case-studies.md)
IDLE_STAGES_S = 90.0  # certify + audit + synthesize + 1000 rollouts of both methods, one term, idle (the gazebo run)
# constant gaps (x, y, theta) that win x0 on the gazebo profile's grid and map (`simgap synthesize
# --gamma`, docs/case-studies.md): what a stochastic certificate has to reach, until --frontier
# has mapped the boundary
WIN_GAMMAS = ((0.0121, 0.0122, 0.2), (0.05, 0.05, 0.1))
TABLE = "separation.json"
FRONTIER = "frontier.json"  # --frontier
FRONTIER_THETAS = (0.05, 0.075, 0.1, 0.125, 0.15, 0.2, 0.25, 0.3)  # rad per sampling period
WHATIF = "nominal_whatif.json"  # --nominal
FIGURE = "separation"


def point_name(level: float, n1hat: int) -> str:
    return f"noise{level:g}_n{n1hat}"


def noise_at(level: float, base: dict, stress: dict) -> tuple:
    """(noise, randomize) of the simulator at ``level``: gazebo's at 0, gazebo_stress's at 1, beyond
    linearly for the per-step terms (slip probability capped at 1) and held for the per-run spread."""
    if not (math.isfinite(level) and level >= 0):
        raise ValueError(f"noise level must be a finite number >= 0, got {level!r}")
    bn, sn = base["noise"], stress["noise"]

    def lerp(a, b, t):
        return [round(x + t * (y - x), 6) for x, y in zip(a, b)]

    noise = {"actuation_std": lerp(bn["actuation_std"], sn["actuation_std"], level), "sensor_std": bn["sensor_std"]}
    if level > 0:
        p, s = sn["wheel_slip"]
        noise["wheel_slip"] = [round(min(1.0, p * level), 6), s]
        noise["actuation_jitter"] = lerp([0.0, 0.0], sn["actuation_jitter"], level)
    t = min(level, 1.0)
    randomize = {k: round(t * float(v), 6) for k, v in stress["randomize"].items()}
    return noise, randomize


def experiments(level: float, n1hat: int, audit: dict | None = None, lhat_pairs: int | None = None) -> dict:
    """The point's experiment per gap term (the gazebo profile with this noise and N1hat; ``audit``
    overrides keys of its [audit] section, ``lhat_pairs`` its [certify] lhat_pairs: reduced runs)."""
    from simgap.config import load_experiment

    exp = load_experiment(EXPERIMENT, BASE)
    stress = load_experiment(EXPERIMENT, STRESS).simulator.to_dict()
    noise, randomize = noise_at(level, exp.simulator.to_dict(), stress)
    exp = dataclasses.replace(exp, simulator=dataclasses.replace(exp.simulator, noise=noise, randomize=randomize),
                              collect=dataclasses.replace(exp.collect, n_runs=int(n1hat)))
    out = {}
    for term in TERMS:
        sections = dict(exp.sections)
        sections["certify"] = {**exp.section("certify"), "lipschitz_term": term}
        if lhat_pairs is not None:
            sections["certify"]["lhat_pairs"] = int(lhat_pairs)
        sections["audit"] = {**exp.section("audit"), **(audit or {})}
        out[term] = dataclasses.replace(exp, sections=sections)
    return out


def point_config(level: float, n1hat: int, rollouts: int, exps: dict) -> dict:
    """What identifies a point: its results are reused only for exactly this configuration."""
    e = exps["paper"]
    return {"level": float(level), "n1hat": int(n1hat), "rollouts": int(rollouts),
            "simulator": json.loads(json.dumps(e.simulator.to_dict())), "audit": e.section("audit"),
            "certify": {t: json.loads(json.dumps(exps[t].section("certify"))) for t in TERMS}}


def read_json(path: Path):
    """A JSON file's content, or None when it is missing or not readable JSON (an interrupted write)."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def _hashes(s) -> tuple:
    ms = [s["methods"].get(m) for m in METHODS]
    return tuple(e.get("dataset_hash") if isinstance(e, dict) else None for e in ms)


def finished(folder: Path, config: dict, term: str) -> bool:
    """True if ``folder`` holds a complete summary.json of this point's configuration and term (the
    gap term's also certified the very data of the point's finished paper term)."""
    s = read_json(Path(folder) / "summary.json")
    if not isinstance(s, dict) or not isinstance(s.get("methods"), dict):
        return False
    if term != "paper":
        p = read_json(Path(folder).parent / "paper" / "summary.json")
        if not (finished(Path(folder).parent / "paper", config, "paper") and None not in _hashes(s)
                and _hashes(s) == _hashes(p)):
            return False
    return (all(isinstance(s["methods"].get(m), dict) for m in METHODS)
            and s.get("simulator") == config["simulator"]
            and (s.get("sections") or {}).get("certify") == config["certify"][term]
            and (s.get("sections") or {}).get("audit") == config["audit"]
            and (s.get("collect") or {}).get("n_runs") == config["n1hat"]
            and s.get("n_rollouts") == config["rollouts"])


def collected(store: Path) -> float:
    """Share of a store's chunks already on disk (0 without a readable manifest): for projections only."""
    m = read_json(Path(store) / "manifest.json")
    try:
        n = int(m["config"]["n_chunks"])
    except (TypeError, KeyError, ValueError):
        return 0.0
    return min(1.0, len(list((Path(store) / "chunks").glob("c*.npz"))) / max(n, 1))


def project_seconds(n_pairs: int, n1hat: int, rollouts: int, terms_left: int, collect_left: float,
                    rate: float, stages: float) -> float:
    """Projected wall time of a point: the share ``collect_left`` of its collection at ``rate`` runs/s
    plus ``stages`` s per term (scaled with the rollouts, the largest part of them)."""
    t = collect_left * n_pairs * n1hat / rate
    return t + terms_left * stages * (0.4 + 0.6 * rollouts / 1000)


def calibration(out: Path, n_pairs: int) -> tuple:
    """(runs per second, stage seconds per term at 1000 rollouts, where from): measured on the
    finished points under ``out`` if any, else the idle figures scaled by the load average."""
    runs = csec = ssec = 0.0
    nterm = 0
    for f in sorted(Path(out).glob("noise*_n*/*/summary.json")):
        s = read_json(f)
        if not isinstance(s, dict) or not isinstance(s.get("seconds"), dict):
            continue
        sec = s["seconds"]
        c = float(sec.get("collect/stochastic", 0.0))
        new = (s.get("collected_runs") or {}).get("stochastic")
        if isinstance(new, (int, float)) and new > 0 and c > 0:  # runs simulated in this call (not resumed ones)
            runs += float(new)
            csec += c
        R = float(s.get("n_rollouts") or 1000)
        ssec += sum(v for k, v in sec.items() if not k.startswith("collect/")) / (0.4 + 0.6 * R / 1000)
        nterm += 1
    load = max(1.0, os.getloadavg()[0] / (os.cpu_count() or 1))
    rate = runs / csec if csec > 0 else IDLE_RUNS_PER_S / load
    stages = ssec / nterm if nterm else IDLE_STAGES_S * load
    how = (f"rate {rate:,.0f} runs/s " + ("measured on finished points" if csec > 0 else
                                          f"(idle {IDLE_RUNS_PER_S:,.0f} / load factor {load:.1f})")
           + f", {stages:.0f} s of stages per term " + ("measured" if nterm else "(idle 90 s x load factor)"))
    return rate, stages, how


def row_from(summary: dict, config: dict, term: str) -> dict:
    """One table row (a point and a gap term) from its summary.json; nothing is recomputed."""
    row = {"level": config["level"], "n1hat": config["n1hat"], "term": term, "rollouts": config["rollouts"],
           "noise": config["simulator"]["noise"], "randomize": config["simulator"]["randomize"],
           "run_id": summary.get("run_id"), "seconds": round(sum(summary.get("seconds", {}).values()), 1),
           "seconds_collect": round(summary.get("seconds", {}).get("collect/stochastic", 0.0), 1)}
    for m in METHODS:
        e = summary["methods"][m]
        skipped = (e.get("rollouts") or {}).get("skipped")
        row[m] = {"x0_won": skipped is None, "skipped": skipped, "failures": e.get("failures"),
                  "n_rollouts": e.get("n_rollouts"), "gamma_max": e["gamma"]["max"],
                  "gamma_max_paper_term": e["gamma"].get("max_paper_term"),
                  "winning_cells": e["winning_cells"], "audit_pass_joint": e["audit_pass_rate_joint"],
                  "audit_violated_joint": e["audit_violated_joint"],
                  "audit_pass_per_dim": e["audit_pass_rate_per_dim"],
                  "closest_approach": e.get("closest_approach")}
    row["separation"] = separation(row)
    row["budget"] = None
    return row


def win_frontier(thetas=FRONTIER_THETAS, xy_max: float = 0.1, tol: float = 0.0005, log=print) -> dict:
    """For each constant heading gap gamma_theta: the largest equal gamma_x = gamma_y [m] with which
    the gazebo profile's synthesis (grid, map, hold, x0) still wins x0, by bisection (a larger gap
    only shrinks the winning domain). Each synthesis is the pipeline's, with a constant gap."""
    import numpy as np

    from simgap.config import load_experiment
    from simgap.pipeline import check_experiment
    from simgap.synthesis.controller import synthesize

    exp = load_experiment(EXPERIMENT, BASE)
    c = check_experiment(exp)
    eta, hold, x0 = np.asarray(c["eta"], float), c["hold"], np.asarray(c["x0"], float)
    t0 = time.perf_counter()
    n_syn = 0

    def wins(gxy: float, gth: float) -> bool:
        nonlocal n_syn
        n_syn += 1
        res = synthesize(exp.system, c["spec"], eta, gap=np.array([gxy, gxy, gth]), hold=hold, x0=x0)
        return (not res.empty) and bool(res.controller.winning(x0[None])[0])

    rows = []
    for gth in thetas:
        lo, hi = 0.0, xy_max
        if not wins(lo, gth):
            rows.append({"gamma_theta": gth, "gamma_xy_max": None})
            log(f"frontier: gamma_theta {gth:g}: x0 lost even with gamma_x = gamma_y = 0")
            continue
        while hi - lo > tol:
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if wins(mid, gth) else (lo, mid)
        rows.append({"gamma_theta": gth, "gamma_xy_max": lo})
        log(f"frontier: gamma_theta {gth:g}: x0 won up to gamma_x = gamma_y = {lo:.4f} m (lost at {hi:.4f})")
    return {"experiment": str(EXPERIMENT.relative_to(ROOT)), "profile": BASE, "x0": x0.tolist(), "eta": eta.tolist(),
            "tolerance": tol, "rows": rows, "syntheses": n_syn, "seconds": round(time.perf_counter() - t0, 1)}


def nominal_whatif(out: Path, level: float, n1hat: int, system_file: Path, rollouts: int = 1000, log=print) -> dict:
    """The point's stochastic data certified against another nominal model (a refined system from
    `simgap refine`, docs/refine.md) with the gap term's options, and the gazebo profile's synthesis
    on that model: does the certificate then win x0? The data are the point's ``paper/`` store
    (simulator runs do not depend on the nominal model: :meth:`simgap.dataset.Dataset.with_nominal`).
    No rollouts: a won x0 is reported, its closed loop is for `simgap run` with that system."""
    import numpy as np

    from simgap.certify.pipeline import certify
    from simgap.dataset import load_store
    import hashlib
    from simgap.pipeline import certify_options, check_experiment
    from simgap.simulators.factory import make_simulator
    from simgap.synthesis.controller import synthesize
    from simgap.system_ref import resolve_system

    folder = Path(out) / point_name(level, n1hat)
    exp = experiments(level, n1hat)["gap"]
    if not finished(folder / "paper", point_config(level, n1hat, rollouts, experiments(level, n1hat)), "paper"):
        from simgap.errors import SimgapError
        raise SimgapError(f"{folder / 'paper'} is not a finished point of this scan (run it first)")
    nominal = resolve_system(str(system_file), steps=exp.system.steps)
    c = check_experiment(exp)
    ds = load_store(folder / "paper" / "data", system=exp.system).with_nominal(nominal)
    sim = make_simulator(exp.simulator.to_dict(), exp.system, workers=2)
    t0 = time.perf_counter()
    try:
        cert = certify(ds, certify_options(exp.section("certify"), "stochastic", nominal), simulator=sim)
    finally:
        sim.close()
    x0 = np.asarray(c["x0"], float)
    res = synthesize(nominal, c["spec"], np.asarray(c["eta"], float), gap=cert, hold=c["hold"], x0=x0)
    won = (not res.empty) and bool(res.controller.winning(x0[None])[0])
    d = json.loads(json.dumps(cert.to_dict(), default=float))
    row = {"level": level, "n1hat": n1hat, "system_file": system_file.name,
           "system_sha256": hashlib.sha256(system_file.read_bytes()).hexdigest(),
           "budget": budget(d, "gap"), "gamma_max": np.max(cert.gamma(ds.x, ds.u), axis=0).tolist(),
           "x0_won": won, "winning_cells": int(res.stats["winning"]), "seconds": round(time.perf_counter() - t0, 1)}
    log(f"[{point_name(level, n1hat)}] against {system_file.name}: gamma max "
        f"{', '.join(f'{g:.3g}' for g in row['gamma_max'])}, x0 {'won' if won else 'not won'}")
    return row


def budget(cert: dict, term: str) -> dict:
    """What the stochastic certificate's gamma max is made of, per dimension, from its own file:
    gamma = observed gap max + (delta_1 + delta_2) + Lipschitz term (the smaller of the two terms
    with the gap's own, docs/certify.md), with Mhat the largest sample variance."""
    dims = cert["dims"]
    lip = [min(d["scp"]["lipschitz_terms"].values()) if term == "gap" else d["L_x"] * cert["epsilon"] for d in dims]
    return {"n1hat": int(cert["n_runs"]), "gap_max": [d["gap_max"] for d in dims],
            "delta": [d["delta1"] + d["delta2"] for d in dims], "lipschitz": lip, "Mhat": [d["Mhat"] for d in dims]}


def n1hat_needed(b: dict, gammas=WIN_GAMMAS) -> float:
    """The smallest N1hat at which the certificate could reach one of ``gammas`` (constant gaps that
    win x0) in the best case: the observed gap all sampling noise (the gap's true mean 0), so that it
    shrinks as 1 / sqrt(N1hat) with delta_1 + delta_2; the Lipschitz term does not shrink. inf if a
    target is not above it (:func:`best_case_gamma`)."""
    best = math.inf
    for g in gammas:
        need = 0.0
        for target, gap, d, lip in zip(g, b["gap_max"], b["delta"], b["lipschitz"]):
            if target <= lip:
                need = math.inf
                break
            need = max(need, b["n1hat"] * ((gap + d) / (target - lip)) ** 2)
        best = min(best, need)
    return best


def budget_gamma(b: dict) -> list:
    """gamma max per dimension from its parts (observed gap + delta_1 + delta_2 + Lipschitz term)."""
    return [g + d + lip for g, d, lip in zip(b["gap_max"], b["delta"], b["lipschitz"])]


def _xt(v, f: str = ".3g") -> str:
    """'larger of x and y / theta' of a per-dimension list."""
    return f"{max(v[0], v[1]):{f}} / {v[2]:{f}}"


def separation(row: dict) -> bool:
    """The paper's claim at this point: deterministic >= 20 / 1000 collisions, the stochastic
    certificate winning x0 with 0 collisions."""
    d, s = row["deterministic"], row["stochastic"]
    return bool(d["x0_won"] and d["failures"] is not None and d["failures"] >= SEPARATION_DET * d["n_rollouts"]
                and s["x0_won"] and s["failures"] == 0)


def build_table(out: Path, projections: list) -> dict:
    """The JSON table of every finished (point, term) under ``out`` plus the projections not run."""
    fr = read_json(Path(out) / FRONTIER)
    gammas = win_gammas(fr)
    rows = []
    for pj in sorted(Path(out).glob("noise*_n*/point.json")):
        cfg = read_json(pj)
        if not isinstance(cfg, dict):
            continue
        for term in TERMS:
            if finished(pj.parent / term, cfg, term):
                rows.append(row_from(read_json(pj.parent / term / "summary.json"), cfg, term))
                cert = read_json(pj.parent / term / "cert_stochastic.json")
                if isinstance(cert, dict):
                    rows[-1]["budget"] = budget(cert, term)
                    rows[-1]["n1hat_needed"] = n1hat_needed(rows[-1]["budget"], gammas)
    rows.sort(key=lambda r: (r["n1hat"], TERMS.index(r["term"]), r["level"]))
    return {"experiment": str(EXPERIMENT.relative_to(ROOT)), "base_profile": BASE, "stress_profile": STRESS,
            "paper": PAPER, "separation_rule": f"deterministic >= {SEPARATION_DET * 1000:g} / 1000, stochastic wins "
            "x0 with 0 collisions", "rows": rows, "projected_not_run": projections,
            "frontier": fr if isinstance(fr, dict) else None, "win_gammas": [list(g) for g in gammas],
            "nominal_whatif": [dict(r, n1hat_needed=n1hat_needed(r["budget"], gammas))
                               for r in (read_json(Path(out) / WHATIF) or {}).get("rows", [])]}


def win_gammas(frontier) -> list:
    """Constant gaps known to win x0: the frontier's (gamma_xy, gamma_xy, gamma_theta), else WIN_GAMMAS."""
    rows = (frontier or {}).get("rows") if isinstance(frontier, dict) else None
    got = [(r["gamma_xy_max"], r["gamma_xy_max"], r["gamma_theta"]) for r in rows or []
           if r.get("gamma_xy_max") is not None]
    return got or list(WIN_GAMMAS)


def _fmt_fail(e: dict) -> str:
    if not e["x0_won"]:
        return "no x0"
    return f"{e['failures']}/{e['n_rollouts']}"


def text_table(table: dict) -> str:
    """The printed table of a JSON table."""
    head = ("noise", "N1hat", "term", "det coll.", "sto x0", "sto coll.", "gamma det x,y,th", "gamma sto x,y,th",
            "closest det/sto [m]", "audit det/sto", "wall [min]", "separation")
    rows = [head]
    for r in table["rows"]:
        d, s = r["deterministic"], r["stochastic"]

        def ca(e):
            return "-" if not e.get("closest_approach") else f"{e['closest_approach']['min']:.3f}"
        rows.append((f"{r['level']:g}", str(r["n1hat"]), r["term"], _fmt_fail(d), "yes" if s["x0_won"] else "no",
                     _fmt_fail(s) if s["x0_won"] else "-", ",".join(f"{g:.3g}" for g in d["gamma_max"]),
                     ",".join(f"{g:.3g}" for g in s["gamma_max"]), f"{ca(d)}/{ca(s)}",
                     f"{d['audit_pass_joint']:.2f}/{s['audit_pass_joint']:.2f}", f"{r['seconds'] / 60:.1f}",
                     "yes" if r["separation"] else "no"))
    w = [max(len(x[c]) for x in rows) for c in range(len(head))]
    lines = ["  ".join(x[c].rjust(w[c]) for c in range(len(head))) for x in rows]
    lines.insert(1, "-" * len(lines[0]))
    if not table["rows"]:
        lines.append("(no finished point)")
    for p in table["projected_not_run"]:
        why = "--project-only" if p.get("project_only") else f"> {p['max_hours']:g} h"
        lines.append(f"not run: noise {p['level']:g}, N1hat {p['n1hat']}: projected {p['hours']:.1f} h "
                     f"({why}; {p['how']})")
    return "\n".join(lines)


def markdown_table(table: dict) -> str:
    """The table as Markdown (docs/turtlebot-separation.md, kept in step by bench/readme_numbers.py)."""
    lines = ["| noise level | N1hat | gap term | deterministic collisions | stochastic wins x0 | stochastic "
             "collisions | gamma max det. (x, y, theta) | gamma max sto. (x, y, theta) | closest approach det. / sto. "
             "[m] | audit pass det. / sto. | wall time |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in table["rows"]:
        d, s = r["deterministic"], r["stochastic"]
        ca = " / ".join("-" if not e.get("closest_approach") else f"{e['closest_approach']['min']:.3f}" for e in (d, s))
        gd, gs = (", ".join(f"{g:.3g}" for g in e["gamma_max"]) for e in (d, s))
        lines.append(f"| {r['level']:g} | {r['n1hat']} | {r['term']} | {_fmt_fail(d)} | "
                     f"{'yes' if s['x0_won'] else 'no'} | {_fmt_fail(s) if s['x0_won'] else '-'} | {gd} | {gs} | "
                     f"{ca} | {d['audit_pass_joint']:.2f} / {s['audit_pass_joint']:.2f} | "
                     f"{r['seconds'] / 60:.1f} min |")
    groups: dict = {}  # one row per N1hat and projected time: the levels listed together
    for p in table["projected_not_run"]:
        groups.setdefault((p["n1hat"], round(p["hours"], 1)), []).append(p["level"])
    for (n, h), lvs in sorted(groups.items()):
        lines.append(f"| {', '.join(f'{lv:g}' for lv in sorted(lvs))} | {n} | both | not run: projected {h:.1f} h "
                     f"per level | | | | | | | |")
    rows = [r for r in table["rows"] if r.get("budget")]
    fr = table.get("frontier")
    wins = ("the constant gaps in the frontier table below" if fr else
            " or ".join(str(tuple(g)) for g in table.get("win_gammas") or WIN_GAMMAS))
    if rows:
        lines += ["", "What the stochastic certificate's gamma max is made of (the larger of x and y / theta, from "
                  "its file): gamma = observed gap + (delta_1 + delta_2) + Lipschitz term. The last column is the "
                  f"N1hat at which it could reach a gap that wins x0 ({wins}) in the best case: the gap's true "
                  "mean 0, so that the observed gap (then sampling noise) shrinks as 1 / sqrt(N1hat) with delta; "
                  "the Lipschitz term does not.", "",
                  "| noise level | N1hat | gap term | gamma max [m / rad] | observed gap | delta_1 + delta_2 | "
                  "Lipschitz term | Mhat [m^2 / rad^2] | N1hat to win x0, best case |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            b = r["budget"]
            gam = budget_gamma(b)
            need = r["n1hat_needed"]
            lines.append(f"| {r['level']:g} | {r['n1hat']} | {r['term']} | {_xt(gam)} | {_xt(b['gap_max'])} | "
                         f"{_xt(b['delta'])} | {_xt(b['lipschitz'], '.2g')} | {_xt(b['Mhat'], '.2g')} | "
                         + ("won" if r["stochastic"]["x0_won"] else "never" if math.isinf(need)
                            else f"{_round2(need):,}") + " |")
    if table.get("nominal_whatif"):
        lines += ["", "The same data certified against a refined nominal model (`--nominal`, the gap term's "
                  "options; the larger of x and y / theta):", "",
                  "| noise level | N1hat | nominal model (sha256) | gamma max [m / rad] | observed gap | "
                  "delta_1 + delta_2 | Lipschitz term | x0 won | N1hat to win x0, best case |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in table["nominal_whatif"]:
            b = r["budget"]
            gam = budget_gamma(b)
            need = r["n1hat_needed"]
            lines.append(f"| {r['level']:g} | {r['n1hat']} | {r['system_file']} ({r['system_sha256'][:12]}) | "
                         f"{_xt(gam)} | {_xt(b['gap_max'])} | {_xt(b['delta'])} | {_xt(b['lipschitz'], '.2g')} | "
                         f"{'yes' if r['x0_won'] else 'no'} | "
                         + ("-" if r["x0_won"] else "never" if math.isinf(need) else f"{_round2(need):,}") + " |")
    if fr:
        lines += ["", f"Constant gaps that win x0 (`--frontier`: {fr['syntheses']} syntheses of the {fr['profile']} "
                  f"profile's grid and map, bisection to {fr['tolerance']:g} m, {fr['seconds'] / 60:.1f} min):", "",
                  "| gamma_theta [rad] | largest gamma_x = gamma_y winning x0 [m] |", "|---|---|"]
        lines += [f"| {r['gamma_theta']:g} | " + ("none (lost at 0)" if r["gamma_xy_max"] is None
                                                   else f"{r['gamma_xy_max']:.4f}") + " |" for r in fr["rows"]]
    return "\n".join(lines)


def _round2(n: float) -> int:
    """n rounded up to two significant digits (an estimate: no more digits than it has)."""
    e = 10 ** max(0, int(math.floor(math.log10(max(n, 1.0)))) - 1)
    return int(math.ceil(n / e) * e)


def figure(table: dict, out_dir: Path, name: str = FIGURE) -> list:
    """Collisions per 1000 runs and "x0 won" against the noise level, from the JSON table alone."""
    import numpy as np

    from simgap_viz.figures import METHOD_STYLE, _plt, save

    plt = _plt()
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(7.5, 6.0), sharex=True, gridspec_kw={"height_ratios": [3, 1.3]})
    rows = table["rows"]
    n1hats = sorted({r["n1hat"] for r in rows})
    markers = dict(zip(n1hats, "osD^v"))
    levels = sorted({r["level"] for r in rows})
    sep = sorted({r["level"] for r in rows if r["separation"]})
    for lv in sep:  # shade around each separating level, half-way to its neighbours
        i = levels.index(lv)
        lo = (levels[i - 1] + lv) / 2 if i > 0 else lv - 0.05
        hi = (levels[i + 1] + lv) / 2 if i + 1 < len(levels) else lv + 0.05
        for a in (ax, bx):  # the rule: deterministic >= 20 / 1000, stochastic winning x0 with 0 / 1000
            a.axvspan(lo, hi, color="tab:green", alpha=0.15, lw=0,
                      label="separation holds" if (a is ax and lv == sep[0]) else None)
    offsets = {}
    for k, (n, term) in enumerate((n, t) for n in n1hats for t in TERMS):
        offsets[(n, term)] = (k - (len(n1hats) * len(TERMS) - 1) / 2) * 0.012
    for n in n1hats:
        for term in TERMS:
            sub = sorted((r for r in rows if r["n1hat"] == n and r["term"] == term), key=lambda r: r["level"])
            if not sub:
                continue
            x = np.array([r["level"] for r in sub])
            ls = "-" if term == "paper" else "--"
            for m in METHODS:
                y = np.array([np.nan if not r[m]["x0_won"] else 1000.0 * r[m]["failures"] / r[m]["n_rollouts"]
                              for r in sub])
                ax.plot(x + offsets[(n, term)], y, ls=ls, marker=markers[n], color=METHOD_STYLE[m], ms=5, lw=1.4,
                        label=f"{m}, N1hat {n}, {term}'s term")
                won = np.array([1.0 if r[m]["x0_won"] else 0.0 for r in sub])
                bx.plot(x + offsets[(n, term)], won + (0.04 if m == "stochastic" else -0.04), ls=ls,
                        marker=markers[n], color=METHOD_STYLE[m], ms=5, lw=1.0)
    ax.axhline(PAPER["deterministic"], color=METHOD_STYLE["deterministic"], ls=":", lw=1.2)
    ax.axhline(PAPER["stochastic"], color=METHOD_STYLE["stochastic"], ls=":", lw=1.2)
    ax.annotate("paper: deterministic 44 / 1000", (0.01, PAPER["deterministic"]), xycoords=("axes fraction", "data"),
                xytext=(0, 3), textcoords="offset points", fontsize=8, color=METHOD_STYLE["deterministic"])
    ax.annotate("paper: stochastic 0 / 1000", (0.99, 0), xycoords=("axes fraction", "data"), xytext=(0, -10),
                textcoords="offset points", fontsize=8, ha="right", color=METHOD_STYLE["stochastic"])
    ax.axhline(SEPARATION_DET * 1000, color="0.5", ls="-.", lw=0.8)
    ax.annotate("20 / 1000", (0.99, SEPARATION_DET * 1000), xycoords=("axes fraction", "data"), xytext=(0, 3),
                textcoords="offset points", fontsize=7, ha="right", color="0.4")
    ax.set_ylabel("collisions per 1000 runs from x0")
    ax.set_ylim(bottom=-0.12 * max(50.0, ax.get_ylim()[1]))
    Rs = sorted({r["rollouts"] for r in rows})
    runs = "" if Rs in ([], [1000]) else f"; scaled from {', '.join(map(str, Rs))} runs per controller"
    ax.set_title("TurtleBot: deterministic vs stochastic gap across simulator noise\n"
                 f"(no point: the certificate does not win x0{runs})", fontsize=10)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(alpha=0.3)
    bx.set_yticks([0, 1], ["no", "yes"])
    bx.set_ylim(-0.3, 1.3)
    bx.set_ylabel("x0 won")
    bx.set_xlabel("noise level (0: gazebo profile, 1: gazebo_stress's noise)")
    bx.grid(alpha=0.3)
    if levels:
        bx.set_xticks(levels, [f"{lv:g}" for lv in levels])
    fig.tight_layout()
    out_dir.mkdir(parents=True, exist_ok=True)
    return save(fig, Path(out_dir), name)


def best_case_gamma(b: dict, n1hat) -> "np.ndarray":
    """gamma max per dimension at N1hat = ``n1hat`` values, (len, 3), in :func:`n1hat_needed`'s best
    case: the observed gap and delta_1 + delta_2 scaled by sqrt(N1hat_0 / N1hat), plus the Lipschitz term."""
    import numpy as np
    n = np.asarray(n1hat, float)[:, None]
    s = (np.asarray(b["gap_max"], float) + np.asarray(b["delta"], float))[None]
    return s * np.sqrt(b["n1hat"] / n) + np.asarray(b["lipschitz"], float)[None]


def budget_figure(table: dict, out_dir: Path, name: str = FIGURE + "_gamma") -> list:
    """The stochastic certificates' (gamma_xy, gamma_theta) against the constant gaps that win x0,
    with each N1hat-100 certificate's best-case path as N1hat grows (from the JSON table alone)."""
    import numpy as np

    from simgap_viz.figures import _plt, save

    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.5, 5.2))
    rows = [r for r in table["rows"] if r.get("budget") and r["term"] == "gap"]
    levels = sorted({r["level"] for r in rows})
    cmap = plt.get_cmap("viridis")
    color = {lv: cmap(i / max(1, len(levels) - 1)) for i, lv in enumerate(levels)}
    fr = table.get("frontier")
    if fr:
        pts = sorted((r["gamma_theta"], r["gamma_xy_max"]) for r in fr["rows"] if r["gamma_xy_max"] is not None)
        if pts:  # between two sampled gamma_theta the larger one's bound holds (the region shrinks upward)
            th = np.array([0.02] + [p[0] for p in pts])
            xy = np.array([pts[0][1]] + [p[1] for p in pts])
            ax.fill_betweenx(th, 1e-4, xy, step="pre", color="tab:green", alpha=0.15, lw=0,
                             label="constant gaps that win x0 (synthesis, --frontier)")
            bx_ = np.concatenate([[xy[0]], np.repeat(xy[1:], 2), [1e-4]])  # the region's outline
            by_ = np.concatenate([[th[0]], np.repeat(th[:-1], 2)[1:], [th[-1], th[-1]]])
            ax.plot(bx_, by_, color="tab:green", lw=1.2)
    for g in (table.get("win_gammas") or []) if not fr else []:
        ax.plot(max(g[0], g[1]), g[2], "g*", ms=9)
    markers = {100: "o", 400: "s", 1000: "D", 2000: "^"}
    grid = np.geomspace(100, 20000, 200)
    for r in rows:
        b = r["budget"]
        gam = np.array(budget_gamma(b))
        c = color[r["level"]]
        ax.plot(max(gam[0], gam[1]), gam[2], marker=markers.get(r["n1hat"], "v"), color=c, ms=7, ls="none",
                mec="k", mew=0.5)
        if r["n1hat"] == min(x["n1hat"] for x in rows if x["level"] == r["level"]) and not r["stochastic"]["x0_won"]:
            path = best_case_gamma(b, grid)
            ax.plot(np.maximum(path[:, 0], path[:, 1]), path[:, 2], ls=":", color=c, lw=1.0)
            for n in (1000, 10000):
                p = best_case_gamma(b, [n])[0]
                ax.plot(max(p[0], p[1]), p[2], marker="|", color=c, ms=8)
                if r["level"] == levels[-1]:
                    ax.annotate(f"N1hat {n:,}", (max(p[0], p[1]), p[2]), xytext=(4, 2), textcoords="offset points",
                                fontsize=7, color="0.3")
    for r in table.get("nominal_whatif") or []:
        b = r["budget"]
        gam = np.array(budget_gamma(b))
        ax.plot(max(gam[0], gam[1]), gam[2], marker="*", color=color.get(r["level"], "k"), ms=13, ls="none",
                mec="k", mew=0.5)
        ax.annotate(f"refined nominal, N1hat {r['n1hat']}", (max(gam[0], gam[1]), gam[2]), xytext=(6, 4),
                    textcoords="offset points", fontsize=7, color="0.3")
    for lv in levels:
        ax.plot([], [], "s", color=color[lv], label=f"noise level {lv:g}")
    for n in sorted({r["n1hat"] for r in rows}):
        ax.plot([], [], marker=markers.get(n, "v"), color="0.5", ls="none", label=f"N1hat {n} (measured)")
    ax.plot([], [], ":", color="0.4", label="best case as N1hat grows (true mean gap 0)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(0.005, 0.3)
    ax.set_ylim(0.02, 1.5)
    ax.set_xlabel("stochastic gamma max, larger of x and y [m per 0.3 s]")
    ax.set_ylabel("stochastic gamma max, heading [rad per 0.3 s]")
    ax.set_title("TurtleBot: the stochastic certificate (gap's Lipschitz term) against the gaps that win x0",
                 fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    out_dir.mkdir(parents=True, exist_ok=True)
    return save(fig, Path(out_dir), name)


def write_outputs(out: Path, projections: list, plot: bool = True) -> dict:
    """Rewrite OUT/separation.json from the finished points; print the text table; draw the figure."""
    from simgap import fileio

    # projections of earlier calls stay until their point is run (a call covers only its own points)
    prev = (read_json(Path(out) / TABLE) or {}).get("projected_not_run") or []
    keep = {(p["level"], p["n1hat"]): p for p in prev if isinstance(p, dict) and "level" in p and "n1hat" in p}
    keep.update({(p["level"], p["n1hat"]): p for p in projections})
    table = build_table(out, [])
    done = {(r["level"], r["n1hat"]) for r in table["rows"]}
    table["projected_not_run"] = [p for k, p in sorted(keep.items()) if k not in done]
    fileio.write_json(Path(out) / TABLE, table)
    print(text_table(table), flush=True)
    if plot and table["rows"]:
        print("figure: " + ", ".join(str(p) for p in figure(table, Path(out))), flush=True)
        if any(r.get("budget") for r in table["rows"]):
            print("figure: " + ", ".join(str(p) for p in budget_figure(table, Path(out))), flush=True)
    return table


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="folder of the scan (created; re-run to resume)")
    ap.add_argument("--levels", type=float, nargs="+", default=list(LEVELS),
                    help="noise levels (0: the gazebo profile, 1: gazebo_stress's noise; default %(default)s)")
    ap.add_argument("--n1hat", type=int, nargs="+", default=[100],
                    help="runs per (heading, input) pair; 400 and 1000 on request (default 100)")
    ap.add_argument("--rollouts", type=int, default=1000, help="closed-loop runs per controller (default 1000)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--audit-points", type=int, help="audit points per certificate (default: the gazebo profile's 100)")
    ap.add_argument("--audit-runs", type=int, help="simulator runs per audit point (default: the profile's 200)")
    ap.add_argument("--lhat-pairs", type=int,
                    help="pairs for Lhat_fhat (default: the profile's 300); reduced runs only")
    ap.add_argument("--max-hours", type=float, default=2.0, help="points projected longer are not run (default 2)")
    ap.add_argument("--table-only", action="store_true", help="only rebuild the table and figure from --out")
    ap.add_argument("--project-only", action="store_true",
                    help="run nothing: add the points' projected wall times to the table (kept beside the finished "
                         "points' rows) and rebuild it")
    ap.add_argument("--frontier", action="store_true",
                    help="only find which constant gaps win x0 (bisection over gamma_x = gamma_y per gamma_theta, "
                         "syntheses only, no simulation) into OUT/frontier.json, then rebuild the table")
    ap.add_argument("--nominal", type=Path, metavar="SYSTEM.json",
                    help="only certify the finished points' (--levels x --n1hat) data against this nominal model "
                         "(a refined system from `simgap refine`) and synthesize: does x0 get won? Into "
                         "OUT/nominal_whatif.json")
    ap.add_argument("--no-figure", action="store_true")
    a = ap.parse_args(argv)
    bad = [lv for lv in a.levels if not (math.isfinite(lv) and 0 <= lv <= 5)]
    small = [f"--{k.replace('_', '-')} {v}" for k, v in (("audit_points", a.audit_points), ("audit_runs", a.audit_runs),
                                                          ("lhat_pairs", a.lhat_pairs)) if v is not None and v < 2]
    if bad or any(n < 2 for n in a.n1hat) or a.rollouts < 1 or a.max_hours <= 0 or small:
        print(f"error: need noise levels in [0, 5] (got {bad or a.levels}), N1hat >= 2 (got {a.n1hat}), "
              f"--rollouts >= 1 (got {a.rollouts}), --max-hours > 0 (got {a.max_hours}), audit points, runs "
              f"and Lhat pairs >= 2 (got {', '.join(small) or 'fine'})", file=sys.stderr)
        return 2
    audit = {k: v for k, v in (("points", a.audit_points), ("runs", a.audit_runs)) if v is not None}
    out = Path(a.out)
    if a.nominal is not None:
        from simgap import fileio
        if not a.nominal.is_file():
            print(f"error: --nominal {a.nominal}: no such file", file=sys.stderr)
            return 2
        prev = read_json(out / WHATIF) or {"rows": []}
        rows = [r for r in prev["rows"] if not (r["level"] in a.levels and r["n1hat"] in a.n1hat
                                                and r["system_file"] == a.nominal.name)]
        from simgap.errors import SimgapError
        try:
            rows += [nominal_whatif(out, lv, n, a.nominal, a.rollouts) for lv in a.levels for n in a.n1hat]
        except SimgapError as e:
            print(f"error: --nominal {a.nominal}: {e}", file=sys.stderr)
            return 2
        fileio.write_json(out / WHATIF, {"rows": rows})
        a.table_only = True
    if a.frontier:
        from simgap import fileio
        out.mkdir(parents=True, exist_ok=True)
        fileio.write_json(out / FRONTIER, win_frontier())
        a.table_only = True
    if a.table_only:
        if not out.is_dir():
            print(f"error: {out} is not a scan folder", file=sys.stderr)
            return 2
        write_outputs(out, (read_json(out / TABLE) or {}).get("projected_not_run", []), plot=not a.no_figure)
        return 0

    from simgap import fileio
    from simgap.errors import SimgapError
    from simgap.pipeline import run_experiment

    out.mkdir(parents=True, exist_ok=True)
    points = [(lv, n) for n in sorted(set(a.n1hat)) for lv in sorted(set(a.levels))]
    plan = []
    for lv, n in points:
        exps = experiments(lv, n, audit, a.lhat_pairs)
        cfg = point_config(lv, n, a.rollouts, exps)
        folder = out / point_name(lv, n)
        left = [t for t in TERMS if not finished(folder / t, cfg, t)]
        plan.append((lv, n, exps, cfg, folder, left))
    n_pairs = plan[0][2]["paper"].plan().n_pairs
    rate, stages, how = calibration(out, n_pairs)

    def left_to_collect(folder, left):
        return 1.0 - collected(folder / "paper" / "data") if "paper" in left else 0.0

    total = sum(project_seconds(n_pairs, n, a.rollouts, len(left), left_to_collect(folder, left), rate, stages)
                for lv, n, _, _, folder, left in plan)
    print(f"scan: {len(points)} point(s) ({', '.join(f'{lv:g}' for lv in sorted(set(a.levels)))} x N1hat "
          f"{sorted(set(a.n1hat))}), {sum(not p[5] for p in plan)} finished; projected wall time of the rest "
          f"{total / 3600:.2f} h ({how})", flush=True)
    projections = []
    t_scan = time.perf_counter()
    for lv, n, exps, cfg, folder, left in plan:
        if not left:
            print(f"[{point_name(lv, n)}] finished earlier: skipped", flush=True)
            continue
        rate, stages, how = calibration(out, n_pairs)
        sec = project_seconds(n_pairs, n, a.rollouts, len(left), left_to_collect(folder, left), rate, stages)
        if sec > a.max_hours * 3600 or a.project_only:
            projections.append({"level": lv, "n1hat": n, "hours": round(sec / 3600, 2), "max_hours": a.max_hours,
                                "how": how, "project_only": bool(a.project_only and sec <= a.max_hours * 3600)})
            print(f"[{point_name(lv, n)}] projected {sec / 3600:.1f} h" + ("" if a.project_only else
                  f" > {a.max_hours:g} h") + ": not run", flush=True)
            continue
        print(f"[{point_name(lv, n)}] noise {cfg['simulator']['noise']}, randomize {cfg['simulator']['randomize']}; "
              f"projected {sec / 60:.0f} min ({how})", flush=True)
        folder.mkdir(exist_ok=True)
        if read_json(folder / "point.json") != cfg:
            fileio.write_json(folder / "point.json", cfg)
        t0 = time.perf_counter()
        for term in TERMS:
            if term not in left:
                continue
            try:
                run_experiment(exps[term], folder / term, workers=a.workers, n_rollouts=a.rollouts,
                               stores_from=None if term == "paper" else folder / "paper",
                               log=lambda msg, t=term: print(f"  [{t}] {msg}", flush=True))
            except SimgapError as e:
                print(f"error: {point_name(lv, n)}, {term}'s term: {e}", file=sys.stderr)
                return 1
            except KeyboardInterrupt:
                print(f"interrupted in {point_name(lv, n)}, {term}'s term: run the same command again to resume "
                      "(finished points are skipped, the collection resumes from its stores)", file=sys.stderr)
                return 130
            write_outputs(out, projections, plot=False)
        print(f"[{point_name(lv, n)}] done in {(time.perf_counter() - t0) / 60:.1f} min", flush=True)
    print(f"scan wall time this call: {(time.perf_counter() - t_scan) / 60:.1f} min", flush=True)
    write_outputs(out, projections, plot=not a.no_figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())

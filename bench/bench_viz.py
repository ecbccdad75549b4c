"""Benchmark of the app and the recorder (run by hand; numbers go to docs/app.md).

    python bench/bench_viz.py                        # pendulum case-study data (collected once into runs/)
    python bench/bench_viz.py --dataset PATH         # any dataset (.npz or store)
    python bench/bench_viz.py --profile small        # quick check on the small profile
    python bench/bench_viz.py --browser results/pendulum-small   # frame time and a change, in chromium

1. Cheap changes: the time from a delta or basis change in the GUI (a handle's value set from
   Python, which fires the same callback as the browser) to the updated gamma surface in the
   scene: re-certification from the cached data on the job thread + redrawing the surface and
   the data points. Several distinct values (no cache hits), median and max reported; then the
   time of a cache hit (switching back to a value seen before).
2. Recording: 1000 closed-loop rollouts x 1000 steps of the pendulum (no-gap controller,
   numpy simulator) logged to an .rrd (column-wise), time and file size; the rollouts
   themselves are computed first and not timed.
3. ``--browser RESULTS``: frame times in headless chromium (software WebGL) with the run's
   winning domain and ``--draw`` rollouts drawn, and a typed confidence change until the new
   surface is in the page (see :func:`bench_browser`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def load_or_collect(args):
    from simgap.collect import collect
    from simgap.config import load_experiment
    from simgap.dataset import load_dataset
    if args.dataset:
        return load_dataset(args.dataset)
    exp = load_experiment("pendulum", args.profile)
    plan = exp.plan()
    store = REPO / "runs" / f"bench-viz-pendulum-{args.profile}"
    t = time.perf_counter()
    res = collect(plan, store, executor="local")
    print(f"data: {plan.n_pairs:,} pairs x {plan.n_runs} runs in store {store} "
          f"({'computed' if res.computed else 'reused'}, {time.perf_counter() - t:.1f} s)", flush=True)
    return res.dataset(exp.system)


def bench_cheap_changes(ds, repeats: int):
    from simgap_viz.app import SimgapApp
    app = SimgapApp(port=0, executor="serial")
    try:
        app.set_dataset(ds)
        cp = app.panels["certificate"]
        t = time.perf_counter()
        app.certify()
        app.wait(600)
        first = time.perf_counter() - t
        cp.mode.value = "per dimension"  # pre-filled with the certificate's deltas (same gamma)
        app.wait(600)
        cp.delta2.value = "0.01, 0.02"
        app.wait(600)

        def timed(change):
            t0 = time.perf_counter()
            change()
            app.wait(600)  # the job's finish redraws the surface (refresh_result_layers in _accept)
            return time.perf_counter() - t0

        rows = {"delta": [], "degree": [], "terms": []}
        for k in range(repeats):
            d = f"{0.010 + 0.001 * (k + 1):.3f}, {0.020 + 0.002 * (k + 1):.3f}"
            rows["delta"].append(timed(lambda: setattr(cp.delta1, "value", d)))
        for deg in (1, 3, 4)[:max(1, min(3, repeats))]:
            rows["degree"].append(timed(lambda: setattr(cp.degree, "value", deg)))
        for terms in ("sin(x1)", "cos(x1)", "sin(x1), x1^5")[:max(1, min(3, repeats))]:
            rows["terms"].append(timed(lambda: setattr(cp.terms, "value", terms)))
        hit = timed(lambda: setattr(cp.terms, "value", "sin(x1)"))
        assert app.status.content.startswith("certify: from cache"), app.status.content
        # the app's share: redrawing the gamma surface and the data points of the slice
        from simgap_viz.layers import scene
        draws = []
        for _ in range(5):
            t0 = time.perf_counter()
            scene.draw_gamma(app)
            draws.append(time.perf_counter() - t0)
        # the engine's share: certify alone on the same data and options
        from simgap_viz import engine
        from simgap_viz.jobs import JobContext
        eng = []
        for k in range(3):
            st = app.settings.replace(delta1=(0.02 + 0.001 * k, 0.03), delta2=(0.02, 0.03))
            t0 = time.perf_counter()
            engine.certify(ds, st, JobContext(name="bench"))
            eng.append(time.perf_counter() - t0)
        errs = [n for n in app.notifications if n[2] == "red"]
        if errs:
            print("notifications:", errs, file=sys.stderr)
        return {"first_certify_s": first, "cache_hit_s": hit, "redraw_median_s": statistics.median(draws),
                "engine_certify_median_s": statistics.median(eng),
                **{k: {"n": len(v), "median_s": statistics.median(v), "max_s": max(v)} for k, v in rows.items()}}
    finally:
        app.stop()


FRAME_JS = """(ms) => new Promise(r => { const t = []; let last = performance.now();
  function f(now) { t.push(now - last); last = now; if (t.length < 400 && now - t0 < ms) requestAnimationFrame(f);
                    else r(t.slice(1)); }
  const t0 = performance.now(); requestAnimationFrame(f); })"""


def bench_browser(results: str, n_draw: int, repeats: int):
    """In headless chromium (software WebGL): (1) frame times with the run's winning domain and
    each count in ``n_draw`` of rollouts drawn, in one browser session so that the counts compare
    under the same load (requestAnimationFrame intervals while the camera moves); (2) a confidence change typed into the page until the new
    surface is in the browser: the status line (sent after the surface) shows in the page, plus
    one animation frame. The 0.5 s typing debounce is part of it and reported."""
    from playwright.sync_api import sync_playwright

    from simgap_viz import screenshot as S
    from simgap_viz.app import SimgapApp
    from simgap_viz.results import load_run
    app = SimgapApp(port=0, executor="serial")
    try:
        app.load_run(load_run(results))
        app.set_view(dim=1)
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path=S.CHROMIUM, args=S.ARGS)
            page = S.open_page(b, app.url)
            S.show_tab(page, "View")
            frames = {}
            for nd in n_draw:
                app.set_time(n_draw=nd)
                time.sleep(2.0)
                frames[nd] = []
                for k in range(repeats):  # orbit the camera so that every frame is redrawn
                    for c in app.server.get_clients().values():
                        c.camera.position = tuple(float(v) for v in (2.5 * math.cos(k), -2.5, 2.0))
                    frames[nd] += page.evaluate(FRAME_JS, 4000)
            S.show_tab(page, "Certificate", settle=1.0)
            conf = page.locator('xpath=//label[normalize-space(text())="Confidence"]'
                                '/ancestor::div[contains(@class, "mantine-Flex-root")][1]//input').first
            changes = []
            for k in range(repeats):
                before = app.status.content
                value = f"{0.9 + 0.01 * (k + 1):.2f}"
                t0 = time.perf_counter()
                conf.fill(value)
                conf.press("Tab")
                deadline = time.time() + 120
                while not (app.status.content != before and app.status.content.startswith("certify: done")) \
                        and time.time() < deadline:
                    time.sleep(0.01)
                # the status line is sent after the new surface: once the page shows it, the surface is there
                page.wait_for_function("(s) => document.body.innerText.includes(s)", arg=app.status.content,
                                       timeout=120_000)
                page.evaluate("() => new Promise(r => requestAnimationFrame(() => r(0)))")
                changes.append(time.perf_counter() - t0)
            b.close()
    finally:
        app.stop()
    return {"frame_ms_by_rollouts_drawn": {nd: {"frames": len(f), "median": statistics.median(f) if f else None,
                                                "max": max(f) if f else None} for nd, f in frames.items()},
            "confidence_change_to_surface_s": {"n": len(changes), "median": statistics.median(changes),
                                               "max": max(changes), "includes_debounce_s": 0.5}}


def bench_recording(R: int, T: int):
    from simgap_viz import engine
    from simgap_viz.jobs import JobContext
    from simgap_viz.record import record_run
    from simgap_viz.settings import Settings
    from simgap.config import load_experiment

    exp = load_experiment("pendulum", "small")
    s = Settings(use_gap=False, eta=(0.005, 0.01), n_rollouts=R, horizon=T)
    ctx = JobContext(name="bench")
    system = exp.system
    spec = engine.default_spec(system)
    t = time.perf_counter()
    syn = engine.synthesize(system, spec, None, s, ctx)
    ro = engine.rollout(system, spec, syn, s, ctx, experiment=exp)
    print(f"rollouts computed in {time.perf_counter() - t:.1f} s (not part of the logging time)", flush=True)
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "rollouts.rrd"
        info = record_run(out, system, rollouts=ro)
        full = Path(d) / "full.rrd"
        info_full = record_run(full, system, spec=spec, synthesis=syn, rollouts=ro)
    return {"rollouts": R, "steps": T + 1, "log_s": info["seconds"], "bytes": info["bytes"],
            "with_winning_domain_log_s": info_full["seconds"], "with_winning_domain_bytes": info_full["bytes"]}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", default=None)
    p.add_argument("--profile", default="paper", help="pendulum experiment profile when collecting (default paper)")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--rollouts", type=int, default=1000)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--skip-certify", action="store_true")
    p.add_argument("--browser", default=None, metavar="RESULTS",
                   help="a finished `simgap run` folder: measure frame times and a change end to end in chromium")
    p.add_argument("--draw", default="0,100,1000", help="rollouts drawn for the frame times, comma separated")
    args = p.parse_args(argv)
    out = {"machine": {"cores": os.cpu_count(), "python": platform.python_version()}}
    if args.browser:
        out["browser"] = bench_browser(args.browser, [int(d) for d in args.draw.split(",")], args.repeats)
        print(json.dumps(out, indent=1))
        return
    if not args.skip_certify:
        ds = load_or_collect(args)
        out["data"] = {"pairs": ds.K, "n_runs": ds.n_runs, "epsilon": ds.epsilon}
        out["cheap_changes"] = bench_cheap_changes(ds, args.repeats)
        print(json.dumps(out["cheap_changes"], indent=1), flush=True)
    out["recording"] = bench_recording(args.rollouts, args.steps)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

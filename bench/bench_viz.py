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


# One frame per animation frame: the camera turns a little (alternating) before each, so that
# viser's on-demand loop renders every frame; returns the intervals and three.js' counts of the
# last rendered frame (draw calls, triangles, line segments, points).
FRAME_JS = """async (n) => {
  const m = window.__viserMutable, info = window.__viserTestpoints.rendererInfo;
  const t = []; let last = performance.now(), k = 0;
  return await new Promise(res => { function f(now) {
    if (k > 0) t.push(now - last);
    last = now;
    if (k++ >= n) { res({ms: t, calls: info.render.calls, triangles: info.render.triangles,
                         lines: info.render.lines, points: info.render.points}); return; }
    m.cameraControl.rotate(0.01 * (k % 2 ? 1 : -1), 0, false);
    requestAnimationFrame(f); }
  requestAnimationFrame(f); }); }"""


def chromium_cpu_s() -> float:
    """CPU seconds used so far by the chromium processes below this one (Linux /proc): the
    browser's own work, which other jobs on a shared machine inflate much less than wall time."""
    kids = {}
    for p in os.listdir("/proc"):
        if not p.isdigit():
            continue
        try:
            with open(f"/proc/{p}/stat") as f:
                st = f.read()
        except OSError:
            continue
        r = st.rfind(")")
        fields = st[r + 2:].split()
        kids.setdefault(int(fields[1]), []).append((int(p), st[st.find("(") + 1:r], int(fields[11]) + int(fields[12])))
    total, stack = 0, [os.getpid()]
    while stack:
        for pid, comm, ticks in kids.get(stack.pop(), []):
            total += ticks if "chrom" in comm.lower() else 0
            stack.append(pid)
    return total / os.sysconf("SC_CLK_TCK")


def frames(page, n: int) -> dict:
    """``n`` rendered frames: median and max wall interval, chromium CPU per frame, counts."""
    page.evaluate(FRAME_JS, 3)  # warm-up: uploads and shader compiles after a scene change
    c0 = chromium_cpu_s()
    r = page.evaluate(FRAME_JS, n)
    cpu = chromium_cpu_s() - c0
    ms = r.pop("ms")
    return {"median_ms": round(statistics.median(ms), 1), "max_ms": round(max(ms), 1),
            "cpu_ms_per_frame": round(1000 * cpu / n, 1), **r}


def draw_previous(app) -> None:
    """The previous drawing of the same results, for a same-run comparison: the default light's
    shadow maps on, the rollout subset as viser line segments (six triangles each), the gamma
    surface as a lit, textured PBR mesh."""
    import numpy as np
    import trimesh
    from PIL import Image

    from simgap_viz import engine
    from simgap_viz.layers import geometry as G
    from simgap_viz.layers import scene
    sc = app.server.scene
    sc.configure_default_lights(enabled=True, cast_shadow=True)
    traj, failed, _, _ = engine.rollout_arrays(app.results["rollout"])
    idx = G.rollout_subset(failed, int(app.view["n_draw"]))
    if idx.size:
        seg = G.rollout_segments(G.Frame(app.system), traj[idx], failed[idx], max_segments=40000)
        seg["points"][..., 2] = 0.004
        sc.add_line_segments("/rollouts/all", points=seg["points"], colors=seg["colors"], thickness=1.5,
                             thickness_units="screen")
    v = app.view
    surf = G.gamma_surface(app.system, engine.gamma_function(app.results["certify"]), v["dim"], v["a"], v["b"],
                           v["fixed"], res=scene.SURFACE_RES)
    verts = surf["vertices"].copy()
    verts[:, 2] *= v["zscale"]
    t = (surf["values"] - surf["values"].min()) / max(float(np.ptp(surf["values"])), 1e-300)
    tex = Image.fromarray(np.repeat(G.colormap(np.linspace(0, 1, 256))[None], 4, axis=0))
    mat = trimesh.visual.material.PBRMaterial(baseColorTexture=tex, metallicFactor=0.0, roughnessFactor=0.9,
                                              doubleSided=True, alphaMode="BLEND", baseColorFactor=[255, 255, 255, 215])
    uv = np.stack([np.clip(t, 0.002, 0.998), np.full(t.shape, 0.5)], axis=1)
    sc.add_mesh_trimesh("/gamma/surface", trimesh.Trimesh(vertices=verts, faces=surf["faces"], process=False,
                                                          visual=trimesh.visual.TextureVisuals(uv=uv, material=mat)))
    app._drawn_keys = {}  # the app's next redraw sends its own layers again


def bench_browser(results: str, n_draw: list, repeats: int, n_frames: int = 20):
    """In headless chromium (software WebGL, device pixel ratio pinned to 1, 1280 x 800):

    (1) frame times with the run's winning domain, gamma surface, data gaps and each count in
    ``n_draw`` of rollouts drawn, and the same scene in the previous drawing
    (:func:`draw_previous`), alternating in one browser session so that they compare under the
    same load. A frame is one requestAnimationFrame interval while the camera turns every frame
    (viser renders on demand); also chromium's CPU time per frame and three.js' counts.
    (2) a confidence typed into the page until the new surface is in the browser: the status
    line (sent after the surface) shows in the page, plus one animation frame. A valid number
    applies without the app's typing wait (invalid ones wait 0.5 s); reported split: typing ->
    app, certify job (the engine plus the redraw), and job end -> page.
    """
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
            page = S.open_page(b, app.url + "/?fixedDpr=1")
            S.show_tab(page, "View")
            out = {}
            for k in range(repeats):
                for nd in n_draw:
                    for kind in ("now", "previous"):
                        app.set_time(n_draw=nd)
                        if kind == "previous":
                            draw_previous(app)
                        else:
                            app.refresh_result_layers()
                            app.server.scene.configure_default_lights(enabled=True, cast_shadow=False)
                        time.sleep(1.5)
                        out.setdefault(f"{kind} {nd} rollouts", []).append(frames(page, n_frames))
                        print(f"frames {kind} {nd}: {out[f'{kind} {nd} rollouts'][-1]}", file=sys.stderr, flush=True)
            app.refresh_result_layers()
            app.server.scene.configure_default_lights(enabled=True, cast_shadow=False)
            S.show_tab(page, "Certificate", settle=3.0)
            frames(page, 5)  # the page has taken in the redraw above before the clock starts
            conf = page.locator('xpath=//label[normalize-space(text())="Confidence"]'
                                '/ancestor::div[contains(@class, "mantine-Flex-root")][1]//input').first
            seen = {}
            orig = app.update_settings

            def update_settings(**kw):
                seen.setdefault("app", time.perf_counter())
                return orig(**kw)
            app.update_settings = update_settings
            changes = []
            for k in range(repeats):
                seen.clear()
                before = app.status.content
                value = f"{0.9 + 0.01 * (k + 1):.2f}"
                t0 = time.perf_counter()
                conf.fill(value)
                conf.press("Tab")
                deadline = time.time() + 120
                while not (app.status.content != before and app.status.content.startswith("certify: done")) \
                        and time.time() < deadline:
                    time.sleep(0.005)
                t_job = time.perf_counter()
                # the status line is sent after the new surface: once the page shows it, the surface is there
                page.wait_for_function("(s) => document.body.innerText.includes(s)", arg=app.status.content,
                                       timeout=120_000)
                page.evaluate("() => new Promise(r => requestAnimationFrame(() => r(0)))")
                t1 = time.perf_counter()
                job = app.timings.get("certify", float("nan"))
                changes.append({"total_s": t1 - t0, "typing_to_app_s": seen.get("app", t0) - t0,
                                "certify_job_s": job, "job_end_to_page_s": t1 - t_job})
                print(f"change {value}: {changes[-1]}", file=sys.stderr, flush=True)
            b.close()
    finally:
        app.stop()

    def med(rows, key):
        return round(statistics.median(r[key] for r in rows), 1)
    frames_out = {k: {"median_ms": med(v, "median_ms"), "cpu_ms_per_frame": med(v, "cpu_ms_per_frame"),
                      "max_ms": max(r["max_ms"] for r in v), "calls": v[-1]["calls"],
                      "triangles": v[-1]["triangles"], "lines": v[-1]["lines"], "points": v[-1]["points"]}
                  for k, v in out.items()}
    def ratio(nd, key):
        return round(frames_out[f"previous {nd} rollouts"][key] / frames_out[f"now {nd} rollouts"][key], 2)
    ratios = {f"previous / now, {nd} rollouts": {"wall": ratio(nd, "median_ms"), "cpu": ratio(nd, "cpu_ms_per_frame")}
              for nd in n_draw}
    return {"load_average": os.getloadavg(), "frames": frames_out, "ratios": ratios,
            "confidence_change": {"n": len(changes),
                                  **{k: round(statistics.median(c[k] for c in changes), 3) for k in changes[0]},
                                  "max_total_s": round(max(c["total_s"] for c in changes), 3)}}


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
    p.add_argument("--draw", default="0,1000", help="rollouts drawn for the frame times, comma separated")
    args = p.parse_args(argv)
    out = {"machine": {"cores": os.cpu_count(), "python": platform.python_version()}}
    if args.browser:
        draw = [int(d) for d in args.draw.split(",")]
        br = out["browser"] = bench_browser(args.browser, draw, min(args.repeats, 3))
        print(json.dumps(out, indent=1))
        f, c = br["frames"][f"now {max(draw)} rollouts"], br["confidence_change"]
        print(f"target frame <= 100 ms with {max(draw)} rollouts + winning domain: median {f['median_ms']} ms "
              f"(chromium CPU {f['cpu_ms_per_frame']} ms/frame; previous drawing "
              f"{br['frames'][f'previous {max(draw)} rollouts']['median_ms']} ms)\n"
              f"target delta change <= 1 s end to end: median {c['total_s']} s (certify job {c['certify_job_s']} s, "
              f"typing to app {c['typing_to_app_s']} s, job end to page {c['job_end_to_page_s']} s)\n"
              f"load average {', '.join(f'{x:.1f}' for x in br['load_average'])} (2 cores shared: compare ratios)")
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

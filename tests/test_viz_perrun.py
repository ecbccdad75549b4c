"""The app's per-run view: the p_cert map, the p_emp markers, the table and the p_emp-against-p_cert plot.

A real per-run results folder is made once with ``simgap run`` (tests/data/perrun_gui.toml: numpy
pendulum, about half a minute) and opened in the app. The checks compare what the app sends to
the browser with the engine's files, refuse tampered files, and look at the pixels in headless
chromium.
"""

import io
import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from simgap.cli import main
from simgap.errors import SimgapError

TOML = Path(__file__).parent / "data" / "perrun_gui.toml"


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("perrun_gui") / "out"
    assert main(["run", str(TOML), "--out", str(out), "--no-record"]) == 0
    return out


@pytest.fixture
def app(run_dir):
    from simgap_viz.app import SimgapApp
    from simgap_viz.results import load_run
    a = SimgapApp(port=0, executor="serial")
    a.load_run(load_run(run_dir))
    yield a
    a.stop()


def test_what_the_app_sends_is_what_the_engine_wrote(app, run_dir):
    from simgap.perrun.value_iteration import PerRunController
    from simgap_viz.layers import perrun as layer
    from simgap_viz.layers.geometry import Frame
    from simgap_viz.panels import perrun as panel

    summary = json.loads((run_dir / "summary.json").read_text())["per_run"]
    ctl = PerRunController.load(run_dir / "controller_perrun.npz")
    pr = app.run.per_run
    assert list(pr.controllers) == list(summary["controllers"])
    drawn = app.panels["perrun"].show()
    # the interval MDP states what it proved in its own words: P(success within H) >= its p_cert
    st = ctl.statement()
    assert st.method == "perrun" and st.per_run.horizon == ctl.horizon and st.headline in app.panels["perrun"].legend.content
    assert st.per_run.p_cert == pytest.approx(float(ctl.p_cert.max()) if ctl.meta.get("x0") is None else
                                              float(ctl.certified(np.asarray(ctl.meta["x0"])[None])[0]))
    # the map: one pixel block per grid cell, p_cert of that cell on the color scale
    m = drawn["map"]
    g = ctl.grid
    assert m["p"].shape == tuple(g.shape)
    np.testing.assert_array_equal(m["p"], ctl.p_cert.reshape(g.shape))
    k = m["image"].shape[1] // g.shape[0]
    assert m["image"].shape == (g.shape[1] * k, g.shape[0] * k, 3)
    # pixel (row, col) shows cell (i = col // k, j = n2 - 1 - row // k): +x2 up
    i, j = np.unravel_index(np.argmax(ctl.p_cert), g.shape)
    np.testing.assert_array_equal(m["image"][(g.shape[1] - 1 - j) * k, i * k], layer.pcolormap(ctl.p_cert.max()))
    assert 0 < ctl.p_cert.max() <= 1 and (ctl.p_cert == 0).any()  # both ends of the scale are on the map
    # the markers: the per-run controller's validated states at their places, colored by p_emp
    st = summary["controllers"]["perrun"]["states"]
    mk = drawn["markers"]
    np.testing.assert_allclose(mk["points"][:, :2], Frame(app.system).xy(np.array([s["x0"] for s in st]))[:, :2],
                               atol=1e-6)
    np.testing.assert_array_equal(mk["colors"], layer.pcolormap([s["p_emp"] for s in st]))
    # the color scale: 0 red, 0.5 yellow, 1 green, monotone in between
    c = layer.pcolormap(np.array([0.0, 0.5, 1.0])).astype(int)
    assert c[0, 0] > 150 > c[0, 1] and c[1, 0] > 200 and c[1, 1] > 200 and c[2, 1] > 100 > c[2, 0]
    # the plot: one point per (controller with p_cert, state), at x = p_cert, y = p_emp, with
    # its interval as a bar of points from lo to hi at the same x; the diagonal from 0 to 1
    pd = panel.plot_data(pr)
    x, *ys = pd["data"]
    assert np.all(np.diff(x) >= 0) and all(len(y) == len(x) for y in ys)
    assert pd["names"] == ["run_baseline", "perrun"]  # the gap controllers state no p_cert
    for name, y in zip(pd["names"], ys):
        pts = sorted(zip(x[np.isfinite(y)], y[np.isfinite(y)]))
        want = sorted((s["p_cert"], s["p_emp"]) for s in summary["controllers"][name]["states"])
        np.testing.assert_allclose(pts, want)
    ci, diag = ys[-2], ys[-1]
    for s in st:
        bar = ci[np.isclose(x, s["p_cert"]) & np.isfinite(ci)]
        assert bar.min() <= s["ci95"][0] + 1e-12 and bar.max() >= s["ci95"][1] - 1e-12
    assert np.all(ci[np.isfinite(ci)] >= 0) and np.all(ci[np.isfinite(ci)] <= 1)
    np.testing.assert_array_equal(x[np.isfinite(diag)], [0.0, 1.0])
    np.testing.assert_array_equal(diag[np.isfinite(diag)], [0.0, 1.0])
    p = app.panels["perrun"]
    assert p.plot.visible and np.array_equal(p.plot.data[0], pd["data"][0])
    # the tables: every state of the chosen controller with its numbers, the soundness count
    for s in st:
        assert f"{s['p_emp']:.4f} [{s['ci95'][0]:.4f}, {s['ci95'][1]:.4f}]" in p.states.content
    n_ok = sum(s["p_emp"] >= s["p_cert"] - 3 * max(s["se"], 1 / s["n_rollouts"]) for s in st)
    assert f"| per-run (interval MDP) | {st[0]['p_cert']:.4f} |" in p.overview.content
    assert f"{n_ok} / {len(st)} |" in p.overview.content


def test_map_of_a_three_dimensional_grid_shows_the_best_third_coordinate():
    """TurtleBot-like (x, y, heading): each (x, y) column shows the largest p_cert over the headings."""
    from types import SimpleNamespace

    from simgap.synthesis.grid import UniformGrid
    from simgap_viz.layers import perrun as layer
    g = UniformGrid([0.0, 0.0, -3.0], [4.0, 2.0, 3.0], [1.0, 0.5, 1.0])
    p = np.random.default_rng(0).random(g.size)
    m = layer.pcert_map(SimpleNamespace(grid=g, p_cert=p))
    best = p.reshape(g.shape).max(axis=2)
    np.testing.assert_array_equal(m["p"], best)
    assert m["reduced_dims"] == 1 and m["p"].shape == g.shape[:2]
    k = m["image"].shape[0] // g.shape[1]
    assert m["image"].shape[:2] == (g.shape[1] * k, g.shape[0] * k)
    # top-left pixel: x1 first cell, x2 last cell
    np.testing.assert_array_equal(m["image"][0, 0], layer.pcolormap(best[0, -1]))
    np.testing.assert_array_equal(m["image"][-1, -1], layer.pcolormap(best[-1, 0]))
    np.testing.assert_allclose(m["lo"], g.domain_lo[:2])
    np.testing.assert_allclose(m["hi"], g.domain_hi[:2])


def test_toggles_and_the_controller_choice(app):
    from simgap_viz.layers import perrun as layer
    p = app.panels["perrun"]
    assert p.controller.options == ("deterministic gap", "stochastic gap (paper)", "union-bound baseline",
                                    "per-run (interval MDP)")
    p.controller.value = "stochastic gap (paper)"
    st = app.run.per_run.controllers["stochastic"]
    assert app.perrun_view["controller"] == "stochastic" and "stochastic gap" in p.states.content
    drawn = layer.draw(app)
    assert len(drawn["markers"]["points"]) == len(st.p_emp)
    assert p.states.content.count("\n| ") == len(st.p_emp) + 1  # header separator + one row per state
    legend = app.panels["view"].legend
    assert "| p_cert map | drawn over the winning map" in legend.content
    p.show_map.value = False
    p.show_markers.value = False
    assert app.perrun_view == {"map": False, "markers": False, "controller": "stochastic"}
    assert "p_cert map" not in legend.content and "| winning map |" in legend.content


def test_a_run_without_per_run_results_says_how_to_get_them(tmp_path, run_dir):
    from simgap_viz.app import SimgapApp
    from simgap_viz.results import load_run
    d = tmp_path / "run"
    shutil.copytree(run_dir, d)
    s = json.loads((d / "summary.json").read_text())
    del s["per_run"]
    (d / "summary.json").write_text(json.dumps(s))
    a = SimgapApp(port=0, executor="serial")
    try:
        a.load_run(load_run(d))
        p = a.panels["perrun"]
        assert a.run.per_run is None and p.note.visible and "[perrun]" in p.note.content
        assert not p.plot.visible and not p.show_map.visible
    finally:
        a.stop()


def _tampered(run_dir, tmp_path, edit) -> Path:
    d = tmp_path / "run"
    shutil.copytree(run_dir, d)
    edit(d)
    return d


def _summary_edit(fn):
    def edit(d):
        s = json.loads((d / "summary.json").read_text())
        fn(s["per_run"])
        (d / "summary.json").write_text(json.dumps(s))
    return edit


def _raise_pcert(d):
    import zipfile
    p = d / "controller_perrun.npz"
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["p_cert"] = np.minimum(arrays["p_cert"] + 0.05, 1.0)  # an optimistic edit, digest left as it was
    with open(p, "wb") as fh:
        np.savez(fh, **arrays)
    assert zipfile.is_zipfile(p)


@pytest.mark.parametrize("edit, msg", [
    (_raise_pcert, "modified after it was written"),
    (lambda d: (d / "controller_perrun.npz").unlink(), "controller_perrun.npz is missing"),
    (_summary_edit(lambda pr: pr["controllers"]["perrun"]["states"][1].update(p_cert=0.999)), "disagree"),
    (_summary_edit(lambda pr: pr["controllers"]["perrun"]["states"][0].update(p_emp=1.5)), "p_emp must be"),
    (_summary_edit(lambda pr: pr["controllers"]["stochastic"]["states"][0].update(p_emp=float("nan"))),
     "p_emp must be"),
    (_summary_edit(lambda pr: pr["controllers"]["perrun"]["states"][0].update(x0=[9.0, 0.0])), "outside X"),
    (_summary_edit(lambda pr: pr["controllers"]["perrun"]["states"][0].update(ci95=[0.0])), "ci95 must be"),
    (_summary_edit(lambda pr: pr["controllers"]["perrun"]["states"][0].update(ci95=[0.0, 0.1])), "outside its ci95"),
    (_summary_edit(lambda pr: pr.update(controllers=[])), "no 'controllers' table"),
])
def test_tampered_per_run_results_are_refused(run_dir, tmp_path, edit, msg):
    from simgap_viz.results import load_run
    d = _tampered(run_dir, tmp_path, edit)
    with pytest.raises(SimgapError, match=None) as e:
        load_run(d)
    assert msg in str(e.value)


def test_cli_gui_refuses_a_tampered_folder_with_a_message(run_dir, tmp_path):
    import subprocess
    import sys
    d = _tampered(run_dir, tmp_path, _raise_pcert)
    p = subprocess.run([sys.executable, "-m", "simgap", "gui", str(d), "--port", "0", "--exit-after", "0.3"],
                       capture_output=True, text=True, timeout=180)
    assert p.returncode != 0 and "modified after it was written" in p.stderr and "Traceback" not in p.stderr


def _count(img, rgb, tol):
    return int(np.count_nonzero(np.all(np.abs(img[..., :3].astype(int) - np.array(rgb)) <= tol, axis=-1)))


@pytest.mark.browser
def test_per_run_view_in_the_browser(run_dir, tmp_path):
    """Headless chromium: the map's colors for p_cert = 0 and for the largest p_cert inside the
    canvas, the markers' colors and rings, and the plot drawn (uPlot's chart object holds our
    series, and its canvas has the points' color); hiding the markers or the map removes them."""
    from PIL import Image
    from test_browser_app import _need_browser
    _need_browser()
    from playwright.sync_api import sync_playwright

    from simgap_viz import screenshot as S
    from simgap_viz.app import SimgapApp
    from simgap_viz.layers import perrun as layer
    from simgap_viz.results import load_run
    a = SimgapApp(port=0, executor="serial")
    try:
        a.load_run(load_run(run_dir))
        for layer_name in ("gamma", "data"):  # the surface and the gap points would cover the map
            a.panels["view"].checks[layer_name].value = False
        pr = a.run.per_run
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path=S.CHROMIUM, args=S.ARGS)
            try:
                page = S.open_page(b, a.url, 1280, 800)
                S.show_tab(page, "Per run")
                shot = np.asarray(Image.open(io.BytesIO(S.canvas_png(page, tmp_path / "perrun.png"))).convert("RGB"))
                page.get_by_text("p_emp against p_cert").first.wait_for(timeout=60_000)
                chart = page.evaluate("""() => {
                    const reg = (window.__viserTestpoints || {}).uplots || {};
                    for (const k in reg) {
                        const u = reg[k].chart;
                        if (u.series.some(s => s.label === 'p_emp = p_cert')) {
                            const cv = u.ctx.canvas;
                            return {labels: u.series.map(s => s.label), n: u.data[0].length,
                                    finite: u.data.map(d => Array.from(d).filter(Number.isFinite).length),
                                    png: cv.toDataURL('image/png')};
                        }
                    }
                    return null; }""")
                a.panels["perrun"].show_markers.value = False
                time.sleep(2.0)
                no_markers = np.asarray(Image.open(io.BytesIO(S.canvas_png(page))).convert("RGB"))
                a.panels["perrun"].show_map.value = False
                time.sleep(2.0)
                hidden = np.asarray(Image.open(io.BytesIO(S.canvas_png(page))).convert("RGB"))
            finally:
                b.close()
    finally:
        a.stop()
    w = shot.shape[1]
    scene, scene_nm, scene_hidden = (im[:, : int(w * 0.68)] for im in (shot, no_markers, hidden))  # left of the panel
    zero = layer.pcolormap(0.0)
    top = layer.pcolormap(float(pr.controller.p_cert.max()))
    assert _count(scene, zero, 12) > 5000, "the map's p_cert = 0 color is missing"
    assert _count(scene, top, 12) > 500, "the map's largest-p_cert color is missing"
    assert _count(scene_hidden, zero, 12) < 0.05 * _count(scene, zero, 12), "hiding the map left its colors"
    # the markers: their p_emp color (the per-run controller's rates are not on the map) and
    # their dark rings, gone when the markers are hidden
    p_emp = layer.pcolormap(float(np.min(pr.controllers["perrun"].p_emp)))
    assert _count(scene, p_emp, 10) > 100 > 10 > _count(scene_nm, p_emp, 10), "the markers' colors"
    assert _count(scene, layer.RING, 25) - _count(scene_nm, layer.RING, 25) > 100, "the markers' rings"
    # the plot: uPlot holds our series (one finite value per point, BAR_POINTS per interval bar,
    # the diagonal's two ends), and its canvas shows the per-run points
    from simgap_viz.panels.perrun import BAR_POINTS, COLORS
    assert chart is not None, "no uPlot chart with the diagonal series"
    assert chart["labels"][1:] == ["union-bound baseline", "per-run (interval MDP)", "95 % CI", "p_emp = p_cert"]
    n_pts = [int(np.isfinite(pr.controllers[c].p_cert).sum()) for c in ("run_baseline", "perrun")]
    assert chart["finite"][1:] == n_pts + [BAR_POINTS * sum(n_pts), 2]
    import base64
    plot = np.asarray(Image.open(io.BytesIO(base64.b64decode(chart["png"].split(",", 1)[1]))).convert("RGB"))
    blue = tuple(int(COLORS["perrun"][i:i + 2], 16) for i in (1, 3, 5))
    assert _count(plot, blue, 30) > 40, "the per-run points are not drawn"


def test_the_p_cert_figure_says_what_it_rests_on(run_dir, tmp_path, monkeypatch):
    """simgap plot's p_cert map is drawn p_cert: like the table, summary and legend it says that it is
    conditional on the estimated Lipschitz constants (issue: every drawn p_cert says so)."""
    from simgap_viz import figures
    from simgap_viz.results import load_run
    seen, real = {}, figures.save

    def capture(fig, out_dir, name):
        seen[name] = " ".join(ax.get_title() for ax in fig.axes)
        seen["overlaps"] = figures.text_overlaps(fig)
        return real(fig, out_dir, name)

    monkeypatch.setattr(figures, "save", capture)
    paths = figures.p_cert(load_run(run_dir), tmp_path)
    assert sorted(Path(p).suffix for p in paths) == [".pdf", ".png"]
    assert all(Path(p).stat().st_size > 0 for p in paths)
    assert "conditional on the estimated Lipschitz constants" in seen["p_cert"], seen
    assert seen["overlaps"] == [], seen["overlaps"]  # no label drawn over another

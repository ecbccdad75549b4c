"""`simgap gui RESULTS_DIR`: a finished `simgap run` folder opens with every stage loaded.

The folder is made by the real pipeline (simgap.pipeline.run_experiment) on a tiny pendulum
experiment with the numpy simulator (about 10 s).
"""

import subprocess
import sys

import numpy as np
import pytest

TINY = """
description = "tiny pendulum run for the app tests"
[system]
name = "pendulum"
steps = 1
[simulator]
kind = "numpy"
noise = { actuation_std = 0.01 }
effects = { linear = [[0.0, 0.0], [0.0, -0.1]] }
[collect]
epsilon = 0.01
n_runs = 20
seed = 1
executor = "serial"
[certify]
degree = 2
beta1 = 0.05
beta2 = 0.05
[audit]
points = 10
runs = 50
seed = 7
[synthesis]
spec = "invariance"
eta = [0.005, 0.01]
hold = 1
[rollout]
n = 50
horizon = 60
x0 = [0.05, 0.1]
seed = 11
"""


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from simgap.config import load_experiment
    from simgap.pipeline import run_experiment
    d = tmp_path_factory.mktemp("run")
    (d / "tiny.toml").write_text(TINY)
    exp = load_experiment(d / "tiny.toml", "base")
    summary = run_experiment(exp, d / "out", log=lambda m: None)
    assert all(summary["methods"][m]["winning_cells"] > 0 for m in ("stochastic", "deterministic"))
    return d / "out"


@pytest.fixture
def loaded(run_dir):
    from simgap_viz.app import SimgapApp
    from simgap_viz.results import load_run
    run = load_run(run_dir)
    app = SimgapApp(port=0, executor="serial")
    app.load_run(run)
    yield app, run
    app.stop()


def test_run_folder_opens_with_every_stage(loaded):
    app, run = loaded
    m = run.methods["stochastic"]
    assert app.results["collect"] is m.dataset and app.results["certify"] is m.certificate
    assert app.results["synthesize"] is m.synthesis and app.results["rollout"] is m.rollouts
    assert app.audit is m.audit and m.audit["certificate_method"] == "stochastic"
    assert app.settings.eta == (0.005, 0.01) and app.settings.x0 == (0.05, 0.1)
    assert app.settings.rollout_seed == 11 and app.panels["rollouts"].seed.value == 11  # the run's seed, shown
    # summaries are tables that wrap in the panel, not clipped code blocks
    for text in (app.panels["synthesis"].stats.content, app.panels["rollouts"].stats.content):
        assert "```" not in text and "|---|---|" in text
    assert "| winning |" in app.panels["synthesis"].stats.content
    assert "| spec held | 50 / 50 |" in app.panels["rollouts"].stats.content
    # the panel's plots: gamma along theta with the data gaps, the audit's margin histogram
    from simgap_viz.panels import plots
    cp = app.panels["certificate"]
    assert cp.slice_plot.visible and cp.audit_plot.visible
    xs, gam, gap = cp.slice_plot.data
    ok = np.isfinite(gap)
    assert ok.sum() == plots.gamma_slice(app, cp.slice_plot) > 0 and np.all(np.diff(xs) >= 0)
    assert np.all(gap[ok] >= 0) and np.isfinite(gam).sum() == 161
    centers, *counts = cp.audit_plot.data
    assert len(counts) == 2 and centers[-1] < 1.0 and np.all(np.diff(centers) > 0)
    # every audit point is counted once per dimension; a margin below 0 would land left of 0
    per = m.audit["per_dim"]["omega"]["margins"]
    assert counts[1].sum() == len(per) == m.audit["points"]
    assert (centers[counts[1] > 0] < 0).any() == (min(per) < 0)
    assert "histogram" in cp.audit_plot.title
    # the other method's results through the Data tab's dropdown
    app.panels["system"].run_method.value = "deterministic"
    d = run.methods["deterministic"]
    assert app.run_method == "deterministic" and app.results["certify"] is d.certificate
    assert app.audit is d.audit and app.audit["certificate_method"] == "deterministic"
    assert app.results["collect"] is d.dataset and app.results["rollout"] is d.rollouts
    # a knob change re-certifies from the run's data
    app.panels["certificate"].degree.value = 1
    out = app.wait(120)
    assert out.ok, out.error
    assert app.results["certify"] is not d.certificate and app.results["certify"].dims[0].terms == ["1", "x1", "x2", "u1"]
    assert not cp.audit_plot.visible  # the run's audit is not about this new certificate


def test_mode_switch_keeps_the_certificate(loaded):
    """Switching 'delta from' pre-fills the current deltas: gamma does not jump to a placeholder."""
    app, run = loaded
    cert = app.results["certify"]
    cp = app.panels["certificate"]
    assert cp.mode.value == "target confidence" and cp.delta1.disabled and not cp.confidence.disabled
    shown = [float(v) for v in cp.delta1.value.split(",")]
    np.testing.assert_allclose(shown, [d.delta1 for d in cert.dims], rtol=1e-3)  # no stale placeholder
    cp.mode.value = "per dimension"
    out = app.wait(120)
    assert out is None or out.ok
    new = app.results["certify"]
    assert [d.delta1 for d in new.dims] == [d.delta1 for d in cert.dims]
    x, u = app.results["collect"].x[::97], app.results["collect"].u[::97]
    np.testing.assert_allclose(new.gamma(x, u), cert.gamma(x, u), rtol=1e-9)
    assert not cp.delta1.disabled and cp.confidence.disabled
    # the winning domain and the rollouts stay on screen, marked stale, until recomputed
    m = run.methods[app.run_method]
    assert app.results["synthesize"] is m.synthesis and app.results["rollout"] is m.rollouts
    assert app.stale == {"synthesize", "rollout"}
    assert "stale: re-synthesize" in app.panels["synthesis"].stats.content
    assert "stale: roll out again" in app.panels["rollouts"].stats.content
    assert "stale: re-synthesize, roll out again" in app.status.content
    app.synthesize()
    out = app.wait(120)
    assert out.ok, out.error
    assert app.results["synthesize"] is not m.synthesis and app.stale == {"rollout"}
    assert "stale" not in app.panels["synthesis"].stats.content
    assert "stale: roll out again" in app.panels["rollouts"].stats.content


def test_cli_gui_opens_a_results_folder(run_dir, tmp_path):
    p = subprocess.run([sys.executable, "-m", "simgap", "gui", str(run_dir), "--port", "0", "--exit-after", "0.5"],
                       capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stderr
    assert "open http://127.0.0.1:" in p.stdout
    bad = subprocess.run([sys.executable, "-m", "simgap", "gui", str(tmp_path), "--port", "0", "--exit-after", "0.5"],
                         capture_output=True, text=True, timeout=180)
    assert bad.returncode != 0 and "summary.json" in bad.stderr and "Traceback" not in bad.stderr


def test_cli_gui_warns_on_all_interfaces():
    p = subprocess.run([sys.executable, "-m", "simgap", "gui", "--host", "0.0.0.0", "--port", "0",
                        "--exit-after", "0.3"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "WARNING" in p.stdout and "listening on 0.0.0.0:" in p.stdout


def _free_port() -> int:
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _near(img: np.ndarray, rgb, tol: int = 40) -> int:
    """Pixels within ``tol`` per channel of ``rgb``."""
    return int(np.count_nonzero(np.all(np.abs(img[..., :3].astype(int) - np.array(rgb)) <= tol, axis=-1)))


@pytest.mark.browser
def test_run_in_browser_every_layer_in_frame(run_dir, tmp_path):
    """The loaded run in headless chromium: the canvas shows the surface's color map, the winning
    map, the rollouts' bold mean and the panel's plots; a screenshot per tab."""
    import io

    from PIL import Image
    from test_browser_app import _need_browser
    _need_browser()
    from playwright.sync_api import sync_playwright

    from simgap_viz import screenshot as S
    from simgap_viz.app import SimgapApp
    from simgap_viz.layers import geometry as G
    from simgap_viz.results import load_run
    app = SimgapApp(port=0, executor="serial")
    try:
        app.load_run(load_run(run_dir))
        app.set_flat_gamma(True)  # this run's gamma is constant on the slice: by default only the legend says so
        app.set_view(dim=1)
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path=S.CHROMIUM, args=S.ARGS)
            try:
                page = S.open_page(b, app.url, 1280, 800)
                shots = {}
                for tab in ("Certificate", "Synthesis", "Rollouts"):
                    if tab == "Rollouts":  # the surface above would tint the trajectories below it
                        app.panels["view"].checks["gamma"].value = False
                    S.show_tab(page, tab, settle=2.0)
                    shots[tab] = np.asarray(Image.open(io.BytesIO(S.canvas_png(page, tmp_path / f"{tab}.png")))
                                            .convert("RGB"))
                page.get_by_role("tab", name="Certificate").click(force=True, no_wait_after=True)
                page.get_by_text("along theta").first.wait_for(timeout=60_000)  # the gamma-slice plot
                page.get_by_text("audit: margin").first.wait_for(timeout=60_000)
            finally:
                b.close()
    finally:
        app.stop()
    img = shots["Rollouts"]
    h, w, _ = img.shape
    scene = img[:, : int(w * 0.68)]  # left of the control panel
    background = _near(scene, (255, 255, 255), 6)
    assert background < 0.9 * scene.shape[0] * scene.shape[1], "the scene is nearly empty"
    # the surface's color map (its blue and its yellow end, lit and translucent), the winning
    # map's green, the mean trajectory's yellow
    # (the surface is colored on the session's scale 0 .. top, so a gamma that varies by a few
    # percent is yellow all over: its blue end no longer appears, by design)
    cert = shots["Certificate"][:, : int(w * 0.68)]
    r, g, bl = (cert[..., k].astype(int) for k in range(3))
    yellow_cert = np.count_nonzero((r > 190) & (g > 190) & (bl < 170))
    assert yellow_cert > 2000
    assert _near(scene, G.WIN_ALL, 35) > 500  # invariance: one light green
    r, g, bl = (scene[..., k].astype(int) for k in range(3))
    assert np.count_nonzero((r > 180) & (g > 150) & (bl < 120)) > 30  # the mean's yellow (lines are lit)
    # hiding the surface removes its colors
    assert np.count_nonzero((r > 190) & (g > 190) & (bl < 170)) < 0.25 * yellow_cert

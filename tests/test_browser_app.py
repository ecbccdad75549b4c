"""The app in a real headless browser (Playwright + Debian's chromium, software WebGL).

Starts the app on a free localhost port, loads the page, changes epsilon and a basis option,
presses Certify (which collects the tiny data set first), waits for the summary table, and
checks that a screenshot is not blank. Needs /usr/bin/chromium: skipped without it, except on
CI (CI=true), where a missing browser is a failure.
"""

import io
import os
import shutil
import time

import numpy as np
import pytest
from test_viz_results import run_dir  # noqa: F401  (a tiny real pendulum run folder, module-scoped fixture)

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]

pytestmark = pytest.mark.browser


def _need_browser():
    have = os.path.exists(CHROMIUM) or shutil.which("chromium")
    try:
        from playwright.sync_api import sync_playwright  # noqa: F401
    except ImportError:
        have = False
    if not have:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail("chromium/playwright missing on CI: .ci/run must install them")
        pytest.skip("chromium or playwright not installed")


def _input(page, label: str):
    """The input next to a viser label (text inputs do not link label and input by id)."""
    return page.locator(f'xpath=//label[normalize-space(text())="{label}"]'
                        f'/ancestor::div[contains(@class, "mantine-Flex-root")][1]//input').first


def _png_stats(png: bytes):
    """Pixel standard deviation of a PNG (0 for a blank image), via trimesh's PIL dependency."""
    from PIL import Image
    im = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)
    return float(im.std()), im.shape


def test_certify_in_browser(tmp_path):
    _need_browser()
    from playwright.sync_api import sync_playwright

    from simgap_viz.app import SimgapApp
    from simgap_viz.settings import Settings

    t0 = time.perf_counter()

    def step(what):  # step timings, printed with -s (the browser test is the slowest test)
        print(f"[browser] {time.perf_counter() - t0:6.2f} s  {what}", flush=True)

    app = SimgapApp(port=0, executor="serial", settings=Settings(epsilon=0.1, n_runs=5, noise_std=0.05))
    try:
        assert app.url.startswith("http://127.0.0.1:")
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                step("goto")
                page.goto(app.url)
                page.wait_for_function("() => !document.body.innerText.includes('Connecting...')", timeout=60_000)
                page.get_by_text("simgap", exact=False).first.wait_for(timeout=30_000)

                step("connected")
                # epsilon on the Data tab
                eps = _input(page, "epsilon")
                eps.fill("0.08")
                eps.press("Tab")
                deadline = time.time() + 20
                while app.settings.epsilon != 0.08 and time.time() < deadline:
                    time.sleep(0.1)
                assert app.settings.epsilon == 0.08

                step("epsilon set")
                # a basis option on the Certificate tab: an extra term
                page.get_by_role("tab", name="Certificate").click(force=True, no_wait_after=True)
                step("tab clicked")
                terms = _input(page, "Extra terms")
                terms.fill("sin(x1)")
                step("terms filled")
                terms.press("Tab")
                deadline = time.time() + 20
                while app.settings.terms != "sin(x1)" and time.time() < deadline:
                    time.sleep(0.1)
                assert app.settings.terms == "sin(x1)"

                step("terms set")
                # a bad value shows a notification in the page
                deg_note = _input(page, "Confidence")
                deg_note.fill("1.5")
                deg_note.press("Tab")
                page.get_by_text("target confidence must be in (0, 1)").first.wait_for(timeout=20_000)
                deg_note.fill("0.9")
                deg_note.press("Tab")

                step("notification seen")
                page.get_by_role("button", name="Certify").click(force=True, no_wait_after=True)
                page.get_by_text("joint confidence").first.wait_for(timeout=120_000)
                step("summary seen")
                assert app.results["certify"] is not None
                assert app.results["certify"].dims[0].terms[-1] == "sin(x1)"
                assert app.results["collect"].epsilon == 0.08
                assert "omega" in page.inner_text("body")
                time.sleep(1.5)  # let the gamma surface render
                step("rendered")
                png = page.screenshot(path=str(tmp_path / "app.png"))
                if os.environ.get("SIMGAP_SCREENSHOT"):
                    page.screenshot(path=os.environ["SIMGAP_SCREENSHOT"])
            finally:
                browser.close()
    finally:
        app.stop()
    std, shape = _png_stats(png)
    assert shape[0] == 800 and shape[1] == 1280
    assert std > 5.0, f"screenshot looks blank (pixel std {std:.2f})"


def _rgb(png: bytes) -> np.ndarray:
    from PIL import Image
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)


def _changed(a: np.ndarray, b: np.ndarray, tol: int = 25) -> np.ndarray:
    """Pixels where two screenshots differ by more than ``tol`` in some channel."""
    return np.abs(a - b).max(axis=-1) > tol


def test_default_scene_shows_the_map_and_the_runs(run_dir, tmp_path):  # noqa: F811
    """The default scene of a loaded pendulum run, by what the page shows: the winning domain is at
    most 20 % covered by the other layers, and the thin rollouts show outside the bold lines.

    Canvas screenshots with one camera: the default scene (A); the same with no thin rollout
    drawn, only the bold mean / mean-map / nominal lines (C); without the bold lines either (D); the
    winning map alone (R, every other result node removed). Covered = R's winning-green pixels that
    look different in A. Thin rollouts seen = pixels that change between C and A, at least a fifth
    of the bold lines' (C vs D). Fails for the earlier scene, whose opaque gamma sheet
    stood over the map and whose rollouts lay under the bold lines."""
    _need_browser()
    from playwright.sync_api import sync_playwright

    from simgap_viz import screenshot as S
    from simgap_viz.app import SimgapApp
    from simgap_viz.layers import scene
    from simgap_viz.results import load_run

    app = SimgapApp(port=0, executor="serial")
    try:
        app.load_run(load_run(run_dir))
        assert app.view["n_draw"] >= app.results["rollout"].n_rollouts  # every rollout drawn by default
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path=S.CHROMIUM, args=S.ARGS)
            try:
                page = S.open_page(b, app.url + "/?fixedDpr=1", 1280, 800)
                S.show_tab(page, "View", settle=3.0)
                A = _rgb(S.canvas_png(page, tmp_path / "A.png"))
                app.set_time(n_draw=0)  # the bold lines stay
                time.sleep(2.5)
                C = _rgb(S.canvas_png(page, tmp_path / "C.png"))
                app.server.scene.remove_by_name("/rollouts")  # the bold lines too
                time.sleep(2.5)
                D = _rgb(S.canvas_png(page, tmp_path / "D.png"))
                for lay in scene.LAYERS:  # everything but the winning map (and the bodies beside it)
                    if lay.key not in ("winning", "bodies"):
                        for node in lay.nodes:
                            app.server.scene.remove_by_name(node)
                time.sleep(2.5)
                R = _rgb(S.canvas_png(page, tmp_path / "R.png"))
            finally:
                b.close()
    finally:
        app.stop()
    r, g, bl = R[..., 0], R[..., 1], R[..., 2]
    winning = (g > r + 40) & (g > bl + 40)  # the map's greens
    assert winning.sum() > 5000, f"the winning domain is hardly visible ({winning.sum()} px)"
    covered = float((_changed(A, R) & winning).sum()) / winning.sum()
    assert covered <= 0.20, f"{100 * covered:.0f} % of the winning domain is covered by other layers"
    thin = int(_changed(A, C).sum())
    bold = int(_changed(C, D).sum())
    assert thin >= 200 and thin >= 0.2 * bold, f"thin rollouts show on {thin} px (bold lines {bold} px)"

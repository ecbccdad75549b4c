"""A box-tube run in a real headless browser (Playwright + chromium, software WebGL), by what the
page shows: the header and the Per run tab name the tube and p_cert in the tube's own words (never an
invariant set E), and the proved-sets layer draws the tube's boxes whole, left of the panel, at
1280 x 800 and 1920 x 1080. One page (about 12 CPU-seconds). Screenshots go to the test's tmp_path."""

import io
import re

import numpy as np
import pytest
from test_browser_app import _assert_window_fit, _need_browser
from test_statement import tube_run  # noqa: F401  (a small box-tube run folder, module-scoped fixture)

pytestmark = pytest.mark.browser


def _orange(png: bytes) -> np.ndarray:
    """Pixels of the tube's color (scene.ROLE_STYLE["tube"], shaded by the lights) in a canvas PNG."""
    from PIL import Image
    im = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    r, g, b = im[..., 0], im[..., 1], im[..., 2]
    return (r > 170) & (g > 60) & (g < 160) & (b < 80) & (r - g > 70)


def test_tube_run_in_the_browser(tube_run, tmp_path):  # noqa: F811
    _need_browser()
    from playwright.sync_api import sync_playwright

    from simgap_viz import screenshot as S
    from simgap_viz.app import SimgapApp
    from simgap_viz.results import load_run

    app = SimgapApp(port=0, executor="serial")
    try:
        app.load_run(load_run(tube_run))
        p_cert = app.run.methods["stochastic"].statement.per_run.p_cert
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path=S.CHROMIUM, args=S.ARGS)
            try:
                page = S.open_page(b, app.url + "/?fixedDpr=1", 1280, 800)
                text = page.inner_text("body")
                assert "box tube from x0" in text and f"p_cert {p_cert:.3g}" in text, text[:400]
                S.show_tab(page, "Per run", settle=1.0)
                per = page.inner_text("body")
                assert "Per-run statements of the methods" in per and f"{p_cert:.4f}" in per
                S.show_tab(page, "View", settle=1.0)
                view = page.inner_text("body")
                assert "noise tube" in view and "terminal box" in view
                for t in (text, per, view):
                    assert not re.search(r"invariant set|Invariant sets E|\bE proved", t)
                shots = {}
                for w, h in ((1280, 800), (1920, 1080)):
                    page.set_viewport_size({"width": w, "height": h})
                    deadline = 30
                    while app.windows.get(max(app.server.get_clients()), {}).get("size") != (w, h) and deadline:
                        page.wait_for_timeout(500)
                        deadline -= 1
                    _assert_window_fit(app, w, h)
                    page.screenshot(path=str(tmp_path / f"tube-{w}.png"))
                    shots[w] = S.settled_canvas(page, tmp_path / f"canvas-{w}.png")
            finally:
                b.close()
    finally:
        app.stop()
    from simgap_viz.app import panel_width
    for w, png in shots.items():
        tube = _orange(png)
        assert tube.sum() > 150, f"{w}: the tube's boxes are hardly drawn ({tube.sum()} px)"
        ys, xs = np.nonzero(tube)
        # whole and left of the panel: no tube pixel on the canvas' edges or under the panel
        assert xs.min() > 2 and ys.min() > 2 and ys.max() < tube.shape[0] - 3, (w, xs.min(), ys.min(), ys.max())
        assert xs.max() < tube.shape[1] - panel_width(w), (w, xs.max(), tube.shape[1] - panel_width(w))

"""Screenshots of the app in headless chromium (Playwright, software WebGL), for the docs and tests.

    python -m simgap_viz.screenshot results/pendulum-small --out docs/app.png

opens the finished run (``simgap run pendulum``) in the app and saves one PNG per tab:
``docs/app.png`` (the Certificate tab; ``--no-main`` skips it) and ``docs/app-<tab>.png`` for the others
named by ``--tabs``. For the "Per run" tab (a run with ``[perrun]``) the gamma surface and the data gaps
are hidden, so the p_cert map shows:

    python -m simgap_viz.screenshot results/perrun-gui --out docs/app.png --tabs "Per run" --no-main
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
# WebGL on SwiftShader (no GPU here); --disable-gpu composites the page in software beside it, the same
# pixels for about a fifth less CPU per page load (11 instead of 14 CPU-seconds for the tests' run)
ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-gpu",
        "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run"]


def open_page(browser, url: str, width: int = 1280, height: int = 800):
    """A page with the app loaded and connected, viser's software-WebGL toast closed."""
    page = browser.new_page(viewport={"width": width, "height": height})
    page.goto(url)
    page.wait_for_function("() => !document.body.innerText.includes('Connecting...')", timeout=120_000)
    page.locator("canvas").first.wait_for(timeout=60_000)
    time.sleep(1.0)
    close_toasts(page)
    settled_canvas(page)  # the scene's nodes arrive and fade in after connecting
    return page


def close_toasts(page) -> None:
    for btn in page.locator(".mantine-Notification-closeButton").all():
        try:
            btn.click(force=True, no_wait_after=True, timeout=2000)
        except Exception:  # the toast closed itself
            pass


def show_tab(page, tab: str, settle: float = 2.5, relayout: bool = False) -> None:
    """Click ``tab``; with ``relayout`` (the docs' pictures) also :func:`redraw` (about 7 s more)."""
    page.get_by_role("tab", name=tab).click(force=True, no_wait_after=True)
    time.sleep(settle)
    if relayout:
        redraw(page)
    close_toasts(page)


def redraw(page, settle: float = 6.0) -> None:
    """Resize the viewport by a pixel and back: a chart drawn while its tab was hidden (zero width,
    its title wrapped word by word) and the scene's tick labels are laid out again (as a person's
    window would be; the labels take a few seconds to come back)."""
    vp = page.viewport_size
    page.set_viewport_size({"width": vp["width"] + 1, "height": vp["height"]})
    time.sleep(1.0)
    page.set_viewport_size(vp)
    time.sleep(settle)


def settled_canvas(page, path=None, changed_from: bytes | None = None, interval: float = 0.25,
                   timeout: float = 60.0) -> bytes:
    """The 3-D canvas once it stopped changing (bytes of a PNG; also written to ``path``): screenshots
    every ``interval`` s until three in a row are the same. With ``changed_from`` (an earlier
    screenshot) it first waits for the canvas to differ from it: a change just sent to the client may
    not be drawn yet. A fixed wait was either long on an idle machine or short under load. After
    ``timeout`` s the last screenshot is returned as it is."""
    deadline = time.time() + timeout
    shot = canvas_png(page)
    while changed_from is not None and shot == changed_from and time.time() < deadline:
        time.sleep(interval)
        shot = canvas_png(page)
    same = 0
    while same < 2 and time.time() < deadline:
        time.sleep(interval)
        nxt = canvas_png(page)
        same = same + 1 if nxt == shot else 0
        shot = nxt
    if path is not None:
        Path(path).write_bytes(shot)
    return shot


def canvas_png(page, path=None) -> bytes:
    """A screenshot of the 3-D canvas alone (bytes of a PNG; also written to ``path``)."""
    return page.locator("canvas").first.screenshot(path=None if path is None else str(path), timeout=180_000)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("results", help="a finished `simgap run` folder")
    p.add_argument("--out", default="docs/app.png", help="the main picture (Certificate tab)")
    p.add_argument("--tabs", default="Synthesis,Rollouts,View", help="further tabs, one PNG each")
    p.add_argument("--no-main", action="store_true", help="skip the main picture")
    p.add_argument("--dim", type=int, default=2, help="gamma of state dimension (1-based)")
    p.add_argument("--method", default="stochastic",
                   help="the run's results to show (stochastic, deterministic; nominal: an invariant-set run's "
                        "nominal-model set and rollouts)")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=800)
    args = p.parse_args(argv)
    from playwright.sync_api import sync_playwright

    from .app import SimgapApp
    from .results import load_run

    app = SimgapApp(port=0, executor="serial")
    out = Path(args.out)
    written = []
    try:
        app.load_run(load_run(args.results), args.method)
        app.set_view(dim=args.dim - 1)
        tabs = [t for t in args.tabs.split(",") if t] + ([] if args.no_main else ["Certificate"])
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = open_page(b, app.url, args.width, args.height)
            # the main picture last: the tick labels appear once the camera has settled
            for tab in tabs:
                for layer in ("gamma", "data"):  # the surface and the gaps would hide the p_cert map
                    app.panels["view"].checks[layer].value = tab != "Per run"
                show_tab(page, tab, relayout=True)
                name = tab.lower().replace(" ", "-")
                path = out if tab == "Certificate" else out.with_name(f"{out.stem}-{name}{out.suffix}")
                page.screenshot(path=str(path), timeout=180_000)
                written.append(path)
            b.close()
    finally:
        app.stop()
    print("wrote " + ", ".join(map(str, written)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

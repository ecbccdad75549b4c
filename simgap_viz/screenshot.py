"""Take a screenshot of the app after a small pendulum walk-through (for the docs).

    python -m simgap_viz.screenshot --out docs/app.png

Runs collect, certify, synthesize (nominal model, no gap, so the domain is not empty at this
coarse data) and 200 rollouts on the pendulum small profile with epsilon 0.05 and N1hat 20,
then opens the page in headless chromium and saves a PNG.
"""

from __future__ import annotations

import argparse
import time

ARGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="docs/app.png")
    p.add_argument("--tab", default="Certificate")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=760)
    args = p.parse_args(argv)
    from playwright.sync_api import sync_playwright

    from .app import SimgapApp
    from .experiment import app_inputs

    st, ds, spec, arena, exp = app_inputs(experiment="pendulum", profile="small")
    app = SimgapApp(port=0, settings=st, spec=spec, arena=arena, experiment=exp, executor="serial")
    try:
        app.update_settings(epsilon=0.05, n_runs=20, use_gap=False, eta=(0.005, 0.01), n_rollouts=100, horizon=300,
                            x0=(0.05, 0.1))
        for stage in ("collect", "certify", "synthesize", "rollout"):
            getattr(app, stage)()
            out = app.wait(600)
            if out is not None and not out.ok:
                raise SystemExit(f"{stage} failed: {out.error}")
        app.set_view(dim=1)
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path="/usr/bin/chromium", args=ARGS)
            page = b.new_page(viewport={"width": args.width, "height": args.height})
            page.goto(app.url)
            page.wait_for_function("() => !document.body.innerText.includes('Connecting...')", timeout=60_000)
            page.get_by_role("tab", name=args.tab).click(force=True, no_wait_after=True)
            time.sleep(1.0)
            # close viser's "software WebGL" toast so it does not cover the scene
            for btn in page.locator(".mantine-Notification-closeButton").all():
                btn.click(force=True, no_wait_after=True)
            time.sleep(3.0)
            page.screenshot(path=args.out, timeout=180_000)
            b.close()
    finally:
        app.stop()
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``simgap gui``: start the web app and print its URL."""

from __future__ import annotations

import argparse
import time


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "gui", help="interactive web app (viser): collect, certify, synthesize, roll out, refine",
        description="Start the simgap web app and print the URL to open in a browser. "
                    "Binds 127.0.0.1 unless --host says otherwise.")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1; 0.0.0.0 exposes it)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080; 0 picks a free one)")
    p.add_argument("--experiment", default=None, help="experiment name or TOML file (e.g. pendulum)")
    p.add_argument("--profile", default=None, help="experiment profile (e.g. small)")
    p.add_argument("--dataset", default=None, help="load this dataset (.npz or store directory) at start")
    p.add_argument("--system", default=None, help="start with this built-in system (pendulum, turtlebot)")
    p.add_argument("--executor", default="local", choices=("serial", "local"),
                   help="how the collect button runs the simulator (default: local process pool)")
    p.add_argument("--exit-after", type=float, default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from .app import SimgapApp
    from .experiment import app_inputs

    settings, dataset, spec, arena, exp = app_inputs(experiment=args.experiment, profile=args.profile,
                                                dataset=args.dataset, system=args.system)
    app = SimgapApp(host=args.host, port=args.port, settings=settings, dataset=dataset, spec=spec, arena=arena,
                    experiment=exp)
    app.executor = args.executor
    print(f"simgap gui: open {app.url} in a browser (Ctrl+C to stop)", flush=True)
    t0 = time.monotonic()
    try:
        while args.exit_after is None or time.monotonic() - t0 < args.exit_after:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        app.stop()
    return 0

"""``simgap gui``: start the web app and print its URL."""

from __future__ import annotations

import argparse
import time

from simgap.checks import check_bindable, host, port
from simgap.systems import BUILTIN

from .results import add_stage_arguments


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "gui", help="interactive web app (viser): collect, certify, synthesize, roll out, refine",
        description="Start the simgap web app and print the URL to open in a browser. "
                    "Binds 127.0.0.1 unless --host says otherwise.")
    p.add_argument("results", nargs="?", default=None,
                   help="a finished `simgap run` folder (e.g. results/pendulum-small): open it fully loaded; or a "
                        "folder of stage outputs (a data store or .npz, a certificate, a controller, rollouts .npz)")
    p.add_argument("--method", default="stochastic", choices=("stochastic", "deterministic", "nominal"),
                   help="which certificate's results of RESULTS to show first (default: stochastic; nominal: an "
                        "invariant-set run's set and rollouts for the nominal model, no gap)")
    p.add_argument("--host", type=host, default="127.0.0.1",
                   help="address to bind (default 127.0.0.1; 0.0.0.0 exposes it)")
    p.add_argument("--port", type=port, default=8080, help="port (default 8080; 0 picks a free one)")
    p.add_argument("--experiment", default=None, help="experiment name or TOML file (e.g. pendulum)")
    p.add_argument("--profile", default=None, help="experiment profile (e.g. small)")
    p.add_argument("--dataset", default=None, help="load this dataset (.npz or store directory) at start; with "
                                                   "--cert/--controller/--rollouts or a stage folder: the data set of "
                                                   "those stage outputs")
    add_stage_arguments(p)
    p.add_argument("--system", default=None,
                   help="start with this system: a built-in or plugin name (" + ", ".join(sorted(BUILTIN)) + "; see simgap plugins), "
                        "a system file (.toml) or a refined-system JSON")
    p.add_argument("--executor", default="local", choices=("serial", "local"),
                   help="how the collect button runs the simulator (default: local process pool)")
    p.add_argument("--exit-after", type=float, default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from simgap.errors import SimgapError

    from .app import SimgapApp
    from .experiment import app_inputs
    from .results import describe_stages, is_run_dir, load_run, load_stages

    check_bindable(args.host)  # an address of this machine? (the server skips a taken port itself)
    run_results = None
    stages = any(v is not None for v in (args.cert, args.controller, args.rollouts))
    if args.results is not None and is_run_dir(args.results) and not stages:
        if args.experiment or args.dataset or args.system:
            raise SimgapError("give either a results folder or --experiment/--dataset/--system, not both")
        run_results = load_run(args.results)
    elif stages or args.results is not None:  # stage-by-stage outputs, each checked against the others
        if args.experiment or args.system:
            raise SimgapError("stage outputs carry their own model: drop --experiment/--system")
        run_results = load_stages(args.results, dataset=args.dataset, cert=args.cert, controller=args.controller,
                                  rollouts=args.rollouts)
        args.dataset = None
        for line in describe_stages(run_results):
            print(f"simgap gui: {line}", flush=True)
    settings, dataset, spec, arena, exp = app_inputs(experiment=args.experiment, profile=args.profile,
                                                dataset=args.dataset, system=args.system)
    app = SimgapApp(host=args.host, port=args.port, settings=settings, dataset=dataset, spec=spec, arena=arena,
                    experiment=exp)
    app.executor = args.executor
    if run_results is not None:
        app.load_run(run_results, args.method if args.method in run_results.methods
                     or (args.method == "nominal" and run_results.nominal is not None)
                     else next(iter(run_results.methods)))
    if args.host in ("0.0.0.0", "::", ""):
        print(f"simgap gui: WARNING: --host {args.host} serves the app to every machine that can reach this one; "
              f"anyone who can connect can run stages and read files the app can read", flush=True)
        print(f"simgap gui: listening on {args.host}:{app.server.get_port()}; addresses of this machine: "
              f"{', '.join(_addresses()) or 'unknown'}", flush=True)
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


def _addresses() -> list:
    """This machine's IPv4 addresses (what another machine would connect to), best effort."""
    import socket
    out = set()
    try:
        for info in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET):
            out.add(info[4][0])
    except OSError:
        pass
    return sorted(out)

"""``simgap plot RUN``: the paper's figures of a finished run, or of stage-by-stage outputs, as PNG
and PDF (matplotlib)."""

from __future__ import annotations

import argparse

from .results import add_stage_arguments


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "plot", help="paper-style figures of a finished run (PNG and PDF): rollouts, states over time, gamma, p_cert",
        description="Draw the figures of a `simgap run` folder with matplotlib: the rollouts of both methods "
                    "over the state space or arena with the mean map and failures, every state over time, "
                    "gamma along each state, and the per-run p_cert map when the run has one. Axes carry the "
                    "system's units. Stage-by-stage outputs (simgap collect, certify, synthesize, rollout run one by "
                    "one) are drawn from a folder holding them or from --dataset/--cert/--controller/--rollouts: "
                    "the rollout figures need the rollouts, gamma the certificate.")
    p.add_argument("run", nargs="?", default=None,
                   help="a `simgap run` results folder (e.g. results/pendulum-small), or a folder of stage outputs")
    p.add_argument("--dataset", default=None, metavar="DATA", help="the data set of the stage outputs (.npz or store)")
    add_stage_arguments(p)
    p.add_argument("--out", default=None, help="output folder (default RUN/figures; for stage files given by name: "
                                               "figures beside the first)")
    p.add_argument("--style", choices=("paper", "slide"), default="paper",
                   help="paper: 7 in wide, 8 pt text, a two-column paper's text width (default); slide: 11 in, 14 pt")
    p.add_argument("--max-drawn", type=int, default=1000, help="rollouts drawn per method (failures first; default 1000)")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from simgap.errors import SimgapError

    from .figures import plot_run
    from .results import describe_stages, is_run_dir, load_stages

    if args.max_drawn < 1:
        raise SimgapError(f"--max-drawn must be >= 1, got {args.max_drawn}")
    given = [v is not None for v in (args.dataset, args.cert, args.controller, args.rollouts)]
    if args.run is None and not any(given):
        raise SimgapError("give a `simgap run` folder, a folder of stage outputs, or --dataset/--cert/--controller/"
                          "--rollouts")
    run = args.run
    if any(given) or not is_run_dir(args.run):  # stage-by-stage outputs, each checked against the others
        run = load_stages(args.run, dataset=args.dataset, cert=args.cert, controller=args.controller,
                          rollouts=args.rollouts)
        for line in describe_stages(run):
            print(line)
    written = plot_run(run, args.out, max_drawn=args.max_drawn, style=args.style,
                       log=lambda line: print(line, flush=True))
    for p in written:
        print(p)
    return 0

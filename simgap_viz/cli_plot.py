"""``simgap plot RUN``: the paper's figures of a finished run as PNG and PDF (matplotlib)."""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "plot", help="paper-style figures of a finished run (PNG and PDF): rollouts, states over time, gamma, p_cert",
        description="Draw the figures of a `simgap run` folder with matplotlib: the rollouts of both methods "
                    "over the state space or arena with the mean map and failures, every state over time, "
                    "gamma along each state, and the per-run p_cert map when the run has one. Axes carry the "
                    "system's units.")
    p.add_argument("run", help="a `simgap run` results folder (e.g. results/pendulum-small)")
    p.add_argument("--out", default=None, help="output folder (default RUN/figures)")
    p.add_argument("--style", choices=("paper", "slide"), default="paper",
                   help="paper: 7 in wide, 8 pt text, a two-column paper's text width (default); slide: 11 in, 14 pt")
    p.add_argument("--max-drawn", type=int, default=1000, help="rollouts drawn per method (failures first; default 1000)")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from simgap.errors import SimgapError

    from .figures import plot_run

    if args.max_drawn < 1:
        raise SimgapError(f"--max-drawn must be >= 1, got {args.max_drawn}")
    written = plot_run(args.run, args.out, max_drawn=args.max_drawn, style=args.style)
    for p in written:
        print(p)
    return 0

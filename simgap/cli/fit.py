"""``simgap fit EXPERIMENT --params a b ... --out FILE``: fit a system file's parameters to the simulator.

    simgap fit examples/husky/experiment.toml --params kv kw kwv d --fix x=3 y=3 --grid 72 \\
               --out husky_fitted.toml

Simulates every input of the experiment's system from the chosen states with the experiment's
simulator, noise and parameter randomization off, fits the named ``[params]`` of its system file
by least squares (:mod:`simgap.fit`) and writes the system file with the fitted values (nothing
else in the file changes).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from ..checks import count
from ..errors import SimgapError
from ..profiles import DEFAULT_PROFILE


#: states drawn when neither --points nor --grid is given
POINTS = 200


def add_parser(sub) -> None:
    p = sub.add_parser(
        "fit", help="fit named parameters of a system file to noise-free simulator transitions",
        description="Fit the named [params] of the experiment's system file to transitions of its simulator with "
                    "the noise and randomization off (least squares over every state dimension, each weighted "
                    "by the RMS of its observed increments), print the fit before and after, and write the system "
                    "file with the fitted values.")
    p.add_argument("experiment", help="experiment name or TOML whose [system] is a system file")
    p.add_argument("--params", nargs="+", required=True, help="names of the system file's [params] to fit")
    p.add_argument("--profile", default=DEFAULT_PROFILE, help="experiment profile (default: small, else base)")
    p.add_argument("--out", required=True, help="the fitted system file (.toml) to write")
    p.add_argument("--points", type=count(1), default=None,
                   help=f"states drawn uniformly in X (seeded), each simulated with every input (default {POINTS})")
    p.add_argument("--grid", type=count(1), default=None,
                   help="instead of --points (not with it): this many evenly spaced values per state dimension "
                        "not fixed")
    p.add_argument("--fix", nargs="+", default=(), metavar="STATE=VALUE",
                   help="hold states at a value, e.g. --fix x=3 y=3 (a uniform floor, or away from obstacles)")
    p.add_argument("--bounds", nargs="+", default=(), metavar="NAME=LO:HI", help="bound parameters, e.g. d=0:1")
    p.add_argument("--seed", type=count(0), default=0, help="seed of the states and the simulator (default 0)")
    p.set_defaults(func=run, outputs=("out",), formats={"out": (".toml",)})


def _pairs(tokens, flag: str, parse):
    out = {}
    for t in tokens:
        k, sep, v = str(t).partition("=")
        if not sep or not k:
            raise SimgapError(f"{flag} {t!r}: expected NAME=VALUE")
        try:
            out[k] = parse(v)
        except ValueError:
            raise SimgapError(f"{flag} {t!r}: {v!r} is not {'LO:HI' if flag == '--bounds' else 'a number'}") from None
    return out


def _bounds(v: str):
    lo, sep, hi = v.partition(":")
    if not sep:
        raise ValueError(v)
    lo, hi = float(lo), float(hi)
    if not lo < hi:
        raise ValueError(v)
    return lo, hi


def check_fit_seconds(seconds: float, what: str) -> None:
    """Refuse a fit whose transitions and first 5 iterations are estimated to take more than a
    command may (:data:`simgap.checks.MAX_COMMAND_SECONDS`; ``SIMGAP_NO_SIZE_CHECK=1`` lifts it)."""
    import os

    from ..checks import MAX_COMMAND_SECONDS, human_seconds
    if seconds > MAX_COMMAND_SECONDS and not os.environ.get("SIMGAP_NO_SIZE_CHECK"):
        raise SimgapError(f"{what}: the fit's transitions and its first 5 iterations would take about "
                          f"{human_seconds(seconds)}, more than the {human_seconds(MAX_COMMAND_SECONDS)} a command may "
                          "take; use fewer --points or a coarser --grid (or set SIMGAP_NO_SIZE_CHECK=1 to run it "
                          "anyway)")


def system_file_path(exp) -> Path:
    """The system file an experiment names (its ``[system] name``, in the experiment's folder)."""
    name = str((exp.section("system") or {}).get("name", ""))
    if not name.endswith(".toml"):
        raise SimgapError(f"experiment {exp.name}: its system {name or exp.system.name!r} is not a system file "
                          "(.toml); simgap fit fits a system file's [params]")
    return exp.path.resolve().parent / name


def run(args) -> int:
    import numpy as np

    from ..config import load_experiment
    from ..cover import calibrate_rate, format_duration
    from ..file_guard import read_text
    from ..fileio import write_text
    from ..checks import one_of
    from ..fit import (check_fit_size, fit_params, fitted_text, sample_states, seconds_per_evaluation,
                       system_file_spec, transitions)
    from ..simulators import make_simulator

    one_of({"--points": args.points, "--grid": args.grid}, "the states the fit simulates from",
           "--points draws that many states at random, --grid takes that many values per free state")
    fix = _pairs(args.fix, "--fix", float)
    bounds = _pairs(args.bounds, "--bounds", _bounds)
    unfitted = [k for k in bounds if k not in args.params]
    if unfitted:
        raise SimgapError(f"--bounds {', '.join(unfitted)}: not among --params {' '.join(args.params)}; a bound only "
                          "applies to a fitted parameter (fit it, or drop the bound)")
    exp = load_experiment(args.experiment, args.profile)
    s = exp.system
    system_file_spec(s)
    path = system_file_path(exp)
    text = read_text(path, "system file")
    if Path(args.out).resolve() == path.resolve():
        raise SimgapError(f"--out {args.out}: that is the experiment's own system file; write the fit to a new file "
                          "and compare before replacing it")
    params = system_file_spec(s).get("params", {})
    bad = [k for k in list(args.params) + list(bounds) if k not in params]
    if bad:
        raise SimgapError(f"--params/--bounds {', '.join(bad)}: not in {path.name}'s [params] "
                          f"({', '.join(params) or 'none'})")
    for k, (lo, hi) in bounds.items():
        v = float(params[k])
        if not lo <= v <= hi:
            print(f"note: --bounds {k}={lo:g}:{hi:g} excludes the file's {k} = {v:g}: the fit starts at the nearest "
                  "bound and is compared with the file's values below", file=sys.stderr)
    rng = np.random.default_rng(args.seed)
    count_, grid = args.grid or args.points or POINTS, args.grid is not None
    what = f"--grid {count_}" if grid else f"--points {count_}"
    rows = check_fit_size(s, count_, grid, fix, len(args.params), what)  # before any state is drawn
    x = sample_states(s, count_, rng, fix, grid=grid)
    cfg = dataclasses.replace(exp.simulator, noise={}, randomize={})
    # the fit: each iteration evaluates the model p + 1 times over every row (finite-difference Jacobian)
    per_iteration = (len(args.params) + 1) * seconds_per_evaluation(s, x, rows)
    with make_simulator(cfg, s) as sim:
        rate = calibrate_rate(sim, n_runs=min(rows, 4096), budget=0.3, work=rows)
        print(f"estimate: {len(x):,} states x {len(s.inputs)} inputs = {rows:,} noise-free simulator runs, about "
              f"{format_duration(rows / rate)} at {rate:,.0f} runs/s (calibrated here), then the least-squares fit, "
              f"about {format_duration(per_iteration)} per iteration ({len(args.params) + 1} model evaluations over "
              f"every row; usually 5 to 20 iterations: {format_duration(5 * per_iteration)} to "
              f"{format_duration(20 * per_iteration)})", flush=True)
        check_fit_seconds(rows / rate + 5 * per_iteration, what)
        X, U, Y = transitions(sim, x, s.inputs, rng)
    res = fit_params(s, args.params, X, U, Y, bounds)
    new = fitted_text(text, res.values())
    width = max(len(k) for k in res.names)
    print(f"fitted {len(res.names)} parameter(s) of {path.name} to {res.rows:,} transitions "
          f"({res.evaluations} model evaluations; {res.message})")
    for k, a, b in zip(res.names, res.initial, res.fitted):
        print(f"  {k.ljust(width)}  {a:.6g} -> {b:.6g}")
    print("noise-free gap per state (rms / max), file's values -> fitted:")
    for j, nm in enumerate(s.state_names):
        print(f"  {nm}: {res.rms_before[j]:.4g} / {res.max_before[j]:.4g} -> {res.rms_after[j]:.4g} / "
              f"{res.max_after[j]:.4g}")
    worse = float(np.sum((res.rms_after / res.scale) ** 2)) > float(np.sum((res.rms_before / res.scale) ** 2))
    if worse:
        print(f"warning: the fitted values match the transitions WORSE than the file's own (weighted rms above); "
              f"the bounds {' '.join(args.bounds) or ''} exclude the better values. {args.out} is written for "
              "inspection: do not replace the system file with it", file=sys.stderr)
    write_text(args.out, new)
    print(f"wrote {args.out} (only these [params] lines changed)", file=sys.stdout)
    return 0

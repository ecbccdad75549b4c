"""``simgap refine``: residual of a nominal model on transition data -> named effects -> refined model.

Examples::

    simgap refine --system pendulum --data transitions.npz --out report.json --save-system refined.json
    simgap refine --system emps --data emps_20hz.npz --out emps_report.json
    simgap refine --system turtlebot --data collected.npz --effects bias,input_gain
    simgap refine --system emps --data emps.npz --term cogging:qd:"sin(2*pi*q/0.01)"
    simgap refine --system emps_refined.json --data DATA_EMPS_PULSES.mat --preset emps
    simgap refine --system emps --data DATA_EMPS.mat --preset emps --validate DATA_EMPS_PULSES.mat
    simgap refine --system cartpole.toml --data DATA --effects affine_ct --save-system cartpole_ct.toml

The data are an .npz with x (K,n), u (K,m), x_next (K,n), tau (and optional t for a time
series), a CSV/Parquet with columns x1.., x1_next.., u1.., tau (or state/input names), or a
collected data set (its empirical means). Rows with NaN/inf are refused unless
--drop-nonfinite. The report JSON holds effects (name, state, input/variable, coefficient,
stderr, explained_fraction, physical units), rms_before/after, max_before/after (held-out,
per state) and unexplained.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from .. import fileio
from ..checks import count
from ..errors import SimgapError


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("refine", help="trace the residual of a model to named effects and refine it",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--system", required=True,
                   help="built-in or plugin system name, a system file (.toml) or a refined-system JSON file")
    p.add_argument("--data", required=True, help="transition data (.npz, .csv, .parquet) or a collected data set")
    p.add_argument("--out", help="write the report JSON here")
    p.add_argument("--save-system", metavar="FILE", help="write the refined system here: a refined-system JSON "
                                                         "(.json), or with --effects affine_ct a system file (.toml)")
    p.add_argument("--effects", help="comma-separated library effects to consider (default: all): "
                                     "bias, viscous_friction, coulomb_friction, drag, input_gain, deadband, "
                                     "gravity, integration; or affine_ct alone: affine continuous-time terms on "
                                     "the velocity states of a system file (damping through the mass matrix), "
                                     "saved as a system file")
    p.add_argument("--term", action="append", default=[], metavar="NAME:STATE:EXPR",
                   help="user-named candidate term entering STATE, e.g. cogging:qd:'sin(2*pi*q/0.01)'")
    p.add_argument("--validate", metavar="DATA", help="a second record the fit never sees (same formats as "
                                                      "--data, or a .mat trajectory with --preset): one-step and "
                                                      "multi-step errors of f and f' on it")
    p.add_argument("--preset", help="trajectory preset for .mat files given to --data/--validate (e.g. emps)")
    p.add_argument("--drop-nonfinite", action="store_true", help="drop rows with NaN/inf instead of refusing")
    p.add_argument("--holdout", type=float, default=0.3, help="held-out fraction (default 0.3)")
    p.add_argument("--segments", type=count(1), default=5, help="contiguous held-out segments for time series")
    p.add_argument("--min-explained", type=float, default=0.005,
                   help="held-out residual-variance fraction an effect must explain to be kept (default 0.005)")
    p.add_argument("--bootstrap", type=count(2), default=100, help="bootstrap resamples for standard errors")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--weighted", action="store_true",
                   help="collected data: weight each pair by 1 / the standard error of its mean (weighted least "
                        "squares; pairs whose runs scatter widely count less)")
    p.add_argument("--name", help="name of the refined system")
    p.add_argument("--quiet", action="store_true", help="no table on the terminal")
    p.add_argument("--record", metavar="FILE.rrd", help="write a Rerun recording of the residual against a "
                                                        "variable, before and after (open with: rerun FILE.rrd)")
    p.add_argument("--against", help="variable for --record (default: the first velocity state)")
    g = p.add_argument_group("gap comparison (collected simulator data sets only)")
    g.add_argument("--compare-gap", action="store_true",
                   help="certify the data against f and f' (paper's method) and report gamma max/mean")
    g.add_argument("--spec", metavar="FILE", help="specification JSON (simgap Spec.to_dict) for synthesizing with "
                                                  "both gaps; reports the winning-domain sizes (needs --eta)")
    g.add_argument("--eta", help="cell widths for the synthesis, comma-separated (one per state)")
    g.add_argument("--hold", type=count(1), default=1, help="sampling periods per abstract step (synthesis)")
    g.add_argument("--compose-hold", action="store_true",
                   help="with --hold > 1: compose the one-period gap over the held steps (not covered by the "
                        "paper's theorem when f is nonlinear; labelled in the report)")
    p.set_defaults(func=run, outputs=("out", "save_system", "record"),
                   formats={"out": (".json",), "save_system": (".json", ".toml"), "record": (".rrd",)})


def run(args) -> int:
    from ..refine.data import load_transitions
    from ..refine.effects import parse_user_terms
    from ..refine.refined import load_system, save_refined
    from ..refine.report import format_gap_comparison, format_table, refine
    from ..refine.selection import SelectionOptions

    system = load_system(args.system)
    data = _load(args.data, args, system)
    extra = _load(args.validate, args, system) if args.validate else None
    names = None
    if args.effects:
        names = [e.strip() for e in args.effects.split(",") if e.strip()]
        if not names:
            raise SimgapError("--effects: empty list")
    if names and "affine_ct" in names:
        return _affine(args, system, data, names)
    if args.save_system and Path(args.save_system).suffix.lower() == ".toml":
        raise SimgapError(f"--save-system {args.save_system!r}: library effects are saved as a refined-system JSON "
                          "(.json); a system file (.toml) is written for --effects affine_ct")
    _check_bootstrap(args.bootstrap, len(data.x))
    from ..refine.residual import match_tau
    from ..refine.effects import MAX_DELAY
    users = parse_user_terms(match_tau(system, data.tau), args.term, MAX_DELAY if data.is_time_series else 0)
    opts = SelectionOptions(holdout=args.holdout, n_segments=args.segments, min_explained=args.min_explained,
                            n_boot=args.bootstrap, seed=args.seed, weighted=args.weighted)
    res = refine(system, data, effects=names, user_terms=users, options=opts, name=args.name)
    if args.compare_gap or args.spec:
        res.report["gap_comparison"] = _compare(args, res)
    if extra is not None:
        from ..refine.report import validate
        res.report["validation"] = validate(res, extra)
    if not args.quiet:
        print(format_table(res.report))
        if "gap_comparison" in res.report:
            print(format_gap_comparison(res.report["gap_comparison"], res.system.state_names))
        if "validation" in res.report:
            from ..refine.report import format_validation
            print(format_validation(res.report["validation"], res.system.state_names))
    if args.out:
        out = Path(args.out)
        bad = _first_nonfinite(res.report)
        if bad:
            raise SimgapError(f"the refinement report holds {bad[1]} at {bad[0]}: the model (--system "
                              f"{args.system!r}) or the data evaluate to inf or NaN; nothing was written to {str(out)!r}")
        fileio.write_text(out, json.dumps(res.report, indent=2, allow_nan=False))
        if not args.quiet:
            print(f"report written to {out}")
    if args.save_system:
        save_refined(res.refined, args.save_system)
        if not args.quiet:
            print(f"refined system written to {args.save_system}")
    if args.record:
        try:
            from simgap_viz.record import record_refinement
        except ImportError:
            from ..paths import install_command
            raise SimgapError(f"--record needs simgap_viz and its dependencies ({install_command(None)})") from None
        info = record_refinement(args.record, res, against=args.against)
        if not args.quiet:
            print(f"recording written to {args.record} (residual vs {info['against']}; open with: rerun {args.record})")
    return 0


def _affine(args, system, data, names) -> int:
    """``--effects affine_ct``: the affine continuous-time fit (simgap.refine.affine_ct), its report
    and the refined system file."""
    from ..refine.affine_ct import fit_affine_ct, format_affine_table, save_system_file
    if names != ["affine_ct"]:
        raise SimgapError(f"--effects {args.effects!r}: affine_ct is fitted on its own (it holds every affine term "
                          "of the velocity states); give --effects affine_ct alone")
    for opt, val, default in (("--term", args.term, []), ("--validate", args.validate, None),
                              ("--spec", args.spec, None), ("--record", args.record, None)):
        if val != default:
            raise SimgapError(f"{opt} is not available with --effects affine_ct")
    if args.save_system and Path(args.save_system).suffix.lower() != ".toml":
        raise SimgapError(f"--save-system {args.save_system!r}: --effects affine_ct writes a system file; give a "
                          "path ending in .toml")
    if data.is_time_series:
        data = type(data)(x=data.x, u=data.u, x_next=data.x_next, tau=data.tau, source=data.source)
    fit = fit_affine_ct(system, data, holdout=args.holdout, seed=args.seed, name=args.name)
    if args.compare_gap:
        from ..refine.compare import gap_comparison
        path = Path(args.data)
        if not (path.is_dir() or (path.suffix == ".npz" and _is_dataset(path))):
            raise SimgapError("--compare-gap needs a collected data set (simgap collect output)")
        from ..dataset import load_dataset
        fit.report["gap_comparison"] = gap_comparison(load_dataset(path, system=fit.base), fit.system)
    if not args.quiet:
        print(format_affine_table(fit.report, system.state_names))
        if "gap_comparison" in fit.report:
            from ..refine.report import format_gap_comparison
            print(format_gap_comparison(fit.report["gap_comparison"], system.state_names))
    if args.out:
        bad = _first_nonfinite(fit.report)
        if bad:
            raise SimgapError(f"the refinement report holds {bad[1]} at {bad[0]}; nothing was written to {args.out!r}")
        fileio.write_text(Path(args.out), json.dumps(fit.report, indent=2, allow_nan=False))
        if not args.quiet:
            print(f"report written to {args.out}")
    if args.save_system:
        save_system_file(fit, args.save_system)
        if not args.quiet:
            print(f"refined system file written to {args.save_system}")
    return 0


#: seconds per row and bootstrap resample (simgap.refine.selection.bootstrap_stderr: a row's count, its
#: share of the weighted normal equations), measured here: 1.5e-7 to 2e-7 at 10^4 to 4 x 10^4 rows
BOOT_SECONDS_PER_ROW = 2e-7


def _check_bootstrap(n_boot: int, rows: int) -> None:
    """Refuse ``--bootstrap`` resamples of ``rows`` rows that would take longer than a command may
    (:data:`simgap.checks.MAX_COMMAND_SECONDS`), naming the option, the need and the limit."""
    from ..checks import MAX_COMMAND_SECONDS, human_seconds
    secs = float(n_boot) * rows * BOOT_SECONDS_PER_ROW
    if secs > MAX_COMMAND_SECONDS:
        raise SimgapError(f"--bootstrap {n_boot:,}: {n_boot:,} resamples of {rows:,} rows would take about "
                          f"{human_seconds(secs)}, more than the {human_seconds(MAX_COMMAND_SECONDS)} a command may "
                          "take; the standard errors need about 100 (the default)")


def _first_nonfinite(obj, where: str = "report"):
    """(path, value) of the first inf or NaN in a JSON-ready report, or None."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return where, obj
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, (list, tuple)) else ()
    for k, v in items:
        hit = _first_nonfinite(v, f"{where}[{k!r}]" if isinstance(k, str) else f"{where}[{k}]")
        if hit:
            return hit
    return None


def _load(path, args, system):
    """Transitions from a data file, or from a trajectory record (.mat) with --preset."""
    from ..refine.data import load_transitions
    if Path(path).suffix.lower() == ".mat":
        if not args.preset:
            raise SimgapError(f"{path}: a .mat trajectory record needs --preset (e.g. emps), or convert it "
                              f"first with simgap data from-trajectory")
        from ..refine.trajectory import from_trajectory_file
        return from_trajectory_file(path, preset=args.preset)
    return load_transitions(path, system=system, drop_nonfinite=args.drop_nonfinite)


def _compare(args, res) -> dict:
    from ..dataset import load_dataset
    from ..refine.compare import gap_comparison

    path = Path(args.data)
    if not (path.is_dir() or (path.suffix == ".npz" and _is_dataset(path))):
        raise SimgapError("--compare-gap/--spec need a collected data set (simgap collect output): the certificate "
                          "needs the per-(x_r, u) statistics of N1hat runs, not plain transitions")
    ds = load_dataset(path, system=res.system)
    spec = eta = None
    if args.spec:
        from ..synthesis.spec import Spec
        if not args.eta:
            raise SimgapError("--spec needs --eta (cell widths)")
        from ..file_guard import read_json
        try:
            spec = Spec.from_dict(read_json(args.spec, "--spec"))
        except (KeyError, TypeError) as e:
            raise SimgapError(f"--spec {args.spec!r}: not a readable specification JSON ({e})") from None
        try:
            eta = [float(v) for v in args.eta.split(",")]
        except ValueError:
            raise SimgapError(f"--eta {args.eta!r}: expected comma-separated numbers") from None
    return gap_comparison(ds, res.refined, spec=spec, eta=eta, hold=args.hold, compose_hold=args.compose_hold)


def _is_dataset(path: Path) -> bool:
    import numpy as np
    try:
        with np.load(path, allow_pickle=False) as z:
            return {"mean", "f_nom", "meta"} <= set(z.files)
    except (OSError, ValueError):
        return False

"""``simgap audit CERT --data DATA``: check a certificate against fresh simulator ground truth.

The simulator is rebuilt from the data set's manifest (its "simulator" config), or from the
manifest of ``--against DATA2``, and the certificate's data hash must match ``--data``. Each fresh
point and dimension is a test of |E fhat_i - f_i| <= gamma_i(x,u), Holm-corrected over all tests
at family-wise false-alarm rate --alpha; the power against a violated fraction --power-fraction
is printed. Exit status 0 when the audit passes, 1 when gamma is violated beyond the audit's
own Monte-Carlo error, 2 on bad input.
"""

from __future__ import annotations

import argparse

from ..checks import count, probability
from ..errors import SimgapError
from ..profiles import DEFAULT_PROFILE

#: defaults without an experiment (the experiment's [audit] section overrides them, flags override both)
POINTS, RUNS, SEED = 200, 2000, 12345


def audit_settings(args, system=None, simulator: dict | None = None) -> dict:
    """points, runs, seed and where they came from: flags, else the experiment's [audit], else the defaults.

    ``system`` / ``simulator``: the data set's; an ``--experiment`` of another system (name or steps) or
    simulator kind is refused: its [audit] settings were chosen for something else."""
    section, src = {}, "defaults"
    if args.experiment:
        from ..config import load_experiment
        exp = load_experiment(args.experiment, args.profile)
        ours = (system.name, int(system.steps)) if system is not None else None
        theirs = (exp.system.name, int(exp.system.steps))
        kind = (simulator or {}).get("kind")
        if ours is not None and (ours != theirs or (kind is not None and kind != exp.simulator.kind)):
            raise SimgapError(
                f"--experiment {args.experiment!r} is an experiment of system {theirs[0]!r} (steps {theirs[1]}) with "
                f"simulator {exp.simulator.kind!r}, but the data set is of system {ours[0]!r} (steps {ours[1]}) with "
                f"simulator {kind!r}: its [audit] settings belong to another experiment; give the certificate's own "
                "experiment, or --points/--runs/--seed without --experiment")
        section = exp.section("audit")
        src = f"{args.experiment} [audit]"
    out = {"points": int(section.get("points", POINTS)), "runs": int(section.get("runs", RUNS)),
           "seed": int(section.get("seed", SEED))}
    given = {k: getattr(args, k) for k in out if getattr(args, k) is not None}
    out.update(given)
    out["source"] = src + (f", flags {', '.join('--' + k for k in given)}" if given else "")
    return out


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("audit", help="audit a certificate with fresh simulator runs",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("cert", help="certificate JSON from `simgap certify`")
    p.add_argument("--data", required=True, help="the data set the certificate was computed from")
    p.add_argument("--against", metavar="DATA2",
                   help="audit against the simulator of another data set (e.g. a deterministic-baseline "
                        "certificate made with a noise-free simulator, against the noisy one)")
    p.add_argument("--system", metavar="NAME|FILE",
                   help="the nominal model the certificate is for, when it was certified with `simgap certify "
                        "--system` (a name, a system file .toml or a refined-system JSON); the simulator stays the "
                        "data set's")
    p.add_argument("--experiment", metavar="EXP",
                   help="read --points, --runs and --seed from this experiment's [audit] section (a name or .toml; "
                        "the flags override it)")
    p.add_argument("--profile", default=DEFAULT_PROFILE,
                   help="the experiment's profile (default: small, or the base settings when it has no small profile)")
    p.add_argument("--points", type=count(1), default=None,
                   help=f"fresh (x,u) points (default: the experiment's [audit] points, else {POINTS})")
    p.add_argument("--runs", type=count(2), default=None,
                   help=f"simulator runs per point (default: the experiment's [audit] runs, else {RUNS})")
    p.add_argument("--seed", type=int, default=None,
                   help=f"seed of the points and runs (default: the experiment's [audit] seed, else {SEED})")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--alpha", type=probability, default=None,
                   help="mean-level certificates: family-wise false-alarm rate of the Holm-corrected tests, in "
                        "(0, 1) (default 0.05); a run-level certificate is audited at its own alpha")
    p.add_argument("--power-fraction", type=probability, default=0.01,
                   help="violated fraction of (x,u) the printed power refers to (default 0.01)")
    p.add_argument("--out", help="write the audit report JSON here")
    p.set_defaults(func=run, outputs=("out",), formats={"out": (".json",)})


def run(args) -> int:
    from ..dataset import load_dataset
    from ..progress import ProgressBar
    from ..simulators import make_simulator

    # the settings and the estimate first (the certificate's modules take seconds to import)
    ds = load_dataset(args.data)
    src = load_dataset(args.against) if args.against else ds
    sim_cfg = src.manifest.get("simulator")
    if not sim_cfg:
        raise SimgapError(f"data set {args.against or args.data!r} has no simulator config in its manifest; "
                          f"cannot audit")
    st = audit_settings(args, ds.system, sim_cfg)
    print(f"audit settings: {st['points']:,} points x {st['runs']:,} runs, seed {st['seed']} ({st['source']})",
          flush=True)
    bar = None if args.no_progress else ProgressBar(unit="runs", desc="audit")
    with make_simulator(sim_cfg, system=ds.system) as sim:
        from ..certify.audit import audit_cost, audit_cost_text, audit_rate, check_audit_cost
        cost = audit_cost(st["points"], st["runs"], ds.system, audit_rate(sim, st["points"], st["runs"]))
        print(audit_cost_text(cost), flush=True)
        check_audit_cost(cost)
        from ..certify import load
        from ..certify.audit import audit, save_report
        from ..system_ref import resolve_system
        nominal = ds if args.system is None else ds.with_nominal(resolve_system(args.system))
        cert = load(args.cert, dataset=nominal)
        if cert.method == "run" and args.alpha is not None:
            raise SimgapError(f"--alpha {args.alpha:g}: not used for a run-level certificate (it is audited at its "
                              f"own alpha = {cert.options.get('alpha')}, the miss probability it claims); leave "
                              f"--alpha out")
        try:
            if cert.method == "run":  # run-level certificate: coverage of gamma^alpha, not the mean gap
                from ..perrun.run_audit import audit_run, report_table
                rep = audit_run(cert, sim, points=st["points"], runs=st["runs"], seed=st["seed"],
                                system=nominal.system, on_progress=bar)
            else:
                from ..certify.audit import report_table
                rep = audit(cert, sim, points=st["points"], runs=st["runs"], seed=st["seed"], dataset=ds,
                            alpha=0.05 if args.alpha is None else args.alpha, power_fraction=args.power_fraction,
                            system=nominal.system, on_progress=bar)
        finally:
            if bar:
                bar.close()
    rep["simulator_source"] = str(args.against or args.data)
    print(report_table(rep))
    if args.out:
        save_report(rep, args.out)
        print(f"wrote {args.out}")
    return 0 if rep["passed"] else 1

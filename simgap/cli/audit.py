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
    p.add_argument("--points", type=count(1), default=200, help="fresh (x,u) points (default 200)")
    p.add_argument("--runs", type=count(2), default=2000, help="simulator runs per point (default 2000)")
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--alpha", type=probability, default=None,
                   help="mean-level certificates: family-wise false-alarm rate of the Holm-corrected tests, in "
                        "(0, 1) (default 0.05); a run-level certificate is audited at its own alpha")
    p.add_argument("--power-fraction", type=probability, default=0.01,
                   help="violated fraction of (x,u) the printed power refers to (default 0.01)")
    p.add_argument("--out", help="write the audit report JSON here")
    p.set_defaults(func=run, outputs=("out",))


def run(args) -> int:
    from ..certify import load
    from ..certify.audit import audit, report_table, save_report
    from ..dataset import load_dataset
    from ..systems import resolve_system

    ds = load_dataset(args.data)
    nominal = ds if args.system is None else ds.with_nominal(resolve_system(args.system))
    cert = load(args.cert, dataset=nominal)
    if cert.method == "run" and args.alpha is not None:
        raise SimgapError(f"--alpha {args.alpha:g}: not used for a run-level certificate (it is audited at its own "
                          f"alpha = {cert.options.get('alpha')}, the miss probability it claims); leave --alpha out")
    src = load_dataset(args.against) if args.against else ds
    sim_cfg = src.manifest.get("simulator")
    if not sim_cfg:
        raise SimgapError(f"data set {args.against or args.data!r} has no simulator config in its manifest; "
                          f"cannot audit")
    from ..simulators import make_simulator
    with make_simulator(sim_cfg, system=ds.system) as sim:
        from ..checks import check_sim_work
        from ..cover import calibrate_rate
        n, m = ds.system.n, ds.system.m
        # the points go in chunks, each point's runs at once: at least one point's runs in memory
        check_sim_work(float(args.points) * args.runs, float(args.runs) * (3 * n + m) * 8 * 4 + args.points * n * 16.0,
                       f"auditing {args.points:,} points x {args.runs:,} runs", "use fewer --points or --runs",
                       calibrate_rate(sim, n_runs=65536, budget=0.3))
        if cert.method == "run":  # run-level certificate: coverage of gamma^alpha, not the mean gap
            from ..perrun.run_audit import audit_run, report_table
            rep = audit_run(cert, sim, points=args.points, runs=args.runs, seed=args.seed, system=nominal.system)
        else:
            rep = audit(cert, sim, points=args.points, runs=args.runs, seed=args.seed, dataset=ds,
                        alpha=0.05 if args.alpha is None else args.alpha,
                    power_fraction=args.power_fraction, system=nominal.system)
    rep["simulator_source"] = str(args.against or args.data)
    print(report_table(rep))
    if args.out:
        save_report(rep, args.out)
        print(f"wrote {args.out}")
    return 0 if rep["passed"] else 1

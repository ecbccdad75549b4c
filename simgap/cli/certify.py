"""``simgap certify DATA``: data set -> certificate JSON, with a summary table.

Examples::

    simgap certify data.npz --degree 2 --beta 0.01 --out cert.json
    simgap certify data.npz --delta 0.05 --term 2:"sin(theta)" --out cert.json
    simgap certify data.npz --method deterministic --out cert_det.json
    simgap certify data.npz --compare          # what each bound option does to delta and gamma
    simgap certify data/ --level run --alpha 0.05 --out cert_run.json   # gamma^alpha for single runs
"""

from __future__ import annotations

import argparse

from ..checks import probability
from ..errors import SimgapError


def _floats(text: str, name: str):
    try:
        vals = [float(v) for v in str(text).split(",")]
    except ValueError:
        raise SimgapError(f"--{name}: expected a number or comma-separated numbers, got {text!r}") from None
    return vals[0] if len(vals) == 1 else vals


def parse_terms(items, system) -> dict:
    """``DIM:EXPR`` items (DIM = a state name, 'all', or a 1-based dimension) -> {0-based dim or -1: [expr]}."""
    from ..certify.basis import term_dimension
    out = {}
    for item in items or []:
        if ":" not in item:
            raise SimgapError(f"--term {item!r}: expected DIM:EXPR, e.g. omega:'sin(theta)' or all:'x1*u1'")
        key, expr = item.split(":", 1)
        out.setdefault(term_dimension(key, system, one_based=True, where=f"--term {item!r}"), []).append(expr.strip())
    return out


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("certify", help="compute the stochastic simulation-gap certificate of a data set",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", help="data set (.npz or collection store directory)")
    p.add_argument("--system", metavar="NAME|FILE",
                   help="certify the gap of this nominal model (a built-in or plugin name, a system file .toml or a "
                        "refined-system JSON) on the data's simulator "
                        "runs: f_nom is recomputed, the empirical means are the data's (default: the data's model)")
    p.add_argument("--method", choices=["stochastic", "deterministic"], default="stochastic",
                   help="stochastic (paper) or the deterministic baseline (no delta, no confidence)")
    p.add_argument("--level", choices=["mean", "run"], default="mean",
                   help="mean: bound the gap of the expected next state (paper); run: gamma^alpha bounding one "
                        "run's deviation with probability >= 1 - alpha (docs/per-run.md)")
    p.add_argument("--alpha", type=probability, help="run level: per-dimension miss probability of one run, in (0, 1)")
    p.add_argument("--degree", default="2", help="total degree of the monomial basis (or one per dimension: 1,2,2); "
                                                 "-1 = user terms only")
    p.add_argument("--term", action="append", metavar="DIM:EXPR",
                   help="extra basis term for a dimension (1-based, state name or 'all'), e.g. 2:'sin(theta)'")
    g = p.add_argument_group("margins and confidence (give delta, beta, or both to check N1hat)")
    g.add_argument("--delta", help="delta_1 = delta_2 (state units; one value or one per dimension)")
    g.add_argument("--delta1", help="delta_1 only")
    g.add_argument("--delta2", help="delta_2 only")
    g.add_argument("--beta", help="target beta_1 = beta_2 (each lemma); the smallest deltas are computed")
    g.add_argument("--beta1", help="target beta_1 only")
    g.add_argument("--beta2", help="target beta_2 only")
    g.add_argument("--confidence", type=float, help="the joint confidence to state (all rows with --uniform): "
                   "beta1 = beta2 = (1 - confidence - n beta_v) / (2 n) in each of the n dimensions")
    g.add_argument("--variance", choices=["empirical", "maurer_pontil"], default="empirical",
                   help="Mhat: paper's safety x max sample variance, or Maurer-Pontil certified bound")
    g.add_argument("--safety", type=float, default=10.0, help="safety factor on the empirical variance (default 10)")
    g.add_argument("--range", type=float, dest="value_range", help="known range b of fhat_i (maurer_pontil, bernstein)")
    g.add_argument("--beta-v", type=float, default=0.001, help="failure probability of the Maurer-Pontil bound")
    b = p.add_argument_group("options beyond the paper (off by default)")
    b.add_argument("--concentration", choices=["chebyshev", "bernstein", "subgaussian"], default="chebyshev")
    b.add_argument("--uniform", action="store_true", help="simultaneous statement: union bound over all K cover rows in Lemma 1 and Lemma 2")
    b.add_argument("--lemma2-factor", type=float, choices=[2.0, 4.0], default=2.0,
                   help="Var(fhat(x)-fhat(x_r)) <= factor*Mhat: 2 (paper) or 4 (general)")
    b.add_argument("--lipschitz", choices=["increment", "state"], default="increment",
                   help="Lipschitz constants of the increments f-x (default) or of f itself")
    b.add_argument("--l2", choices=["analytic", "estimated"], default="analytic")
    b.add_argument("--lhat", choices=["data", "simulator"], default="data",
                   help="Lhat_fhat from the data's means (default) or from the simulator with common random numbers")
    b.add_argument("--lipschitz-term", choices=["paper", "gap"], default="paper",
                   help="the Lipschitz term of gamma: the paper's (L_f + Lhat_fhat + L_2) eps, or the gap's own slopes "
                        "times the cover's radius per dimension, sum_j L_ij eps_j (both are computed and shown)")
    b.add_argument("--continuous-inputs", action="store_true",
                   help="also certify gamma between the input grid's values (for controllers with any u in the box)")
    s = p.add_argument_group("solver")
    s.add_argument("--solver", choices=["CLARABEL", "HIGHS"], default="CLARABEL")
    s.add_argument("--scp", choices=["cg", "full"], default="cg", help="constraint generation or the whole LP")
    s.add_argument("--seed", type=int, default=0)
    p.add_argument("--compare", action="store_true",
                   help="certify under each bound option and print delta and gamma side by side")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (--lhat simulator, --compare)")
    p.add_argument("--out", help="write the certificate JSON here")
    p.add_argument("--sign-key", metavar="KEY", help="sign the certificate with this private key (simgap key new; "
                                                     "default: $SIMGAP_SIGNING_KEY, if set)")
    p.set_defaults(func=run, outputs=("out",), formats={"out": (".json",)})


def options_from_args(args, system):
    from ..certify import BoundOptions, CertifyOptions

    deg = _floats(args.degree, "degree")
    for d in deg if isinstance(deg, list) else [deg]:
        if d != int(d) or d < -1:
            raise SimgapError(f"--degree {args.degree!r}: each degree must be an integer >= 0 "
                              "(or -1 for the --term terms only)")
    deg = [int(d) for d in deg] if isinstance(deg, list) else int(deg)
    d1 = args.delta1 or args.delta
    d2 = args.delta2 or args.delta
    b1 = args.beta1 or args.beta
    b2 = args.beta2 or args.beta
    return CertifyOptions(
        method=args.method, degree=deg, terms=parse_terms(args.term, system),
        delta1=None if d1 is None else _floats(d1, "delta1"), delta2=None if d2 is None else _floats(d2, "delta2"),
        beta1=None if b1 is None else _floats(b1, "beta1"), beta2=None if b2 is None else _floats(b2, "beta2"),
        confidence=args.confidence,
        variance=args.variance, safety=args.safety, value_range=args.value_range, beta_v=args.beta_v,
        bounds=BoundOptions(concentration=args.concentration, lemma2_factor=args.lemma2_factor,
                            uniform=args.uniform, value_range=args.value_range),
        lipschitz_mode=args.lipschitz, l2=args.l2, lhat=args.lhat, lipschitz_term=args.lipschitz_term,
        continuous_inputs=args.continuous_inputs, scp_method=args.scp, solver=args.solver, seed=args.seed)


def check_certify_size(opts, ds) -> None:
    """Refuse a basis too large for the data set before building it (:func:`simgap.checks.check_basis`)."""
    from ..dataset import invariant_dims
    from ..checks import check_basis

    s = ds.system
    degs = list(opts.degree) if isinstance(opts.degree, (list, tuple)) else [opts.degree] * s.n
    terms = opts.terms or {}
    n_terms = max(len(terms.get(-1, [])) + len(terms.get(i, [])) for i in range(s.n))
    check_basis(ds.K, s.n + s.m - len(invariant_dims(ds)), degs, n_terms, what="--degree")
    import numpy as np

    from ..checks import check_degree_values  # the data's values per variable, as the collection's pre-check
    inv = invariant_dims(ds)
    values = {nm: len(np.unique(ds.x[:, j])) for j, nm in enumerate(s.state_names) if j not in inv}
    values.update({nm: len(np.unique(ds.u[:, k])) for k, nm in enumerate(s.input_names)})
    check_degree_values([d if d is not None else -1 for d in degs], values, s.state_names, "--degree",
                        {nm: f"data collected on a finer cover along {nm}" for nm in values})


def run(args) -> int:
    if args.level == "run":
        return _run_level(args)
    if args.alpha is not None:
        raise SimgapError("--alpha belongs to --level run (the mean-level certificate has beta, not alpha)")
    ds = _data(args)
    if args.compare:
        return _compare(args, ds)
    if args.lhat == "simulator":
        cert = _certify_with_simulator(args, ds)
    else:
        from ..certify import certify
        opts = options_from_args(args, ds.system)
        check_certify_size(opts, ds)
        cert = certify(ds, opts)
    print(cert.summary())
    if args.out:
        cert.save(args.out, sign_key=args.sign_key)
        print(f"wrote {args.out}")
    return 0


def _compare(args, ds) -> int:
    """``--compare``: the estimate first (with lhat = "simulator" its runs are timed on the simulator
    before any of them), then one progress bar over all the certifications, then the table."""
    import contextlib

    from ..certify.pipeline import compare_estimate_text, compare_options, comparison_table, lhat_cost
    from ..progress import ProgressBar
    opts = options_from_args(args, ds.system)
    check_certify_size(opts, ds)
    if opts.method != "stochastic":
        raise SimgapError("--compare needs the stochastic method")
    with contextlib.ExitStack() as stack:
        sim = cost = None
        if opts.lhat == "simulator":
            from ..simulators import make_simulator
            cfg = ds.manifest.get("simulator")
            if not cfg:
                raise SimgapError("--lhat simulator needs the data manifest's simulator config; this data set has "
                                  "none (use --lhat data)")
            sim = stack.enter_context(make_simulator(cfg, system=ds.system))
            cost = lhat_cost(ds, opts, sim)
        print(compare_estimate_text(ds, opts, cost), flush=True)
        bar = None if args.no_progress else ProgressBar(
            unit="certifications", desc="compare",  # the first certification's runs move it in fractions
            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total} certifications [{elapsed}<{remaining}]")
        try:
            rows = compare_options(ds, opts, simulator=sim, on_progress=bar)
        finally:
            if bar:
                bar.close()
    print(comparison_table(rows, ds.system.state_names))
    return 0


def _certify_with_simulator(args, ds):
    """certify with ``lhat="simulator"``: the simulator runs' estimate first (before the fitting
    modules are imported), then the options and a progress bar while the runs go."""
    from ..certify.lipschitz import crn_cost_text
    from ..certify.pipeline import lhat_cost
    from ..progress import ProgressBar
    from ..simulators import make_simulator

    cfg = ds.manifest.get("simulator")
    if not cfg:
        raise SimgapError("--lhat simulator needs the data manifest's simulator config; this data set has none "
                          "(use --lhat data)")
    opts = options_from_args(args, ds.system)
    check_certify_size(opts, ds)
    with make_simulator(cfg, system=ds.system) as sim:
        cost = lhat_cost(ds, opts, sim)  # every simulator run of this certify call: the gap's term's too
        if cost is not None:
            print(crn_cost_text(cost), flush=True)
        desc = "Lipschitz runs (simulator)" if cost and cost["gap_rows"] else "Lhat_fhat (simulator)"
        bar = None if args.no_progress else ProgressBar(unit="runs", desc=desc)
        from ..certify import certify
        try:
            return certify(ds, opts, simulator=sim, on_progress=bar)
        finally:
            if bar:
                bar.close()


def _data(args):
    """The data set, against ``--system`` when given (:meth:`simgap.dataset.Dataset.with_nominal`)."""
    from ..dataset import load_dataset
    from ..system_ref import resolve_system

    ds = load_dataset(args.data)
    return ds if args.system is None else ds.with_nominal(resolve_system(args.system))


def _run_level(args) -> int:
    from ..perrun.realization import RunCertifyOptions, certify_run

    if args.alpha is None:
        raise SimgapError("--level run needs --alpha (per-dimension miss probability of one run, in (0, 1))")
    ignored = [opt for opt, given in (("--method", args.method != "stochastic"), ("--delta", args.delta),
                                      ("--delta1", args.delta1), ("--delta2", args.delta2),
                                      ("--beta1", args.beta1), ("--beta2", args.beta2),
                                      ("--uniform", args.uniform), ("--compare", args.compare),
                                      ("--term", args.term)) if given]
    if ignored:
        raise SimgapError(f"{', '.join(ignored)}: not used at --level run (the run level bounds an order statistic of "
                          "the kept deviations with a Bonferroni union over all pairs; its options are --alpha, "
                          "--beta and --degree)")
    deg = _floats(args.degree, "degree")
    if isinstance(deg, list) or deg != int(deg) or deg < 0:
        raise SimgapError(f"--degree {args.degree!r}: --level run takes one integer degree >= 0")
    beta = 0.01 if args.beta is None else _floats(args.beta, "beta")
    if isinstance(beta, list):
        raise SimgapError("--beta: the run level takes one value (the whole certificate's failure probability)")
    opts = RunCertifyOptions(alpha=args.alpha, beta=beta, seed=args.seed, solver=args.solver,
                             degree=int(deg))
    opts.validate()  # before the data are loaded: bad input costs nothing
    if args.system is not None:
        raise SimgapError("--level run takes no --system: the per-run deviations were kept against the data's own "
                          "model; collect with that system instead (an experiment's system.name may be a refined "
                          "JSON)")
    ds = _data(args)
    check_certify_size(opts, ds)  # as the mean level: a basis too large is refused before any work
    cert = certify_run(ds, opts)
    print(cert.summary())
    print(f"alpha = {cert.options['alpha']:g} per dimension and run (smallest alpha these data support: "
          f"{cert.options['alpha_min']:.4g}); order statistic {cert.options['order_statistic']}")
    if args.out:
        cert.save(args.out, sign_key=args.sign_key)
        print(f"wrote {args.out}")
    return 0

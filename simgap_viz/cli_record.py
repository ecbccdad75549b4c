"""``simgap record``: a headless Rerun recording (.rrd) of a whole run.

Stages given as files (--dataset, --certificate, --controller, --rollouts) are loaded; the
others up to --upto are computed through the engine with the experiment's settings and the
overrides given here. Open the result with ``rerun run.rrd``.
"""

from __future__ import annotations

import argparse
import sys


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "record", help="headless Rerun recording (.rrd) of a run: map, winning domain, gamma, data, rollouts",
        description="Write a Rerun .rrd recording of a run (open it with `rerun FILE.rrd`). Stages not given "
                    "as files are computed through the engine up to --upto.")
    p.add_argument("--out", required=True, help="output .rrd file")
    p.add_argument("--experiment", default=None, help="experiment name or TOML file (e.g. pendulum)")
    p.add_argument("--profile", default=None, help="experiment profile (e.g. small)")
    p.add_argument("--system", default=None,
                   help="system when no experiment is given: a built-in or plugin name, a system file (.toml) "
                        "or a refined-system JSON")
    p.add_argument("--dataset", default=None, help="collected data (.npz or store directory)")
    p.add_argument("--certificate", default=None, help="certificate JSON (simgap certify --out)")
    p.add_argument("--controller", default=None, help="controller .npz (simgap synthesize --out)")
    p.add_argument("--rollouts", default=None, help="rollouts .npz (simgap rollout --out)")
    p.add_argument("--upto", default="rollout", choices=("collect", "certify", "synthesize", "rollout"),
                   help="last stage to compute when not given as a file (default rollout)")
    p.add_argument("--epsilon", type=float, default=None, help="cover radius epsilon")
    p.add_argument("--n-runs", type=int, default=None, help="N1hat runs per (x_r, u)")
    p.add_argument("--confidence", type=float, default=None, help="target joint confidence")
    p.add_argument("--degree", type=int, default=None, help="basis degree")
    p.add_argument("--terms", default=None, help="extra basis terms, comma separated (e.g. 'x3, u1, u2')")
    p.add_argument("--eta", default=None, help="grid cell widths, comma separated")
    p.add_argument("--hold", type=int, default=None, help="sampling periods an input is held")
    p.add_argument("--no-gap", action="store_true", help="synthesize on the nominal model alone")
    p.add_argument("--n-rollouts", type=int, default=None, help="number of rollouts (default 1000)")
    p.add_argument("--horizon", type=int, default=None, help="rollout length in simulator steps")
    p.add_argument("--x0", default=None, help="initial state, comma separated")
    p.add_argument("--executor", default="local", choices=("serial", "local"), help="collection executor")
    p.set_defaults(func=run, outputs=("out",), formats={"out": (".rrd",)})
    return p


def settings_from_args(args):
    """(settings, dataset, spec, arena, experiment) from the command line."""
    from .experiment import app_inputs
    from .settings import parse_vector

    settings, dataset, spec, arena, exp = app_inputs(experiment=args.experiment, profile=args.profile,
                                                     dataset=args.dataset, system=args.system)
    n = dataset.system.n if dataset is not None else None
    ch = {}
    for name, key in (("epsilon", "epsilon"), ("n_runs", "n_runs"), ("confidence", "confidence"),
                      ("degree", "degree"), ("hold", "hold"), ("n_rollouts", "n_rollouts"), ("horizon", "horizon")):
        v = getattr(args, name)
        if v is not None:
            ch[key] = v
    if dataset is not None:
        ch.update(system=dataset.system.name, steps=int(dataset.system.steps), epsilon=float(dataset.epsilon),
                  n_runs=int(dataset.n_runs))
    if args.terms is not None:
        ch["terms"] = args.terms
    if args.no_gap:
        ch["use_gap"] = False
    settings = settings.replace(**ch)
    from . import engine
    n = n or engine.make_system(settings, exp).n
    if args.eta:
        settings = settings.replace(eta=parse_vector(args.eta, "--eta", n))
    if args.x0:
        settings = settings.replace(x0=parse_vector(args.x0, "--x0", n))
    return settings, dataset, spec, arena, exp


def run(args) -> int:
    from simgap.rollout import load_rollout

    from .pipeline import compute, load_synthesis
    from .record import record_run

    settings, dataset, spec, arena, exp = settings_from_args(args)
    cert = syn = ro = None
    if args.certificate:
        from simgap.certify.certificate import load
        cert = load(args.certificate, dataset)
    from . import engine
    system = dataset.system if dataset is not None else engine.make_system(settings, exp)
    if args.controller:
        syn = load_synthesis(args.controller, system)
    if args.rollouts:
        ro = load_rollout(args.rollouts)
    res = compute(settings, experiment=exp, spec=spec, arena=arena, upto=args.upto, dataset=dataset,
                  certificate=cert, synthesis=syn, rollouts=ro, executor=args.executor)
    info = record_run(args.out, res.system, dataset=res.dataset, certificate=res.certificate, spec=res.spec,
                      synthesis=res.synthesis, rollouts=res.rollouts)
    print(f"wrote {args.out}: {info['bytes'] / 1e6:.1f} MB, {len(info['entities'])} entities, "
          f"{info['n_rollouts']} rollouts x {info['n_steps']} steps, logging {info['seconds']:.2f} s")
    print(f"open it with: rerun {args.out}   (without a display: simgap view {args.out})")
    if res.synthesis is not None and res.synthesis.empty:
        print("note: the winning domain is empty (no rollouts recorded)", file=sys.stderr)
    return 0

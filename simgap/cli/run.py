"""``simgap run EXPERIMENT``: the whole deterministic-vs-stochastic case study from one command."""

from __future__ import annotations

import sys
from pathlib import Path

from ..checks import count
from ..file_guard import output_dir
from ..profiles import DEFAULT_PROFILE


def add_parser(sub):
    p = sub.add_parser(
        "run", help="run a case study end to end: collect, certify (both methods), audit, synthesize, roll out",
        description="Collect (resumable), certify with the deterministic baseline and the stochastic method, "
                    "audit both, synthesize a controller with each, run closed-loop rollouts in the stochastic "
                    "simulator, and write results/<experiment>-<profile>/summary.json plus a Rerun recording.")
    p.add_argument("experiment", help="experiment name (assets/experiments/<name>.toml) or a TOML path")
    p.add_argument("--profile", default=DEFAULT_PROFILE,
                   help="profile in the experiment file (default: small, or the base settings when the file has no "
                        "small profile; base = no profile)")
    p.add_argument("--out", default=None, help="output folder (default results/<experiment>-<profile>)")
    p.add_argument("--executor", choices=("local", "serial", "ray"), default=None,
                   help="where the collections' chunks and the per-run stage's interval-MDP sampling run "
                        "(default: [collect] executor, else a local pool)")
    p.add_argument("--workers", type=count(1), default=None, help="worker processes / Ray CPUs (default: all cores)")
    p.add_argument("--address", default=None, help="Ray cluster address for --executor ray (default: a local "
                                                     "Ray instance)")
    p.add_argument("--rollouts", type=count(1), default=None,
                   help="closed-loop rollouts per controller (default: [rollout] n, else 1000)")
    p.add_argument("--no-record", action="store_true", help="skip the Rerun recording")
    p.add_argument("--force", action="store_true", help="replace the results of a different run (another experiment "
                                                        "or profile) that --out holds (refused otherwise)")
    p.set_defaults(func=run, output_dirs=("out",))


def run(args) -> int:
    from ..config import load_experiment
    from ..pipeline import comparison_table, per_run_note, run_experiment
    from ..progress import ProgressBar

    exp = load_experiment(args.experiment, args.profile)
    out = output_dir(args.out or Path("results") / f"{exp.name}-{exp.profile or 'base'}")
    print(f"simgap run {exp.name} (profile {exp.profile or 'base'}): results go to {out.absolute()}", file=sys.stderr)
    summary = run_experiment(exp, out, executor=args.executor, workers=args.workers, address=args.address,
                             n_rollouts=args.rollouts, force=args.force,
                             log=lambda m: print(m, file=sys.stderr, flush=True), progress=lambda stage, unit: ProgressBar(unit, desc=stage))
    print(comparison_table(summary))
    note = per_run_note(summary)
    if note:
        print()
        print(note)
    if "per_run" in summary:
        from ..perrun.stage import table
        print()
        print(table(summary["per_run"]))
    print(f"\nsummary: {out / 'summary.json'}")
    if not args.no_record:
        rrd = _record(exp, out)
        if rrd:
            print(f"recording: {rrd}   (open with: rerun {rrd}; without a display: simgap view {out})")
        written = ["run.rrd"] if rrd else []
        if rrd and "per_run" in summary:
            from simgap_viz.record_perrun import record_per_run

            from ..perrun.value_iteration import PerRunController
            record_per_run(out / "perrun.rrd", PerRunController.load(out / "controller_perrun.npz"), summary["per_run"])
            written.append("perrun.rrd")
            print(f"per-run recording: {out / 'perrun.rrd'}")
        from ..results_folder import add_files
        add_files(out, written)  # the recordings belong to this summary too
    print(f"GUI: simgap gui {out}")
    return 0


def _record(exp, out: Path):
    """Write out/run.rrd from the saved stage outputs: the deterministic method beside the stochastic one."""
    try:
        from simgap_viz.record import record_run
        from simgap_viz.results import load_run
    except ImportError:
        print("(simgap_viz not installed: no recording)", file=sys.stderr)
        return None
    from ..pipeline import experiment_spec

    run = load_run(out)
    spec, _, _ = experiment_spec(exp)
    methods = {m: run.methods[m] for m in ("deterministic", "stochastic") if m in run.methods}
    if run.nominal is not None:  # an invariant-set run's nominal-model set and rollouts
        methods["nominal"] = run.nominal
    record_run(out / "run.rrd", exp.system, spec=spec, methods=methods)
    return out / "run.rrd"

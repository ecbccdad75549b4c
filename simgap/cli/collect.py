"""``simgap collect EXPERIMENT``: build the epsilon-cover and collect the simulator data set.

Prints the cover size, (x_r, u) pairs, simulator steps and an estimated time (from a short
calibration of the simulator in this process) before running, shows a progress bar, and prints
where the data went. Re-running the same command resumes an interrupted collection.
"""

from __future__ import annotations

import argparse
import sys

from ..checks import count
from ..collect import check_collection, printed_collection_estimate
from ..config import builtin_experiments
from ..errors import SimgapError
from ..file_guard import output_dir
from ..profiles import DEFAULT_PROFILE


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "collect", help="collect simulator data on an epsilon-cover (resumable)",
        description="Collect N1hat simulator runs for every (cover point, input) pair of an experiment. "
                    f"EXPERIMENT is a TOML file or a built-in name ({', '.join(builtin_experiments())}). Running the same "
                    "command again resumes an interrupted collection.")
    p.add_argument("experiment", metavar="EXPERIMENT", help="experiment TOML path or built-in name")
    p.add_argument("--profile", default=DEFAULT_PROFILE,
                   help="profile in the TOML (default: small, or the base settings when the file has no small "
                        "profile; e.g. paper; base = no profile)")
    p.add_argument("--out", help="store directory (default: results/<experiment>-<profile>/data, where simgap run collects)")
    p.add_argument("--executor", choices=["local", "ray", "serial"], help="where chunks run (default from TOML)")
    p.add_argument("--workers", type=count(1), help="worker processes / Ray CPUs (default: all cores)")
    p.add_argument("--address", help="Ray cluster address (default: a local Ray instance)")
    p.add_argument("--seed", type=count(0), help="root seed")
    p.add_argument("--epsilon", type=float, help="cover radius epsilon")
    p.add_argument("--n-runs", type=count(2), dest="n_runs", help="N1hat, simulator runs per (x_r, u) pair")
    p.add_argument("--chunk-size", type=count(1), dest="chunk_size", help="(x_r, u) pairs per chunk")
    p.add_argument("--keep-samples", action="store_true", default=None, dest="keep_samples",
                   help="also store the raw N1hat next states per pair (large)")
    p.add_argument("--dry-run", action="store_true", help="print the cover size and cost estimate, collect nothing")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run, output_dirs=("out",))
    return p


def run(args) -> int:
    from ..collect import collect, store_status
    from ..config import load_experiment
    from ..cover import calibrate_rate, estimate_cost
    from ..executors import make_executor
    from ..progress import ProgressBar
    from ..simulators import make_simulator

    over = {"collect": {"seed": args.seed, "epsilon": args.epsilon, "n_runs": args.n_runs,
                        "chunk_size": args.chunk_size, "keep_samples": args.keep_samples,
                        "executor": args.executor, "workers": args.workers, "address": args.address,
                        "out": args.out}}
    exp = load_experiment(args.experiment, args.profile, overrides=over)
    if exp.collect.tube_margin is not None:  # the same cover along the nominal tube as `simgap run` collects
        from ..tube_collect import along_tube
        exp = along_tube(exp)
    c = exp.collect
    store = output_dir(exp.store_dir(), "store")
    print(f"experiment {exp.name} (profile {exp.profile or 'base'}): system {exp.system.name}, tau={exp.system.tau:g} s; "
          f"simulator {exp.simulator.kind}")
    cover = exp.cover()
    print(cover.summary())
    plan = exp.plan(cover)
    ex = make_executor(c.executor, c.workers, c.address)

    with make_simulator(exp.simulator, exp.system) as sim:
        rate = calibrate_rate(sim, budget=0.3, work=plan.n_pairs * float(plan.n_runs))
    # sizes refused before the workers time pairs (one pair of a huge N1hat would not fit in memory)
    check_collection(plan.n_pairs, plan.n_runs, exp.system.n, exp.system.m, exp.system.steps, plan.batch_runs,
                     ex.workers, plan.keep_samples, store, rate)
    est = printed_collection_estimate(plan, store, ex, c.workers, c.address, rate, ex.workers) \
        if ex.name in ("local", "serial") else \
        estimate_cost(cover, plan.n_runs, rate_per_worker=rate, workers=ex.workers,
                      rate_source=f"calibrated here, executor {ex.name}")
    print(est.summary())
    print(f"N1hat={plan.n_runs}, seed={plan.seed}, {plan.n_chunks} chunks of {plan.chunk_size} pairs")
    _check_certify_section(exp, plan)
    if args.dry_run:
        print(f"dry run: nothing collected (store would be {store.absolute()})")
        return 0

    if (store / "manifest.json").exists():
        st = store_status(store)
        if st["hash"] == plan.hash():
            print(f"resuming {store}: {st['done']} of {st['n_chunks']} chunks already done")
    bar = None if args.no_progress else ProgressBar(unit="pairs", scale=plan.n_runs * exp.system.steps,
                                                    scale_unit="sim steps")
    try:
        res = collect(plan, store, executor=ex, on_progress=bar)
    except KeyboardInterrupt:
        if bar:
            bar.close()
        print(f"interrupted; finished chunks are kept in {store}: run the same command to resume", file=sys.stderr)
        raise
    finally:
        if bar:
            bar.close()
    rate_s = res.runs * exp.system.steps / res.seconds if res.seconds > 0 and res.runs else 0.0
    print(f"collected {res.computed} chunks ({res.runs:,} simulator runs) in {res.seconds:.1f} s"
          + (f", {rate_s:,.0f} simulator steps/s" if rate_s else ""))
    print(f"data: {store.absolute()} ({plan.n_pairs:,} pairs, hash {res.hash[:12]})")
    print(f"load with: simgap.dataset.load_dataset({str(store)!r})")
    return 0


def _check_certify_section(exp, plan) -> None:
    """Warn, before collecting, when the experiment's own [certify] settings will be refused on these
    data (``simgap run`` refuses them before its collection; ``simgap certify`` takes its own flags,
    so here it is a warning)."""
    if not exp.section("certify"):
        return
    from ..pipeline import METHODS, certify_options, check_against_cover
    try:
        for method in METHODS:
            check_against_cover(exp.system, plan.cover, certify_options(exp.section("certify"), method, exp.system))
    except SimgapError as e:
        print(f"warning: these data will not certify with the experiment's settings: {e}", file=sys.stderr)

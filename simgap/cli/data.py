"""``simgap data``: prepare transition data for ``simgap refine``.

``simgap data from-trajectory``: a measured time series (only positions measured) -> the
transition .npz (x, u, x_next, tau, t). Velocities come from a zero-phase Butterworth
low-pass of the positions and central differences; edge samples are trimmed; inputs are
filtered with the same filter unless --no-filter-input.

Examples::

    simgap data from-trajectory DATA_EMPS.mat --preset emps --cutoff 20 --out emps_20hz.npz
    simgap data from-trajectory --preset emps --record validation --out emps_val.npz
        (the EMPS record found through $SIMGAP_EMPS_DIR or ../shared/data/emps)
    simgap data from-trajectory log.csv --time t --position q --input u --cutoff 15 --out log.npz
"""

from __future__ import annotations

import argparse

from ..errors import SimgapError


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("data", help="prepare transition data (e.g. from a measured trajectory)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="data_command", metavar="ACTION")
    t = sub.add_parser("from-trajectory", help="measured trajectory (.mat/.csv/.npz) -> transition .npz",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    t.add_argument("file", nargs="?", help="trajectory file (.mat, .csv, .npz); with --preset emps it may be "
                                          "omitted: the EMPS --record is looked up ($SIMGAP_EMPS_DIR)")
    t.add_argument("--preset", help="known record layout: emps (t, qm, vir)")
    t.add_argument("--record", choices=("estimation", "validation"), default="estimation",
                   help="with --preset emps and no file: which EMPS record (default estimation)")
    t.add_argument("--time", help="name of the time variable [s]")
    t.add_argument("--position", action="append", help="name of a measured position variable (repeatable)")
    t.add_argument("--input", action="append", help="name of an input variable (repeatable)")
    t.add_argument("--cutoff", type=float, help="low-pass cutoff [Hz] (preset default: emps 20 Hz)")
    t.add_argument("--order", type=int, default=4, help="Butterworth order (applied forwards and backwards)")
    t.add_argument("--trim", type=int, help="samples dropped at each edge (default max(20, 2 fs / cutoff))")
    t.add_argument("--no-filter-input", action="store_true", help="do not filter the inputs")
    t.add_argument("--out", required=True, help="transition .npz to write")
    t.set_defaults(func=run_from_trajectory, outputs=("out",), formats={"out": (".npz",)})
    p.set_defaults(func=lambda args: (p.print_help(), 0)[1])


def run_from_trajectory(args) -> int:
    from ..refine.trajectory import from_trajectory_file

    if not args.out.endswith(".npz"):
        raise SimgapError(f"--out {args.out!r}: the transition file must end in .npz")
    if args.file is None:
        if args.preset != "emps":
            raise SimgapError("give the trajectory file (only --preset emps can find its record by itself)")
        from ..records import emps_record

        args.file = str(emps_record(args.record))
        print(f"EMPS {args.record} record: {args.file}")
    tr = from_trajectory_file(args.file, preset=args.preset, time=args.time, positions=args.position,
                              inputs=args.input, cutoff_hz=args.cutoff, order=args.order, trim=args.trim,
                              filter_input=not args.no_filter_input)
    tr.save_npz(args.out)
    m = tr.meta
    print(f"{m['samples_in']} samples at {m['fs_hz']:g} Hz -> {tr.K} transitions (tau = {tr.tau:g} s), "
          f"low-pass {m['cutoff_hz']:g} Hz order {m['order']} (zero phase), trimmed {m['trim']} samples "
          f"per edge, input {'filtered' if m['filter_input'] else 'unfiltered'}")
    print(f"x = ({', '.join(m['positions'])}, velocity) range {tr.x.min(axis=0).tolist()} .. "
          f"{tr.x.max(axis=0).tolist()}")
    print(f"written to {args.out}")
    return 0

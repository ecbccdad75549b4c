"""``simgap synthesize``: certificate + specification -> symbolic controller file and a summary.

    simgap synthesize --system turtlebot --steps 10 --cert cert.json --spec arena --eta 0.08 \\
        --out turtlebot.npz
    simgap synthesize --system pendulum --no-gap --safe 0,0.2,-0.5,0.5 --eta 0.002,0.005 \\
        --out pendulum.npz

``--spec`` is a map (a name under assets/maps or a .toml map file: reach-avoid with the map's
target and obstacles grown by the robot radius), an experiment (a name under
assets/experiments or an experiment .toml: its system, ``[synthesis]`` spec, eta and hold are
the defaults), or a JSON file holding ``Spec.to_dict()``; ``--safe`` gives an invariance spec
directly. Exactly one of ``--cert``, ``--gamma`` and
``--no-gap`` says how the simulation gap enters. U is restricted to the inputs the certificate
covers (the summary says so). With a gap, ``--hold k > 1`` is refused unless ``--compose-hold``
is given: the default abstract step is the certificate's own step (``--steps``).

``--level run`` synthesizes on an interval MDP sampled from the experiment's simulator (its
``[perrun]`` section: eta, hold, n_runs, pilot_runs, beta, horizon) and writes a time-varying
controller with the certified one-run success probability p_cert per cell (docs/per-run.md)::

    simgap synthesize --level run --spec pendulum --profile noisy --out perrun.npz

Its simulator work runs in chunks on a local pool (``--executor``, ``--workers``; Ray with
``--executor ray --address HOST:PORT``), kept in ``--store`` and resumed from it if given; the
projected cost is printed first and work this machine cannot hold is refused.

Exit status: 0 with a controller written (and x0, when one is requested or recorded, winning),
1 when the winning domain is empty (nothing written; the summary says why), 2 on bad input, 3 when
the controller is written but the requested x0 lies outside its winning domain.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from .. import fileio
from ..checks import count
from ..profiles import DEFAULT_PROFILE

#: exit status: a controller was written, but the requested x0 is outside its winning domain
X0_OUTSIDE = 3
from ..errors import SimgapError
from ..systems import BUILTIN


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "synthesize", help="synthesize a symbolic controller that treats the certified gap as a disturbance",
        description="Abstraction on a uniform grid (SCOTS conventions) and a reach-avoid or invariance game; "
                    "writes the controller (.npz) and prints grid size, boxes/transitions, winning domain and times.")
    p.add_argument("--system", default=None,
                   help=f"built-in or plugin system name ({', '.join(sorted(BUILTIN))}; see simgap plugins), a system "
                        "file (.toml) or a refined-system JSON; default: the experiment's, else the one the "
                        "certificate records")
    p.add_argument("--steps", type=int, default=None,
                   help="base periods per sampling period (default: the certificate's, else 1)")
    p.add_argument("--hold", type=int, default=None,
                   help="sampling periods per abstract step, input held (default: the experiment's, else 1); "
                        "with a gap only together with --compose-hold")
    p.add_argument("--compose-hold", action="store_true",
                   help="accept a one-period gap composed over --hold periods (not covered by the certificate "
                        "for a nonlinear model; labelled in the controller). Default: certify at the abstraction "
                        "step and use --steps")
    p.add_argument("--level", choices=["mean", "run"], default="mean",
                   help="mean: robust game on the certified gap (default); run: interval MDP from the experiment's "
                        "simulator with p_cert per cell (needs an experiment --spec with a [perrun] section)")
    p.add_argument("--horizon", type=int, default=None, help="--level run: horizon in sampling periods "
                                                                "(default: [perrun] or [rollout] horizon); "
                                                                "--method box_tube: the periods of the per-run "
                                                                "statement (default 2 T0 + 1)")
    p.add_argument("--executor", choices=["local", "ray", "serial"], default="local",
                   help="--level run: where the interval MDP's sampling chunks run (default: a local pool)")
    p.add_argument("--workers", type=count(1), default=None,
                   help="--level run: worker processes / Ray CPUs (default: all cores)")
    p.add_argument("--address", default=None, help="--level run: Ray cluster address (default: a local Ray instance)")
    p.add_argument("--store", default=None, help="--level run: keep the sampling's chunks in this folder; the same "
                                                 "command resumes an interrupted sampling from it (kill -9 included)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--cert", help="certificate JSON written by 'simgap certify'")
    g.add_argument("--gamma", help="a constant gap per state dimension, comma separated (or one value)")
    g.add_argument("--no-gap", action="store_true", help="synthesize on the nominal model alone")
    s = p.add_mutually_exclusive_group(required=True)
    s.add_argument("--spec", help="map (name or .toml), experiment (name or .toml) or a JSON spec file")
    s.add_argument("--safe", help="invariance: safe box lo1,hi1,lo2,hi2,... (one pair per state)")
    p.add_argument("--eta", default=None,
                   help="cell width, one value or one per state dimension (comma separated); "
                        "default: the experiment's [synthesis] eta")
    p.add_argument("--profile", default=DEFAULT_PROFILE,
                   help="experiment profile (with an experiment --spec; default: small, or the base settings when "
                        "the file has no small profile)")
    p.add_argument("--out", required=True, help="controller file to write (.npz)")
    p.add_argument("--x0", default=None, help="initial state to record and check (default: the map's)")
    p.add_argument("--json", default=None, help="also write the statistics as JSON here")
    p.add_argument("--method", choices=["grid", "invariant_set", "box_tube"], default=None,
                   help="grid: abstraction and game (default); invariant_set: a linear feedback on an ellipsoid "
                        "proved invariant under the gap; box_tube: a time-varying feedback on a box tube from x0 "
                        "to a box around an equilibrium (reach and stay; needs --x0) (invariance specs; "
                        "docs/synthesis.md). Default: the experiment's [synthesis] method, else grid")
    p.add_argument("--no-strict-domain", action="store_true",
                   help="let cells stick out of X by eta/2 (SCOTS's convention) instead of blocking them")
    p.set_defaults(func=run, outputs=("out", "json"), output_dirs=("store",))


def _floats(text: str, what: str) -> np.ndarray:
    try:
        v = np.array([float(t) for t in str(text).replace(" ", ",").split(",") if t != ""])
    except ValueError:
        raise SimgapError(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if v.size == 0 or not np.all(np.isfinite(v)):
        raise SimgapError(f"{what}: expected finite numbers, got {text!r}")
    return v


def load_spec(text: str, system):
    """A Spec from a map name/.toml file or a JSON spec file; also returns the map's x0 or None."""
    from ..synthesis.spec import Spec
    path = Path(text)
    if path.suffix == ".json":
        from ..file_guard import read_json
        d = read_json(path, "spec file")
        try:
            return Spec.from_dict(d), None
        except (KeyError, TypeError) as e:
            raise SimgapError(f"spec file {text!r} is not a spec ({e})") from None
    amap = _load_map(text)
    return amap.spec(system), amap.x0(system)


def _load_map(text: str):
    """The map ``text`` names; an unknown name is answered with the shipped maps and experiments."""
    from ..config import builtin_experiments
    from ..maps import load_map
    try:
        return load_map(text)
    except SimgapError as e:
        if "unknown map" in str(e):
            raise SimgapError(f"{e}; built-in experiments: {', '.join(builtin_experiments())} (--spec takes a map, "
                              "an experiment or a spec .json)") from None
        raise


def _experiment_path(text: str):
    """The experiment file ``text`` names, or None when it is a map / spec file."""
    from ..maps import MAPS_DIR
    path = Path(text)
    if path.suffix == ".json":
        return None
    if path.suffix == ".toml" and path.is_file():
        import tomllib
        try:
            raw = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError):
            return None  # the map loader reports the problem
        return path if "system" in raw and "obstacles" not in raw else None
    if (MAPS_DIR / f"{text}.toml").is_file():
        return None
    from ..config import EXPERIMENTS_DIR
    return EXPERIMENTS_DIR / f"{text}.toml" if (EXPERIMENTS_DIR / f"{text}.toml").is_file() else None


def run(args) -> int:
    if args.level == "run":
        return _run_level(args)
    if not (args.cert or args.gamma or args.no_gap):
        raise SimgapError("give one of --cert, --gamma or --no-gap (how the simulation gap enters)")
    from ..system_ref import resolve_system
    from ..synthesis.controller import synthesize
    from ..synthesis.spec import Box, Spec

    cert = None
    if args.cert:
        from ..certify.certificate import load as load_cert
        cert = load_cert(args.cert)
        if cert.method == "run":
            raise SimgapError(
                f"--cert {args.cert!r} is a run-level certificate (gamma^alpha, alpha = "
                f"{cert.options.get('alpha')}): it bounds one run's deviation with probability 1 - alpha, not the "
                "gap of the mean, so a mean-level controller built on it would claim a mean-map guarantee it does "
                "not give. Use a mean-level certificate (simgap certify without --level run), or --level run")
    exp = _experiment_path(args.spec) if args.spec else None
    syn = {}
    x0 = None
    if exp is not None:
        from ..config import load_experiment
        from ..pipeline import experiment_spec
        e = load_experiment(exp, args.profile)
        syn = e.section("synthesis")
        system = e.system
        if args.system is not None and resolve_system(args.system).name != system.name:
            raise SimgapError(f"--system {args.system!r} does not match the experiment's system {system.name!r}")
        if args.steps is not None and args.steps != system.steps:
            system = system.with_steps(args.steps)
        from ..synthesis import invariant_stage
        invariant_stage.check_method(syn, args.method)
        spec, x0, _ = experiment_spec(e)
        if x0 is None and "x0" in e.section("rollout"):  # recorded, so `simgap rollout` needs no --x0
            x0 = _floats(",".join(map(str, np.ravel(e.section("rollout")["x0"]))), "[rollout] x0")
            system.check_states(x0[None], what="[rollout] x0")
    else:
        recorded = cert.nominal_system() if cert is not None and args.system is None else None
        if args.system is None and recorded is None:
            if args.spec and Path(args.spec).suffix != ".json":
                _load_map(args.spec)  # names an unknown map or experiment before asking for --system
            raise SimgapError("give --system (or an experiment as --spec)")
        steps = args.steps if args.steps is not None else (getattr(cert, "steps", 1) if cert is not None else 1)
        system = resolve_system(args.system, steps) if recorded is None else recorded.with_steps(steps)
    if cert is not None:
        cert.check_system(system)
        gap = cert
    elif args.gamma:
        gap = _floats(args.gamma, "--gamma")
    else:
        gap = None
    if args.safe:
        v = _floats(args.safe, "--safe")
        if v.size != 2 * system.n:
            raise SimgapError(f"--safe: need {2 * system.n} numbers (lo, hi per state), got {v.size}")
        lo, hi = v[0::2], v[1::2]
        bad = np.flatnonzero(lo > hi)
        if bad.size:
            i = int(bad[0])
            raise SimgapError(f"--safe: the pair for {system.state_names[i]} is lo = {lo[i]:g} > hi = {hi[i]:g}; give "
                              "lo1,hi1,lo2,hi2,... with each lo <= hi")
        spec = Spec(kind="invariance", safe=Box(lo, hi))
    elif exp is None:
        spec, x0 = load_spec(args.spec, system)
    if args.x0 is not None:
        x0 = _floats(args.x0, "--x0")
        system.check_states(x0[None], what="--x0")
    method = args.method or syn.get("method", "grid")
    if method in ("invariant_set", "box_tube"):
        return _invariant_set(args, system, spec, gap, dict(syn, method=method), x0)
    if args.eta is not None:
        eta = _floats(args.eta, "--eta")
    elif "eta" in syn:
        eta = np.asarray(syn["eta"], dtype=float).ravel()
    else:
        raise SimgapError("give --eta (cell width)")
    if eta.size not in (1, system.n):
        raise SimgapError(f"--eta: need 1 or {system.n} values, got {eta.size}")
    hold = args.hold if args.hold is not None else int(syn.get("hold", 1))
    from ..progress import ProgressBar
    bar = ProgressBar(unit="classes", desc="abstraction")
    try:
        res = synthesize(system, spec, eta, gap=gap, hold=hold, strict_domain=not args.no_strict_domain,
                         x0=x0, compose_hold=args.compose_hold, log=lambda m: print(m, flush=True),
                         on_progress=bar)
    finally:
        bar.close()
    return _finish(args, res, x0, spec, "EMPTY winning domain", "the winning domain")


def _invariant_set(args, system, spec, gap, syn, x0) -> int:
    """--method invariant_set / box_tube: design, prove, write (nothing written when no set is proved)."""
    from ..synthesis import invariant_stage
    meth = syn["method"]
    if args.hold not in (None, 1):
        raise SimgapError(f"--method {meth} applies u(x) every period: --hold must be 1")
    invariant_stage.check_section(system, dict(syn, hold=1), spec)
    res = invariant_stage.synthesize(system, spec, gap, syn, x0=x0, horizon=args.horizon,
                                     log=lambda t: print(f"[synthesize] {t}", file=sys.stderr, flush=True))
    if meth == "box_tube":
        return _finish(args, res, x0, spec, "no box tube proved", "the box tube")
    return _finish(args, res, x0, spec, "no invariant set proved", "the invariant set E")


def _finish(args, res, x0, spec, empty: str, domain: str) -> int:
    """Print the result, write the stats and the controller; exit 1 when nothing was won, 3 when the
    controller is written but x0 lies outside its domain (rollouts from x0 are refused)."""
    print(res.summary())
    if args.json:
        _write_json(args.json, res.stats)
    if res.empty:
        print(f"result: {empty}, no controller written")
        return 1
    ctrl = res.controller
    ctrl.save(args.out)
    print(f"wrote         {args.out}")
    if x0 is None:
        return 0
    if not ctrl.winning(x0[None])[0]:
        print(f"result: x0 {np.asarray(x0).tolist()} is OUTSIDE {domain}: the controller is written (its domain "
              "can be looked at) but rollouts from x0 are refused (exit status 3)")
        return X0_OUTSIDE
    if hasattr(ctrl, "steps_to_go") and spec.kind == "reach_avoid":
        print(f"x0            {np.asarray(x0).tolist()}: winning, {int(ctrl.steps_to_go(x0[None])[0])} "
              f"abstract steps to go (worst case)")
    else:
        print(f"x0            {np.asarray(x0).tolist()}: winning")
    return 0


def _write_json(path, obj) -> None:
    fileio.write_json(path, obj)


def _run_level(args) -> int:
    from ..config import load_experiment
    from ..perrun.stage import synthesize_experiment

    if args.cert or args.gamma or args.no_gap:
        raise SimgapError("--level run learns its transition probabilities from the simulator; drop --cert/--gamma/--no-gap")
    exp = _experiment_path(args.spec) if args.spec else None
    if exp is None:
        raise SimgapError("--level run needs an experiment as --spec (its simulator and [perrun] section)")
    e = load_experiment(exp, args.profile)
    x0 = None if args.x0 is None else _floats(args.x0, "--x0")
    if args.eta is not None:
        from ..perrun.stage import check_eta
        check_eta(_floats(args.eta, "--eta"), e.system, "--eta")
    from ..progress import ProgressBar
    ctl, text = synthesize_experiment(e, horizon=args.horizon, x0=x0,
                                      eta=None if args.eta is None else _floats(args.eta, "--eta").tolist(),
                                      hold=args.hold, on_progress=ProgressBar("pairs", desc="interval MDP"),
                                      log=lambda m: print(m, file=sys.stderr, flush=True), executor=args.executor,
                                      workers=args.workers, address=args.address, store=args.store)
    print(text)
    ctl.save(args.out)
    print(f"wrote {args.out}")
    return 0

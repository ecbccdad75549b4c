"""``simgap rollout``: run a saved controller on a stochastic simulator R times and report.

    simgap rollout --controller ctrl.npz --simulator sim.json --x0 3.5 2 1.5 --n 1000 \\
                   --horizon 800 --seed 0 --out report.json --trajectories traj.npz

The report gives the rollouts, the nominal model, the mean map m+ = E fhat(m, u(m)) (what the
controller's guarantee is about; ``--mean-map-runs`` runs per step) and, separately, the
average of the rollouts. ``--simulator`` takes a JSON SimulatorConfig (file or inline
``{...}``) or an experiment (name or TOML, via :func:`simgap.config.load_experiment`). ``--map`` supplies the PyBullet
TurtleBot's physical obstacles (when the config has none) and the default x0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..checks import count
from ..errors import SimgapError


def add_parser(sub) -> None:
    p = sub.add_parser("rollout", help="closed-loop rollouts of a controller on a stochastic simulator",
                       description="Run R closed-loop rollouts of a synthesized controller on a stochastic "
                                   "simulator (batched, seeded) plus the nominal model; write a JSON report.")
    p.add_argument("--controller", required=True, help="controller file written by 'simgap synthesize'")
    p.add_argument("--simulator", required=True,
                   help="simulator: JSON SimulatorConfig file or inline JSON, or an experiment name/TOML")
    p.add_argument("--profile", default=None, help="experiment profile (with an experiment --simulator)")
    p.add_argument("--map", default=None, help="map name or TOML: obstacles for the PyBullet world, default x0")
    p.add_argument("--x0", nargs="+", default=None, help="initial state, e.g. --x0 3.5 2 1.5 or --x0 3.5,2,1.5")
    p.add_argument("--n", type=count(1), default=None,
                   help="number of rollouts R (default: an experiment --simulator's [rollout] n, else 1000)")
    p.add_argument("--horizon", type=count(1), default=None,
                   help="simulator steps T (default: an experiment --simulator's [rollout] horizon, else from the "
                        "controller)")
    p.add_argument("--seed", type=count(0), default=None,
                   help="seed of the numpy generator (default: an experiment --simulator's [rollout] seed, else 0)")
    p.add_argument("--hold", type=count(1), default=None,
                   help="simulator steps per controller query: only what the controller records (its proof's; "
                        "another is refused)")
    p.add_argument("--on-exit", choices=("hold", "stop"), default="hold",
                   help="outside the winning domain: keep the last input (hold) or stop the rollout")
    p.add_argument("--one-at-a-time", action="store_true", help="step rollouts one by one (benchmarking)")
    p.add_argument("--mean-map-runs", type=count(0), default=None,
                   help="simulator runs per step for the mean map m+ = E fhat(m, u(m)), the sequence the "
                        "controller's guarantee is about (default: --n clipped to [100, 1000]; 0 skips it)")
    p.add_argument("--out", required=True, help="JSON report path")
    p.add_argument("--trajectories", default=None, help="also write all arrays to this .npz")
    p.set_defaults(func=run, outputs=("out", "trajectories"), formats={"out": (".json",), "trajectories": (".npz",)})


def parse_vector(tokens, what: str) -> np.ndarray:
    """Numbers from CLI tokens ("3.5 2 1.5" or "3.5,2,1.5")."""
    parts = [t for tok in tokens for t in str(tok).replace(",", " ").split()]
    try:
        return np.array([float(t) for t in parts])
    except ValueError:
        raise SimgapError(f"{what}: expected numbers, got {' '.join(map(str, tokens))!r}") from None


def load_controller(path):
    """A controller saved by the synthesis engine (``simgap.synthesis.controller``)."""
    if not Path(path).is_file():
        raise SimgapError(f"controller file {str(path)!r} does not exist")
    try:
        from ..synthesis import controller as cmod
    except ImportError as e:
        raise SimgapError(f"controller support is not available in this installation ({e})") from None
    for name in ("load_controller", "load"):
        fn = getattr(cmod, name, None)
        if callable(fn):
            return fn(path)
    return cmod.Controller.load(path)


def simulator_config(arg: str, profile=None, rollout_section: dict | None = None) -> dict:
    """SimulatorConfig dict from a JSON file / inline JSON, or from an experiment (name or TOML).

    ``rollout_section``, if given, receives the experiment's ``[rollout]`` section (empty for JSON)."""
    text = None
    if arg.lstrip().startswith("{"):
        text = arg
    elif arg.endswith(".json"):
        from ..file_guard import read_text
        text = read_text(arg, "simulator config file")
    if text is not None:
        from ..file_guard import loads_json, printable
        d = loads_json(text, f"simulator config {printable(arg[:60])!r}")
        if not isinstance(d, dict):
            raise SimgapError("simulator config: expected a JSON object")
        d = d.get("simulator", d)  # a whole experiment/manifest JSON also works
        from ..simulators.base import SimulatorConfig
        return SimulatorConfig.from_dict(d).to_dict()
    try:
        from ..config import load_experiment
    except ImportError:
        raise SimgapError(f"--simulator {arg!r}: not JSON, and experiment files are not supported in this "
                          f"installation") from None
    exp = load_experiment(arg, profile) if profile is not None else load_experiment(arg)
    if rollout_section is not None:
        rollout_section.update(exp.section("rollout"))
    sim = getattr(exp, "simulator", None)
    if sim is None and isinstance(exp, dict):
        sim = exp.get("simulator")
    if sim is None:
        raise SimgapError(f"experiment {arg!r} defines no simulator")
    return sim.to_dict() if hasattr(sim, "to_dict") else dict(sim)


def run(args) -> int:
    from ..maps import load_map
    from ..simulators import make_simulator
    from ..rollout import rollout

    ctrl = load_controller(args.controller)
    section: dict = {}
    cfg = simulator_config(args.simulator, args.profile, section)
    n = args.n if args.n is not None else int(section.get("n", 1000))
    seed = args.seed if args.seed is not None else int(section.get("seed", 0))
    horizon = args.horizon if args.horizon is not None else section.get("horizon")
    given = [f"--{k}" for k in ("n", "seed", "horizon") if getattr(args, k) is not None]
    src = "[rollout] of " + args.simulator if section else "defaults"
    print(f"rollout settings: n {n}, seed {seed}, horizon {horizon if horizon is not None else 'from the controller'}"
          f" ({src}" + (f", flags {', '.join(given)}" if given else "") + ")", flush=True)
    amap = load_map(args.map) if args.map else None
    if amap is not None and cfg.get("kind") == "pybullet_turtlebot" and not cfg.get("options", {}).get("obstacles"):
        cfg = dict(cfg, options={**cfg.get("options", {}), **amap.simulator_options()})
    spec = getattr(ctrl, "spec", None)
    if (cfg.get("kind") == "pybullet_turtlebot" and spec is not None and spec.obstacles
            and not cfg.get("options", {}).get("obstacles")):
        print("note: the PyBullet world has no obstacle bodies; collisions are judged from the controller's "
              "spec only (pass --map to build them)")
    sim = make_simulator(cfg, getattr(ctrl, "system", None))  # the controller's X and inputs
    from ..progress import ProgressBar
    bar = ProgressBar(unit="steps", desc="rollouts, then mean map")
    try:
        if args.x0 is not None:
            x0 = parse_vector(args.x0, "--x0")
        elif getattr(ctrl, "x0", None) is not None:
            x0 = np.asarray(ctrl.x0, dtype=float)
        elif amap is not None:
            x0 = amap.x0(sim.system)
        else:
            raise SimgapError("give --x0 (or --map, whose initial_state is used)")
        res = rollout(ctrl, sim, x0, n_rollouts=n, horizon=horizon, seed=seed, hold=args.hold,
                      on_exit=args.on_exit, batched=not args.one_at_a_time, mean_map_runs=args.mean_map_runs,
                      on_estimate=lambda text: print(text, flush=True), on_progress=bar)
    finally:
        bar.close()
        sim.close()
    res.save_json(args.out)
    if args.trajectories:
        res.save_npz(args.trajectories)
    print("\n".join(res.summary_lines()))
    print(f"report: {args.out}" + (f", trajectories: {args.trajectories}" if args.trajectories else ""))
    return 0

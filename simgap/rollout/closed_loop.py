"""Closed-loop rollouts: a synthesized controller driving the stochastic simulator, R runs at once.

Semantics
---------
Time is counted in *simulator steps* t = 0..T of length ``tau`` = simulator.system.tau [s]
(``steps_s`` in seconds = t * tau). The controller is queried every ``hold`` simulator steps
at the current state (its abstract step) and its input is held in between:

* ``hold`` defaults to (controller base periods per abstract step) / (simulator base periods per
  step) = controller.system.steps * controller.hold / simulator.system.steps, which must be an
  integer: a controller synthesized on a system with steps = k (or with ``hold=k``) applies each
  input for k base periods, whether the simulator runs them as one step of k*tau0 or k steps of tau0.
* The specification is checked on every simulator state x(t), t >= 1 (also between two controller
  queries, so a collision in mid-hold counts). Reach-avoid: the rollout **succeeds** when it
  reaches the target at some t <= T before any violation (leaving X or entering a -- grown --
  obstacle); a state that is both in the target and violating counts as a violation.
  Invariance: it succeeds when no state x(0..T) leaves the safe set or X.
* A rollout stops at its first violation or (reach-avoid) when it reaches the target. Its
  trajectory row keeps the last state after it stopped (no NaN padding, so the mean trajectory
  and drawing need no masks); ``lengths[i]`` is the index of that last real state.
* Leaving the winning domain: when the controller returns -1 at a query time, the time is
  recorded in ``left_domain_time``. With ``on_exit="hold"`` (default) the rollout keeps applying
  its previous input (the fallback) and is judged by the specification alone; with
  ``on_exit="stop"`` it stops there with outcome ``left_domain`` (counted as a failure).
  The initial state must be in the winning domain (SimgapError otherwise).

Randomness: one ``numpy.random.Generator`` (from ``seed``); at every simulator step the noise for
all R rollouts is drawn with ``simulator.draw_noise(R, rng)`` and the still-active rows are
passed to ``simulator.step_with_noise`` (with ``randomize.per = "episode"`` the per-run parameters
are replaced by each rollout's, drawn once from a child generator: persistent randomization). Rollout i's noise therefore does not depend on which
other rollouts are still running, and the one-at-a-time mode (``batched=False``, for the
benchmark) reproduces the batched results exactly.

The nominal model f (the controller's system at the simulator's step length) is run from the
same x0 with the same controller and rules, as one deterministic trajectory.

The controller's guarantee concerns neither the rollouts nor their average but the mean map
m+ = E fhat(m, u(m)) (:mod:`simgap.rollout.mean_map`); :func:`rollout` computes it too
(``mean_map_runs`` simulator runs per step from the current mean, its own child generator, so
the rollouts' draws do not depend on it) and reports it separately from the rollout average.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import SimgapError
from ..synthesis.spec import Spec
from .judge import LEFT_DOMAIN, OUTCOMES, SUCCESS, TIMEOUT, VIOLATION, VIOLATION_KINDS, circular_mean, classify
from .mean_map import mean_map
from .result import RolloutResult

DEFAULT_HORIZON = 1000


class _NominalModel:
    """The nominal model f as a noise-free 'simulator' (same interface as Simulator)."""

    def __init__(self, system):
        self.system = system

    def draw_noise(self, B, rng):
        return {}

    def step_with_noise(self, x, u, noise):
        return self.system.f(x, u)


@dataclass
class _Trace:
    """Raw arrays of one batched run (internal)."""

    traj: np.ndarray
    lengths: np.ndarray
    outcome: np.ndarray
    violation_time: np.ndarray
    violation_kind: np.ndarray
    reach_time: np.ndarray
    left_domain_time: np.ndarray
    input_index: np.ndarray
    robot_steps: int
    sim_seconds: float
    ctrl_seconds: float


def _run(controller, sim, spec: Spec, x0: np.ndarray, R: int, T: int, hold: int,
         rng: np.random.Generator, on_exit: str, batched: bool, progress=None) -> _Trace:
    """Run R closed-loop rollouts for T simulator steps (see module docstring)."""
    system = sim.system
    n = system.n
    U = controller.system.inputs
    x_lo, x_hi = system.x_lo, system.x_hi
    reach_avoid = spec.kind == "reach_avoid"

    traj = np.empty((R, T + 1, n))
    traj[:, 0] = x0
    uidx = np.full((R, T), -1, dtype=np.int32)
    lengths = np.zeros(R, dtype=np.int64)
    outcome = np.full(R, SUCCESS if not reach_avoid else TIMEOUT, dtype=np.int8)
    vtime = np.full(R, -1, dtype=np.int64)
    vkind = np.zeros(R, dtype=np.int8)
    rtime = np.full(R, -1, dtype=np.int64)
    ltime = np.full(R, -1, dtype=np.int64)
    cur = np.full(R, -1, dtype=np.int64)
    x = np.repeat(x0[None], R, axis=0)
    alive = np.ones(R, dtype=bool)
    # randomize.per = "episode": per-run parameters drawn once per rollout, from a child stream
    episode = sim.draw_episode(R, rng.spawn(1)[0]) if getattr(sim, "per_episode", False) else None
    if reach_avoid and spec.reached(x0[None])[0]:
        rtime[:] = 0
        outcome[:] = SUCCESS
        alive[:] = False

    robot_steps = 0
    t_sim = t_ctrl = 0.0
    continuous = bool(getattr(controller, "continuous_input", False))
    timed = bool(getattr(controller, "time_varying", False))
    cur_u = np.zeros((R, system.m))  # the held input values (a continuous-input controller)
    for t in range(T):
        act = np.flatnonzero(alive)
        if act.size == 0:
            break
        if t % hold == 0:
            c0 = time.perf_counter()
            # a time-varying controller (the box tube) is told its period since x0
            kw = {"t": t // hold} if timed else {}
            if batched:
                q = np.asarray(controller.input_index(x[act], **kw), dtype=np.int64).reshape(-1)
            else:
                q = np.array([int(np.asarray(controller.input_index(x[i:i + 1], **kw)).reshape(-1)[0]) for i in act])
            uq = controller.input(x[act], strict=False, **kw) if continuous else None
            t_ctrl += time.perf_counter() - c0
            out = q < 0
            if out.any():
                lost = act[out]
                ltime[lost[ltime[lost] < 0]] = t
                if on_exit == "stop":
                    outcome[lost] = LEFT_DOMAIN
                    alive[lost] = False
                    act, q = act[~out], q[~out]
                    uq = uq[~out] if continuous else None
                    if act.size == 0:
                        break
                else:  # fallback: keep the previous input (x0 is in the domain, so one exists)
                    q[out] = cur[lost]
                    if continuous:
                        uq[out] = cur_u[lost]
            cur[act] = q
            if continuous:
                cur_u[act] = uq
        # noise for all R rows, so rollout i's draws do not depend on the others
        noise = sim.draw_noise(R, rng)
        if episode:
            noise = sim.with_episode(noise, episode)
        u = cur_u[act] if continuous else U[cur[act]]
        s0 = time.perf_counter()
        if batched:
            xn = sim.step_with_noise(x[act], u, {k: v[act] for k, v in noise.items()})
        else:
            xn = np.concatenate([sim.step_with_noise(x[i:i + 1], u[j:j + 1], {k: v[i:i + 1] for k, v in noise.items()})
                                 for j, i in enumerate(act)])
        t_sim += time.perf_counter() - s0
        xn = np.asarray(xn, dtype=float)
        if not np.all(np.isfinite(xn)):
            raise SimgapError(f"simulator {getattr(getattr(sim, 'config', None), 'kind', 'nominal')!r} "
                              f"returned NaN/inf at step {t + 1}")
        robot_steps += act.size
        x[act] = xn
        traj[act, t + 1] = xn
        lengths[act] = t + 1
        uidx[act, t] = cur[act]
        kind = classify(spec, xn, x_lo, x_hi)
        bad = kind > 0
        if bad.any():
            ib = act[bad]
            vtime[ib] = t + 1
            vkind[ib] = kind[bad]
            outcome[ib] = VIOLATION
            alive[ib] = False
        if reach_avoid:
            hit = spec.reached(xn) & ~bad
            if hit.any():
                ih = act[hit]
                rtime[ih] = t + 1
                outcome[ih] = SUCCESS
                alive[ih] = False
        if progress is not None:
            progress(t + 1, T)
    # rollouts that stopped keep their last state (see module docstring)
    idx = np.minimum(np.arange(T + 1)[None, :], lengths[:, None])
    traj = traj[np.arange(R)[:, None], idx]
    return _Trace(traj, lengths, outcome, vtime, vkind, rtime, ltime, uidx, robot_steps, t_sim, t_ctrl)


def resolve_hold(controller, simulator) -> int:
    """Simulator steps per controller query: controller base periods per abstract step
    (controller.system.steps * controller.hold) over simulator base periods per step."""
    cs, ss = controller.system, simulator.system
    if not np.isclose(cs.base_tau, ss.base_tau):
        raise SimgapError(f"controller base tau {cs.base_tau:g} s differs from the simulator's {ss.base_tau:g} s")
    periods = int(cs.steps) * int(getattr(controller, "hold", 1) or 1)
    if periods % int(ss.steps):
        raise SimgapError(f"controller holds its input for {periods} base periods, not a multiple of the "
                          f"simulator step ({ss.steps} base periods)")
    return periods // int(ss.steps)


def steps_to_go(controller, x0: np.ndarray) -> Optional[float]:
    """The controller's (worst-case) abstract steps to go at x0 when it reports them
    (``steps_to_go``/``value``), else None."""
    for name in ("steps_to_go", "value"):
        fn = getattr(controller, name, None)
        if callable(fn):
            try:
                v = float(np.asarray(fn(x0[None])).reshape(-1)[0])
            except Exception:  # an optional hint only
                continue
            if np.isfinite(v) and v >= 0:
                return v
    return None


#: steps of the nominal model's path run before the estimate (it is run to the horizon later if it has not stopped)
NOMINAL_PROBE = 1000


def _check_rollout_seconds(seconds: float, n_rollouts: int, horizon: int) -> None:
    """Refuse rollouts estimated to take more than a command may (:data:`simgap.checks.MAX_COMMAND_SECONDS`;
    ``SIMGAP_NO_SIZE_CHECK=1`` lifts it), naming the counts, the need and the limit."""
    import os

    from ..checks import MAX_COMMAND_SECONDS, human_seconds
    if seconds > MAX_COMMAND_SECONDS and not os.environ.get("SIMGAP_NO_SIZE_CHECK"):
        raise SimgapError(f"rollout: {int(n_rollouts):,} rollouts x horizon {int(horizon):,} would take about "
                          f"{human_seconds(seconds)} (the estimate above), more than the "
                          f"{human_seconds(MAX_COMMAND_SECONDS)} a command may take; use fewer rollouts (--n) or a "
                          "shorter --horizon (or set SIMGAP_NO_SIZE_CHECK=1 to run it anyway)")


def default_horizon(controller, x0: np.ndarray, hold: int) -> int:
    """A horizon in simulator steps: 2x the controller's steps-to-go at x0 (+1 abstract step) when it
    reports one (``steps_to_go``/``value``), else DEFAULT_HORIZON."""
    v = steps_to_go(controller, x0)
    return DEFAULT_HORIZON if v is None else int(max(hold * (2 * v + 1), hold))


def expected_rollout_steps(spec, nominal, controller, x0, hold: int):
    """The simulator steps a rollout is expected to take before it stops (None: the whole horizon).

    Reach-avoid runs end at the target: the nominal model's closed loop from x0 (``nominal``, a
    one-run result of ``_run``) gives the steps when it reaches the target, else the controller's
    worst-case steps to go x hold (+ one hold) when it reports them. Other specifications run to
    the horizon."""
    if spec.kind != "reach_avoid":
        return None
    if nominal is not None and int(nominal.outcome[0]) == SUCCESS and int(nominal.reach_time[0]) >= 0:
        return max(1, int(nominal.reach_time[0]))
    v = steps_to_go(controller, x0)
    return None if v is None else hold * (v + 1)


def rollout_cost(n_rollouts: int, horizon: int, mean_map_runs: int, rate=None, expected_steps=None) -> dict:
    """Simulator runs and time of :func:`rollout` before it runs.

    At most R T runs for the rollouts (every rollout to the horizon; runs that stop early cost
    less) and, with the mean map, T (runs + G floor(runs / G)) <= 2 T runs for its estimate and its
    G repetitions (``rows``, ``max_seconds``). ``expected_steps``: the steps a run is expected to
    take (a reach-avoid controller's worst-case steps to go from x0 x hold: runs end at the
    target); ``seconds`` then prices min(T, expected_steps) steps per run, else T.
    ``seconds`` = runs / rate at ``rate`` [simulator runs/s] (None: unknown)."""
    R, T, mm = int(n_rollouts), int(horizon), int(mean_map_runs)
    G = min(10, mm // 2) if mm else 0
    per_step = float(R) + ((mm + G * (mm // G)) if mm else 0.0)
    rows = per_step * T
    steps = T if expected_steps is None else min(T, max(1, int(np.ceil(expected_steps))))
    return {"n_rollouts": R, "horizon": T, "mean_map_runs": mm, "rollout_rows": float(R) * T,
            "mean_map_rows": rows - float(R) * T, "rows": rows, "expected_steps": steps, "rate": rate,
            "seconds": per_step * steps / rate if rate else None, "max_seconds": rows / rate if rate else None}


def rollout_cost_text(c: dict) -> str:
    """:func:`rollout_cost` as the line the commands print before the rollouts start."""
    from ..cover import format_duration
    if c["seconds"] is None:
        t = "time unknown"
    elif c["expected_steps"] < c["horizon"]:
        t = (f"about {format_duration(c['seconds'])} if the runs end at the target within the expected "
             f"{c['expected_steps']} steps from x0 (the nominal path's, else the controller's steps to go), at most {format_duration(c['max_seconds'])} at the full "
             f"horizon, at {c['rate']:,.0f} runs/s (calibrated here)")
    else:
        t = f"at most about {format_duration(c['seconds'])} at {c['rate']:,.0f} runs/s (calibrated here)"
    mm = (f" + mean map {c['mean_map_runs']:,} runs x 2 x {c['horizon']:,} steps" if c["mean_map_runs"]
          else " (no mean map)")
    return (f"estimate: {c['n_rollouts']:,} rollouts x {c['horizon']:,} steps{mm} = {c['rows']:,.0f} "
            f"simulator runs; {t}")


def rollout(controller, simulator, x0=None, n_rollouts: int = 1000, horizon: Optional[int] = None,
            seed: Optional[int] = 0, rng: Optional[np.random.Generator] = None, hold: Optional[int] = None,
            spec: Optional[Spec] = None, on_exit: str = "hold", batched: bool = True,
            progress=None, mean_map_runs: Optional[int] = None, on_estimate=None,
            on_progress=None) -> RolloutResult:
    """Run ``n_rollouts`` closed-loop rollouts of ``controller`` on ``simulator`` from ``x0``.

    Parameters
    ----------
    controller
        Anything with ``input_index(x (B,n)) -> (B,) int`` (row of ``controller.system.inputs``,
        -1 outside the winning domain), ``system`` and ``spec``; optional ``hold``. A controller
        with ``continuous_input = True`` (the invariant-set controller) gives its input values by
        ``input(x, strict=False)``; its ``input_index`` is 0 inside its set and -1 outside.
    simulator
        A :class:`~simgap.simulators.base.Simulator` (``draw_noise``, ``step_with_noise``, ``system``).
    x0 : (n,) array
        Initial state [state units]; must be in X, not violate the spec, and be in the winning
        domain. Default: ``controller.x0`` if the controller records one.
    n_rollouts : int
        R, the number of independent rollouts.
    horizon : int, optional
        T in simulator steps of tau [s]; default :func:`default_horizon`.
    seed, rng
        Randomness: ``rng`` if given, else ``numpy.random.default_rng(seed)``.
    hold : int, optional
        Simulator steps per controller query: :func:`resolve_hold`, what the controller's proof
        assumed (another value is refused).
    spec : Spec, optional
        Judge against this spec instead of ``controller.spec``.
    on_exit : {"hold", "stop"}
        What a rollout does when the controller returns -1 (module docstring).
    batched : bool
        One simulator call per step for all active rollouts (default) or one call per rollout
        (same results; for benchmarks).
    progress : callable, optional
        ``progress(t, T)`` after every simulator step (GUI progress bars; raise to cancel).
    mean_map_runs : int, optional
        Simulator runs per step for the mean map m+ = E fhat(m, u(m)) (>= 4; 0 skips it).
        Default: n_rollouts clipped to [100, 1000], so it costs about as much as the rollouts.
    on_estimate : callable, optional
        ``on_estimate(text)`` once before any rollout: the work and time of everything this call
        simulates (:func:`rollout_cost_text`, the simulator's rate measured here in about 0.3 s).
    on_progress : callable, optional
        ``on_progress(done, total)`` in simulator steps of the horizon: the rollouts' T steps, then
        the mean map's T (total = 2 T with the mean map, T without).

    Returns
    -------
    RolloutResult
    """
    start = time.perf_counter()
    system = simulator.system
    if controller.system.n != system.n or controller.system.m != system.m:
        raise SimgapError(f"controller for {controller.system.name!r} (n={controller.system.n}, m={controller.system.m}) "
                          f"does not match the simulator's system {system.name!r} (n={system.n}, m={system.m})")
    spec = spec if spec is not None else controller.spec
    if spec is None:
        raise SimgapError("rollout: the controller records no specification; pass spec=")
    if on_exit not in ("hold", "stop"):
        raise SimgapError(f"rollout: on_exit must be 'hold' or 'stop', got {on_exit!r}")
    if int(n_rollouts) != n_rollouts or n_rollouts < 1:
        raise SimgapError(f"rollout: n_rollouts must be an integer >= 1, got {n_rollouts!r}")
    n_rollouts = int(n_rollouts)
    if x0 is None:
        x0 = getattr(controller, "x0", None)
        if x0 is None:
            raise SimgapError("rollout: give an initial state x0")
    x0 = system.check_states(np.asarray(x0, dtype=float).reshape(1, -1), what="rollout x0")[0]
    x0 = system.wrap(x0[None])[0]
    kind0 = classify(spec, x0[None], system.x_lo, system.x_hi)[0]
    if kind0:
        raise SimgapError(f"rollout x0 {x0.tolist()} violates the specification ({VIOLATION_KINDS[kind0]})")
    if int(np.asarray(controller.input_index(x0[None])).reshape(-1)[0]) < 0 and not (
            spec.kind == "reach_avoid" and spec.reached(x0[None])[0]):
        raise SimgapError(f"rollout x0 {x0.tolist()} is outside the controller's winning domain")
    if getattr(controller, "time_varying", False) and not bool(controller.winning(x0[None], t=0)[0]):
        # a tube's proof starts at its own x0 (its box at period 0): from elsewhere it proves nothing
        raise SimgapError(f"rollout x0 {x0.tolist()} is outside the controller's box at period 0: its proof starts at "
                          f"x0 = {np.asarray(controller.x0).tolist()}; roll out from there (drop --x0), or synthesize "
                          "a tube from this x0")
    if hold is not None and (int(hold) != hold or hold < 1):
        raise SimgapError(f"rollout: hold must be an integer >= 1, got {hold!r}")
    proved = resolve_hold(controller, simulator)
    if hold is not None and int(hold) != proved:
        raise SimgapError(f"rollout: hold = {hold!r} simulator steps per input, but the controller was proved with its "
                          f"input held {proved} step(s) (its hold {getattr(controller, 'hold', 1)} x its "
                          f"{controller.system.steps} base period(s) per step, over the simulator's "
                          f"{simulator.system.steps}): another hold voids its guarantee; drop the hold")
    hold = proved
    if horizon is None:
        horizon = default_horizon(controller, x0, hold)
    if int(horizon) != horizon or horizon < 1:
        raise SimgapError(f"rollout: horizon must be an integer >= 1 simulator steps, got {horizon!r}")
    horizon = int(horizon)
    from ..checks import check_memory
    # trajectories (R, T+1, n) float64 + inputs (R, T) int32, and the mean trajectory's copy
    check_memory(n_rollouts * (horizon + 1) * (2 * system.n * 8 + 4), f"{n_rollouts:,} rollouts x horizon {horizon:,}",
                 "use fewer rollouts (--n) or a shorter --horizon")
    if mean_map_runs is None:
        mean_map_runs = int(np.clip(n_rollouts, 100, 1000))
    if int(mean_map_runs) != mean_map_runs or 0 < mean_map_runs < 4 or mean_map_runs < 0:
        raise SimgapError(f"rollout: mean_map_runs must be 0 (skip) or an integer >= 4 (two groups of two: the "
                          f"propagated standard error), got {mean_map_runs!r}")
    if mean_map_runs:
        from ..checks import check_sim_work
        from ..cover import calibrate_rate
        work = float(mean_map_runs) * horizon
        # each step simulates mean_map_runs runs from the mean: states, noise and next states at once;
        # the simulator's rate is measured (0.5 s) only when the work could be long
        check_sim_work(work, float(mean_map_runs) * (3 * system.n + system.m) * 8 * 4,
                       f"the mean map with {int(mean_map_runs):,} runs per step x horizon {horizon:,}",
                       "use fewer --mean-map-runs (the standard error falls as 1/sqrt(runs))",
                       calibrate_rate(simulator, n_runs=65536, budget=0.3) if work > 1e9 else None)
    estimate_s = None
    nom_sys = controller.system.with_steps(system.steps)
    nt = None
    if on_estimate is not None:
        from ..cover import calibrate_rate
        # the nominal model's closed loop from x0 (cheap, deterministic; reported with the results):
        # a reach-avoid run is expected to end where the nominal path reaches the target
        # only a reach-avoid run ends early, and at most NOMINAL_PROBE steps before the estimate: a long
        # horizon's own nominal path (a model in formulas: ~1 ms a step) must not delay it
        probe = min(horizon, NOMINAL_PROBE) if spec.kind == "reach_avoid" else 0
        nt = _run(controller, _NominalModel(nom_sys), spec, x0, 1, probe, hold, np.random.default_rng(0), on_exit,
                  True) if probe else None
        cost = rollout_cost(n_rollouts, horizon, int(mean_map_runs),
                            # the rate at the batch the rollouts step (R rows per call, mean map runs per call)
                            calibrate_rate(simulator, n_runs=max(int(n_rollouts), int(mean_map_runs), 1), budget=0.3,
                                           work=(float(n_rollouts) + float(mean_map_runs)) * horizon),
                            expected_steps=expected_rollout_steps(spec, nt, controller, x0, hold))
        estimate_s = cost["seconds"]
        on_estimate(rollout_cost_text(cost))
        nominal_s = 0.0
        if nt is None or (probe < horizon and int(nt.lengths[0]) >= probe):
            nt = None  # the nominal path did not stop within the probe: run it to the horizon after the rollouts
            if horizon > NOMINAL_PROBE:  # then it is long work of its own (one run, one model step at a time)
                k = min(horizon, 20)
                t0 = time.perf_counter()
                _run(controller, _NominalModel(nom_sys), spec, x0, 1, k, hold, np.random.default_rng(0), on_exit, True)
                from ..cover import format_duration
                nominal_s = (time.perf_counter() - t0) / k * horizon
                on_estimate(f"estimate: then the nominal model's path, 1 run x up to {horizon:,} steps one at a time: "
                            f"at most about {format_duration(nominal_s)} (timed here)")
        _check_rollout_seconds((estimate_s or 0.0) + nominal_s, n_rollouts, horizon)
    if rng is None:
        rng = np.random.default_rng(seed)
    else:
        seed = None
    mm_rng = rng.spawn(1)[0]  # a child stream: the rollouts' draws do not depend on the mean map
    total = horizon * (2 if mean_map_runs else 1)

    def step_done(offset):
        if progress is None and on_progress is None:
            return None

        def report(t, T):
            if progress is not None and offset == 0:
                progress(t, T)
            if on_progress is not None:
                on_progress(offset + t, total)
        return report

    w0, c0 = time.perf_counter(), time.process_time()
    tr = _run(controller, simulator, spec, x0, n_rollouts, horizon, hold, rng, on_exit, batched, step_done(0))
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0

    if nt is None:
        nt = _run(controller, _NominalModel(nom_sys), spec, x0, 1, horizon, hold, np.random.default_rng(0), on_exit,
                  True)
    nominal = {"outcome": OUTCOMES[int(nt.outcome[0])], "satisfied": bool(nt.outcome[0] == SUCCESS),
               "reach_time": int(nt.reach_time[0]), "violation_time": int(nt.violation_time[0]),
               "violation_kind": VIOLATION_KINDS[int(nt.violation_kind[0])],
               "left_domain_time": int(nt.left_domain_time[0]), "length": int(nt.lengths[0]),
               "x_lo": system.x_lo.tolist(), "x_hi": system.x_hi.tolist()}
    m0 = time.perf_counter()
    mm = mean_map(controller, simulator, spec, x0, int(mean_map_runs), horizon, hold, mm_rng, on_exit,
                  progress=step_done(horizon)) if mean_map_runs else None
    if on_progress is not None:
        on_progress(total, total)  # runs that all stopped early end the count too
    cfg = getattr(simulator, "config", None)
    # total_wall_s: everything this call did (checks, rate calibration, rollouts, nominal run, mean map)
    timing = {"mean_map_s": time.perf_counter() - m0, "wall_s": wall, "total_wall_s": time.perf_counter() - start,
              "estimate_s": estimate_s,
              "simulator_s": tr.sim_seconds, "controller_s": tr.ctrl_seconds,
              "cpu_s": cpu, "robot_steps": int(tr.robot_steps),
              "robot_steps_per_s": tr.robot_steps / wall if wall > 0 else 0.0,
              "robot_steps_per_cpu_s": tr.robot_steps / cpu if cpu > 0 else 0.0,
              "batched": bool(batched)}
    return RolloutResult(
        x0=x0, trajectories=tr.traj, lengths=tr.lengths, outcome=tr.outcome, violation_time=tr.violation_time,
        violation_kind=tr.violation_kind, reach_time=tr.reach_time, left_domain_time=tr.left_domain_time,
        input_index=tr.input_index, mean_trajectory=circular_mean(tr.traj, system.angle_dims),
        nominal_trajectory=nt.traj[0], nominal=nominal, spec=spec, tau=float(system.tau), hold=hold,
        horizon=horizon, seed=seed, on_exit=on_exit, system=system.name,
        simulator=cfg.to_dict() if hasattr(cfg, "to_dict") else {}, timing=timing,
        mean_map_trajectory=None if mm is None else mm.trajectory, mean_map=None if mm is None else mm.to_dict(),
        controller_digest=(getattr(controller, "meta", None) or {}).get("digest"))

"""The set-based synthesis stage (formerly ``set_synthesis``): the methods inside ``simgap run`` and ``simgap synthesize``: ``[synthesis] method =
"invariant_set"`` (an ellipsoid) and ``"box_tube"`` (a box tube from x0, reach and stay): checks before
any work, the synthesis call with the experiment's options, and the rollouts from states drawn in the
proved set (docs/synthesis.md, "Invariant sets" and "Box tubes")."""

from __future__ import annotations

import numpy as np

from ..errors import SimgapError

METHOD_NAMES = ("grid", "invariant_set", "box_tube")
#: the methods that return a set controller (no grid, no eta)
SET_METHODS = ("invariant_set", "box_tube")


def method_of(syn: dict) -> str:
    """The synthesis method an experiment's ``[synthesis]`` asks for (default: the grid)."""
    m = syn.get("method", "grid")
    if m not in METHOD_NAMES:
        raise SimgapError(f"[synthesis] method must be one of {', '.join(METHOD_NAMES)}, got {m!r}")
    return m


def is_set_method(syn: dict) -> bool:
    """True for the methods that prove a set (an ellipsoid or a box tube) instead of solving a game."""
    return method_of(syn) in SET_METHODS


def said(syn: dict, key: str, names: dict | None = None) -> str:
    """How the user wrote ``key``: ``names[key]`` (e.g. ``--method box_tube`` on the command line),
    else ``[synthesis] key = value``."""
    if names and key in names:
        return names[key]
    v = syn.get(key)
    return f"[synthesis] {key} = " + (f'"{v}"' if isinstance(v, str) else repr(v))


def check_method(syn: dict, method: str | None = None, names: dict | None = None) -> None:
    """Refuse a set method (``invariant_set``, ``box_tube``) with ``spec = "reach_avoid"`` by both
    names, before the specification is built (a reach-avoid map's start would otherwise be checked
    first). ``method``: given on the command line (``names['method']`` says how)."""
    if method is not None:
        syn = dict(syn, method=method)
        names = {"method": f"--method {method}", **(names or {})}
    method = method_of(syn)
    if method in SET_METHODS and syn.get("spec", "invariance") != "invariance":
        raise SimgapError(f"{said(syn, 'method', names)} handles spec = \"invariance\" only, but "
                          f"{said(syn, 'spec', names)}: use method = \"grid\" for reach-avoid, or "
                          "spec = \"invariance\" with safe_lo/safe_hi")


def check_section(system, syn: dict, spec, names: dict | None = None) -> None:
    """Refuse what the set methods cannot do before any stage runs: a spec other than invariance or
    with obstacles, a hold other than 1, a model without formulas for the interval proof, x_star /
    u_star / K of the wrong size, and K given together with the LQR weights it would override.
    ``simgap run`` and ``simgap synthesize`` both call it (``names``: how the command line spelled a
    key, e.g. ``{"method": "--method box_tube"}``; default ``[synthesis] key = value``)."""
    from ..checks import one_of
    from .interval_map import IntervalMap
    meth = method_of(syn) if method_of(syn) in SET_METHODS else "invariant_set"
    if spec.kind != "invariance":
        raise SimgapError(f"{said(syn, 'method', names)} handles spec = \"invariance\" only, not "
                          f"{spec.kind!r} (use the grid for reach-avoid)")
    if spec.obstacles:
        raise SimgapError(f"{said(syn, 'method', names)}: the safe set must be a box without obstacles")
    if int(syn.get("hold", 1)) != 1:
        raise SimgapError(f"{said(syn, 'method', names)} applies u(x) every period, but {said(syn, 'hold', names)}: "
                          "hold must be 1 (certify at a longer step with [system] steps instead)")
    for key in ("lqr_q", "lqr_r"):
        one_of({said(syn, k, names): syn.get(k) for k in ("K", key)}, "the feedback gain",
               "K is used as given; lqr_q / lqr_r are the weights of the LQR that designs K when it is not given")
    if meth == "box_tube":
        for key in ("target_lo", "target_hi"):
            if key in syn and len(syn[key]) != system.n:
                raise SimgapError(f"[synthesis] {key}: need {system.n} values, got {syn[key]!r}")
        if ("target_lo" in syn) != ("target_hi" in syn):
            raise SimgapError("[synthesis] give both target_lo and target_hi, or neither")
        if "target_lo" in syn and any(a >= b for a, b in zip(syn["target_lo"], syn["target_hi"])):
            raise SimgapError(f"[synthesis] target_lo must be below target_hi in every state, got "
                              f"{syn['target_lo']!r} and {syn['target_hi']!r}")
        sh = syn.get("shells", 16)
        if not isinstance(sh, int) or sh < 1:
            raise SimgapError(f"[synthesis] shells: an integer >= 1, got {sh!r}")
        if not isinstance(syn.get("per_run", True), bool):
            raise SimgapError(f"[synthesis] per_run: true or false, got {syn['per_run']!r}")
        if syn.get("terminal", "largest") not in ("largest", "smallest"):
            raise SimgapError(f"[synthesis] terminal: \"largest\" or \"smallest\", got {syn['terminal']!r}")
        im = syn.get("input_margin", 0.3)
        if not isinstance(im, (int, float)) or not 0 <= im < 1:
            raise SimgapError(f"[synthesis] input_margin: a number in [0, 1), got {im!r}")
    n, m = system.n, system.m
    for key, size in (("x_star", n), ("u_star", m)):
        if key in syn and len(syn[key]) != size:
            raise SimgapError(f"[synthesis] {key}: need {size} values, got {syn[key]!r}")
    if ("x_star" in syn) != ("u_star" in syn):
        raise SimgapError("[synthesis] give both x_star and u_star, or neither (simgap then finds an equilibrium)")
    for key in ("K", "K_plan"):
        if key in syn:
            rows = syn[key]
            lens = [len(r) if isinstance(r, (list, tuple)) else None for r in rows] \
                if isinstance(rows, (list, tuple)) else None
            if lens is None or None in lens or len(set(lens)) > 1 or len(rows) != m or lens[0] != n:
                raise SimgapError(f"[synthesis] {key} must have shape {m} x {n} (inputs x states: one row of {n} "
                                  f"gains per input, one column per state {', '.join(system.state_names)}), got "
                                  f"{key} = {rows!r}: " + ("rows of lengths " + ", ".join(map(str, lens))
                                                           if lens and None not in lens else "no list of rows"))
    for key, size, names in (("lqr_q", n, system.state_names), ("lqr_r", m, system.input_names)):
        if key in syn and np.ndim(syn[key]) and len(syn[key]) not in (1, size):
            raise SimgapError(f"[synthesis] {key} = {syn[key]!r}: need one weight or {size} (one per "
                              f"{'state' if key == 'lqr_q' else 'input'}: {', '.join(names)}), got {len(syn[key])}")
    IntervalMap(system)  # a model the proof can differentiate


#: a per-run statement estimated to take longer than this prints an estimate line first [s]
ESTIMATE_SECONDS = 10.0


def synthesize(system, spec, gap, syn: dict, x0=None, horizon=None, log=None, what: str = "[rollout] horizon"):
    """:func:`~simgap.synthesis.invariant_set.synthesize_invariant_set` or (``method = "box_tube"``)
    :func:`~simgap.synthesis.box_tube.synthesize_box_tube` with the section's options (``horizon``:
    the rollouts' periods, for the box tube's per-run statement, priced first and refused by the
    name ``what`` when it cannot fit; a long one is announced through ``log``)."""
    if method_of(syn) == "box_tube":
        from .box_tube import INPUT_MARGIN, SHELLS, synthesize_box_tube
        if x0 is None:
            raise SimgapError("[synthesis] method = \"box_tube\" starts its tube at x0: give [rollout] x0 (or --x0)")
        if horizon is not None and bool(syn.get("per_run", True)):
            from ..cover import format_duration
            from .noise_tube import check_horizon, why_no_statement
            cost = check_horizon(horizon, system.n, what)
            if log is not None and cost["seconds"] > ESTIMATE_SECONDS and why_no_statement(gap) is None:
                log(f"estimate: the per-run statement over {what} = {int(horizon):,} periods takes about "
                    f"{format_duration(cost['seconds'])} (its cost grows as the horizon squared; calibrated here)")
        return synthesize_box_tube(system, spec, gap, x0=x0, x_star=syn.get("x_star"), u_star=syn.get("u_star"),
                                   K=syn.get("K"), lqr_q=syn.get("lqr_q"), lqr_r=syn.get("lqr_r"),
                                   target_lo=syn.get("target_lo"), target_hi=syn.get("target_hi"),
                                   shells=int(syn.get("shells", SHELLS)),
                                   input_margin=float(syn.get("input_margin", INPUT_MARGIN)),
                                   margin_search=bool(syn.get("margin_search", True)),
                                   terminal=syn.get("terminal", "largest"), K_plan=syn.get("K_plan"),
                                   plan_input_weight=syn.get("plan_input_weight"),
                                   per_run=bool(syn.get("per_run", True)), horizon=horizon, log=log)
    from .invariant_set import synthesize_invariant_set
    return synthesize_invariant_set(system, spec, gap, x_star=syn.get("x_star"), u_star=syn.get("u_star"),
                                    K=syn.get("K"), lqr_q=syn.get("lqr_q"), lqr_r=syn.get("lqr_r"),
                                    solver=syn.get("solver", "CLARABEL"), x0=x0, log=log)


def states_in_set(ctrl, k: int, seed: int) -> np.ndarray:
    """(k, n) states drawn uniformly in E (seeded): x* + L^-T z, z uniform in the unit ball, P = L L^T."""
    rng = np.random.default_rng(seed)
    n = ctrl.x_star.size
    z = rng.normal(size=(k, n))
    z *= (rng.random((k, 1)) ** (1.0 / n)) / np.linalg.norm(z, axis=1, keepdims=True)
    L = np.linalg.cholesky(ctrl.P)
    return ctrl.x_star + np.linalg.solve(L.T, z.T).T * (1 - 1e-9)


def rollouts_in_set(rollout, ctrl, sim, k: int, n_rollouts: int, horizon, seed: int, on_exit: str,
                    log=print) -> dict:
    """R rollouts from each of k states drawn in E (the mean map too, 100 runs per step): failures per
    start and in total. ``rollout``: :func:`simgap.rollout.rollout`, passed by the caller (rollouts
    are the stage after synthesis: this package does not import it)."""
    starts = states_in_set(ctrl, k, seed)
    per = []
    for i, x in enumerate(starts):
        rr = rollout(ctrl, sim, x, n_rollouts=n_rollouts, horizon=horizon, seed=seed + 1 + i, on_exit=on_exit,
                     mean_map_runs=100)
        per.append({"x0": x.tolist(), "failures": int(rr.n_failures), "n_rollouts": int(rr.n_rollouts),
                    "left_set": int(np.count_nonzero(rr.left_domain_time >= 0)),
                    "mean_map_satisfies": None if rr.mean_map is None else rr.mean_map["satisfied"]})
        log(f"  start {i + 1}/{k} in E: {per[-1]['failures']} failures of {n_rollouts}, "
            f"{per[-1]['left_set']} left E")
    return {"states": k, "seed": seed, "per_state": per, "failures": int(sum(p["failures"] for p in per)),
            "n_rollouts": int(sum(p["n_rollouts"] for p in per)),
            "left_set": int(sum(p["left_set"] for p in per)),
            "mean_map_all_satisfy": all(bool(p["mean_map_satisfies"]) for p in per)}

"""The invariant-set method inside ``simgap run`` and ``simgap synthesize`` (``[synthesis] method =
"invariant_set"``): checks before any work, the synthesis call with the experiment's options, and the
rollouts from states drawn in E (docs/synthesis.md, "Invariant sets")."""

from __future__ import annotations

import numpy as np

from .errors import SimgapError

METHOD_NAMES = ("grid", "invariant_set")


def method_of(syn: dict) -> str:
    """The synthesis method an experiment's ``[synthesis]`` asks for (default: the grid)."""
    return syn.get("method", "grid")


def check_method(syn: dict, method: str | None = None) -> None:
    """Refuse ``method = "invariant_set"`` with ``spec = "reach_avoid"`` by both names, before the
    specification is built (a reach-avoid map's start would otherwise be checked first)."""
    method = method or method_of(syn)
    if method == "invariant_set" and syn.get("spec", "invariance") != "invariance":
        raise SimgapError(f"[synthesis] method = \"invariant_set\" handles spec = \"invariance\" only, but the "
                          f"experiment sets spec = {syn.get('spec')!r}: use method = \"grid\" for reach-avoid, or "
                          "spec = \"invariance\" with safe_lo/safe_hi")


def check_section(system, syn: dict, spec) -> None:
    """Refuse what the invariant-set synthesis cannot do before any stage runs: a spec other than
    invariance or with obstacles, a hold other than 1, a model without formulas for the interval
    proof, and x_star / u_star / K of the wrong size."""
    from .synthesis.interval_map import IntervalMap
    if spec.kind != "invariance":
        raise SimgapError(f"[synthesis] method = \"invariant_set\" handles spec = \"invariance\" only, not "
                          f"{spec.kind!r} (use the grid for reach-avoid)")
    if spec.obstacles:
        raise SimgapError("[synthesis] method = \"invariant_set\": the safe set must be a box without obstacles")
    if int(syn.get("hold", 1)) != 1:
        raise SimgapError("[synthesis] method = \"invariant_set\" applies u(x) every period: hold must be 1 "
                          "(certify at a longer step with [system] steps instead)")
    n, m = system.n, system.m
    for key, size in (("x_star", n), ("u_star", m)):
        if key in syn and len(syn[key]) != size:
            raise SimgapError(f"[synthesis] {key}: need {size} values, got {syn[key]!r}")
    if ("x_star" in syn) != ("u_star" in syn):
        raise SimgapError("[synthesis] give both x_star and u_star, or neither (simgap then finds an equilibrium)")
    if "K" in syn:
        rows = syn["K"]
        lens = [len(r) if isinstance(r, (list, tuple)) else None for r in rows] if isinstance(rows, (list, tuple)) \
            else None
        if lens is None or None in lens or len(set(lens)) > 1 or len(rows) != m or lens[0] != n:
            raise SimgapError(f"[synthesis] K must have shape {m} x {n} (inputs x states: one row of {n} gains per "
                              f"input, one column per state {', '.join(system.state_names)}), got K = {rows!r}: "
                              + ("rows of lengths " + ", ".join(map(str, lens)) if lens and None not in lens
                                 else "no list of rows"))
    for key, size, names in (("lqr_q", n, system.state_names), ("lqr_r", m, system.input_names)):
        if key in syn and np.ndim(syn[key]) and len(syn[key]) not in (1, size):
            raise SimgapError(f"[synthesis] {key} = {syn[key]!r}: need one weight or {size} (one per "
                              f"{'state' if key == 'lqr_q' else 'input'}: {', '.join(names)}), got {len(syn[key])}")
    IntervalMap(system)  # a model the proof can differentiate


def synthesize(system, spec, gap, syn: dict, x0=None):
    """:func:`~simgap.synthesis.invariant_set.synthesize_invariant_set` with the section's options."""
    from .synthesis.invariant_set import synthesize_invariant_set
    return synthesize_invariant_set(system, spec, gap, x_star=syn.get("x_star"), u_star=syn.get("u_star"),
                                    K=syn.get("K"), lqr_q=syn.get("lqr_q"), lqr_r=syn.get("lqr_r"),
                                    solver=syn.get("solver", "CLARABEL"), x0=x0)


def states_in_set(ctrl, k: int, seed: int) -> np.ndarray:
    """(k, n) states drawn uniformly in E (seeded): x* + L^-T z, z uniform in the unit ball, P = L L^T."""
    rng = np.random.default_rng(seed)
    n = ctrl.x_star.size
    z = rng.normal(size=(k, n))
    z *= (rng.random((k, 1)) ** (1.0 / n)) / np.linalg.norm(z, axis=1, keepdims=True)
    L = np.linalg.cholesky(ctrl.P)
    return ctrl.x_star + np.linalg.solve(L.T, z.T).T * (1 - 1e-9)


def rollouts_in_set(ctrl, sim, k: int, n_rollouts: int, horizon, seed: int, on_exit: str, log=print) -> dict:
    """R rollouts from each of k states drawn in E (the mean map too, 100 runs per step): failures per
    start and in total."""
    from .rollout import rollout
    starts = states_in_set(ctrl, k, seed)
    per = []
    for i, x in enumerate(starts):
        # the first start prices all k (each costs about the same: the same R, horizon and mean map)
        rr = rollout(ctrl, sim, x, n_rollouts=n_rollouts, horizon=horizon, seed=seed + 1 + i, on_exit=on_exit,
                     mean_map_runs=100, on_estimate=(lambda t: log(f"  {t} per start; x {k} starts")) if i == 0
                     else None)
        per.append({"x0": x.tolist(), "failures": int(rr.n_failures), "n_rollouts": int(rr.n_rollouts),
                    "left_set": int(np.count_nonzero(rr.left_domain_time >= 0)),
                    "mean_map_satisfies": None if rr.mean_map is None else rr.mean_map["satisfied"]})
        log(f"  start {i + 1}/{k} in E: {per[-1]['failures']} failures of {n_rollouts}, "
            f"{per[-1]['left_set']} left E")
    return {"states": k, "seed": seed, "per_state": per, "failures": int(sum(p["failures"] for p in per)),
            "n_rollouts": int(sum(p["n_rollouts"] for p in per)),
            "left_set": int(sum(p["left_set"] for p in per)),
            "mean_map_all_satisfy": all(bool(p["mean_map_satisfies"]) for p in per)}

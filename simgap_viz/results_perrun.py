"""The per-run results of a ``simgap run`` folder (an experiment with ``[perrun]``), loaded and checked.

Read, never recomputed: ``controller_perrun.npz`` (the interval-MDP controller with p_cert per
cell, loaded by the engine's loader, which verifies the file's content digest) and
``summary.json["per_run"]`` (per controller and validated initial state: x0, p_cert, p_emp, ci95,
se, n_rollouts, horizon). The summary carries no digest of its own, so every field is checked
for kind and range, and the per-run controller's p_cert values in it must be the controller
file's values at those states (a look-up in the file, not a recomputation).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from simgap.errors import SimgapError

CONTROLLER_FILE = "controller_perrun.npz"


@dataclass
class ControllerStates:
    """One controller's validated initial states (arrays over states; p_cert NaN where the method
    states no per-run probability)."""

    name: str
    x0: np.ndarray        # (S, n)
    p_cert: np.ndarray    # (S,)
    p_emp: np.ndarray     # (S,)
    ci95: np.ndarray      # (S, 2) two-sided Clopper-Pearson
    se: np.ndarray        # (S,)
    n_rollouts: int
    horizon: int

    @property
    def certified(self) -> bool:
        """True if the method states a per-run probability (p_cert) at its states."""
        return bool(np.isfinite(self.p_cert).any())


@dataclass
class PerRunResults:
    controller: object    # simgap.perrun.value_iteration.PerRunController
    controllers: dict     # name -> ControllerStates, in the summary's order
    horizon: int
    n_rollouts: int
    info: dict            # the rest of summary["per_run"] (alpha, beta, imdp, baseline_rule, ...)


def _number(v, what: str, lo: float = -np.inf, hi: float = np.inf) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or not lo <= v <= hi:
        raise SimgapError(f"summary.json per_run: {what} must be a number in [{lo:g}, {hi:g}], got {v!r}")
    return float(v)


def _count(v, what: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise SimgapError(f"summary.json per_run: {what} must be a whole number >= 1, got {v!r}")
    return v


def _states(name: str, c, system) -> ControllerStates:
    if not isinstance(c, dict) or not isinstance(c.get("states"), list) or not c["states"]:
        raise SimgapError(f"summary.json per_run: controller {name!r} has no list of states")
    rows = []
    for i, s in enumerate(c["states"]):
        w = f"{name} state {i}"
        if not isinstance(s, dict):
            raise SimgapError(f"summary.json per_run: {w} is not a table")
        missing = {"x0", "p_cert", "p_emp", "ci95", "se", "n_rollouts", "horizon"} - set(s)
        if missing:
            raise SimgapError(f"summary.json per_run: {w} lacks {sorted(missing)}")
        x0 = s["x0"]
        if not isinstance(x0, list) or len(x0) != system.n:
            raise SimgapError(f"summary.json per_run: {w}: x0 must be a list of {system.n} numbers, got {x0!r}")
        x0 = [_number(v, f"{w} x0") for v in x0]
        pc = np.nan if s["p_cert"] is None else _number(s["p_cert"], f"{w} p_cert", 0.0, 1.0)
        pe = _number(s["p_emp"], f"{w} p_emp", 0.0, 1.0)
        ci = s["ci95"]
        if not isinstance(ci, list) or len(ci) != 2:
            raise SimgapError(f"summary.json per_run: {w}: ci95 must be [lo, hi], got {ci!r}")
        lo, hi = (_number(v, f"{w} ci95", 0.0, 1.0) for v in ci)
        if not lo <= pe <= hi:
            raise SimgapError(f"summary.json per_run: {w}: p_emp = {pe:g} is outside its ci95 [{lo:g}, {hi:g}]")
        rows.append((x0, pc, pe, lo, hi, _number(s["se"], f"{w} se", 0.0, 1.0),
                     _count(s["n_rollouts"], f"{w} n_rollouts"), _count(s["horizon"], f"{w} horizon")))
    x0 = np.array([r[0] for r in rows], float)
    system.check_states(x0, f"summary.json per_run: {name} initial state")
    ns = {r[6] for r in rows}
    hs = {r[7] for r in rows}
    if len(ns) != 1 or len(hs) != 1:
        raise SimgapError(f"summary.json per_run: {name}: the states differ in n_rollouts or horizon")
    return ControllerStates(name=name, x0=x0, p_cert=np.array([r[1] for r in rows]),
                            p_emp=np.array([r[2] for r in rows]), ci95=np.array([r[3:5] for r in rows]),
                            se=np.array([r[5] for r in rows]), n_rollouts=ns.pop(), horizon=hs.pop())


def load_per_run(root: Path, summary: dict, system) -> PerRunResults | None:
    """The folder's per-run results, or None if its summary has none (an experiment without [perrun]).

    Raises SimgapError naming the file and the problem (missing controller file, a modified
    file, a summary field of the wrong kind or range, summary and controller file disagreeing)."""
    from simgap.perrun.value_iteration import PerRunController

    pr = summary.get("per_run")
    if pr is None:
        return None
    if not isinstance(pr, dict) or not isinstance(pr.get("controllers"), dict) or not pr["controllers"]:
        raise SimgapError(f"{root / 'summary.json'}: per_run has no 'controllers' table")
    path = (root / CONTROLLER_FILE).resolve()
    if root.resolve() not in path.parents:
        raise SimgapError(f"results folder: {CONTROLLER_FILE!r} points outside {root}")
    if not path.is_file():
        raise SimgapError(f"results folder {root}: the summary has per-run results but {CONTROLLER_FILE} is missing")
    ctl = PerRunController.load(path)
    from simgap.results_folder import check_listed
    check_listed(root, summary, CONTROLLER_FILE)  # after the file's own digest check (the more specific)
    if ctl.grid.n != system.n:
        raise SimgapError(f"{path}: its grid has {ctl.grid.n} dimensions, the run's system {system.n}")
    controllers = {str(k): _states(str(k), c, system) for k, c in pr["controllers"].items()}
    per = controllers.get("perrun")
    if per is not None:
        have = ctl.certified(per.x0)
        bad = np.flatnonzero(~np.isclose(per.p_cert, have, rtol=0.0, atol=1e-9))
        if bad.size:
            i = int(bad[0])
            raise SimgapError(f"{root / 'summary.json'} and {CONTROLLER_FILE} disagree: p_cert at state {i} "
                              f"{per.x0[i].tolist()} is {per.p_cert[i]:.6g} in the summary, {have[i]:.6g} in the "
                              f"controller file (refused)")
    return PerRunResults(controller=ctl, controllers=controllers, horizon=_count(pr.get("horizon"), "horizon"),
                         n_rollouts=_count(pr.get("n_rollouts"), "n_rollouts"),
                         info={k: v for k, v in pr.items() if k != "controllers"})

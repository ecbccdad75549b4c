"""Pessimistic interval value iteration: a controller and the certified success probability p_cert per cell.

For an interval MDP (:mod:`.imdp`) and a value vector V (cells plus the sink, V_sink = 0), the
adversary picks, for each (cell, input), the distribution p with lo <= p <= hi, sum p = 1 that
minimizes sum_j p_j V_j. The minimizer is greedy: start from p = lo and pour the free mass
1 - sum lo into successors in ascending order of V, each up to hi (Givan et al. 2000). With
the true transition probabilities inside the intervals (probability >= 1 - beta over the
samples), the pessimistic value is a lower bound of the true one.

Finite horizon of H sampling periods, and the specification's kind given explicitly (never
inferred from the labels):

* invariance: Ha = ceil(H / k) abstract steps (staying safe for Ha k >= H periods implies H);
  V_0 = 1 on live cells;
* reach-avoid: Ha = floor(H / k) abstract steps (the target is only credited at the end of a
  hold, so reaching it within Ha k <= H periods implies reaching it within H; rounding up would
  credit runs that arrive after period H); V_0 = 1 on target cells, 0 elsewhere, and target cells
  stay at 1 (absorbing: reaching counts). A horizon shorter than one hold, or an interval MDP
  without target cells, is refused;
* V_{h+1}(c) = max_a Qpess_h(c, a) on live cells, 0 on the others; policy_h(c) = argmax.

p_cert(c) = V_Ha(c) lower-bounds, for every x in cell c, the probability that one run under the
time-varying policy (policy_{Ha-1-t} at abstract step t) satisfies the specification within H
periods (invariance: for Ha k >= H periods; reach-avoid: reaching within Ha k <= H periods).
Each step is one pass of a compiled kernel over the interval MDP's CSR arrays
(:mod:`.vi_kernel`: a weighted quickselect per row, no sort, no copy of the entries).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from .. import fileio
from ..errors import BAD_FILE_ERRORS, SimgapError
from ..synthesis.grid import UniformGrid
from .imdp import IMDP

FORMAT = "simgap-perrun-controller"


def pessimistic_q(imdp: IMDP, V: np.ndarray, out: Optional[np.ndarray] = None) -> np.ndarray:
    """Qpess (C*M,) = min over interval distributions of sum_j p_j V_j, per row (module docstring).

    Computed on the interval MDP's own CSR arrays by a compiled row kernel
    (:mod:`.vi_kernel`: no copy of the entries, no sort); ``out`` (C*M,) float64 is filled in
    place when given."""
    from .vi_kernel import pessimistic_rows  # numba: loaded only by value iteration
    Vx = np.append(np.asarray(V, dtype=np.float64), 0.0)  # the sink's value
    Q = np.empty(imdp.row_ptr.size - 1) if out is None else out
    pessimistic_rows(imdp.row_ptr, imdp.col, imdp.lo, imdp.hi, Vx, Q)
    return Q


@dataclass
class PerRunController:
    """Time-varying controller of the interval MDP with its certified success probabilities.

    policy (Ha, C) int16: input index at abstract steps-to-go h+1 (row Ha-1 is used first); -1 = none.
    p_cert (C,): certified lower bound of the success probability over the horizon from each cell.
    """

    grid: UniformGrid
    inputs: np.ndarray
    hold: int
    horizon: int                 # sampling periods H
    policy: np.ndarray
    p_cert: np.ndarray
    target: np.ndarray
    meta: dict

    @property
    def steps(self) -> int:
        return self.policy.shape[0]

    def cells(self, x: np.ndarray) -> np.ndarray:
        return self.grid.x_to_ids(np.atleast_2d(x))

    def certified(self, x: np.ndarray) -> np.ndarray:
        """(B,) p_cert at states x (0 outside the grid)."""
        ids = self.cells(x)
        return np.where(ids >= 0, self.p_cert[np.maximum(ids, 0)], 0.0)

    def input_index(self, x: np.ndarray, t: int) -> np.ndarray:
        """(B,) input index at abstract step t (0-based) for states x; -1 outside the grid / no input."""
        ids = self.cells(x)
        h = self.steps - 1 - min(int(t), self.steps - 1)
        return np.where(ids >= 0, self.policy[h, np.maximum(ids, 0)], -1)

    def statement(self, entry: Optional[dict] = None):
        """What the interval MDP proved, in its words (:mod:`simgap.synthesis.statement`): p_cert per
        cell, a lower bound on P(one run satisfies the spec within the horizon)."""
        from ..synthesis.statement import DrawnSet, PerRunStatement, Row, Statement
        x0 = self.meta.get("x0")
        p = float(self.certified(np.asarray(x0, float)[None])[0]) if x0 is not None else float(self.p_cert.max())
        where = "x0" if x0 is not None else "the best cell"
        event = f"one run satisfies the spec within {self.horizon} periods"
        per_run = PerRunStatement(p_cert=p, event=event, horizon=int(self.horizon),
                                  rests_on="the interval MDP's transition intervals (docs/per-run.md)")
        rows = [Row("cells", f"{self.grid.size:,}", "proof"),
                Row(f"p_cert at {where} ({self.horizon} periods)", f"{p:.4f}", "per_run"),
                Row("cells with p_cert > 0", f"{int(np.count_nonzero(self.p_cert > 0)):,}", "per_run")]
        return Statement(method="perrun", name="per-run interval MDP", proved=True, set_name="the p_cert map",
                         rows=rows, sets=[DrawnSet("winning_domain", "p_cert > 0", "cells")], per_run=per_run,
                         headline=f"per-run interval MDP: P({event}) >= {p:.3g} at {where}")

    def save(self, path) -> Path:
        """Write the controller as .npz with a content digest of its metadata and arrays."""
        import json
        meta = dict(self.meta, format=FORMAT, hold=self.hold, horizon=self.horizon, grid=self.grid.describe())
        meta.pop("digest", None)
        meta = json.loads(json.dumps(meta, default=str))  # the JSON the file holds
        arrays = dict(inputs=self.inputs, policy=self.policy, p_cert=self.p_cert, target=self.target)
        meta["digest"] = fileio.content_digest(meta, arrays)
        return fileio.savez(path, **arrays, meta=np.array(json.dumps(meta)))

    @classmethod
    def load(cls, path) -> "PerRunController":
        from ..file_guard import loads_json, regular_file
        path = regular_file(path, "per-run controller file")
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = loads_json(str(z["meta"]), f"per-run controller file {str(path)!r}: its metadata")
                arrays = {k: z[k] for k in ("inputs", "policy", "p_cert", "target")}
        except (*BAD_FILE_ERRORS, KeyError) as e:
            raise SimgapError(f"{str(path)!r} is not a per-run controller: {e}") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise SimgapError(f"{str(path)!r} is not a per-run controller (format tag)")
        want = meta.get("digest")
        have = fileio.content_digest({k: v for k, v in meta.items() if k != "digest"}, arrays)
        if want != have:
            raise SimgapError(f"{str(path)!r} was modified after it was written or has no content digest (refused; "
                              f"synthesize again): its digest is {have[:16]}... but the file records {str(want)[:16]}...")
        grid = UniformGrid.from_dict(meta["grid"])
        if arrays["policy"].ndim != 2 or arrays["policy"].shape[1] != grid.size or arrays["p_cert"].shape != (grid.size,):
            raise SimgapError(f"{str(path)!r}: policy/p_cert do not match the grid")
        from ..synthesis.controller import check_input_indices
        check_input_indices(arrays["policy"], arrays["inputs"], f"per-run controller file {str(path)!r}: policy")
        p = np.asarray(arrays["p_cert"], float)
        if not np.all((p >= 0.0) & (p <= 1.0)):  # also refuses NaN
            raise SimgapError(f"{str(path)!r}: p_cert holds values outside [0, 1]")
        return cls(grid=grid, inputs=arrays["inputs"], hold=int(meta["hold"]), horizon=int(meta["horizon"]),
                   policy=arrays["policy"], p_cert=arrays["p_cert"], target=arrays["target"], meta=meta)


KINDS = ("invariance", "reach_avoid")


def abstract_steps(kind: str, horizon: int, hold: int) -> int:
    """Ha: abstract steps of ``hold`` periods that certify a horizon of H periods (module docstring):
    ceil(H / k) for invariance, floor(H / k) for reach-avoid."""
    return -(-int(horizon) // int(hold)) if kind == "invariance" else int(horizon) // int(hold)


def check_horizon(kind: str, horizon: int, hold: int) -> int:
    """Ha for a horizon of H periods (:func:`abstract_steps`); refuses H < 1 and a reach-avoid H shorter
    than one hold (call it before sampling: bad input is refused before any work)."""
    if int(horizon) < 1:
        raise SimgapError(f"horizon must be >= 1 sampling period, got {horizon}")
    Ha = abstract_steps(kind, horizon, hold)
    if Ha < 1:
        raise SimgapError(f"reach-avoid horizon of {horizon} periods is shorter than one hold of {hold} "
                          f"periods: the target is credited only at the end of a hold, so nothing can be "
                          f"certified (use a horizon >= {hold} or a shorter hold)")
    return Ha


def synthesize_imdp(imdp: IMDP, horizon: int, kind: str, policy: Optional[np.ndarray] = None) -> PerRunController:
    """Interval value iteration over ``horizon`` sampling periods (see module docstring).

    ``kind`` is the specification's kind, "invariance" or "reach_avoid" (the interval MDP's
    ``meta["spec"]``, if recorded, must agree). ``policy`` (C,) fixed input indices (-1: none)
    evaluates that stationary controller instead of maximizing (its pessimistic success probability)."""
    if kind not in KINDS:
        raise SimgapError(f"specification kind must be one of {KINDS}, got {kind!r}")
    recorded = (imdp.meta.get("spec") or {}).get("kind")
    if recorded is not None and recorded != kind:
        raise SimgapError(f"the interval MDP was built for a {recorded} specification, not {kind}")
    Ha = check_horizon(kind, horizon, imdp.hold)
    t0 = time.perf_counter()
    C, M = imdp.C, imdp.M
    if kind == "reach_avoid" and not imdp.target.any():
        raise SimgapError("reach-avoid: the interval MDP has no target cell (no cell lies wholly in the target)")
    Q = np.empty(C * M)  # reused by every sweep
    live, target = imdp.live, imdp.target
    V = (live | target).astype(float) if kind == "invariance" else target.astype(float)
    pol = np.full((Ha, C), -1, np.int16)
    for h in range(Ha):
        Q = pessimistic_q(imdp, V, Q.ravel()).reshape(C, M)
        if policy is None:
            a = np.argmax(Q, axis=1)
        else:
            a = np.asarray(policy, np.int64)
        q = np.where(a >= 0, Q[np.arange(C), np.maximum(a, 0)], 0.0)
        Vn = np.where(live, q, 0.0)
        Vn[target] = 1.0
        pol[h] = np.where(live, a, -1)
        V = np.clip(Vn, 0.0, 1.0)
    meta = dict(imdp.meta, steps=Ha, kind=kind, certified_periods=Ha * imdp.hold,
                horizon_rule=("invariance: ceil(H / k) holds, safe for Ha k >= H periods" if kind == "invariance"
                              else "reach-avoid: floor(H / k) holds, the target reached within Ha k <= H periods"),
                seconds_vi=time.perf_counter() - t0,
                evaluated="fixed policy" if policy is not None else "maximized")
    return PerRunController(grid=imdp.grid, inputs=imdp.inputs, hold=imdp.hold, horizon=int(horizon), policy=pol,
                            p_cert=V, target=target.copy(), meta=meta)

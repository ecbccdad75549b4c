"""Synthesized controllers: the result of a game, how to query it, and how to store it.

Determinization (``input_index``)
---------------------------------
* reach-avoid: the lowest-index valid input. Every valid input recorded for a cell won at
  level j keeps all successors in W_{j-1}, so each guarantees at most j steps to go in the worst
  case: the lowest index is also an input minimizing the worst-case steps-to-go.
  Target cells carry no input (the specification is met there): ``input_index`` returns -1
  for them, ``winning`` is True and ``steps_to_go`` is 0.
* invariance: the valid input with the largest margin (the largest k <= 3 such that the
  successor box grown by k cells still lies in the winning domain), ties by lowest index.

The input is held for ``hold`` sampling periods of ``system`` (``hold * system.steps`` base
periods) per controller query.

File format (``.npz``, no pickle): arrays ``steps`` (N,) int32, ``valid`` (N, ceil(M/8)) uint8
(np.packbits of the valid-input mask), ``chosen`` (N,) int32, ``target`` (N,) bool, ``inputs``
(M, m), and ``meta`` (a JSON string: system.describe(), grid, spec.to_dict(), gap provenance
(for a certificate: its content, digest included), hold, stats, and ``digest`` = sha256 of the
meta without it and of every array). :meth:`Controller.load` recomputes the digest and refuses
an edited file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import BAD_FILE_ERRORS, SimgapError
from ..systems import System
from .abstraction import (COMPOSED_HOLD_LABEL, as_gap, build_abstraction, certified_input_mask, check_hold,
                          describe_gap, growth_function, uncertified_inputs_message)
from .controller_file import FORMAT, VERSION, check_digest, write_controller
from .cost import check_synthesis_cost, synthesis_cost, synthesis_cost_text
from .ellipsoid_controller import EllipsoidController
from .fixed_point import game_progress
from .games import METHODS, GameResult, solve_invariance, solve_reach
from .grid import UniformGrid
from .spec import Spec


#: systems whose f(x, u) - x and Jacobian growth bound do not depend on these state dimensions
TRANSLATION_INVARIANT = {"turtlebot": (0, 1), "scots_vehicle": (0, 1)}


class Controller:
    """A static symbolic controller on a uniform grid (see module docstring)."""

    def __init__(self, grid: UniformGrid, inputs: np.ndarray, kind: str, steps: np.ndarray,
                 valid_packed: np.ndarray, chosen: np.ndarray, target: np.ndarray,
                 hold: int = 1, meta: Optional[dict] = None, system: Optional[System] = None,
                 spec: Optional[Spec] = None):
        self.grid = grid
        self.inputs = np.asarray(inputs, dtype=float)
        self.kind = kind
        self.steps = np.asarray(steps, dtype=np.int32)
        self.valid_packed = np.asarray(valid_packed, dtype=np.uint8)
        self.chosen = np.asarray(chosen, dtype=np.int32)
        self.target = np.asarray(target, dtype=bool)
        self.hold = int(hold)
        self.meta = dict(meta or {})
        self.system = system
        self.spec = spec
        x0 = self.meta.get("x0")
        self.x0 = None if x0 is None else np.asarray(x0, dtype=float)

    # ----- sizes -----------------------------------------------------------------------
    @property
    def n_inputs(self) -> int:
        return self.inputs.shape[0]

    @property
    def winning_mask(self) -> np.ndarray:
        """(N,) bool: cells in the winning domain (reach: including the target cells)."""
        return self.steps >= 0

    @property
    def size(self) -> int:
        """Winning cells excluding target cells (SCOTS's count)."""
        return int(np.count_nonzero(self.winning_mask & ~self.target))

    @property
    def size_with_target(self) -> int:
        """Winning cells including the target cells."""
        return int(np.count_nonzero(self.winning_mask))

    # ----- queries ---------------------------------------------------------------------
    def cells(self, x: np.ndarray) -> np.ndarray:
        """(B, n) states -> (B,) cell ids (-1 outside the grid)."""
        return self.grid.x_to_ids(x)

    def _lookup(self, table: np.ndarray, x, fill):
        ids = self.cells(x)
        out = np.full(ids.shape, fill, dtype=table.dtype)
        inside = ids >= 0
        out[inside] = table[ids[inside]]
        return out

    def winning(self, x: np.ndarray) -> np.ndarray:
        """(B,) bool: x lies in a winning cell (reach: target cells count as winning)."""
        return self._lookup(self.steps, x, -1) >= 0

    def in_target(self, x: np.ndarray) -> np.ndarray:
        """(B,) bool: x lies in a target cell."""
        return self._lookup(self.target, x, False)

    def steps_to_go(self, x: np.ndarray) -> np.ndarray:
        """(B,) int: worst-case abstract steps to the target (reach), 0 for winning cells of an
        invariance controller, -1 outside the winning domain."""
        return self._lookup(self.steps, x, -1)

    def input_index(self, x: np.ndarray) -> np.ndarray:
        """(B,) int: the determinized input (row of ``inputs``); -1 outside the winning domain
        and on target cells."""
        return self._lookup(self.chosen, x, -1)

    def valid_inputs(self, x: np.ndarray) -> np.ndarray:
        """(B, M) bool: all inputs the controller allows at x (none outside the domain)."""
        ids = self.cells(x)
        rows = np.zeros((ids.size, self.valid_packed.shape[1]), dtype=np.uint8)
        inside = ids >= 0
        rows[inside] = self.valid_packed[ids[inside]]
        return np.unpackbits(rows, axis=1, count=self.n_inputs).astype(bool)

    def check_winning(self, x: np.ndarray, what: str = "initial state") -> None:
        """Raise SimgapError if any x (B, n) lies outside the winning domain, naming it."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        ok = self.winning(x)
        if not ok.all():
            i = int(np.flatnonzero(~ok)[0])
            ids = self.cells(x[i:i + 1])[0]
            where = "outside the grid" if ids < 0 else f"in cell {int(ids)} (center {self.grid.points([ids])[0].round(6).tolist()})"
            raise SimgapError(f"{what} {x[i].tolist()} is outside the controller's winning domain ({where}); "
                              f"{self.size_with_target} of {self.grid.size} cells are winning")

    def input(self, x: np.ndarray, strict: bool = True) -> np.ndarray:
        """(B, m) input values at x. Target cells give NaN rows (nothing left to do).

        With ``strict`` a state outside the winning domain raises SimgapError; otherwise its
        row is NaN.
        """
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if strict:
            self.check_winning(x, "state")
        idx = self.input_index(x)
        out = np.full((idx.size, self.inputs.shape[1]), np.nan)
        ok = idx >= 0
        out[ok] = self.inputs[idx[ok]]
        return out

    # ----- files -----------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write the controller as .npz (written to a temp file, then renamed; :mod:`.controller_file`)."""
        arrays = dict(steps=self.steps, valid=self.valid_packed, chosen=self.chosen, target=self.target,
                      inputs=self.inputs)
        self.meta["grid"] = self.grid.describe()
        return write_controller(path, self.meta, self.kind, self.hold, self.system, self.spec, arrays)

    @classmethod
    def load(cls, path, system: Optional[System] = None) -> "Controller":
        """Load a controller saved by :meth:`save` (no pickle).

        The system is rebuilt from its description (built-ins, the SCOTS vehicle, an embedded
        refined system) with the stored input set, unless ``system`` is given.
        """
        path = Path(path)
        from ..file_guard import loads_json, regular_file
        regular_file(path, "controller file")
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = loads_json(str(z["meta"]), f"controller file {str(path)!r}: its metadata")
                if not isinstance(meta, dict) or meta.get("format") != FORMAT:
                    raise SimgapError(f"controller file {str(path)!r} is not a simgap controller (format tag)")
                if meta.get("version") != VERSION:
                    raise SimgapError(f"controller file version {meta.get('version')} is not supported (need "
                                      f"{VERSION}: files without a content digest are refused; synthesize again)")
                if meta.get("kind") == "invariant_set":  # u = u* + K (x - x*) on an ellipsoid
                    return EllipsoidController.from_arrays(path, z, meta, system)
                if meta.get("kind") == "box_tube":  # u = u_nom(t) + K (x - x_nom(t)) on a box tube
                    from .tube_controller import TubeController
                    return TubeController.from_arrays(path, z, meta, system)
                arrays = {k: z[k] for k in ("steps", "valid", "chosen", "target", "inputs")}
        except SimgapError:
            raise
        except (*BAD_FILE_ERRORS, KeyError) as e:
            raise SimgapError(f"controller file {str(path)!r} is not a simgap controller ({e})") from None
        check_digest(path, meta, arrays)
        grid = UniformGrid.from_dict(meta["grid"])
        if arrays["steps"].shape != (grid.size,):
            raise SimgapError(f"controller file {str(path)!r}: arrays do not match the grid size {grid.size}")
        check_input_indices(arrays["chosen"], arrays["inputs"], f"controller file {str(path)!r}: chosen")
        if arrays["valid"].ndim != 2 or arrays["valid"].shape != (grid.size, -(-len(arrays["inputs"]) // 8)):
            raise SimgapError(f"controller file {str(path)!r}: the valid-input mask has shape {arrays['valid'].shape}, "
                              f"expected ({grid.size}, {-(-len(arrays['inputs']) // 8)}) for {len(arrays['inputs'])} "
                              "inputs")
        spec = Spec.from_dict(meta["spec"]) if meta.get("spec") else None
        if system is None and meta.get("system"):
            system = _rebuild_system(meta["system"], arrays["inputs"])
        return cls(grid, arrays["inputs"], meta["kind"], arrays["steps"], arrays["valid"], arrays["chosen"],
                   arrays["target"], hold=meta.get("hold", 1), meta=meta, system=system, spec=spec)

    def statement(self, entry: Optional[dict] = None):
        """What the grid proved, in its words (:mod:`.statement`): the winning domain of the
        abstraction's game (the mean map from each winning cell satisfies the spec)."""
        from .statement import DrawnSet, Row, Statement, gap_words
        entry = entry or {}
        nominal = (self.meta.get("gap") or {}).get("kind") == "none"
        conf = None if nominal or entry.get("confidence_proof") is None else "all rows"
        rows = [Row("proved", "yes" if self.size_with_target else "no (empty winning domain)", "proof", conf),
                Row("winning cells", f"{self.size:,}", "proof", conf)]
        if self.x0 is not None:
            rows.append(Row("x0 in the winning domain", "yes" if bool(self.winning(self.x0[None])[0]) else "no",
                            "proof", conf))
        name = f"grid abstraction ({self.kind.replace('_', '-')} game, hold {self.hold})"
        return Statement(method="grid", name=name, proved=self.size_with_target > 0, set_name="the winning domain",
                         rows=rows, sets=[DrawnSet("winning_domain", "winning domain", "cells")],
                         headline=f"{name}: {self.size:,} winning cells with {gap_words(self.meta)}; "
                                  "no per-run probability")

    def describe(self) -> dict:
        return {"kind": self.kind, "grid": self.grid.describe(), "n_inputs": self.n_inputs,
                "hold": self.hold, "winning": self.size, "winning_with_target": self.size_with_target}


def check_input_indices(idx, inputs, what: str) -> None:
    """Refuse input indices outside -1 (none) .. M-1 for the M rows of ``inputs`` (finite numbers)."""
    inputs = np.asarray(inputs)
    if inputs.ndim != 2 or inputs.shape[0] < 1 or not np.issubdtype(inputs.dtype, np.number) \
            or not np.all(np.isfinite(inputs)):
        raise SimgapError(f"{what}: the input table must be a finite (M, m) array, got shape {inputs.shape}")
    idx = np.asarray(idx)
    if not np.issubdtype(idx.dtype, np.integer):
        raise SimgapError(f"{what}: input indices must be integers, got {idx.dtype}")
    bad = (idx < -1) | (idx >= inputs.shape[0])
    if bad.any():
        raise SimgapError(f"{what}: {int(bad.sum())} input index(es) outside -1..{inputs.shape[0] - 1} (the file has "
                          f"{inputs.shape[0]} inputs), e.g. {int(idx[bad].flat[0])} (refused)")


def gap_source(meta: dict) -> tuple:
    """How the gap entered a controller, from its file's meta: ("certificate", the certificate's
    digest), ("none", None) for the nominal model alone, or (the gap's kind, None) for a constant
    or other gap (grid controllers record ``{"type", "info"}``, invariant-set ones ``{"kind", ...}``)."""
    g = (meta or {}).get("gap")
    if not g:
        return ("none", None)
    if "kind" in g:
        return (str(g["kind"]), g.get("digest"))
    if g.get("type") == "Certificate":
        return ("certificate", (g.get("info") or {}).get("digest"))
    return (str(g.get("type", "unknown")), None)


def _rebuild_system(d: dict, inputs: np.ndarray) -> Optional[System]:
    from ..systems import is_named
    from ..system_ref import ref_of_description, resolve_system
    name = d.get("name")
    ref = ref_of_description(d)
    if name == "scots_vehicle":
        from .examples import vehicle_system
        sysm = vehicle_system()
    elif isinstance(ref, dict) or is_named(ref):
        sysm = resolve_system(ref, int(d.get("steps", 1)), paths=False)
    else:
        return None  # a system defined in Python only: pass it to Controller.load(system=...)
    if sysm.inputs.shape != inputs.shape or not np.allclose(sysm.inputs, inputs):
        sysm = dataclasses.replace(sysm, inputs=np.asarray(inputs, dtype=float))
    return sysm


# ---------------------------------------------------------------------------------------
# synthesis front end
# ---------------------------------------------------------------------------------------

@dataclass
class SynthesisResult:
    """``controller`` and ``stats`` (JSON-ready dict: sizes, times [s], memory [MB])."""

    controller: Controller
    stats: dict = field(default_factory=dict)

    @property
    def empty(self) -> bool:
        return self.controller.size_with_target == 0 or (
            self.controller.kind == "reach_avoid" and self.controller.size == 0)

    def summary(self) -> str:
        s = self.stats
        lines = [
            f"system        {s['system']} (tau = {s['tau']:g} s, hold = {s['hold']})",
            f"gap per step  {s['hold_mode']}",
            f"spec          {s['spec_kind']}",
            f"grid          {' x '.join(map(str, s['grid_shape']))} = {s['cells']:,} cells, eta = {s['eta']}",
            f"inputs        {s['inputs']}" + (f" ({s['inputs_note']})" if s.get("inputs_note") else ""),
            f"boxes         {s['boxes']:,} valid (cell, input) boxes ({s['pairs']:,} pairs)",
            f"transitions   {s['transitions']:,} (sum of box volumes)",
            f"winning       {s['winning']:,} cells ({s['winning_with_target']:,} with the target's "
            f"{s['target_cells']:,})" if s["spec_kind"] == "reach_avoid" else
            f"winning       {s['winning']:,} of {s['safe_cells']:,} safe cells",
            f"iterations    {s['iterations']}",
            f"time          abstraction {s['seconds']['abstraction']:.3f} s, game {s['seconds']['game']:.3f} s, "
            f"total {s['seconds']['total']:.3f} s",
            f"peak memory   {s['peak_rss_mb']:.0f} MB (process max RSS)",
        ]
        if s.get("diagnosis"):
            lines.append(f"note          {s['diagnosis']}")
        return "\n".join(lines)


def label_cells(grid: UniformGrid, spec: Spec, x_lo, x_hi, strict_domain: bool = True):
    """(blocked, target_or_safe) (N,) bool masks for ``spec`` on ``grid``.

    Obstacle cells: cells whose extent meets an obstacle box (SCOTS's rule, 1e-10 slack).
    Target/safe cells: cells whose whole extent lies in the target/safe box. With
    ``strict_domain`` cells sticking out of X in a bounded dimension are blocked too (the grid
    covers X +- eta/2 under the SCOTS alignment).
    """
    N = grid.size
    blocked = np.zeros(N, dtype=bool)
    for b in spec.obstacles:
        blocked |= grid.cells_intersecting(b.lo, b.hi)
    if strict_domain:
        lo = np.where(grid.periodic_mask, -np.inf, x_lo)
        hi = np.where(grid.periodic_mask, np.inf, x_hi)
        blocked |= ~grid.cells_inside(lo, hi)
    x_lo, x_hi = np.asarray(x_lo, float), np.asarray(x_hi, float)
    if spec.kind == "reach_avoid":
        box, what = spec.target, "target"
    else:
        box, what = spec.safe, "safe set"
    if box.lo.size != grid.n:
        raise SimgapError(f"{what} box has {box.lo.size} components, the state has {grid.n}")
    if np.any(box.hi < x_lo) or np.any(box.lo > x_hi):
        raise SimgapError(f"{what} {box.to_dict()} lies outside X = {x_lo.tolist()} .. {x_hi.tolist()}")
    for b in spec.obstacles:
        if spec.kind == "reach_avoid" and np.all(b.lo <= box.lo) and np.all(box.hi <= b.hi):
            raise SimgapError(f"target {box.to_dict()} lies inside obstacle {b.to_dict()}")
    inside = grid.cells_inside(box.lo, box.hi)
    cells = inside & ~blocked
    if not cells.any():
        why = ("no cell lies entirely inside it at eta = " + str(grid.eta.round(6).tolist()) +
               " (use a smaller eta or a bigger box)") if not inside.any() else \
            "every cell inside it is an obstacle cell or sticks out of X"
        raise SimgapError(f"empty {what}: {why}")
    return blocked, cells


def synthesize(system: System, spec: Spec, eta, gap=None, hold: int = 1, *, growth=None,
               invariant_dims=None, periodic=None, guard: float = 1e-10, strict_domain: bool = True,
               x0=None, compose_hold: bool = False, method: str = "auto", log=None,
               on_progress=None) -> SynthesisResult:
    """Synthesize a controller for x+ in f(x, u) + [-gamma(x, u), gamma(x, u)] enforcing ``spec``.

    Parameters
    ----------
    system : System
        Nominal model f (sampling time tau = system.tau).
    spec : Spec
        ``reach_avoid`` (target, obstacles, stay in X) or ``invariance`` (safe box).
    eta : float or (n,)
        Cell widths (state units).
    gap : None, constant vector, or object with ``gamma_upper_box`` (e.g. a Certificate)
        The certified gap gamma (state units per sampling period tau). A certificate bounds
        gamma only at the inputs its data covered (``gap.inputs``): U is restricted to those
        (``stats['inputs_note']`` says so; none certified is an error).
    hold : int
        Sampling periods per abstract step with the input held (abstraction module docstring).
        With a gap, ``hold > 1`` needs ``compose_hold=True``; the default way to a k-period
        step is ``system.with_steps(k)`` with a gap certified at that step.
    compose_hold : bool
        Accept a one-period gap composed over ``hold`` periods (labelled ``hold_mode`` in the
        stats and the controller file).
    growth : callable, optional
        SCOTS-style radius_post ``growth(r, x, u, tau)`` over the sampling period tau = system.tau;
        default: the system's Jacobian bound.
    invariant_dims : tuple, optional
        Dimensions f(x,u) - x does not depend on (default: known built-ins, see
        ``TRANSLATION_INVARIANT``; checked numerically).
    periodic : tuple, optional
        Grid dimensions that wrap (default: ``system.angle_dims``).
    strict_domain : bool
        Block cells that stick out of X (default True; False reproduces SCOTS exactly).
    x0 : optional initial state recorded in the controller (checked against the domain by users).
    method : str
        Game algorithm: ``worklist`` (SCOTS-style predecessor counters, cost ~ transitions),
        ``sat`` (level-wise summed-area tables, cost ~ 2^n per pair: for large boxes) or
        ``auto`` (by the mean box volume); the results are identical.
    log : callable, optional
        ``log(text)`` receives the cost estimate (:mod:`simgap.synthesis.cost`) before the
        abstraction is built; a synthesis over the available memory is refused either way.
    on_progress : callable, optional
        ``on_progress(classes_done, classes)`` while the abstraction is built.

    Returns
    -------
    SynthesisResult
        An empty winning domain is a result (``result.empty``, ``stats['diagnosis']``).
    """
    t0 = time.perf_counter()
    if gap is not None and hasattr(gap, "check_system"):
        gap.check_system(system)
    if gap is not None and hasattr(gap, "require_inside"):  # the grid covers X: gamma is taken over every cell
        gap.require_inside(system.x_lo, system.x_hi, "the grid synthesis's domain X")
    gap = as_gap(gap, system)
    check_hold(hold, gap, compose_hold)
    keep = certified_input_mask(system, gap)
    inputs_note = None
    if not keep.any():
        raise SimgapError(uncertified_inputs_message(system, keep) + "; none is left to synthesize with")
    if not keep.all():  # restrict U to the certified inputs, and say so (stats, summary, controller file)
        inputs_note = (f"restricted to the {int(keep.sum())} inputs the certificate covers "
                       f"(the system has {keep.size}; gamma is not certified for the other {int((~keep).sum())})")
        system = dataclasses.replace(system, inputs=system.inputs[keep])
    if invariant_dims is None:
        from ..system_file import translation_invariant_dims
        invariant_dims = TRANSLATION_INVARIANT.get(system.name, ()) or translation_invariant_dims(system)
    if periodic is None:
        periodic = system.angle_dims
    growth = growth_function(system, growth)
    if method not in METHODS:
        raise SimgapError(f"game method must be one of {', '.join(METHODS)}, got {method!r}")
    grid = UniformGrid(system.x_lo, system.x_hi, eta, periodic=periodic, check_size=False)
    cost = synthesis_cost(system, grid, gap, hold, invariant_dims, growth)  # before any per-cell array
    if log is not None:
        log(synthesis_cost_text(cost, grid))
    check_synthesis_cost(cost, grid)
    grid.check_size()
    blocked, cells = label_cells(grid, spec, system.x_lo, system.x_hi, strict_domain=strict_domain)
    t1 = time.perf_counter()
    ab = build_abstraction(system, grid, growth=growth, gap=gap, hold=hold,
                           invariant_dims=invariant_dims, guard=guard, compose_hold=compose_hold,
                           on_progress=on_progress)
    if log is not None:
        log(f"game: {spec.kind} on {grid.size:,} cells (a line every 10 s while it runs) ...")
    t2 = time.perf_counter()
    with game_progress(log) if log is not None else contextlib.nullcontext():
        if spec.kind == "reach_avoid":
            res = solve_reach(ab, cells, blocked, method=method)
            chosen = _first_valid(res.valid_packed, ab.n_inputs)
            chosen[res.target] = -1
        else:
            res = solve_invariance(ab, cells, blocked, method=method)
            chosen = res.chosen
    t3 = time.perf_counter()
    stats = {
        "system": system.name, "tau": system.tau, "hold": int(hold), "hold_mode": _hold_mode(hold, gap),
        "spec_kind": spec.kind,
        "grid_shape": list(grid.shape), "cells": grid.size, "eta": grid.eta.round(9).tolist(),
        "inputs": ab.n_inputs, "inputs_note": inputs_note, "pairs": grid.size * ab.n_inputs, "classes": ab.n_classes,
        "boxes": res.info["boxes"], "transitions": res.info["transitions"],
        "winning": int(np.count_nonzero(res.winning & ~res.target)),
        "winning_with_target": int(np.count_nonzero(res.winning)),
        "target_cells": int(np.count_nonzero(res.target)),
        "safe_cells": int(np.count_nonzero(cells)) if spec.kind == "invariance" else None,
        "blocked_cells": int(np.count_nonzero(blocked)),
        "iterations": res.iterations, "pairs_tested": res.info["pairs_tested"],
        "game_method": res.info["method"], "game_seconds": res.info["seconds_parts"],
        "invariant_dims": list(ab.info["invariant_dims"]),
        "abstraction_mb": ab.nbytes() / 2 ** 20,
        "seconds": {"labels": t1 - t0, "abstraction": t2 - t1, "game": t3 - t2, "total": t3 - t0},
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    meta = {"stats": stats, "gap": describe_gap(gap), "strict_domain": strict_domain,
            "invariant_dims": list(ab.info["invariant_dims"]), "guard": guard}
    if x0 is not None:
        meta["x0"] = np.asarray(x0, dtype=float).tolist()
    ctrl = Controller(grid, ab.inputs, spec.kind, res.steps, res.valid_packed, chosen, res.target,
                      hold=hold, meta=meta, system=system, spec=spec)
    out = SynthesisResult(ctrl, stats)
    if out.empty:
        stats["diagnosis"] = diagnose_empty(ab, spec, gap, res)
    return out


def _hold_mode(hold: int, gap) -> str:
    """How the gap enters one abstract step (recorded in stats and the controller file)."""
    if gap is None:
        return "none (nominal model)"
    if hold > 1:
        return COMPOSED_HOLD_LABEL
    if hasattr(gap, "check_system"):
        return "certified at the abstraction step (one gap per abstract step)"
    return "a given bound per abstract step (not a certificate)"


def _first_valid(packed: np.ndarray, M: int) -> np.ndarray:
    """(N,) lowest valid input index per cell, -1 where none."""
    N = packed.shape[0]
    out = np.full(N, -1, dtype=np.int32)
    B = max(1, (1 << 22) // max(1, M))
    for s in range(0, N, B):  # blocks bound the unpacked memory
        rows = np.unpackbits(packed[s:s + B], axis=1, count=M).view(bool)
        has = rows.any(axis=1)
        out[s:s + B] = np.where(has, rows.argmax(axis=1), -1)
    return out


def diagnose_empty(ab, spec: Spec, gap, res: GameResult) -> str:
    """A one-line guess at why the winning domain is empty."""
    usable = ab.ok
    if res.info.get("boxes", 0) == 0 or not usable.any():
        return ("no (cell, input) box stays inside the grid: the growth bound plus the gap exceed the state "
                "set; use a smaller eta or a smaller gap")
    lo = ab.off_lo[usable].astype(np.int64)
    hi = ab.off_hi[usable].astype(np.int64)
    selfish = np.all((lo <= 0) & (hi >= 0), axis=1)
    g = ""
    if gap is not None:
        g = " plus the gap"
        try:  # the gap's size against the cell width, over X and all inputs
            grid = ab.grid
            U = ab.inputs
            gs = np.asarray(gap.gamma_upper_box(np.broadcast_to(grid.lo, (len(U), grid.n)),
                                                np.broadcast_to(grid.hi, (len(U), grid.n)), U)).max(axis=0)
            g = (f" plus the gap (gamma up to {np.round(gs, 6).tolist()} per period, cell width "
                 f"{np.round(grid.eta, 6).tolist()})")
        except Exception:  # the diagnosis is a hint; never fail on it
            pass
    if spec.kind == "reach_avoid" and selfish.all():
        return ("empty winning domain: every successor box contains its own cell, i.e. the motion in one "
                f"abstract step is smaller than the growth bound{g} (the one-step control authority is too "
                "small); certify the gap at a longer step (data collected at steps=k, then --steps k), "
                "hold the input for more periods (--hold k; with a gap only with --compose-hold), "
                "or use a smaller eta")
    width = (hi - lo + 1).mean(axis=0)
    return (f"empty winning domain: successor boxes are {np.round(width, 1).tolist()} cells wide on average; "
            f"the growth bound{g} is too large for the {'target' if spec.kind == 'reach_avoid' else 'safe set'} "
            "and obstacles at this eta; try a smaller gap, a longer step (--steps/--hold) or a different eta")

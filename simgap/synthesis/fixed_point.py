"""What the fixed-point games share: their outcome (:class:`GameResult`) and the choice
between their two algorithms, worklist or summed-area tables (:func:`choose_method`).
"""

from __future__ import annotations

import contextlib
import contextvars
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import SimgapError
from .abstraction import Abstraction
from .boxes import pair_volumes


@dataclass
class GameResult:
    """Outcome of a game.

    ``winning`` (N,) bool (for reach: includes the target cells); ``steps`` (N,) int32 steps to go
    (reach: 0 on target, -1 losing; invariance: 0 winning, -1 losing); ``valid`` (N, M) packed
    bits (np.packbits along axis 1) of the controller's valid inputs; ``iterations``, ``seconds``.
    """

    kind: str
    winning: np.ndarray
    steps: np.ndarray
    valid_packed: np.ndarray
    n_inputs: int
    target: np.ndarray
    chosen: Optional[np.ndarray] = None
    iterations: int = 0
    seconds: float = 0.0
    info: dict = field(default_factory=dict)


METHODS = ("auto", "worklist", "sat")

#: the running game's progress reporter (set by :func:`game_progress`; None: silent)
_PROGRESS: contextvars.ContextVar = contextvars.ContextVar("game_progress", default=None)


@contextlib.contextmanager
def game_progress(log, every: float = 10.0):
    """Within the block, the games report ``log("game: iteration i, ...")`` at most every ``every``
    seconds (the number of iterations is not known beforehand: what changed last is reported)."""
    t0 = time.perf_counter()
    state = {"last": t0}

    def report(it: int, changed: int) -> None:
        now = time.perf_counter()
        if now - state["last"] >= every:
            state["last"] = now
            log(f"game: iteration {it:,}, {changed:,} cells decided in the last one, {now - t0:.0f} s so far")

    token = _PROGRESS.set(report)
    try:
        yield
    finally:
        _PROGRESS.reset(token)


def tick(it: int, changed: int) -> None:
    """Called by the games once per iteration (cheap when nobody listens)."""
    report = _PROGRESS.get()
    if report is not None:
        report(it, changed)
_WORKLIST_MAX_PAIRS = 1 << 26  # (cell, input) pairs: the worklist keeps 2 bytes or so per pair


def choose_method(method: str, ab: Abstraction) -> str:
    """``worklist`` or ``sat`` for ``auto``: the worklist touches every transition into the
    changed cells once (SCOTS's algorithm, cost ~ transitions), the SAT game tests 2^n table
    entries per candidate pair and rebuilds a table of all cells per level; the worklist wins
    unless the boxes are large (mean box volume above a few times 2^n, as with long held
    inputs; with a corner index, boxes small enough for it) or the pairs too many for its
    per-pair counters."""
    if method not in METHODS:
        raise SimgapError(f"game method must be one of {', '.join(METHODS)}, got {method!r}")
    if method != "auto":
        return method
    if ab.grid.size * ab.n_inputs > _WORKLIST_MAX_PAIRS:
        return "sat"
    if ab.corner_index is not None:  # one class per cell, small boxes: an index of one entry per pair
        return "worklist"
    vol = pair_volumes(ab)[ab.ok]
    # one class per cell: the worklist also builds the predecessor index (one entry per
    # transition), so it wins only for smaller boxes (measured: bench_synthesis_generic.py)
    limit = 1.25 if len(ab.class_dims) == ab.grid.n else 4
    return "worklist" if vol.size == 0 or vol.mean() <= limit * (1 << ab.grid.n) else "sat"

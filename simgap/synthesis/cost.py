"""What a synthesis will cost, from eta, before anything of its size is built.

:func:`synthesis_cost` counts the grid (cells N, classes K of translation-invariant cells, inputs
M), computes the successor boxes of a seeded sample of cells exactly as
:func:`~simgap.synthesis.abstraction.build_abstraction` does (growth bound plus gap, ``hold``
periods), and extrapolates: the valid boxes and the transitions (sum of box volumes), the
abstraction's build time (the sample's time per pair), and the peak memory of the stages:

* the abstraction: per (class, input) pair 2 n offsets (int8, int16 when a box reaches past 127
  cells) and a flag; with ``hold > 1`` 2 n int16 intermediate offsets;
* the predecessor index of a grid with one class per cell (:class:`~.corner_index.CornerIndex`,
  at most 2^26 pairs): about 4 + n bytes per pair while it is built and 5 per indexed pair;
* the game and the controller: per cell the labels, steps, chosen input, frontier buffers and
  the packed valid inputs (about 24 + ceil(M / 8) bytes);
* the worklist game's predecessor lists when there is no corner index and the game chosen is the
  worklist (:func:`~.fixed_point.choose_method`: boxes of at most 1.25 x 2^n cells on average with
  one class per cell, 4 x 2^n with shared boxes, and at most
  :data:`~.fixed_point._WORKLIST_MAX_PAIRS` pairs): one int32 per transition with one class per
  cell; with shared boxes one per (class, input, class-dimension index its box covers)
  (:class:`~.predecessors.Predecessors`), far fewer. Otherwise the summed-area-table game: two
  int64 tables of the grid.

These are estimates (the sample's boxes stand for all cells); the refusal compares the memory
with what is available, as collection does.
"""

from __future__ import annotations

import time

import numpy as np

from .abstraction import as_gap, gamma_upper_wrapped, growth_function
from .corner_index import CornerIndex
from .fixed_point import _WORKLIST_MAX_PAIRS
from .grid import UniformGrid

#: (cell, input) pairs sampled for the box sizes and the time per pair (one block of the build)
SAMPLE_PAIRS = 1 << 14
#: the interpreter, numpy and the process's other arrays
BASE_BYTES = 200 * 2 ** 20


def synthesis_cost(system, grid: UniformGrid, gap=None, hold: int = 1, invariant_dims=(), growth=None,
                   sample: int = SAMPLE_PAIRS, seed: int = 0) -> dict:
    """Estimated cells, boxes, transitions, memory [bytes] and abstraction time [s] (module docstring).

    ``system`` with the inputs the synthesis will use; ``gap`` as for
    :func:`~simgap.synthesis.controller.synthesize`; ``invariant_dims`` the dimensions whose cells
    share their boxes."""
    n, M = grid.n, int(system.inputs.shape[0])
    inv = sorted(set(int(d) for d in invariant_dims))
    N = float(grid.size)
    K = float(np.prod([grid.shape[d] for d in range(n) if d not in inv])) if len(inv) < n else 1.0
    growth = growth_function(system, growth)
    gap = as_gap(gap, system)
    S = int(min(max(1, sample // M), K))  # cells, all inputs each
    mi = np.stack([_sample_ints(seed * 16 + d, S, grid.shape[d]) for d in range(n)], axis=1)
    x = np.repeat(grid.multi_to_points(mi), M, axis=0)
    u = np.tile(system.inputs, (S, 1))
    eta, z = grid.eta, 1e-10 * grid.eta
    r = np.broadcast_to(eta / 2 + z, x.shape).copy()
    # the build computes the radii once per input when they are the same for every cell
    fast = getattr(growth, "state_independent", False) and (gap is None or type(gap).__name__ == "ConstantGap")
    x0, r0 = x, r
    kernel = None
    if fast and gap is None and int(hold) == 1 and not grid.periodic_mask.any():  # build_abstraction's test
        from .grid_kernel import grid_kernel
        kernel = grid_kernel(system, int(K * M * system.steps))  # the compiled pass is what will be timed
    for rep in range(2):  # timed the second time: the first pays one-off costs (caches, compiled formulas)
        x, r, t_r, t_f = x0, r0, 0.0, 0.0
        with np.errstate(all="ignore"):
            for _ in range(int(hold)):
                t0 = time.perf_counter()
                g = gamma_upper_wrapped(gap, x - r, x + r, u, grid) if gap is not None else 0.0
                r = np.asarray(growth(r, x, u, system.tau), dtype=float) + g
                t1 = time.perf_counter()
                x = system.f(x, u) if kernel is None else kernel.posts(system, x, np.tile(np.arange(M), S))
                t_f += time.perf_counter() - t1
                t_r += t1 - t0
    per_pair = (t_f + (0.0 if fast else t_r)) / max(1, x.shape[0])
    free = ~grid.periodic_mask
    ok = np.all(np.isfinite(x) & np.isfinite(r), axis=1)
    ok &= ~np.any(free & ((x - r - z <= grid.domain_lo) | (x + r + z >= grid.domain_hi)), axis=1)
    cells_wide = np.floor((x + r + z) / eta + 0.5) - np.floor((x - r - z) / eta + 0.5) + 1
    vol = np.prod(np.where(np.isfinite(cells_wide), cells_wide, 0.0), axis=1)
    frac = float(ok.mean()) if ok.size else 0.0
    mean_vol = float(vol[ok].mean()) if ok.any() else 0.0
    pairs_stored = K * M
    boxes = frac * N * M
    transitions = boxes * mean_vol
    width = 2 if ok.any() and float(np.max(cells_wide[ok])) > 127 else 1
    abstraction = pairs_stored * (2 * n * width + 1) + (pairs_stored * 4 * n if hold > 1 else 0)
    index = (4 + n + 5) * pairs_stored if not inv and pairs_stored <= CornerIndex.MAX_PAIRS else 0
    game = N * (24 + (M + 7) // 8)
    if not index:  # the game choose_method("auto") picks, and what it keeps beyond the per-cell arrays
        shared = bool(inv)
        worklist = N * M <= _WORKLIST_MAX_PAIRS and mean_vol <= (4 if shared else 1.25) * 2 ** n
        if worklist and shared:
            cls = [d for d in range(n) if d not in inv]
            per_pair = float(np.prod(cells_wide[ok][:, cls], axis=1).mean()) if ok.any() and cls else 1.0
            game += 4.0 * frac * pairs_stored * per_pair
        elif worklist:
            game += 4.0 * transitions
        else:
            game += 16.0 * N
    memory = BASE_BYTES + abstraction + index + game
    return {"cells": N, "classes": K, "inputs": M, "pairs": N * M, "boxes": boxes, "transitions": transitions,
            "mean_box_cells": mean_vol, "sampled_cells": S, "memory": memory,
            "memory_parts": {"abstraction": abstraction, "index": index, "game": game},
            "abstraction_seconds": per_pair * pairs_stored * 1.5}  # + storing the offsets


def _sample_ints(stream: int, count: int, high: int) -> np.ndarray:
    """``count`` seeded pseudo-random integers in [0, high): splitmix64 of (stream, i), by integer
    arithmetic (numpy.random, about 6 MB of resident memory, is not loaded for a sample)."""
    with np.errstate(over="ignore"):
        z = (np.arange(1, count + 1, dtype=np.uint64) + np.uint64(stream & 0xFFFFFFFF) * np.uint64(1 << 32)) \
            * np.uint64(0x9E3779B97F4A7C15)
        z ^= z >> np.uint64(30)
        z *= np.uint64(0xBF58476D1CE4E5B9)
        z ^= z >> np.uint64(27)
        z *= np.uint64(0x94D049BB133111EB)
        z ^= z >> np.uint64(31)
    return (z % np.uint64(max(int(high), 1))).astype(np.int64)


def synthesis_cost_text(c: dict, grid: UniformGrid) -> str:
    """:func:`synthesis_cost` as the lines printed before the abstraction is built."""
    from ..fileio import human_bytes
    from ..memory import available_memory
    from ..cover import format_duration
    shared = f", {c['classes']:,.0f} classes of shared boxes" if c["classes"] < c["cells"] else ""
    return (f"estimate: grid {' x '.join(map(str, grid.shape))} = {c['cells']:,.0f} cells x {c['inputs']} inputs"
            f"{shared}; about {c['boxes']:,.3g} valid boxes and {c['transitions']:,.3g} transitions (boxes of "
            f"{c['mean_box_cells']:.3g} cells on average, from {c['sampled_cells']:,} sampled cells); peak memory "
            f"about {human_bytes(c['memory'])} ({human_bytes(available_memory())} available); abstraction about "
            f"{format_duration(c['abstraction_seconds'])}, then the game")


def check_synthesis_cost(c: dict, grid: UniformGrid) -> None:
    """Refuse a synthesis whose estimated peak memory exceeds the available memory, with the numbers."""
    from ..memory import check_memory
    check_memory(c["memory"], f"synthesis on {c['cells']:,.0f} cells x {c['inputs']} inputs (grid "
                 f"{' x '.join(map(str, grid.shape))}, eta {np.round(grid.eta, 9).tolist()}; about "
                 f"{c['transitions']:.3g} transitions)", "use a coarser --eta (each halving of eta in one "
                 "dimension doubles the cells), fewer inputs, or split the system (docs/own-system.md)")


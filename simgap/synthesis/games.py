"""Fixed-point games on an implicit abstraction: a worklist over predecessors, or summed-area tables.

Two algorithms with identical results (``method``; :func:`choose_method` picks one):

* worklist (SCOTS's algorithm, level-synchronous): a predecessor index inverts the box relation
  (:class:`Predecessors` for shared boxes; without them the abstraction's
  :class:`~simgap.synthesis.corner_index.CornerIndex`); reach keeps per-pair counters of box
  cells not yet won, invariance drops the pairs whose box meets a lost cell. The work of a
  level is the number of transitions into the cells changed in the level before.
* summed-area tables (SAT): O(2^n) per pair test whatever the box volume, plus one table of all
  cells per level; better when boxes hold many cells.

This module gathers the games' names (``from simgap.synthesis.games import ...`` keeps working);
each idea has its own module:

* :mod:`~simgap.synthesis.reach`: reach-avoid, the least fixed point (:func:`solve_reach`)
* :mod:`~simgap.synthesis.invariance`: invariance, the greatest fixed point, and its safety
  controller (:func:`solve_invariance`)
* :mod:`~simgap.synthesis.fixed_point`: what both share, :class:`GameResult` and
  :func:`choose_method`
* :mod:`~simgap.synthesis.boxes`: index boxes and the summed-area tables that test them
* :mod:`~simgap.synthesis.live`: the pairs a game can ever use, found once up front
* :mod:`~simgap.synthesis.predecessors`: the predecessor index and the frontier of a level
* :mod:`~simgap.synthesis.pair_rows`: pairs as packed bit rows and flat ids
"""

from __future__ import annotations

from .boxes import BoxCounter, BoxFamily, DistinctBoxes, PairEvaluator, RowBoxes, pair_volumes
from .fixed_point import _WORKLIST_MAX_PAIRS, METHODS, GameResult, choose_method  # noqa: F401
from .invariance import (_distinct, _erode, _invariance_sat, _invariance_worklist,  # noqa: F401
                         _row_counts, _safety_controller, solve_invariance)
from .live import _per_class, _usable_pairs, _valid_shared, live_pairs  # noqa: F401
from .pair_rows import _block_size, _unpack, pack_rows, unpack_rows  # noqa: F401
from .predecessors import Predecessors, _frontier, _predecessors  # noqa: F401
from .reach import _counter_dtype, _reach_sat, _reach_worklist, solve_reach  # noqa: F401

__all__ = [
    "BoxCounter", "BoxFamily", "DistinctBoxes", "GameResult", "METHODS", "PairEvaluator",
    "Predecessors", "RowBoxes", "choose_method", "live_pairs", "pack_rows", "pair_volumes",
    "solve_invariance", "solve_reach", "unpack_rows",
]

"""The synthetic interval MDP of ``bench_perrun.py vi``: the pendulum target size with a sparse structure.

201 x 201 cells, 21 inputs, hold 20; every row holds ``succ`` neighbour cells of its cell
(clipped at the border, the same for every input) plus the sink, with random valid intervals
[max(p - 0.02, 0), min(p + 0.02, 1)] around a Dirichlet draw p. Built in blocks of rows, so the
peak memory is the interval MDP itself (12 bytes per entry) plus a block; the draws are those of
one ``rng.dirichlet(..., size=rows)`` call (the generator fills blocks in the same order).
Imports ``simgap`` from whatever comes first on ``sys.path`` (``bench_vs_previous.py`` runs it
against an earlier tree).
"""

from __future__ import annotations

import numpy as np


def synthetic_imdp(succ: int, block: int = 1 << 14):
    from simgap.perrun.imdp import IMDP
    from simgap.synthesis.grid import UniformGrid
    from simgap.systems import get_system, input_grid

    s = get_system("pendulum")
    grid = UniformGrid(s.x_lo, s.x_hi, [0.4 / 200, 1.0 / 200])
    C, M, S = grid.size, 21, int(succ)
    rng = np.random.default_rng(0)
    rows = C * M
    mi = grid.ids_to_multi(np.arange(C))
    off = np.stack(np.meshgrid(np.arange(-1, 2), np.arange(-(S // 6), S // 6 + 1), indexing="ij"), -1).reshape(-1, 2)[:S]
    cols = np.empty((rows, S + 1), np.int32)
    for j, o in enumerate(off):  # neighbours of each cell (clipped at the border), same for every input
        cols[:, j] = np.repeat(grid.multi_to_ids(np.clip(mi + o, 0, np.array(grid.shape) - 1)), M)
    cols[:, S] = C
    lo = np.empty((rows, S + 1), np.float32)
    hi = np.empty((rows, S + 1), np.float32)
    for r0 in range(0, rows, block):
        p = rng.dirichlet(np.ones(S + 1), size=min(block, rows - r0))
        lo[r0:r0 + len(p)] = np.maximum(p - 0.02, 0)
        hi[r0:r0 + len(p)] = np.minimum(p + 0.02, 1)
    live = np.ones(C, bool)
    live[mi[:, 0] == 0] = live[mi[:, 0] == grid.shape[0] - 1] = False
    return IMDP(grid=grid, inputs=input_grid([-1], [1], [M]), hold=20, live=live, target=np.zeros(C, bool),
                row_ptr=np.arange(rows + 1, dtype=np.int64) * (S + 1), col=cols.reshape(-1), lo=lo.reshape(-1),
                hi=hi.reshape(-1))

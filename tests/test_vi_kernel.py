"""The compiled value-iteration kernel against the row-sorting formula it replaces."""

from __future__ import annotations

import numpy as np
import pytest

from simgap.perrun import value_iteration as vi
from simgap.perrun.imdp import IMDP
from simgap.synthesis.grid import UniformGrid


def _sorted_pour(im: IMDP, V: np.ndarray) -> np.ndarray:
    """The earlier implementation: each row sorted by value, the free mass poured from the bottom."""
    Vx = np.append(V, 0.0)
    Q = np.empty(im.row_ptr.size - 1)
    for r in range(Q.size):
        sl = slice(im.row_ptr[r], im.row_ptr[r + 1])
        v, lo = Vx[im.col[sl]], im.lo[sl].astype(np.float64)
        cap = im.hi[sl].astype(np.float64) - lo
        order = np.argsort(v, kind="stable")
        vs, cs = v[order], cap[order]
        add = np.clip(1.0 - lo.sum() - (np.cumsum(cs) - cs), 0.0, cs)
        Q[r] = (lo * v).sum() + (add * vs).sum()
    return Q


def _random_imdp(rng, C=60, M=3, levels=None):
    rows, ptr, cols, los, his = C * M, [0], [], [], []
    for r in range(rows):
        k = int(rng.integers(1, 40))
        c = np.append(rng.choice(C, k, replace=False), C)
        p = rng.dirichlet(np.ones(k + 1))
        kind = r % 4
        lo = np.maximum(p - rng.random(k + 1) * 0.1, 0)
        hi = np.minimum(p + rng.random(k + 1) * 0.1, 1)
        if kind == 1:                      # the lower bounds already hold all the mass
            lo, hi = p, p
        elif kind == 2:                    # caps that cannot hold the free mass (sum hi < 1)
            hi = lo + (hi - lo) * 0.01
        cols.append(c)
        los.append(lo)
        his.append(hi)
        ptr.append(ptr[-1] + c.size)
    im = IMDP(grid=UniformGrid([0], [C - 1], 1.0), inputs=np.zeros((M, 1)), hold=1, live=np.ones(C, bool),
              target=np.zeros(C, bool), row_ptr=np.array(ptr, np.int64), col=np.concatenate(cols).astype(np.int32),
              lo=np.concatenate(los).astype(np.float32), hi=np.concatenate(his).astype(np.float32))
    return im


def test_kernel_equals_the_sorted_pour(rng):
    im = _random_imdp(rng)
    for V in (rng.random(im.C),                              # distinct values
              rng.integers(0, 4, im.C) / 3.0,                 # many ties
              np.zeros(im.C), np.ones(im.C)):
        assert np.allclose(vi.pessimistic_q(im, V), _sorted_pour(im, V), rtol=0, atol=1e-12)


@pytest.mark.parametrize("kind", ["invariance", "reach_avoid"])
def test_value_iteration_equals_the_sorted_pour(rng, kind):
    """Whole sweeps (max over inputs, policy, clipping) as before, with the earlier row formula."""
    im = _random_imdp(rng, C=40, M=4)
    im.live[:3] = False
    if kind == "reach_avoid":
        im.target[30:34] = True
        im.live[30:34] = False
    new = vi.synthesize_imdp(im, 6, kind)
    real = vi.pessimistic_q
    try:
        vi.pessimistic_q = lambda imdp, V, out=None: _sorted_pour(imdp, V)
        old = vi.synthesize_imdp(im, 6, kind)
    finally:
        vi.pessimistic_q = real
    assert np.allclose(new.p_cert, old.p_cert, rtol=0, atol=1e-12)
    assert np.array_equal(new.policy, old.policy)
    assert 0.05 < new.p_cert[im.live].mean() < 0.999  # not a trivial fixed point

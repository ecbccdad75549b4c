"""Benchmark: what one float64 cosine costs in numpy and in compiled scalar code (numba).

    python bench/bench_trig_floor.py

The per-cell SCOTS vehicle evaluates about 3.6e8 cosines and sines (4.46 million pairs, 40
right-hand sides each); this measures the floor that sets, per element, for ``np.cos``,
``np.sin`` and ``np.exp`` (for scale) on 16,384 arguments in [-4.5, 4.5], and for ``math.cos`` in
a numba loop (after compiling; numba's import and compile time printed), and checks that the two
cosines agree bit for bit, also on 2^20 arguments in [-1000, 1000].
"""

from __future__ import annotations

import math
import time

import numpy as np


def per_element_ns(f, x, k=50):
    f()
    c = time.perf_counter()
    for _ in range(k):
        f()
    return (time.perf_counter() - c) / k / x.size * 1e9


def main() -> int:
    x = np.random.default_rng(0).uniform(-4.5, 4.5, 16384)
    print(f"np.cos {per_element_ns(lambda: np.cos(x), x):.1f} ns/element, np.sin "
          f"{per_element_ns(lambda: np.sin(x), x):.1f}, np.exp {per_element_ns(lambda: np.exp(x), x):.1f}")
    c0 = time.perf_counter()
    import numba

    @numba.njit(cache=False)
    def cos_loop(a, out):
        for i in range(a.size):
            out[i] = math.cos(a[i])
    out = np.empty_like(x)
    cos_loop(x, out)
    print(f"numba import and compile {time.perf_counter() - c0:.2f} s; math.cos in a numba loop "
          f"{per_element_ns(lambda: cos_loop(x, out), x):.1f} ns/element")
    y = np.random.default_rng(1).uniform(-1e3, 1e3, 1 << 20)
    o2 = np.empty_like(y)
    cos_loop(y, o2)
    print(f"bit-equal to np.cos: {np.array_equal(out, np.cos(x))} (16,384 in [-4.5, 4.5]), "
          f"{np.array_equal(o2, np.cos(y))} (2^20 in [-1000, 1000])")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

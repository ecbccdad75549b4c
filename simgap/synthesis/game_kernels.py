"""The predecessor index's build and the reach game's level in C (issue 56: no numba start in a grid
synthesis).

Three fixed kernels, the numpy code's operations per pair (integers only, so the same results
by construction; asserted by tests/test_compiled_kernels.py against the numpy paths):

* ``corner_counts`` and ``corner_place``: the two passes of
  :meth:`~simgap.synthesis.corner_index.CornerIndex.build` (per corner key the number of usable
  pairs and the per-cell bits, boxes, transitions and largest extents; then every usable pair at
  its key's next free slot, input-major, with its extents as a mixed-radix code);
* ``reach_level``: one level of the worklist reach game (``reach._reach_worklist``): for every
  transition (c, u) -> r with r just won and c not won, cnt[c M + u] -= 1; the pairs reaching 0;
* ``inv_level``: one round of the invariance worklist (``invariance._invariance_worklist``): every
  alive pair whose box holds a just-lost cell is dropped once; the cells left without one;
* ``safety_choose``: the safety controller's input per winning cell (``invariance._safety_controller``):
  the first valid input of the largest margin, a pair's margin the min over its box of the
  erosions a cell survives.

The integer types of the tables (int8 or int16 offsets, int32 or int64 pair ids, the counters'
and per-cell sums' smallest dtypes) are written into the source, one library per combination,
compiled by :func:`simgap.compile.load_c` and cached on disk like the grid kernel (about 0.12 s CPU the
first time, then a load of about 1 ms; numba's start costs about 0.45 s CPU and 65 MB each
process). Used when ``SIMGAP_JIT`` is not 0 and a C compiler is found, in auto mode when the
library is cached or the job is large (:data:`AUTO_PAIRS`); otherwise the numpy code runs.
"""

from __future__ import annotations

import ctypes
from typing import Optional

import numpy as np

#: (cell, input) pairs from which a first compile (about 0.12 s CPU) pays in auto mode (the numpy index
#: and level cost about 0.1 us a pair)
AUTO_PAIRS = 1_000_000
_CTYPE = {np.dtype(t): f"{np.dtype(t).name}_t" for t in (np.int8, np.int16, np.int32, np.int64,
                                                          np.uint8, np.uint16, np.uint32, np.uint64)}

_SOURCE = r"""/* simgap.synthesis.game_kernels: fixed code, integer types substituted */
#include <stdint.h>
#include <stdlib.h>

typedef {off} off_t_;
typedef {q} q_t;
typedef {cnt} cnt_t;
typedef {boxes} boxes_t;
typedef {trans} trans_t;

static inline int64_t pmod(int64_t a, int64_t b) {{ int64_t r = a % b; return r < 0 ? r + b : r; }}

/* CornerIndex.build's pair (c, u): usable, corner key, box volume, extents ext (uncapped) */
static inline int corner_pair(const off_t_ *lo_t, const off_t_ *hi_t, const uint8_t *ok, int64_t c, int64_t u,
                              int64_t M, int64_t n, const int64_t *coord, const int64_t *shape,
                              const int64_t *strides, const uint8_t *pmask, int64_t *key, int32_t *vol, int32_t *ext)
{{
    int usable = ok[c * M + u] != 0;
    int64_t k = 0;
    int32_t v = 1;
    for (int64_t d = 0; d < n; d++) {{
        const int32_t ol = (int32_t)lo_t[(c * M + u) * n + d];
        int64_t lo = (int64_t)ol + coord[d];
        int32_t e = (int32_t)hi_t[(c * M + u) * n + d] - ol + 1;
        if (pmask[d]) {{
            lo = pmod(lo, shape[d]);
            if (e > shape[d]) e = (int32_t)shape[d];
        }} else {{
            usable = usable && lo >= 0 && lo + e <= shape[d];
        }}
        k += lo * strides[d];
        v *= e;
        ext[d] = e;
    }}
    *key = k;
    *vol = v;
    return usable;
}}

static inline void coords(int64_t c, int64_t n, const int64_t *shape, const int64_t *strides, int64_t *coord)
{{
    for (int64_t d = 0; d < n; d++) coord[d] = (c / strides[d]) % shape[d];
}}

/* the next cell's multi-index (row-major: the last dimension fastest), no division */
static inline void advance(int64_t n, const int64_t *shape, int64_t *coord)
{{
    for (int64_t d = n - 1; d >= 0 && ++coord[d] == shape[d]; d--) coord[d] = 0;
}}

void corner_counts(int64_t N, int64_t M, int64_t n, const off_t_ *lo_t, const off_t_ *hi_t, const uint8_t *ok,
                   const int64_t *shape, const int64_t *strides, const uint8_t *pmask, int64_t *counts,
                   uint8_t *usable_bits, boxes_t *cell_boxes, trans_t *cell_trans, int64_t *emax)
{{
    int64_t coord[64], key;
    int32_t ext[64], vol;
    const int64_t W = (M + 7) / 8;
    coords(0, n, shape, strides, coord);
    for (int64_t c = 0; c < N; c++, advance(n, shape, coord)) {{
        for (int64_t u = 0; u < M; u++) {{
            if (!corner_pair(lo_t, hi_t, ok, c, u, M, n, coord, shape, strides, pmask, &key, &vol, ext)) continue;
            counts[key] += 1;
            cell_boxes[c] = (boxes_t)(cell_boxes[c] + 1);
            cell_trans[c] = (trans_t)(cell_trans[c] + vol);
            usable_bits[c * W + (u >> 3)] |= (uint8_t)(1 << (7 - (u & 7)));
            for (int64_t d = 0; d < n; d++) {{
                const int64_t e = ext[d] < 255 ? ext[d] : 255;
                if (e > emax[d]) emax[d] = e;
            }}
        }}
    }}
}}

void corner_place(int64_t N, int64_t M, int64_t n, const off_t_ *lo_t, const off_t_ *hi_t, const uint8_t *ok,
                  const int64_t *shape, const int64_t *strides, const uint8_t *pmask, const int64_t *emax,
                  int64_t *nxt, q_t *q, uint8_t *code_out)
{{
    int64_t coord[64], key;
    int32_t ext[64], vol;
    for (int64_t u = 0; u < M; u++) {{
        coords(0, n, shape, strides, coord);
        for (int64_t c = 0; c < N; c++, advance(n, shape, coord)) {{
            if (!corner_pair(lo_t, hi_t, ok, c, u, M, n, coord, shape, strides, pmask, &key, &vol, ext)) continue;
            int64_t code = 0;
            for (int64_t d = 0; d < n; d++) {{
                const int64_t e = ext[d] < 255 ? ext[d] : 255;
                code = code * emax[d] + (e > 1 ? e : 1) - 1;
            }}
            const int64_t k = nxt[key]++;
            q[k] = (q_t)(c * M + u);
            code_out[k] = (uint8_t)code;
        }}
    }}
}}

/* the index row of the boxes whose lo corner is cell r minus offset a, or -1 outside the grid */
static inline int64_t corner_key(int64_t r, int64_t a, int64_t n, const int64_t *offsets, const int64_t *shape,
                                 const int64_t *strides, const uint8_t *pmask)
{{
    int64_t key = 0;
    for (int64_t d = 0; d < n; d++) {{
        int64_t c = (r / strides[d]) % shape[d] - offsets[a * n + d];
        if (pmask[d]) c = pmod(c, shape[d]);
        else if (c < 0) return -1;
        key += c * strides[d];
    }}
    return key;
}}

/* one level: the pairs whose count reached 0 (malloc'ed into *out, freed by kfree) and the
   transitions visited */
int64_t reach_level(int64_t nR, const int64_t *R, const int32_t *indptr, const q_t *q, const uint8_t *code,
                    int64_t E, int64_t n, const int64_t *offsets, int64_t ncodes, const uint8_t *fits,
                    const int64_t *shape, const int64_t *strides, const uint8_t *pmask, int64_t M,
                    const uint8_t *won, cnt_t *cnt, int64_t **out, int64_t *n_out)
{{
    int64_t cap = 1024, nd = 0, tested = 0;
    int64_t *done = (int64_t *)malloc(cap * sizeof(int64_t));
    for (int64_t i = 0; i < nR; i++) {{
        const int64_t r = R[i];
        for (int64_t a = 0; a < E; a++) {{
            const int64_t key = corner_key(r, a, n, offsets, shape, strides, pmask);
            if (key < 0) continue;
            for (int64_t e = indptr[key]; e < indptr[key + 1]; e++) {{
                if (!fits[a * ncodes + code[e]]) continue;
                const int64_t p = (int64_t)q[e];
                if (won[p / M]) continue;
                tested++;
                cnt[p] -= 1;
                if (cnt[p] == 0) {{
                    if (nd == cap) {{ cap *= 2; done = (int64_t *)realloc(done, cap * sizeof(int64_t)); }}
                    done[nd++] = p;
                }}
            }}
        }}
    }}
    *out = done;
    *n_out = nd;
    return tested;
}}

/* one level of the invariance worklist: drop every alive pair (c, u) whose box holds a cell of R
   (each once); the cells whose last alive pair went are returned (malloc'ed, freed by kfree) */
int64_t inv_level(int64_t nR, const int64_t *R, const int32_t *indptr, const q_t *q, const uint8_t *code,
                  int64_t E, int64_t n, const int64_t *offsets, int64_t ncodes, const uint8_t *fits,
                  const int64_t *shape, const int64_t *strides, const uint8_t *pmask, int64_t M,
                  uint8_t *alive, int32_t *n_alive, int64_t **out, int64_t *n_out)
{{
    int64_t cap = 1024, nd = 0, tested = 0;
    int64_t *done = (int64_t *)malloc(cap * sizeof(int64_t));
    for (int64_t i = 0; i < nR; i++) {{
        const int64_t r = R[i];
        for (int64_t a = 0; a < E; a++) {{
            const int64_t key = corner_key(r, a, n, offsets, shape, strides, pmask);
            if (key < 0) continue;
            for (int64_t e = indptr[key]; e < indptr[key + 1]; e++) {{
                if (!fits[a * ncodes + code[e]]) continue;
                const int64_t p = (int64_t)q[e];
                if (!alive[p]) continue;
                alive[p] = 0;
                tested++;
                const int64_t c = p / M;
                if (--n_alive[c] == 0) {{
                    if (nd == cap) {{ cap *= 2; done = (int64_t *)realloc(done, cap * sizeof(int64_t)); }}
                    done[nd++] = c;
                }}
            }}
        }}
    }}
    *out = done;
    *n_out = nd;
    return tested;
}}

/* the safety controller's choice: per cell the first valid input of the largest margin, the margin
   of a pair the min of D (erosions survived) over its box (invariance._safety_controller) */
void safety_choose(int64_t N, int64_t M, int64_t n, const off_t_ *lo_t, const off_t_ *hi_t, const uint8_t *valid,
                   const int8_t *D, const int64_t *shape, const int64_t *strides, const uint8_t *pmask,
                   int64_t max_margin, int32_t *chosen)
{{
    int64_t coord[64], lo[64], ext[64], t[64];
    for (int64_t d = 0; d < n; d++) coord[d] = 0;
    for (int64_t c = 0; c < N; c++, advance(n, shape, coord)) {{
        int64_t best = -1;
        chosen[c] = -1;
        for (int64_t u = 0; u < M && best < max_margin; u++) {{
            if (!valid[c * M + u]) continue;
            for (int64_t d = 0; d < n; d++) {{
                lo[d] = coord[d] + (int64_t)lo_t[(c * M + u) * n + d];
                ext[d] = (int64_t)hi_t[(c * M + u) * n + d] - (int64_t)lo_t[(c * M + u) * n + d] + 1;
                if (pmask[d]) {{ lo[d] = pmod(lo[d], shape[d]); if (ext[d] > shape[d]) ext[d] = shape[d]; }}
                t[d] = 0;
            }}
            int64_t mg = max_margin;
            for (;;) {{  /* every cell of the box (an odometer over its extents); stop once no better */
                int64_t cell = 0;
                for (int64_t d = 0; d < n; d++) cell += ((lo[d] + t[d]) % shape[d]) * strides[d];
                if (D[cell] < mg) mg = D[cell];
                if (mg <= best) break;
                int64_t d = n - 1;
                while (d >= 0 && ++t[d] == ext[d]) t[d--] = 0;
                if (d < 0) break;
            }}
            if (mg > best) {{ best = mg; chosen[c] = (int32_t)u; }}
        }}
    }}
}}

void kfree(void *p) {{ free(p); }}
"""

_LIBS: dict = {}


def source(off, q, cnt=np.uint8, boxes=np.uint8, trans=np.uint8) -> str:
    """The C source for these integer dtypes."""
    t = {k: _CTYPE[np.dtype(v)] for k, v in dict(off=off, q=q, cnt=cnt, boxes=boxes, trans=trans).items()}
    return _SOURCE.format(**t)


def library(pairs: int, off, q, cnt=np.uint8, boxes=np.uint8, trans=np.uint8):
    """The compiled library for these dtypes when ``SIMGAP_JIT`` and the job's ``pairs`` say so (module
    docstring), else None."""
    from .. import jit
    from ..compile import c_cached, c_compiler, load_c
    if jit.mode() == "0" or c_compiler() is None:
        return None
    src = source(off, q, cnt, boxes, trans)
    if src in _LIBS:
        return _LIBS[src]
    if jit.mode() == "auto" and pairs < AUTO_PAIRS and not c_cached(src):
        return None
    lib = load_c(src)
    if lib is not None:
        lib.reach_level.restype = ctypes.c_int64
        lib.inv_level.restype = ctypes.c_int64
        lib.kfree.argtypes = [ctypes.c_void_p]
        _LIBS[src] = lib
    return lib


def for_abstraction(ab):
    """The library for an abstraction's tables (one class per cell): its index build and safety
    controller, or None (:func:`library`)."""
    from .corner_index import _cell_dtypes
    N, M = ab.ok.shape
    boxes_t, trans_t = _cell_dtypes(M)
    return library(N * M, ab.off_lo.dtype, np.int32 if N * M < 2 ** 31 else np.int64, boxes=boxes_t, trans=trans_t)


def safety_choose(lib, ab, valid: np.ndarray, D: np.ndarray, max_margin: int) -> np.ndarray:
    """(N,) int32 the first valid input of the largest margin per cell, -1 without one."""
    g = ab.grid
    N, M = valid.shape
    chosen = np.empty(N, dtype=np.int32)
    vp, i64 = ctypes.c_void_p, ctypes.c_int64
    arrays = (np.ascontiguousarray(ab.off_lo), np.ascontiguousarray(ab.off_hi), np.ascontiguousarray(valid),
              np.ascontiguousarray(D, dtype=np.int8), np.array(g.shape, dtype=np.int64), g.strides.astype(np.int64),
              np.asarray(g.periodic_mask, dtype=np.uint8))
    lib.safety_choose(i64(N), i64(M), i64(g.n), *(vp(_p(a)) for a in arrays), i64(int(max_margin)), vp(_p(chosen)))
    return chosen


def _p(a: np.ndarray) -> int:
    return a.ctypes.data


def corner_counts(lib, off_lo, off_hi, ok, shape, strides, pmask, counts, usable_bits, cell_boxes, cell_trans, emax):
    N, M = ok.shape
    i64 = ctypes.c_int64
    lib.corner_counts(i64(N), i64(M), i64(len(shape)), *(ctypes.c_void_p(_p(a)) for a in (
        off_lo, off_hi, ok, shape, strides, pmask, counts, usable_bits, cell_boxes, cell_trans, emax)))


def corner_place(lib, off_lo, off_hi, ok, shape, strides, pmask, emax, indptr, q, code_out):
    N, M = ok.shape
    nxt = indptr[:-1].astype(np.int64)
    i64 = ctypes.c_int64
    lib.corner_place(i64(N), i64(M), i64(len(shape)), *(ctypes.c_void_p(_p(a)) for a in (
        off_lo, off_hi, ok, shape, strides, pmask, emax, nxt, q, code_out)))


def reach_level(lib, R, indptr, q, code, offsets, fits, shape, strides, pmask, M, won, cnt):
    """(pairs whose count reached 0, transitions visited), as the numpy level."""
    return _level(lib, lib.reach_level, R, indptr, q, code, offsets, fits, shape, strides, pmask, M, won, cnt)


def invariance_level(lib, R, indptr, q, code, offsets, fits, shape, strides, pmask, M, alive, n_alive):
    """(cells whose last alive pair went, pairs dropped), as one round of ``invariance._invariance_worklist``
    (``alive`` (N*M,) bool and ``n_alive`` (N,) int32 updated in place)."""
    return _level(lib, lib.inv_level, R, indptr, q, code, offsets, fits, shape, strides, pmask, M, alive, n_alive)


def _level(lib, fn, R, indptr, q, code, offsets, fits, shape, strides, pmask, M, flags, counts):
    R = np.ascontiguousarray(R, dtype=np.int64)
    out, n_out = ctypes.c_void_p(), ctypes.c_int64()
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    E, n = offsets.shape
    tested = fn(i64(R.size), vp(_p(R)), vp(_p(indptr)), vp(_p(q)), vp(_p(code)), i64(E), i64(n),
                vp(_p(offsets)), i64(fits.shape[1]), vp(_p(fits)), vp(_p(shape)), vp(_p(strides)),
                vp(_p(pmask)), i64(M), vp(_p(flags)), vp(_p(counts)), ctypes.byref(out), ctypes.byref(n_out))
    try:
        done = np.ctypeslib.as_array(ctypes.cast(out, ctypes.POINTER(ctypes.c_int64)), (n_out.value,)).copy() \
            if n_out.value else np.empty(0, dtype=np.int64)
    finally:
        lib.kfree(out)
    return done, int(tested)

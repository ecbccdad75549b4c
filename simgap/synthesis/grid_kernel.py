"""A system file's successor boxes by one compiled kernel: the RK4 post of every cell centre, the
growth radius and SCOTS's box formula in a single pass (issue 56).

:func:`~simgap.synthesis.abstraction.build_abstraction` computes, per (cell c, input u),

    x+ = f(c, u)  (``steps`` base periods, each ``substeps`` RK4 substeps or the map),
    r+ = growth(eta/2 + z, u)  (per input: the growth of a system file is state-independent),
    lo = floor(((x+ - r+) - z - first + eta/2) / eta) - i(c),  hi likewise with (x+ + r+) + z,

with numpy over blocks of pairs (the oracle). For a system file this module runs the same
operations, in the same order, in C code generated from the file's expression trees by
:func:`simgap.compile.grid_source` (one generator: the trees' DAG, emitted for C), writing the
int8 / int16 offset tables and the valid flags directly: no per-pair float array is allocated,
and there is no Python loop over blocks of pairs. Sub-trees that read no state (the inputs, dt,
constants; the vehicle's alpha = arctan(tan(steer)/2)) are evaluated by numpy once per input
(:func:`simgap.compile.hoist`): numpy's own values, so the tables are bit-identical to the numpy
path's (asserted by tests/test_grid_kernel.py).

Used when ``SIMGAP_JIT`` is not 0, a C compiler is found (``$CC``, cc, gcc) and either the
library is in the disk cache or the job has at least :data:`AUTO_ROWS` step rows (a first
compile costs about 0.2 s); with a gap, ``hold > 1``, periodic dimensions or angle wrapping the
numpy loop runs.
"""

from __future__ import annotations

import numpy as np

from ..errors import SimgapError

#: step rows from which a first compile (about 0.12 s CPU of the C compiler, measured) pays in auto
#: mode: the numpy step of a system file costs about 1 us per row
AUTO_ROWS = 200_000
#: classes per kernel call (progress reports between calls)
BLOCK_CLASSES = 1 << 16


class GridKernel:
    """The compiled ``grid_boxes`` of a system file's formulas and the input terms it reads."""

    def __init__(self, lib, hoisted_trees, n: int, m: int, substeps: int, continuous: bool):
        import ctypes
        self.fn = lib.grid_boxes
        self.fn.restype = None
        p, i64, f64 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
        self.fn.argtypes = [i64, i64, p, p, p, i64, p, i64, p, p, p, p, p, p, f64, i64, i64, i64, f64, i64,
                            p, p, p, p]
        self.posts_fn = lib.grid_posts
        self.posts_fn.restype = None
        self.posts_fn.argtypes = [i64, p, p, p, i64, p, f64, i64, i64, i64, p]
        self.hoisted_trees, self.n, self.m = hoisted_trees, n, m
        self._terms = (None, None)  # (inputs, tau) -> their hoisted terms, the last ones
        self.substeps, self.continuous = substeps, continuous

    def input_terms(self, U: np.ndarray, tau: float) -> np.ndarray:
        """(M, H): the hoisted sub-trees on the inputs, by numpy (:func:`simgap.expr.evaluate`)."""
        from ..expr import evaluate
        M = U.shape[0]
        z = np.zeros((M, self.n + self.m + 1))
        z[:, self.n:self.n + self.m] = U
        z[:, self.n + self.m] = tau
        H = np.empty((M, max(1, len(self.hoisted_trees))))
        with np.errstate(all="ignore"):
            for k, t in enumerate(self.hoisted_trees):
                H[:, k] = np.broadcast_to(np.asarray(evaluate(t, z), dtype=float), (M,))
        return H

    def posts(self, system, X: np.ndarray, J: np.ndarray) -> np.ndarray:
        """f(X[p], U[J[p]]) (P, n) by the kernel's own code (``system.f``'s bits; tests compare them)."""
        return self._posts(X, J, system.inputs, float(system.base_tau), int(system.steps))

    def step(self, X: np.ndarray, U: np.ndarray, tau: float) -> np.ndarray:
        """One period of length ``tau`` from X (P, n) under the input rows U (P, m): the file's step
        (its bits), the hoisted terms by numpy once per distinct input row."""
        from ..runge_kutta import _input_rows  # the abstraction's blocks repeat their inputs: no sort
        uu, inv = _input_rows(np.asarray(U, dtype=float).reshape(len(X), self.m))
        return self._posts(X, inv.reshape(-1), uu, float(tau), 1)

    def _posts(self, X, J, U, tau: float, steps: int) -> np.ndarray:
        U = np.ascontiguousarray(U, dtype=float)
        key = (U.shape, U.tobytes(), tau)
        if self._terms[0] != key:  # the same inputs block after block: their terms once
            self._terms = (key, self.input_terms(U, tau))
        H = self._terms[1]
        X = np.ascontiguousarray(X, dtype=np.float64)
        J = np.ascontiguousarray(J, dtype=np.int64)
        if X.ndim != 2 or X.shape[1] != self.n or J.shape != (X.shape[0],) or (J.size and not 0 <= J.min() <= J.max() < len(U)):
            raise SimgapError(f"posts: X must be (P, {self.n}) and J (P,) indices of the {len(U)} inputs")
        out = np.empty_like(X)
        self.posts_fn(X.shape[0], X.ctypes.data, J.ctypes.data, U.ctypes.data, H.shape[1], H.ctypes.data,
                      tau, int(self.substeps), steps, int(self.continuous), out.ctypes.data)
        return out

    def boxes(self, system, grid, R, z, class_dims, off: dict, ok: np.ndarray, limit: float, on_progress=None):
        """Fill ``off["lo"]``, ``off["hi"]`` ((K, M, n) int8, widened to int16 when an offset does not
        fit, as the numpy loop's ``_store``) and ``ok`` (K, M) for every class; ``R`` (M, n) the
        radii after the sampling period."""
        n = grid.n
        U = np.ascontiguousarray(system.inputs, dtype=float)
        M = U.shape[0]
        K = ok.shape[0]
        cshape = np.array([grid.shape[d] if d in class_dims else 1 for d in range(n)], dtype=np.int64)
        inv = np.array([d not in class_dims for d in range(n)], dtype=np.uint8)
        f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
        H = self.input_terms(U, float(system.base_tau))
        first, eta, Rc, zc = f64(grid.first), f64(grid.eta), f64(R), f64(z)
        dlo, dhi = f64(grid.domain_lo), f64(grid.domain_hi)
        ok8 = ok.view(np.uint8)
        mm = np.empty(2)
        keep = (cshape, first, eta, U, H, Rc, zc, dlo, dhi, inv)  # alive during the calls
        ptr = lambda a: a.ctypes.data  # noqa: E731
        for k0 in range(0, K, BLOCK_CLASSES):
            k1 = min(K, k0 + BLOCK_CLASSES)
            while True:
                wide = int(off["lo"].dtype == np.int16)
                self.fn(k0, k1, ptr(cshape), ptr(first), ptr(eta), M, ptr(U), H.shape[1], ptr(H), ptr(Rc),
                        ptr(zc), ptr(dlo), ptr(dhi), ptr(inv), float(system.base_tau), int(self.substeps),
                        int(system.steps), int(self.continuous), float(limit), wide,
                        ptr(off["lo"][k0:k1]), ptr(off["hi"][k0:k1]), ptr(ok8[k0:k1]), ptr(mm))
                if wide or (-128 <= mm[0] and mm[1] <= 127):
                    break
                for s in off:  # int8 -> int16 (+-limit fits); the block is written again
                    off[s] = off[s].astype(np.int16)
            if on_progress is not None:
                on_progress(k1, K)
        del keep


def grid_kernel(system, rows: int):
    """The :class:`GridKernel` of ``system`` when it is a system file whose state formulas compile
    to numpy's bits and compiling pays (module docstring), else None (the numpy loop)."""
    from .. import jit
    if jit.mode() == "0" or system.angle_dims:
        return None
    spec = system.params.get("_system_file")
    from ..system_file import is_spec
    if not is_spec(spec) or "_refined_json" in system.params:  # a refined model's effects are not trees
        return None
    return _kernel(spec, system.n, system.m, rows, jit.mode() == "auto")


def _kernel(spec, n: int, m: int, rows: int, auto: bool):
    """The GridKernel of a checked system-file table, or None (no bit-identical kernel for its
    formulas, no C compiler, or in auto mode a first compile that does not pay for ``rows``)."""
    from ..compile import c_cached, grid_source, load_c
    from ..system_file import _spec_trees
    t = _spec_trees(spec)
    try:
        src, hoisted = grid_source(t["trees"], n, m)
    except SimgapError:  # a function without numpy's bits compiled (exp, tan of the state, ...)
        return None
    if auto and rows < AUTO_ROWS and not c_cached(src):
        return None
    lib = load_c(src)
    if lib is None:
        return None
    return GridKernel(lib, hoisted, n, m, t["substeps"], t["continuous"])


_FILES: dict = {}


def file_step(path, rows: int = 0, force: bool = False):
    """The :meth:`GridKernel.step` of the system file at ``path`` (a file of the package: the built-in
    examples' compiled step), or None when ``SIMGAP_JIT`` and the job's ``rows`` (or the declared
    work) say numpy; ``force``: whenever a C compiler is found."""
    from .. import jit
    if not force and jit.mode() == "0":
        return None
    key = str(path)
    if key not in _FILES:
        from ..system_file import load_system_file
        s = load_system_file(path)
        _FILES[key] = (s.params["_system_file"], s.n, s.m, {})
    spec, n, m, loaded = _FILES[key]
    if "kernel" not in loaded:
        k = _kernel(spec, n, m, max(int(rows), jit._WORK.get()), auto=not force and jit.mode() == "auto")
        if k is None:
            return None
        loaded["kernel"] = k
    return loaded["kernel"].step

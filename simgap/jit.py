"""When the compiled (numba) kernels are used instead of their numpy twins.

The compiled kernels (:mod:`simgap.synthesis.kernels`, :mod:`simgap.perrun.vi_kernel`) give the
same bits as the numpy code they replace, so the choice is about cost only: importing numba and
loading a cached kernel costs about 0.33 s CPU and 115 MB of resident memory per process
(llvmlite's library, LLVM's start and numba's registries; measured idle, 2026-11-29, with the
BLAS probe deferred: 0.61 s and 131 MB without), paid once.
A kernel pays for that only on large jobs, so
:func:`~simgap.synthesis.abstraction.build_abstraction` declares its work (the number of rows
it is about to pass to the system's step, ``pairs * hold * steps``) with
:func:`expected_work`, and a step function with a compiled twin asks :func:`use_compiled`:

* ``SIMGAP_JIT=0`` (environment): never (the numpy path: the test oracle and the fallback);
* ``SIMGAP_JIT=1``: always (tests of the compiled path);
* otherwise (``auto``): when numba is already imported (no cost left), or when the declared
  work is at least the twin's break-even (``min_rows`` step rows, default :data:`AUTO_WORK`)
  and numba is installed.

This module never imports numba at its own import; :func:`njit` (used by the kernel modules)
imports it on first use, with numba's BLAS probe deferred (:func:`_defer_blas_probe`).
"""

from __future__ import annotations

import contextlib
import contextvars
import importlib.util
import os

from .errors import SimgapError

#: declared step rows from which a compiled twin is used in auto mode, unless it names its own
#: break-even (``use_compiled(min_rows)``). Importing numba and loading a cached kernel costs
#: about 0.33 s CPU and 115 MB of resident memory (LLVM's start), measured on the 2-core machine.
AUTO_WORK = 2_000_000

_WORK: contextvars.ContextVar = contextvars.ContextVar("simgap_jit_work", default=0)
_AVAILABLE = None


def mode() -> str:
    """``"0"``, ``"1"`` or ``"auto"`` from the environment variable SIMGAP_JIT."""
    v = os.environ.get("SIMGAP_JIT", "auto").strip().lower() or "auto"
    if v not in ("0", "1", "auto"):
        raise SimgapError(f"environment variable SIMGAP_JIT={v!r} is not one of 0, 1, auto; "
                          "unset it or set SIMGAP_JIT=auto")
    return v


def available() -> bool:
    """numba is installed (found without importing it)."""
    global _AVAILABLE
    if _AVAILABLE is None:
        _AVAILABLE = importlib.util.find_spec("numba") is not None
    return _AVAILABLE


@contextlib.contextmanager
def expected_work(rows: int):
    """Within the block, a job declares about ``rows`` step rows to come (module docstring)."""
    token = _WORK.set(int(rows))
    try:
        yield
    finally:
        _WORK.reset(token)


def use_compiled(min_rows: int = AUTO_WORK) -> bool:
    """Whether a step with a compiled twin should use it now (module docstring); ``min_rows``:
    the declared step rows from which the twin pays for numba's start in auto mode."""
    import sys
    m = mode()
    if m == "0":
        return False
    if m == "1":
        if not available():
            raise SimgapError("SIMGAP_JIT=1 but numba is not installed: pip install numba, or unset SIMGAP_JIT")
        return True
    if "numba" in sys.modules:
        return True
    return _WORK.get() >= min_rows and available()


def _defer_blas_probe() -> None:
    """Import ``numba.np.arraymath`` without its import-time BLAS probe.

    numba's first compile or cache load installs its NumPy implementations; their module
    ``numba.np.arraymath`` checks at import whether BLAS is available by importing
    ``scipy.linalg.cython_blas``, i.e. all of ``scipy.linalg`` (measured: 0.23 s CPU and 28 MB of
    resident memory per process, about a third of numba's start; none of simgap's kernels uses
    BLAS). The probe is answered from whether scipy is installed instead (found without importing
    it); numba's linear algebra still imports scipy itself, when a function using it is compiled
    (``ensure_blas`` in ``numba.np.linalg``), and fails there as before without it. Nothing is
    done when numba has loaded that module already, or when its layout differs (other versions).
    """
    import sys
    if "numba.np.arraymath" in sys.modules:
        return
    try:
        import numba.np.linalg as linalg
        probe = linalg.ensure_blas
    except (ImportError, AttributeError):
        return

    def deferred():
        raise ImportError("BLAS probe deferred by simgap (numba.np.linalg.ensure_blas runs on use)")

    linalg.ensure_blas = deferred
    try:
        import numba.np.arraymath as arraymath
    finally:
        linalg.ensure_blas = probe
    if hasattr(arraymath, "_HAVE_BLAS"):
        arraymath._HAVE_BLAS = importlib.util.find_spec("scipy") is not None


def njit(**kw):
    """``numba.njit(cache=True, nogil=True, **kw)`` (compiled without a cache when no cache
    location is writable), numba imported here on first use (:func:`_defer_blas_probe`)."""
    import numba
    _defer_blas_probe()

    def deco(fn):
        try:
            return numba.njit(cache=True, nogil=True, **kw)(fn)
        except RuntimeError:  # no writable cache location: compiled in every process instead
            return numba.njit(nogil=True, **kw)(fn)
    return deco

"""When the compiled (numba) kernels are used instead of their numpy twins.

The compiled kernels (:mod:`.kernels`) give the same bits as the numpy code they replace, so
the choice is about cost only: importing numba and loading a cached kernel costs about 0.8 s
CPU and 130 MB of resident memory per process (llvmlite's library and LLVM's start), paid once.
A kernel pays for that only on large jobs, so
:func:`~simgap.synthesis.abstraction.build_abstraction` declares its work (the number of rows
it is about to pass to the system's step, ``pairs * hold * steps``) with
:func:`expected_work`, and a step function with a compiled twin asks :func:`use_compiled`:

* ``SIMGAP_JIT=0`` (environment): never (the numpy path: the test oracle and the fallback);
* ``SIMGAP_JIT=1``: always (tests of the compiled path);
* otherwise (``auto``): when numba is already imported (no cost left), or when the declared
  work is at least the twin's break-even (``min_rows`` step rows, default :data:`AUTO_WORK`)
  and numba is installed.

This module never imports numba itself.
"""

from __future__ import annotations

import contextlib
import contextvars
import importlib.util
import os

from ..errors import SimgapError

#: declared step rows from which a compiled twin is used in auto mode, unless it names its own
#: break-even (``use_compiled(min_rows)``). Importing numba and loading a cached kernel costs
#: about 0.8 s CPU and 130 MB of resident memory (LLVM's start), measured on the 2-core machine.
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

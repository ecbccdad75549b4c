"""One simulator spread over several processes: the rows of a batch split across cores.

Collection spreads its chunks over worker processes, but the stages that call a simulator
directly (the simulator estimate of Lhat_fhat, the audit, the closed-loop rollouts) hand it one
large batch at a time. :class:`ParallelSimulator` serves such a batch with ``workers``
processes: the calling process simulates one contiguous share of the rows and ``workers - 1``
helper processes (each with its own simulator built from the same config) the others.

Results are bit-identical to the wrapped simulator's: noise is drawn here, by the wrapped
simulator's :meth:`draw_noise` from the caller's generator, and every backend's
``step_with_noise`` computes row i from (x_i, u_i, noise_i) alone, whatever the batch split
(tested for the PyBullet backends).

The results of the last few large batches (>= ``MEMO_ROWS`` rows) are kept, keyed by a digest
of (x, u, noise): the pipeline audits both certificates at the same points with the same seed,
and the second audit's batch is then a lookup (the same numbers, since a batch's result is a
function of its inputs).
"""

from __future__ import annotations

import hashlib
import os
from collections import OrderedDict
from concurrent.futures import ProcessPoolExecutor
from typing import Dict, Optional

import numpy as np

from ..system_ref import system_ref
from .base import Simulator, SimulatorConfig, build_simulator

#: batches smaller than this many rows per process run in the calling process only
MIN_ROWS_PER_PROCESS = 8
#: batches of at least this many rows are remembered (the last MEMO_BATCHES of them)
MEMO_ROWS, MEMO_BATCHES = 5000, 4

_HELPER: Optional[Simulator] = None  # the simulator of a helper process


def _start_helper(config: dict, system, parent: int) -> None:
    global _HELPER
    from ..executors import exit_with_parent
    from ..system_ref import resolve_system
    exit_with_parent(parent)
    _HELPER = build_simulator(config, None if system is None else resolve_system(system, paths=False))


def _helper_step(x, u, noise):
    return _HELPER.step_with_noise(x, u, noise)


class ParallelSimulator(Simulator):
    """``inner`` (a built simulator) served by ``workers`` processes (see module docstring).

    The helper processes start on the first batch large enough to split and stop at
    :meth:`close`. ``config``, ``system``, ``draw_noise`` are the wrapped simulator's.
    """

    def __init__(self, inner: Simulator, workers: int, system=None):
        self.inner = inner
        self.config: SimulatorConfig = inner.config
        self.system = inner.system
        self.PARAMETER_DRAWS = inner.PARAMETER_DRAWS
        self.randomize_per = inner.randomize_per
        self.workers = max(1, int(workers))
        # what the helpers rebuild the system from: a System's step is a closure that does not
        # pickle (forkserver/spawn), so a built-in or plugin name or the embedded system file / refined system travels instead
        self._system_arg = system if system is None else (system_ref(system) or system)
        self._pool = None
        self._memo: OrderedDict = OrderedDict()

    def __getattr__(self, name):  # anything else a backend offers (e.g. the numpy one's mean_next)
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def draw_noise(self, B: int, rng: np.random.Generator) -> Dict[str, np.ndarray]:
        return self.inner.draw_noise(B, rng)

    def step_with_noise(self, x, u, noise):
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        B = x.shape[0]
        key = None
        if B >= MEMO_ROWS:
            h = hashlib.sha256()
            for name, a in [("x", x), ("u", u)] + sorted(noise.items()):
                a = np.ascontiguousarray(a)
                h.update(f"{name}{a.dtype.str}{a.shape}".encode())
                h.update(a.tobytes())
            key = h.hexdigest()
            if key in self._memo:
                self._memo.move_to_end(key)
                return self._memo[key].copy()
        y = self._step(x, u, noise)
        if key is not None:
            self._memo[key] = y.copy()
            while len(self._memo) > MEMO_BATCHES:
                self._memo.popitem(last=False)
        return y

    def _step(self, x, u, noise):
        B = x.shape[0]
        parts = min(self.workers, B // MIN_ROWS_PER_PROCESS)
        if parts <= 1 or u.shape[0] != B:
            return self.inner.step_with_noise(x, u, noise)
        from ..executors import LocalExecutor, submit_without_sigint
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.workers - 1, mp_context=LocalExecutor()._context(),
                                             initializer=_start_helper,
                                             initargs=(self.config.to_dict(), self._system_arg, os.getpid()))
        cuts = np.linspace(0, B, parts + 1).astype(int)
        try:
            futures = [submit_without_sigint(self._pool.submit, _helper_step, x[a:b], u[a:b],
                                             {k: v[a:b] for k, v in noise.items()})
                       for a, b in zip(cuts[1:-1], cuts[2:])]
            own = self.inner.step_with_noise(x[:cuts[1]], u[:cuts[1]], {k: v[:cuts[1]] for k, v in noise.items()})
            return np.concatenate([own] + [f.result() for f in futures])
        except BaseException:
            # Ctrl-C, SIGTERM or an error: the helpers' shares are lost anyway; end them now rather
            # than wait for them in close()
            from ..executors import stop_pool
            pool, self._pool = self._pool, None
            stop_pool(pool)
            raise

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self.inner.close()

    def __del__(self):  # helpers of a simulator dropped without close() (an error in a stage)
        if self.__dict__.get("_pool") is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)

"""Executors: where the chunks of a collection run, behind one small interface.

``executor.map_chunks(fn, job, chunk_ids, on_result, should_stop)`` calls ``fn(job, c)`` for
every chunk id c (in any order, possibly in other processes) and ``on_result(c, result)`` in the
calling thread as each one finishes. ``fn`` must be a module-level function and ``job`` a
picklable, small description of the work (workers rebuild and cache heavy objects such as
simulators themselves). Between chunks ``should_stop()`` is polled; when it returns True no new
chunk is started, chunks in flight are finished and delivered, and ``map_chunks`` returns False.

Results never depend on the executor: each chunk draws its randomness from its own generator
keyed by the chunk id (see :mod:`simgap.collect`).

Backends:

* ``serial``: in this process, one chunk after the other (debugging, tests, the GUI's small jobs);
* ``local``: ``concurrent.futures.ProcessPoolExecutor`` with ``workers`` processes (default
  ``os.cpu_count()``). Workers are forked when the caller has a single thread (scripts need no
  ``if __name__ == "__main__"`` guard) and started by ``forkserver`` when it has more (the GUI)
  or native threads of their own name (:func:`native_threads`: Ray's outlive ``ray.shutdown()``),
  since forking a threaded process is unsafe;
* ``ray``: Ray tasks on a cluster (``address``, checked to accept a connection within
  ``RAY_CONNECT_TIMEOUT`` seconds when the executor is made) or on a local instance started
  here with ``num_cpus=workers``; needs the optional extra ``pip install simgap[ray]``.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Iterable, Optional

from .errors import SimgapError

EXECUTORS = ("serial", "local", "ray")
RAY_CONNECT_TIMEOUT = 5.0  # seconds to reach a Ray cluster's address


class Executor:
    """Base class: run ``fn(job, chunk_id)`` for every chunk id (see module docstring)."""

    name = "base"
    workers = 1

    def session(self):
        """A context in which several ``map_chunks`` calls share one start-up (a Ray instance)."""
        import contextlib
        return contextlib.nullcontext(self)

    def map_chunks(self, fn: Callable[[Any, int], Any], job: Any, chunk_ids: Iterable[int],
                   on_result: Callable[[int, Any], None],
                   should_stop: Callable[[], bool] = lambda: False) -> bool:
        raise NotImplementedError


class SerialExecutor(Executor):
    name = "serial"

    def map_chunks(self, fn, job, chunk_ids, on_result, should_stop=lambda: False):
        for c in chunk_ids:
            if should_stop():
                return False
            on_result(c, fn(job, c))
        return True


#: the start method a local pool uses unless it is given one (None: fork from a single-threaded caller, else
#: forkserver). The command line sets "forkserver" (``simgap.cli.POOL_START``): its own ``__main__`` is safe to preload, and its workers
#: then never inherit the command's state (a Ctrl-C while a forked pool was still starting its workers hung the
#: command for more than 30 s in the test suite; forked workers are kept for scripts without a ``__main__`` guard)
PREFERRED_START = None


class LocalExecutor(Executor):
    """A pool of ``workers`` processes on this machine (at most 2 * workers chunks in flight)."""

    name = "local"

    def __init__(self, workers: Optional[int] = None, start_method: Optional[str] = None):
        self.workers = _check_workers(workers)
        self.start_method = start_method

    def _context(self):
        cli = sys.modules.get("simgap.cli")  # a command's choice (simgap.cli.main), without importing this module
        method = self.start_method or PREFERRED_START or getattr(cli, "POOL_START", None)
        if method is not None and method not in multiprocessing.get_all_start_methods():
            method = None
        if method is None:
            methods = multiprocessing.get_all_start_methods()
            if threading.active_count() == 1 and "fork" in methods and not native_threads():
                method = "fork"
            elif "forkserver" in methods:
                method = "forkserver"
        return multiprocessing.get_context(method) if method else None

    def map_chunks(self, fn, job, chunk_ids, on_result, should_stop=lambda: False):
        todo = list(chunk_ids)
        if not todo:
            return True
        pool = ProcessPoolExecutor(max_workers=min(self.workers, len(todo)), mp_context=self._context(),
                                   initializer=exit_with_parent, initargs=(os.getpid(),))
        pending = {}

        def result(fut, c):
            try:
                return fut.result()
            except BrokenProcessPool as e:
                raise SimgapError(
                    f"a worker process died while computing chunk {c} ({e}). If you call this from a "
                    "script in a threaded program, guard it with `if __name__ == '__main__':`; "
                    "finished chunks are kept, run again to resume") from None

        try:
            done = _bounded_map(lambda c: submit_without_sigint(pool.submit, fn, job, c),
                                lambda p: wait(p, return_when=FIRST_COMPLETED)[0],
                                result, todo, 2 * self.workers, pending, on_result, should_stop)
        except BaseException:
            # Ctrl-C, SIGTERM or an error: a busy worker's chunk is lost either way (finished chunks
            # are stored), so end the workers now instead of waiting for their chunks
            stop_pool(pool)
            raise
        for fut in pending:
            fut.cancel()
        pool.shutdown(wait=True, cancel_futures=True)
        return done


def native_threads() -> list:
    """Names of this process's threads started by native code under a name of their own (Linux;
    elsewhere ``["ray"]`` once Ray is loaded, else none). Ray's gRPC threads outlive
    ``ray.shutdown()`` and are no Python threads: a child forked beside them can inherit one of
    their locks held and hang for good (seen after a Ray collection in the same process). BLAS and
    numba threads keep the process's name."""
    try:
        own = open("/proc/self/comm").read()
        names = []
        for t in os.listdir("/proc/self/task"):
            try:
                names.append(open(f"/proc/self/task/{t}/comm").read())
            except OSError:  # the thread ended meanwhile
                pass
    except OSError:
        return ["ray"] if "ray" in sys.modules else []
    return sorted({n.strip() for n in names if n != own})


class RayExecutor(Executor):
    """Ray tasks; a local Ray instance with ``num_cpus=workers`` unless ``address`` is given."""

    name = "ray"

    def __init__(self, workers: Optional[int] = None, address: Optional[str] = None):
        self.workers = _check_workers(workers)
        self.address = address
        if address:  # fail in seconds, not minutes, before anything is written (ray.init retries long)
            from .checks import reachable
            reachable(address, timeout=RAY_CONNECT_TIMEOUT, what="Ray cluster")
        try:
            import ray  # noqa: F401  (optional extra)
        except ImportError:
            from .paths import install_command
            raise SimgapError(f"executor 'ray' needs Ray: {install_command('ray')} (or pip install ray)") from None

    def _init(self) -> bool:
        """Connect to (or start) Ray unless it is up already; True if this call did."""
        import ray
        if ray.is_initialized():
            return False
        kw = dict(include_dashboard=False, log_to_driver=False, configure_logging=False)
        if self.address:
            ray.init(address=self.address, **kw)
        else:
            ray.init(num_cpus=self.workers, **kw)
        return True

    def session(self):
        """One Ray connection (or local instance) for every ``map_chunks`` inside; shut down after it
        if it was started here."""
        import contextlib

        @contextlib.contextmanager
        def ctx():
            import ray
            started = self._init()
            try:
                yield self
            finally:
                if started:
                    ray.shutdown()
        return ctx()

    def map_chunks(self, fn, job, chunk_ids, on_result, should_stop=lambda: False):
        import ray

        todo = list(chunk_ids)
        if not todo:
            return True
        started_here = self._init()
        try:
            task = ray.remote(num_cpus=1, max_retries=0)(_call)
            job_ref = ray.put(job)
            limit = 2 * max(self.workers, int(ray.cluster_resources().get("CPU", 1)))

            def result(ref, c):
                try:
                    return ray.get(ref)
                except ray.exceptions.RayTaskError as e:
                    cause = getattr(e, "cause", None)
                    if isinstance(cause, SimgapError):
                        raise SimgapError(str(cause)) from None
                    raise

            return _bounded_map(lambda c: task.remote(fn, job_ref, c),
                                lambda p: ray.wait(list(p), num_returns=1)[0],
                                result, todo, limit, {}, on_result, should_stop)
        finally:
            if started_here:
                ray.shutdown()



def _bounded_map(submit, wait_some, result, todo, limit, pending, on_result, should_stop) -> bool:
    """Run ``todo`` with at most ``limit`` chunks in flight (so cancellation is quick and memory
    stays small); ``on_result(c, result)`` in this thread as chunks finish, in completion order.

    ``submit(c) -> handle``, ``wait_some(pending) -> finished handles``, ``result(handle, c)``.
    ``pending`` (handle -> chunk) is the caller's, so it can cancel what is left on error.
    Returns False when ``should_stop`` stopped the submission of new chunks.
    """
    it = iter(todo)
    stopped = False
    while True:
        while not stopped and len(pending) < limit:
            if should_stop():
                stopped = True
                break
            c = next(it, None)
            if c is None:
                break
            pending[submit(c)] = c
        if not pending:
            return not stopped
        for h in wait_some(pending):
            c = pending.pop(h)
            on_result(c, result(h, c))

#: seconds a worker gets to end after SIGTERM before it is killed (the whole stop stays well under 5 s)
STOP_GRACE = 1.0


def stop_pool(pool, grace: float = STOP_GRACE) -> None:
    """End a ProcessPoolExecutor's workers now, busy or not (interrupt, SIGTERM, error).

    ``shutdown(wait=True)`` would wait for every running task (a simulator chunk can take
    minutes). The queued tasks are cancelled, each worker gets SIGTERM (their handler is the
    default one, :func:`exit_with_parent`), then SIGKILL after ``grace`` seconds, and the pool is
    shut down without waiting. The worker processes are read from the pool's ``_processes``
    (CPython's ProcessPoolExecutor keeps them there; an empty dict before the first task)."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    deadline = time.monotonic() + grace
    for p in procs:
        p.join(max(0.0, deadline - time.monotonic()))
        if p.is_alive():
            p.kill()
            p.join(1.0)


def _process_token(pid: int):
    """(alive, start time) of a process from /proc (Linux); None where /proc is not available."""
    if not os.path.exists("/proc/self/stat"):
        return None                                    # no /proc (macOS): the caller falls back to os.kill
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return fields[0] != b"Z", fields[19]          # state, start time (fields 3 and 22)
    except FileNotFoundError:
        return False, None
    except OSError:
        return None


def exit_with_parent(pid: int, period: float = 1.0) -> None:
    """In a pool worker: exit when process ``pid`` (the one that started the pool) is gone.

    A worker of a killed or crashed parent would otherwise finish its task and block for ever on a
    result pipe that nobody reads (it holds both ends). Its OS parent is the fork server, not the
    pool's owner, so this polls: once per ``period`` seconds, by the /proc start time (immune to pid
    reuse) where there is /proc, else by ``os.kill(pid, 0)``.

    Ctrl-C is ignored here: the terminal sends SIGINT to the whole process group, and the parent
    alone turns it into a clean "interrupted" (the workers printed KeyboardInterrupt tracebacks)
    and ends the pool; a worker whose parent is gone exits through the watch below."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # a forked worker inherits the command's SIGTERM handler (raise, then clean up as the parent does);
    # the parent's stop_pool ends a worker by SIGTERM, which must end it at once
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    first = _process_token(pid)

    def gone() -> bool:
        if first is None:
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return True
            except PermissionError:
                return True                            # the pid now belongs to another user's process
            return False
        now = _process_token(pid)
        return now is None or not now[0] or now[1] != first[1]

    def watch():
        while not gone():
            time.sleep(period)
        os._exit(1)

    threading.Thread(target=watch, name="simgap-exit-with-parent", daemon=True).start()


def submit_without_sigint(submit, *args):
    """``submit(*args)`` with SIGINT blocked in this thread: a worker the pool forks meanwhile (the
    fork server too) starts with SIGINT blocked, so a Ctrl-C in the moment between its fork and
    :func:`exit_with_parent` cannot kill it and leave the pool broken while the parent shuts it
    down. A SIGINT that arrives meanwhile is delivered to this process when the mask is restored."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        return submit(*args)
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        return submit(*args)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _call(fn, job, c):
    return fn(job, c)


def _check_workers(workers) -> int:
    if workers is None or workers == 0:
        return os.cpu_count() or 1
    try:
        w = int(workers)
    except (TypeError, ValueError):
        raise SimgapError(f"workers must be a positive integer, got {workers!r}") from None
    if w < 1 or w != workers:
        raise SimgapError(f"workers must be a positive integer (0 or None = all cores), got {workers!r}")
    return w


def make_executor(name: str = "local", workers: Optional[int] = None, address: Optional[str] = None) -> Executor:
    """An executor by name: ``serial``, ``local`` (default) or ``ray``."""
    if name == "serial":
        return SerialExecutor()
    if name == "local":
        return LocalExecutor(workers)
    if name == "ray":
        return RayExecutor(workers, address)
    raise SimgapError(f"unknown executor {name!r}; choose one of {', '.join(EXECUTORS)}")

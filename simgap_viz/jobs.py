"""Long work off the GUI thread: one background job at a time, with progress and cancel.

A job is a function ``fn(ctx) -> result``. ``ctx.progress(done, total)`` reports progress
(and is what engine stages receive as their ``on_progress`` callback); once the user has pressed
cancel it raises :class:`JobCancelled`, so a stage that reports progress is interrupted at its
next report even if it has no cancellation support of its own. ``ctx.cancelled`` is a
``threading.Event`` for stages that take one.
"""

from __future__ import annotations

import threading
import time
import traceback
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

from simgap.errors import SimgapError


class JobCancelled(Exception):
    """Raised inside a job when the user pressed cancel."""


@dataclass
class JobContext:
    """A job's cancel flag and progress. ``stage`` is the stage running now, which differs from the
    job's ``name`` when a job computes missing upstream stages first (a certify job that must collect
    reports "collect" until the data are in); ``stage_started`` is when it began (``time.monotonic``)."""

    name: str
    cancelled: threading.Event = field(default_factory=threading.Event)
    superseded: bool = False  # cancelled because newer settings replace it (no notice to the user)
    on_progress: Optional[Callable[[float], None]] = None
    done: float = 0.0
    total: float = 1.0
    _last: float = 0.0
    stage: str = ""
    stage_started: float = field(default_factory=time.monotonic)

    def __post_init__(self):
        self.stage = self.stage or self.name

    def begin(self, stage: str) -> None:
        """Mark the start of ``stage`` within this job (progress restarts from 0 under its name)."""
        self.stage, self.stage_started = stage, time.monotonic()
        self.done, self.total, self._last = 0.0, 1.0, 0.0
        if self.on_progress is not None:
            self.on_progress(0.0)

    def elapsed(self) -> float:
        """Seconds since the current stage began."""
        return time.monotonic() - self.stage_started

    def progress(self, done, total=None) -> None:
        """Report progress (done of total); raises JobCancelled after cancel."""
        if self.cancelled.is_set():
            raise JobCancelled(self.name)
        self.done = float(done)
        if total is not None:
            self.total = max(float(total), 1e-12)
        now = time.monotonic()
        # throttle GUI updates to ~20 Hz: engine stages may report per chunk
        if self.on_progress is not None and (now - self._last > 0.05 or self.done >= self.total):
            self._last = now
            self.on_progress(min(1.0, self.done / self.total))

    def check(self) -> None:
        if self.cancelled.is_set():
            raise JobCancelled(self.name)


@dataclass
class JobOutcome:
    name: str
    ok: bool
    result: Any = None
    error: Optional[str] = None
    cancelled: bool = False
    superseded: bool = False
    seconds: float = 0.0


class JobRunner:
    """Runs at most one job at a time on a daemon thread.

    Parameters
    ----------
    on_progress : callable(name, fraction)
        Called from the worker thread with the fraction done in [0, 1].
    on_finish : callable(JobOutcome)
        Called from the worker thread when a job ends (ok, failed or cancelled).
    """

    def __init__(self, on_progress=None, on_finish=None):
        self._on_progress = on_progress
        self._on_finish = on_finish
        self._lock = threading.Lock()
        self._thread: Optional[threading.Thread] = None
        self._ctx: Optional[JobContext] = None
        self.last: Optional[JobOutcome] = None

    @property
    def busy(self) -> bool:
        t = self._thread
        return t is not None and t.is_alive()

    @property
    def context(self) -> Optional[JobContext]:
        """The running job's context (its stage, progress and timing), or None."""
        return self._ctx if self.busy else None

    @property
    def current(self) -> Optional[str]:
        return self._ctx.name if self.busy and self._ctx else None

    def submit(self, name: str, fn: Callable[[JobContext], Any],
               then: Optional[Callable[[Any], None]] = None) -> None:
        """Start ``fn`` in the background; ``then(result)`` runs on the worker after success.

        Raises SimgapError if another job is still running.
        """
        with self._lock:
            if self.busy:
                raise SimgapError(f"'{self._ctx.name}' is still running; wait or press cancel")
            ctx = JobContext(name=name)
            if self._on_progress:  # reported under the stage running now (ctx.stage), not the job's name
                ctx.on_progress = lambda f: self._on_progress(ctx.stage, f)
            self._ctx = ctx
            self._thread = threading.Thread(target=self._run, args=(ctx, fn, then), name=f"simgap-{name}",
                                            daemon=True)
            self._thread.start()

    def _run(self, ctx: JobContext, fn, then) -> None:
        t0 = time.perf_counter()
        try:  # no report before fn runs: its first stage reports 0 % under its own name (ctx.begin)
            result = fn(ctx)
            if then is not None:
                then(result)
            out = JobOutcome(ctx.name, True, result=result)
        except JobCancelled:
            out = JobOutcome(ctx.name, False, error="cancelled", cancelled=True, superseded=ctx.superseded)
        except SimgapError as e:
            out = JobOutcome(ctx.name, False, error=str(e))
        except Exception as e:  # a bug must not kill the GUI: report it instead
            traceback.print_exc()
            out = JobOutcome(ctx.name, False, error=f"{type(e).__name__}: {e}")
        out.seconds = time.perf_counter() - t0
        self.last = out
        if self._on_finish:
            try:
                self._on_finish(out)
            except Exception:
                traceback.print_exc()

    def cancel(self, superseded: bool = False) -> bool:
        """Ask the running job to stop; True if there was one. ``superseded``: newer settings
        replace it, which its outcome says (the app then shows no "Cancelled" notice)."""
        ctx = self._ctx
        if ctx is not None and self.busy:
            ctx.superseded = superseded
            ctx.cancelled.set()
            return True
        return False

    def wait(self, timeout: float = 60.0) -> Optional[JobOutcome]:
        """Block until the current job ends (for tests and scripts); returns its outcome."""
        t = self._thread
        if t is not None:
            t.join(timeout)
            if t.is_alive():
                raise TimeoutError(f"job {self._ctx.name!r} still running after {timeout} s")
        return self.last

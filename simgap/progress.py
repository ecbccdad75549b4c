"""Progress reporting: a callback protocol and a dependency-free terminal progress bar.

Long stages report ``on_progress(done, total)`` (both ints, in the stage's own unit, e.g.
(x_r, u) pairs) after every finished unit of work; the GUI passes its own callback, the CLI a
:class:`ProgressBar`. Cancellation is cooperative: a stage polls ``should_stop()`` between
chunks (use :func:`as_stop_check` to accept a ``threading.Event`` or a callable).
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Callable, Optional, Protocol, Union

from .cover import format_duration


class ProgressCallback(Protocol):
    def __call__(self, done: int, total: int) -> None: ...


StopCheck = Union[threading.Event, Callable[[], bool], None]


def as_stop_check(should_stop: StopCheck) -> Callable[[], bool]:
    """A zero-argument callable from a threading.Event, a callable or None (never stop)."""
    if should_stop is None:
        return lambda: False
    if isinstance(should_stop, threading.Event):
        return should_stop.is_set
    if callable(should_stop):
        return lambda: bool(should_stop())
    raise TypeError(f"should_stop must be a threading.Event or a callable, got {type(should_stop).__name__}")


class ProgressBar:
    """Terminal progress bar on stderr: ``[####....]  41%  1,234/3,000 pairs  2,345/s  ETA 0:45``.

    Callable as ``bar(done, total)``. The rate and ETA count only the work done since the bar
    was created (a resumed run starts with ``done > 0``). On a terminal the line is redrawn at
    most every ``interval`` seconds; otherwise a plain line is printed every ~10 %.
    ``scale`` converts units for the rate (e.g. N1hat * k simulator steps per pair).
    """

    def __init__(self, unit: str = "pairs", stream=None, width: int = 28, interval: float = 0.2,
                 scale: float = 1.0, scale_unit: str = "steps"):
        self.unit, self.width, self.interval = unit, width, interval
        self.scale, self.scale_unit = scale, scale_unit
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.t0: Optional[float] = None
        self.done0 = 0
        self.last_draw = 0.0
        self.last_decile = -1
        self.finished = False

    def __call__(self, done: int, total: int) -> None:
        now = time.perf_counter()
        if self.t0 is None:
            self.t0, self.done0 = now, done
        final = done >= total
        if self.tty:
            if not final and now - self.last_draw < self.interval:
                return
        else:
            decile = int(10 * done / max(total, 1))
            if not final and decile == self.last_decile:
                return
            self.last_decile = decile
        self.last_draw = now
        self.stream.write(("\r" if self.tty else "") + self.line(done, total, now) + ("" if self.tty else "\n"))
        if final and self.tty and not self.finished:
            self.stream.write("\n")
        self.finished = self.finished or final
        self.stream.flush()

    def line(self, done: int, total: int, now: float) -> str:
        frac = done / total if total else 1.0
        fill = int(round(self.width * frac))
        elapsed = now - (self.t0 or now)
        new = done - self.done0
        rate = new / elapsed if elapsed > 0 and new > 0 else 0.0
        if rate > 0:
            eta = "ETA " + format_duration((total - done) / rate) if done < total else "in " + format_duration(elapsed)
            sr = f"  {rate * self.scale:,.0f} {self.scale_unit}/s" if self.scale != 1.0 else f"  {rate:,.0f}/s"
        else:
            eta, sr = "", ""
        return (f"[{'#' * fill}{'.' * (self.width - fill)}] {100 * frac:5.1f}%  "
                f"{done:,}/{total:,} {self.unit}{sr}  {eta}").rstrip() + "   "

    def close(self) -> None:
        if self.tty and not self.finished:
            self.stream.write("\n")
            self.stream.flush()

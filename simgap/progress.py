"""Progress reporting: a callback protocol and a progress bar (tqdm on a terminal, lines in a log).

Long stages report ``on_progress(done, total)`` (both ints, in the stage's own unit, e.g.
(x_r, u) pairs) after every finished unit of work; the GUI passes its own callback, the CLI a
:class:`ProgressBar`. Cancellation is cooperative: a stage polls ``should_stop()`` between
chunks (use :func:`as_stop_check` to accept a ``threading.Event`` or a callable).
"""

from __future__ import annotations

import sys
import threading
import time
from typing import TYPE_CHECKING, Callable, Optional, Protocol, Union

if TYPE_CHECKING:
    from tqdm import tqdm


def _interval(seconds: float) -> str:
    """[H:]MM:SS, as tqdm's format_interval."""
    m, s = divmod(int(seconds), 60)
    h, m = divmod(m, 60)
    return f"{h:d}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"


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
    """Progress on stderr: percentage, count, rate and ETA.

    Callable as ``bar(done, total)``. The rate and ETA count only the work done since the bar
    was created (a resumed run starts with ``done > 0``). ``scale`` converts units for the
    rate (e.g. N1hat * k simulator steps per pair). On a terminal it is a tqdm bar redrawn in
    place. Written to a file or a pipe (a log, ``2> log``) each update is a line of its own
    (a carriage-return redraw would leave a log one line long), the first at once, then at most
    one every ``interval_off_tty`` seconds, and the last when the work is done or the bar closed.
    """

    def __init__(self, unit: str = "pairs", stream=None, scale: float = 1.0, scale_unit: str = "steps",
                 desc: Optional[str] = None, interval_off_tty: float = 10.0, bar_format: Optional[str] = None):
        self.unit, self.scale, self.scale_unit, self.desc = unit, scale, scale_unit, desc
        self.bar_format = bar_format  # tqdm's, e.g. for a count that moves in fractions
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.mininterval = 0.2 if self.tty else interval_off_tty
        self.bar: Optional["tqdm"] = None
        self._lines: Optional[dict] = None  # off a terminal: start, counts, the last line written

    def __call__(self, done: int, total: int) -> None:
        if not self.tty:
            self._line_update(done, total)
            return
        if self.bar is None:
            from tqdm import tqdm  # on a terminal only: 50 ms of imports a command off one skips
            self.bar = tqdm(total=total, initial=done, unit=self.unit, desc=self.desc, file=self.stream,
                            mininterval=self.mininterval, dynamic_ncols=True, smoothing=0.1,
                            bar_format=self.bar_format)
        bar = self.bar
        if total != bar.total:
            bar.total = total
        elapsed = bar.format_dict["elapsed"]
        if self.scale != 1.0 and elapsed > 0 and done > bar.initial:
            rate = (done - bar.initial) * self.scale / elapsed
            bar.set_postfix_str(f"{rate:,.0f} {self.scale_unit}/s", refresh=False)
        bar.update(done - bar.n)
        if done >= total:
            self.close()

    def _line_update(self, done, total) -> None:
        now = time.monotonic()
        if self._lines is None:
            self._lines = {"t0": now, "initial": done, "written_at": None, "written": None}
        st = self._lines
        st["done"], st["total"] = done, total
        if st["written_at"] is None or done >= total or now - st["written_at"] >= self.mininterval:
            self._write_line(now)
        if done >= total:
            self._lines = None  # a later call starts a new bar, as tqdm's close does

    def _write_line(self, now: float) -> None:
        st = self._lines
        done, total, elapsed = st["done"], st["total"], now - st["t0"]
        rate = (done - st["initial"]) / elapsed if elapsed > 0 else 0.0
        text = (f"{self.desc}: " if self.desc else "") + f"{100.0 * done / total if total else 100.0:3.0f}% "
        count = f"{done}" if float(done).is_integer() else f"{done:.1f}"  # certify --compare moves in fractions
        text += f"{count}/{total} {self.unit} [{_interval(elapsed)} elapsed"
        if rate > 0 and done < total:
            text += f", {_interval((total - done) / rate)} left"
        if rate > 0:
            r = rate * self.scale
            text += f", {r:,.0f}" if r >= 100 else f", {r:.3g}"
            text += f" {self.scale_unit if self.scale != 1.0 else self.unit}/s"
        self.stream.write(text + "]\n")
        self.stream.flush()
        st["written_at"], st["written"] = now, done

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        if self._lines is not None:  # stopped before the end: say where, unless the last line did
            if self._lines["written"] != self._lines["done"]:
                self._write_line(time.monotonic())
            self._lines = None


class StageLog:
    """Lines about a long computation that has no natural unit count (a proof's searches): ``log(text)``
    prints a line at once; while the stage runs (``with StageLog(...) as log:``), a line is also printed
    whenever ``every`` seconds passed without one, naming what is being done (the last ``log.doing(text)``)
    and the time so far, so a user never watches ``every`` seconds of silence. ``write`` receives each line
    (default: stderr); None makes a silent log (the library default)."""

    def __init__(self, prefix: str = "", write: Optional[Callable[[str], None]] = None, every: float = 10.0):
        import time
        self._time = time.monotonic
        self.prefix, self.every = prefix, float(every)
        self.write = write
        self.t0 = self._time()
        self._last = self.t0
        self._what = "starting"
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: Optional[threading.Thread] = None

    @property
    def elapsed(self) -> float:
        return self._time() - self.t0

    def __call__(self, text: str) -> None:
        if self.write is None:
            return
        with self._lock:
            self._last = self._time()
            self.write(f"{self.prefix}{text}")

    def doing(self, what: str) -> None:
        """Name the step under way (used by the heartbeat line; printed only by the heartbeat)."""
        self._what = what

    def _beat(self) -> None:
        while not self._stop.wait(min(1.0, self.every / 4)):
            if self._time() - self._last >= self.every:
                self(f"... {self._what} ({self.elapsed:.0f} s so far)")

    def __enter__(self) -> "StageLog":
        self._depth = getattr(self, "_depth", 0) + 1  # re-entered by a callee: one heartbeat
        if self._depth == 1 and self.write is not None and self.every > 0:
            self._stop.clear()
            self._thread = threading.Thread(target=self._beat, daemon=True, name="simgap-stage-log")
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._depth -= 1
        if self._depth:
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


def quiet_log(_text: str) -> None:
    """A log that prints nothing (library calls without a ``log``)."""

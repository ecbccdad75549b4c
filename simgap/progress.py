"""Progress reporting: a callback protocol and a terminal progress bar (tqdm).

Long stages report ``on_progress(done, total)`` (both ints, in the stage's own unit, e.g.
(x_r, u) pairs) after every finished unit of work; the GUI passes its own callback, the CLI a
:class:`ProgressBar`. Cancellation is cooperative: a stage polls ``should_stop()`` between
chunks (use :func:`as_stop_check` to accept a ``threading.Event`` or a callable).
"""

from __future__ import annotations

import sys
import threading
from typing import Callable, Optional, Protocol, Union

from tqdm import tqdm


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
    """Terminal progress on stderr (tqdm): percentage, count, rate and ETA.

    Callable as ``bar(done, total)``. The rate and ETA count only the work done since the bar
    was created (a resumed run starts with ``done > 0``). ``scale`` converts units for the
    rate (e.g. N1hat * k simulator steps per pair). Off a terminal tqdm redraws at most every
    ``interval_off_tty`` seconds, so logs stay short.
    """

    def __init__(self, unit: str = "pairs", stream=None, scale: float = 1.0, scale_unit: str = "steps",
                 desc: Optional[str] = None, interval_off_tty: float = 10.0, bar_format: Optional[str] = None):
        self.unit, self.scale, self.scale_unit, self.desc = unit, scale, scale_unit, desc
        self.bar_format = bar_format  # tqdm's, e.g. for a count that moves in fractions
        self.stream = stream if stream is not None else sys.stderr
        tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.mininterval = 0.2 if tty else interval_off_tty
        self.bar: Optional[tqdm] = None

    def __call__(self, done: int, total: int) -> None:
        if self.bar is None:
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

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

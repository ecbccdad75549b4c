"""The machine's available memory and the refusal of work that needs more (imported by stages
whose cost models price their work; :mod:`simgap.checks` re-exports both)."""

from __future__ import annotations

import os

from .errors import SimgapError
from .fileio import human_bytes


def available_memory() -> int:
    """Bytes of memory available to new allocations (MemAvailable), or total RAM."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 34


def check_memory(need: float, what: str, hint: str = "") -> None:
    """Refuse work whose estimated peak memory ``need`` [bytes] exceeds the available memory."""
    have = available_memory()
    if need > have:
        raise SimgapError(f"{what} needs about {human_bytes(need)} of memory, {human_bytes(have)} is available"
                          + (f"; {hint}" if hint else ""))

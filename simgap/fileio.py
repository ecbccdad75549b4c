"""Atomic file writes: every result file is written to a temporary name in the same folder and
renamed into place, so a crash never leaves a half-written file under the final name."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np


def _umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux /proc)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # elsewhere: read by setting and restoring
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "w", fsync: bool = False) -> Iterator:
    """Open a temporary file beside ``path``; on success rename it to ``path``, else delete it.

    The file gets the permissions an ordinary ``open`` would give (0666 less the umask), not
    the 0600 of the private temporary file.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, mode) as fh:
            yield fh
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_text(path, text: str) -> Path:
    with atomic_file(path) as fh:
        fh.write(text)
    return Path(path)


def write_json(path, obj, **kw) -> Path:
    """JSON with ``indent=1`` unless given; extra keywords go to :func:`json.dumps`."""
    kw.setdefault("indent", 1)
    return write_text(path, json.dumps(obj, **kw))


def savez(path, compressed: bool = False, **arrays) -> Path:
    """``np.savez`` (or ``savez_compressed``) atomically; the name is used as given."""
    with atomic_file(path, "wb") as fh:
        (np.savez_compressed if compressed else np.savez)(fh, **arrays)
    return Path(path)


# ----- content digests -----------------------------------------------------------------------
# A digest detects a file edited or corrupted after simgap wrote it (every reader recomputes
# and compares it). It is a plain sha256, not a signature: whoever rewrites the digest too can
# still forge a file, so results also carry the digests of what they were made from.

def canonical_json(obj, allow_nan: bool = False) -> str:
    """Canonical JSON (sorted keys, no whitespace) of JSON-ready data; numpy scalars/arrays and tuples allowed."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=allow_nan, default=_json_default)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (tuple, set)):
        return list(o)
    raise TypeError(f"not JSON-serializable: {type(o).__name__}")


def content_digest(meta=None, arrays: dict | None = None) -> str:
    """sha256 hex digest of JSON data ``meta`` (canonical form) and named ``arrays`` (dtype, shape, bytes)."""
    import hashlib
    h = hashlib.sha256()
    h.update(canonical_json(meta, allow_nan=True).encode())
    for name in sorted(arrays or {}):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"\0{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()

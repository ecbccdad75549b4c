"""Atomic file writes: every result file is written to a temporary name in the same folder and
renamed into place, so a crash never leaves a half-written file under the final name."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import SimgapError

#: what a write fails with when the disk (or a quota, or a file-size limit) has no room
NO_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


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


def human_bytes(b: float) -> str:
    """A byte count for messages: 3 significant digits and a decimal unit (B, KB, ..., PB)."""
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if abs(b) < 1000 or unit == "PB":
            return f"{b:.3g} {unit}"
        b /= 1000.0
    return f"{b:.3g} PB"


def write_error(path, err: OSError, need: float | None = None, written: float | None = None) -> SimgapError:
    """A SimgapError for a failed write of ``path``: the path, the system's reason, and for a
    full disk the bytes needed (``need``, where known) or written before the failure, and the
    bytes free in the folder."""
    msg = f"cannot write {str(path)!r}: {err.strerror or err}"
    if getattr(err, "errno", None) in NO_ROOM:
        msg += f" ({room_note(path, need, written)}); " + (
            "a file-size limit is in force (ulimit -f): raise it or write elsewhere" if err.errno == errno.EFBIG
            else "free some space or write elsewhere")
    return SimgapError(msg)


def room_note(path, need: float | None = None, written: float | None = None) -> str:
    """``it needs about X; Y free in 'folder'`` (or the bytes written before a failure)."""
    folder = Path(path).absolute().parent
    try:
        free = human_bytes(shutil.disk_usage(folder).free)
    except OSError:
        free = "unknown"
    size = (f"it needs about {human_bytes(need)}" if need else
            f"{human_bytes(written)} were written before the write failed" if written else "")
    return f"{size + '; ' if size else ''}{free} free in {str(folder)!r}"


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "w", fsync: bool = False,
                need: float | None = None, verify=None) -> Iterator:
    """Open a temporary file beside ``path``; on success rename it to ``path``, else delete it.

    The file gets the permissions an ordinary ``open`` would give (0666 less the umask), not
    the 0600 of the private temporary file. A write that fails (full disk, file-size limit,
    I/O error) leaves no temporary file and raises a SimgapError naming ``path`` and, for a full
    disk, ``need`` (the bytes to be written, where the caller knows them) and the free space.
    ``verify(tmp_path)``, if given, reads the closed file back before it takes the final name
    and raises if it is not whole.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as e:
        raise write_error(path, e, need) from None
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, mode) as fh:
            yield fh
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
        if verify is not None:
            verify(Path(tmp))
        os.replace(tmp, path)
    except BaseException as e:
        written = None
        with contextlib.suppress(OSError):
            written = os.stat(tmp).st_size
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if isinstance(e, OSError):
            raise write_error(path, e, need, written) from None
        raise


def write_bytes(path, data: bytes, fsync: bool = False) -> Path:
    """``data`` to ``path`` atomically (:func:`atomic_file`)."""
    with atomic_file(path, "wb", fsync=fsync, need=len(data)) as fh:
        fh.write(data)
    return Path(path)


def write_text(path, text: str) -> Path:
    with atomic_file(path, need=len(text.encode())) as fh:
        fh.write(text)
    return Path(path)


def write_json(path, obj, **kw) -> Path:
    """JSON with ``indent=1`` unless given; extra keywords go to :func:`json.dumps`."""
    kw.setdefault("indent", 1)
    return write_text(path, json.dumps(obj, **kw))


def savez(path, compressed: bool = False, **arrays) -> Path:
    """``np.savez`` (or ``savez_compressed``) atomically; the name is used as given.

    A compressed file is built in memory first (it is the smaller one), so a full disk is
    reported with its exact size; an uncompressed one is streamed, its size estimated."""
    if compressed:
        import io
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        return write_bytes(path, buf.getbuffer())
    need = sum(np.asarray(a).nbytes + 256 for a in arrays.values())  # + zip and .npy headers
    with atomic_file(path, "wb", need=need) as fh:
        np.savez(fh, **arrays)
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

"""A results folder's own list of files: which files belong to its ``summary.json``.

``simgap run`` may be pointed at a folder that already holds an earlier run. Before any stage
writes, the earlier run's result files (:data:`RESULT_PATTERNS`) are removed, so nothing stale
can stand beside the new results; the collection stores stay (they are resumable and verified
by their configuration hash). When the run ends, ``summary.json`` lists every file it wrote
with its sha256 and size, under the run's id (``run_id``). Every reader of the folder
(:func:`check_listed`) refuses a file the summary does not list or whose digest differs, e.g. a
``rollouts_*.npz`` copied in from another run.

The digests detect accidents and mix-ups, not forgery: whoever edits a file can recompute its
digest in ``summary.json`` too (README, "What the digests protect against").
"""

from __future__ import annotations

import hashlib
import uuid
from pathlib import Path

from .errors import SimgapError

#: result files of a run (the stores data/ and data_deterministic/ are not among them)
RESULT_PATTERNS = ("summary.json", "run.rrd", "perrun.rrd", "cert_*.json", "audit_*.json", "controller_*.npz",
                   "rollouts_*.npz")


def new_run_id() -> str:
    return uuid.uuid4().hex


def file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def remove_stale(out: Path, log=None) -> list:
    """Remove an earlier run's result files from ``out`` (the summary first, so a run stopped
    half-way never leaves an old summary beside new files). Returns the names removed."""
    out = Path(out)
    gone = []
    names = ["summary.json"] + sorted({p.name for pat in RESULT_PATTERNS[1:] for p in out.glob(pat)})
    for name in names:
        p = out / name
        if p.is_file() or p.is_symlink():
            p.unlink()
            gone.append(name)
    if gone and log:
        log(f"removed {len(gone)} result file(s) of an earlier run in {out}: {', '.join(gone)}")
    return gone


def list_files(out: Path, run_id: str) -> dict:
    """{name: {sha256, bytes, run_id}} of every result file now in ``out`` (summary.json excluded)."""
    out = Path(out)
    files = {}
    for pat in RESULT_PATTERNS[1:]:
        for p in sorted(out.glob(pat)):
            if p.is_file():
                files[p.name] = {"sha256": file_digest(p), "bytes": p.stat().st_size, "run_id": run_id}
    return files


def check_listed(root: Path, summary: dict, name: str, digest: bool = True) -> None:
    """Refuse ``root/name`` unless ``summary.json`` lists it (and, with ``digest``, with this
    sha256). A summary written before the list existed (no ``files``) is accepted as it is."""
    files = summary.get("files")
    if files is None:
        return
    where = Path(root) / name
    if not isinstance(files, dict):
        raise SimgapError(f"{Path(root) / 'summary.json'}: 'files' must be a table")
    entry = files.get(name)
    if not isinstance(entry, dict) or "sha256" not in entry:
        raise SimgapError(f"{where} is not part of this run: summary.json (run {summary.get('run_id', '?')}) does "
                          "not list it; it was left by another run or copied in (refused)")
    if digest and file_digest(where) != entry["sha256"]:
        raise SimgapError(f"{where} differs from the file this run wrote (sha256 does not match summary.json, run "
                          f"{summary.get('run_id', '?')}): it was changed or comes from another run (refused)")


def unlisted(root: Path, summary: dict) -> list:
    """Result files in ``root`` that the summary does not list (stale or copied in)."""
    files = summary.get("files")
    if not isinstance(files, dict):
        return []
    return sorted({p.name for pat in RESULT_PATTERNS[1:] for p in Path(root).glob(pat)} - set(files))


def add_files(out: Path, names) -> None:
    """List files written after the summary (the recordings) in ``out/summary.json``."""
    import json

    from . import fileio

    path = Path(out) / "summary.json"
    summary = json.loads(path.read_text())
    files = summary.setdefault("files", {})
    for name in names:
        p = Path(out) / name
        files[name] = {"sha256": file_digest(p), "bytes": p.stat().st_size, "run_id": summary.get("run_id")}
    fileio.write_json(path, summary)


LOCK = ".run.lock"


def run_lock(out: Path):
    """Hold ``out/.run.lock`` while a run writes into ``out``: a second ``simgap run`` into the same
    folder is refused instead of mixing its files with the first one's."""
    import contextlib
    import fcntl
    import os

    @contextlib.contextmanager
    def held():
        fd = os.open(Path(out) / LOCK, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                raise SimgapError(f"another simgap run is writing into {str(out)!r}; wait for it or use another "
                                  "--out") from None
            yield
        finally:
            os.close(fd)
    return held()

"""A results folder's own list of files: which files belong to its ``summary.json``.

A results folder owns only what simgap wrote into it. ``simgap run`` may be pointed at a folder
that already holds an earlier run, or the user's own files. Before the new run writes, it
:func:`claim` s the folder: the files it owns are those listed in the folder's own manifests with
the digest they have now (``summary.json`` of a finished run, :data:`JOURNAL` of a run that was
stopped); every other file is foreign. A foreign file under a name the run would write is
refused (the run would overwrite it); foreign files under other names stay, untouched, beside
the results. Only after every check that can refuse the run has passed are the owned files
removed (:meth:`Claim.release`, the summary first). While the run writes, :data:`JOURNAL`
records every file with its sha256 (:func:`record`); at the end ``summary.json`` lists them
under the run's id (``run_id``). Every reader of the folder (:func:`check_listed`,
:func:`check_complete`) refuses a file the summary does not list or whose digest differs, e.g. a
``rollouts_*.npz`` copied in from another run, and names a listed file that is missing.

The collection stores (``data/``, ``data_deterministic/``) are not result files: they are
resumable and verified by their configuration hash (:mod:`simgap.store`).

A file list is a license to delete only when simgap can verify it wrote the list: the summary and
the journal carry ``files_digest``, the sha256 of their ``run_id`` and ``files`` table (:func:`seal`),
renewed with every file recorded. A list without it, or whose digest does not match (a hidden
``.simgap-files.json`` written by hand to name a user's file with its sha256, an older tool's
list), owns nothing: the files it names are foreign, kept, and refused if the run would overwrite
them. Only names simgap writes (:data:`RESULT_PATTERNS`) can be owned at all.

The digests detect accidents and mix-ups, not forgery: whoever edits a file can recompute its
digest in ``summary.json`` too (docs/deviations.md, "What the digests protect against").
"""

from __future__ import annotations

import hashlib
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from .errors import SimgapError
from .file_guard import printable, read_json

#: result files of a run (the stores data/ and data_deterministic/ are not among them)
RESULT_PATTERNS = ("summary.json", "run.rrd", "perrun.rrd", "cert_*.json", "audit_*.json", "controller_*.npz",
                   "rollouts_*.npz")
#: the running run's list of the files it wrote so far, with their digests (hidden; kept after the run)
JOURNAL = ".simgap-files.json"


def new_run_id() -> str:
    return uuid.uuid4().hex


def file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def files_digest(run_id: str, files: dict) -> str:
    """sha256 of a file list (canonical JSON of ``run_id`` and ``files``): what :func:`seal` records."""
    import json
    text = json.dumps({"run_id": run_id, "files": files}, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return hashlib.sha256(text.encode()).hexdigest()


def seal(manifest: dict) -> dict:
    """``manifest`` (a summary or journal with ``run_id`` and ``files``) with its ``files_digest`` set."""
    manifest["files_digest"] = files_digest(manifest["run_id"], manifest["files"])
    return manifest


def _manifest(path: Path):
    """A manifest simgap wrote (its ``files_digest`` matches its ``run_id`` and ``files``), or None when
    ``path`` is missing, is no simgap manifest, or is a list simgap cannot verify."""
    if not path.is_file() or path.is_symlink():
        return None
    try:
        d = read_json(path, "manifest")
    except SimgapError:
        return None
    if not isinstance(d, dict) or not isinstance(d.get("run_id"), str) or not isinstance(d.get("files"), dict):
        return None
    try:
        if d.get("files_digest") != files_digest(d["run_id"], d["files"]):
            return None
    except (TypeError, ValueError):
        return None
    return d


def _owned(out: Path) -> tuple:
    """(owned names, why-foreign {name: reason}) of the result-like files in ``out``."""
    listed: dict = {}
    summary = _manifest(out / "summary.json")
    journal = _manifest(out / JOURNAL)
    for man, where in ((summary, "summary.json"), (journal, f"run journal {JOURNAL}")):
        for name, e in (man or {}).get("files", {}).items() if man else ():
            if isinstance(e, dict) and isinstance(e.get("sha256"), str) and "/" not in name and name not in (".", ".."):
                listed.setdefault(name, {}).setdefault(e["sha256"], where)
    unverified = [n for n in ("summary.json", JOURNAL) if (out / n).exists() and _manifest(out / n) is None]
    nolist = ("not listed in a file list simgap can verify"
              + (f" ({', '.join(unverified)} {'is' if len(unverified) == 1 else 'are'} not simgap's: no matching "
                 "files_digest)" if unverified else " (the folder has no summary.json or run journal)"))
    # only names simgap writes can be owned: a manifest listing any other file (forged, or another
    # tool's) never gets it deleted
    present = sorted({p.name for pat in RESULT_PATTERNS for p in out.glob(pat) if p.is_file() or p.is_symlink()})
    owned, foreign = [], {}
    for name in present:
        p = out / name
        if name == "summary.json":
            if summary is not None and not p.is_symlink():
                owned.append(name)
            else:
                foreign[name] = ("not a summary simgap can verify (no run_id and file list with a matching "
                                 "files_digest)")
        elif p.is_symlink() or not p.is_file():
            foreign[name] = "a link or not a regular file"
        elif name not in listed:
            foreign[name] = nolist
        elif file_digest(p) not in listed[name]:
            foreign[name] = (f"changed since simgap wrote it (sha256 differs from the folder's "
                             f"{' and '.join(sorted(set(listed[name].values())))})")
        else:
            owned.append(name)
    return owned, foreign


def _owner(out: Path) -> str:
    """Which verified list made the owned files simgap's, for the log."""
    if _manifest(out / "summary.json") is not None:
        return "listed in its summary.json with matching sha256"
    return f"listed in the run journal {JOURNAL} of a run that stopped before its summary, with matching sha256"


@dataclass
class Claim:
    """What a new run found in its results folder (:func:`claim`)."""

    out: Path
    owned: list = field(default_factory=list)      # an earlier run's files, listed with matching digests
    foreign: dict = field(default_factory=dict)    # every other result-like file: {name: why it is not owned}

    def release(self, run_id: str, log=None, resume: str | None = None) -> list:
        """Remove the owned files (the summary first, so a run stopped half-way never leaves an old
        summary beside new files) and start this run's journal. Call only after every check that
        can refuse the run has passed. Files changed since :func:`claim` looked are kept. ``resume``: the
        command that finishes this run if it stops (kept in the journal, named by :func:`unfinished`)."""
        from . import fileio
        now, _ = _owned(self.out)
        owner = _owner(self.out)
        gone = []
        for name in sorted(set(self.owned) & set(now), key=lambda n: n != "summary.json"):
            (self.out / name).unlink(missing_ok=True)
            gone.append(name)
        journal = {"run_id": run_id, "files": {}, **({"resume": resume} if resume else {})}
        fileio.write_json(self.out / JOURNAL, seal(journal))
        if log and gone:
            log(f"removed {len(gone)} file(s) of the earlier run in {self.out} ({owner}): {', '.join(gone)}")
        if log and self.foreign:
            log(f"left {len(self.foreign)} file(s) simgap did not write untouched beside the results in {self.out}: "
                + ", ".join(printable(n) for n in sorted(self.foreign)))
        return gone


def check_same_run(out: Path, experiment: str, profile, force: bool = False) -> None:
    """Refuse a run into a folder holding a finished run of another experiment or profile (its
    verified ``summary.json``), naming that run and the files this one would replace, unless
    ``force``: the results of a different run are not replaced without a word (the collection
    stores are checked and reused by their configuration, :mod:`simgap.store`)."""
    prev = _manifest(Path(out) / "summary.json")
    if prev is None or force:
        return
    was = (prev.get("experiment"), prev.get("profile"))
    if was == (experiment, profile):
        return
    owned, _ = _owned(Path(out))
    raise SimgapError(
        f"--out {str(out)!r} holds the finished run of experiment {printable(was[0])!r} (profile "
        f"{printable(was[1] or 'base')}); this run of {experiment!r} (profile {profile or 'base'}) would replace its "
        f"{', '.join(printable(n) for n in sorted(owned, key=lambda n: n != 'summary.json'))}. Nothing was changed; "
        "choose another --out, or give --force to replace them")


def claim(out: Path, will_write) -> Claim:
    """Sort ``out``'s result-like files into an earlier run's (owned) and foreign ones; refuse the
    run if a foreign file has a name in ``will_write`` (the run would overwrite or stand beside it,
    and readers would refuse the folder). Nothing is changed."""
    out = Path(out)
    if not out.is_dir():
        return Claim(out)
    owned, foreign = _owned(out)
    clash = sorted(n for n in foreign if n in set(will_write) or n == "summary.json")
    if clash:
        raise SimgapError(
            f"--out {str(out)!r} holds file(s) this run would overwrite that simgap did not write there: "
            + "; ".join(f"{printable(n)} ({foreign[n]})" for n in clash)
            + ". Nothing was changed; move them away or choose another --out")
    return Claim(out, owned, foreign)


def record(out: Path, names) -> None:
    """Add ``names`` (just written into ``out``) with their sha256 to the running run's journal."""
    from . import fileio
    path = Path(out) / JOURNAL
    j = read_json(path, "run journal")
    for name in names:
        p = Path(out) / name
        j["files"][name] = {"sha256": file_digest(p), "bytes": p.stat().st_size, "run_id": j["run_id"]}
    fileio.write_json(path, seal(j))


def list_files(out: Path, run_id: str) -> dict:
    """{name: {sha256, bytes, run_id}} of every file this run recorded in its journal."""
    j = read_json(Path(out) / JOURNAL, "run journal")
    if j.get("run_id") != run_id:
        raise SimgapError(f"{Path(out) / JOURNAL} belongs to another run ({printable(j.get('run_id'))}); was a second "
                          "run started in this folder?")
    return dict(j["files"])


def check_listed(root: Path, summary: dict, name: str, digest: bool = True) -> None:
    """Refuse ``root/name`` unless ``summary.json`` lists it (and, with ``digest``, with this
    sha256). A summary written before the list existed (no ``files``) is accepted as it is."""
    files = summary.get("files")
    if files is None:
        return
    where = Path(root) / name
    run = printable(summary.get("run_id", "?"))
    if not isinstance(files, dict):
        raise SimgapError(f"{Path(root) / 'summary.json'}: 'files' must be a table")
    entry = files.get(name)
    if not isinstance(entry, dict) or "sha256" not in entry:
        raise SimgapError(f"{where} is not part of this run: summary.json (run {run}) does "
                          "not list it; it was left by another run or copied in (refused)")
    if digest and file_digest(where) != entry["sha256"]:
        raise SimgapError(f"{where} differs from the file this run wrote (sha256 does not match summary.json, run "
                          f"{run}): it was changed or comes from another run (refused)")


def check_complete(root: Path, summary: dict) -> None:
    """Refuse a folder whose ``summary.json`` lists a file that is missing, naming every such file
    (a reader that drew what it could would show a run that is not the one the summary describes)."""
    files = summary.get("files")
    if not isinstance(files, dict):
        return
    gone = sorted(n for n in files if not (Path(root) / n).is_file())
    if gone:
        raise SimgapError(f"results folder {str(root)!r}: {', '.join(printable(n) for n in gone)} "
                          f"{'is' if len(gone) == 1 else 'are'} missing, though summary.json (run "
                          f"{printable(summary.get('run_id', '?'))}) lists {'it' if len(gone) == 1 else 'them'} "
                          "(deleted or moved?); run the experiment again or restore the file (refused)")


def unfinished(root: Path):
    """A message naming ``root`` as a run that did not finish (a run journal, no summary.json) with the
    command that finishes it, or None for any other folder."""
    root = Path(root)
    if (root / "summary.json").exists() or not (root / JOURNAL).is_file():
        return None
    try:
        j = read_json(root / JOURNAL, "run journal")
    except SimgapError:
        j = {}
    resume = j.get("resume") if isinstance(j, dict) and isinstance(j.get("resume"), str) else None
    how = (f"finish it with: {printable(resume)}" if resume else
           f"finish it with: simgap run EXPERIMENT --out {str(root)!r} (the experiment and profile it was started with)")
    return (f"{str(root)!r} is a `simgap run` folder whose run did not finish (it has a run journal {JOURNAL} but no "
            f"summary.json; stopped or killed before its end): {how}; its collections resume where they stopped")


def add_files(out: Path, names) -> None:
    """List files written after the summary (the recordings) in the run's journal and in
    ``out/summary.json``."""
    from . import fileio

    record(out, names)
    path = Path(out) / "summary.json"
    summary = read_json(path, "summary")
    summary["files"] = list_files(out, summary.get("run_id"))
    fileio.write_json(path, seal(summary))


LOCK = ".run.lock"


def run_lock(out: Path):
    """Hold ``out/.run.lock`` while a run writes into ``out``: a second ``simgap run`` into the same
    folder is refused instead of mixing its files with the first one's. The file is removed when the
    run ends (finished or failed), so a finished folder holds only the run's files; a lock taken on a
    file the run before had just removed (the path gone or a new file there) is taken again."""
    import contextlib
    import fcntl
    import os

    path = Path(out) / LOCK

    def refuse():
        return SimgapError(f"another simgap run is writing into {str(out)!r}; wait for it or use another --out")

    def locked() -> int:
        """A descriptor holding the lock on the file now at ``path``."""
        for _ in range(3):
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                raise refuse() from None
            try:
                if os.stat(path).st_ino == os.fstat(fd).st_ino:
                    return fd
            except FileNotFoundError:
                pass
            os.close(fd)  # locked a file the run before us removed on its way out: take the new one
        raise refuse()

    @contextlib.contextmanager
    def held():
        fd = locked()
        try:
            yield
        finally:
            path.unlink(missing_ok=True)  # while still locked: nobody can lock this file after us
            os.close(fd)
    return held()

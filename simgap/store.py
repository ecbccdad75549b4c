"""The collection store: the on-disk form of a collection, its manifest, chunk files, lock and reader.

The store is a directory::

    manifest.json          full configuration (system, simulator, cover, N1hat, seed, chunking,
                           simgap version) and "hash" = sha256 of its canonical JSON
    chunks/c000000.npz     one file per chunk, written atomically (temp file + os.replace), no pickle;
                           it carries its chunk id, the configuration hash, the sha256 of every
                           array ("digests", JSON) and a digest over those ("digest")
    .lock                  locked by the one process collecting into the store (a second is refused)

:mod:`simgap.collect` computes the chunks and writes them here; :func:`simgap.dataset.load_store`
reads a complete store (:func:`read_store`) as a Dataset. Reading verifies every chunk: a chunk
re-saved with other numbers is refused. This module knows the file format only, neither the
simulator nor the Dataset type, so both the collection stage and the Dataset can import it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import os
import shutil
import zipfile
from pathlib import Path
from typing import NamedTuple, Optional, Sequence

import numpy as np

from . import fileio
from .errors import SimgapError
from .systems import System
from .system_ref import ref_of_description, resolve_system

STORE_FORMAT = "simgap-store/1"
MANIFEST = "manifest.json"
LOCK = ".lock"  # held by the one process collecting into the store (see store_lock)
CHUNK_DIR = "chunks"


# ----------------------------------------------------------------------------------------
# Configuration hash and the system's description
# ----------------------------------------------------------------------------------------

def canonical_json(obj) -> str:
    """Canonical JSON (sorted keys, no whitespace, no NaN) used for configuration hashes."""
    return fileio.canonical_json(obj)


def config_hash(config: dict) -> str:
    """sha256 hex digest of the canonical JSON of ``config``."""
    return hashlib.sha256(canonical_json(config).encode()).hexdigest()


def describe_system(system: System) -> dict:
    """System description for manifests: :meth:`System.describe` plus the full input set."""
    d = json.loads(canonical_json(system.describe()))
    d["inputs"] = system.inputs.tolist()
    return d



def system_from_config(desc: dict, steps: int) -> System:
    """Rebuild a built-in, plugin, system-file or refined system (with its recorded input set) from a
    manifest description."""
    s = resolve_system(ref_of_description(desc), steps=steps, paths=False)
    U = np.asarray(desc["inputs"], dtype=float)
    if U.shape != s.inputs.shape or not np.array_equal(U, s.inputs):
        s = dataclasses.replace(s, inputs=U)
    return s



def portable_system(system: System) -> Optional[System]:
    """None when workers can rebuild ``system`` from its description (:func:`system_from_config`),
    else the System itself, to travel to them by pickle (define a user system at module level)."""
    d = describe_system(system)
    try:
        if describe_system(system_from_config(d, system.steps)) == d:
            return None
    except SimgapError:
        pass
    return system


# ----------------------------------------------------------------------------------------
# Chunk files, lock, manifest
# ----------------------------------------------------------------------------------------

def _chunk_path(store: Path, c: int) -> Path:
    return store / CHUNK_DIR / f"c{c:06d}.npz"


@contextlib.contextmanager
def _pid_tmp(path: Path, need: Optional[float] = None):
    """A temporary ``.<name>.<pid>.tmp`` beside ``path`` (the pid lets a later collector delete
    the leftovers of a killed one), fsynced and renamed into place; on failure it is removed
    and a failed write (e.g. a full disk) is a SimgapError naming ``path``."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        written = tmp.stat().st_size if tmp.exists() else None
        tmp.unlink(missing_ok=True)
        if isinstance(e, OSError):
            raise fileio.write_error(path, e, need, written) from None
        raise


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    with _pid_tmp(path, len(data)) as f:
        f.write(data)


def _chunk_digests(c: int, h: str, arrays: dict) -> tuple:
    """({name: sha256 of the array}, digest over the chunk id, configuration hash and those)."""
    per = {k: fileio.content_digest(None, {k: v}) for k, v in arrays.items()}
    return per, fileio.content_digest({"chunk": int(c), "config_hash": h, "digests": per})


def _write_chunk(store: Path, c: int, h: str, arrays: dict) -> None:
    path = _chunk_path(store, c)
    per, dig = _chunk_digests(c, h, arrays)
    buf = io.BytesIO()  # a chunk is small: its exact size is known before the disk is touched
    np.savez(buf, chunk=np.int64(c), hash=np.array(h), digests=np.array(json.dumps(per)), digest=np.array(dig),
             **arrays)
    with _pid_tmp(path, buf.tell()) as f:
        f.write(buf.getbuffer())


@contextlib.contextmanager
def store_lock(store: Path, what: str = "collected"):
    """Hold the store's exclusive lock (``.lock``) while collecting into it.

    A second collector into the same store is refused at once instead of recomputing every
    chunk the first one computes. It is a POSIX record lock (``lockf``): it belongs to this
    process alone (forked pool workers do not inherit it) and the kernel drops it when the
    process ends, even by kill -9, so a killed collection never blocks its resumption.
    """
    import fcntl

    fh = open(store / LOCK, "a")
    try:
        fcntl.lockf(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        raise SimgapError(f"store {str(store)!r} is being {what} by another process; wait for it to finish "
                          "(then run the same command to check it is complete) or write into another "
                          "folder") from None
    try:
        yield
    finally:
        fh.close()


def _pid_alive(pid: str) -> bool:
    try:
        pid_i = int(pid)
        if pid_i == os.getpid():
            return False
        os.kill(pid_i, 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:
        return True
    return True


def _read_manifest(store: Path, fmt: str = STORE_FORMAT) -> dict:
    mpath = store / MANIFEST
    if not store.is_dir():
        raise SimgapError(f"store {str(store)!r} does not exist or is not a directory")
    if not mpath.is_file():
        raise SimgapError(f"{str(store)!r} is not a simgap store (no {MANIFEST})")
    from .file_guard import read_json
    man = read_json(mpath, f"store {str(store)!r}: {MANIFEST}")
    try:
        cfg, h = man["config"], man["hash"]
    except (KeyError, TypeError) as e:
        raise SimgapError(f"store {str(store)!r}: {MANIFEST} is unreadable: {e}") from None
    if not isinstance(cfg, dict) or cfg.get("format") != fmt:
        raise SimgapError(f"store {str(store)!r}: unknown format {cfg.get('format') if isinstance(cfg, dict) else cfg!r}"
                          f" (expected {fmt})")
    if config_hash(cfg) != h:
        raise SimgapError(f"store {str(store)!r}: {MANIFEST} was modified (its hash does not match its configuration)")
    return man


def _done_chunks(store: Path, n_chunks: int, h: Optional[str] = None) -> set:
    """Chunk ids with a file in the store; with the configuration hash ``h``, only files that verify."""
    d = store / CHUNK_DIR
    done = set()
    if d.is_dir():
        for p in d.glob("c*.npz"):
            try:
                c = int(p.stem[1:])
            except ValueError:
                continue
            if 0 <= c < n_chunks:
                done.add(c)
    if h is not None:
        done = {c for c in done if _chunk_problem(store, c, h)[0] is None}
    return done


def _chunk_problem(store: Path, c: int, h: str, names: Optional[Sequence[str]] = None, optional: Sequence[str] = ()):
    """(None, arrays) if chunk ``c`` verifies, else (reason, None).

    Returns (and verifies) the arrays ``names`` plus those of ``optional`` the chunk has; with
    ``names`` None it verifies every array and returns none.
    """
    p = _chunk_path(store, c)
    try:
        with np.load(p, allow_pickle=False) as z:
            if "digest" not in z.files or "digests" not in z.files:
                return f"chunk file {p.name} carries no content digest (written by an older simgap)", None
            if str(z["hash"]) != h or int(z["chunk"]) != c:
                return f"chunk file {p.name} belongs to another collection", None
            per = json.loads(str(z["digests"]))
            want = str(z["digest"])
            if not isinstance(per, dict) or fileio.content_digest(
                    {"chunk": int(c), "config_hash": h, "digests": per}) != want:
                return f"chunk file {p.name}: its digest list does not match its digest (modified)", None
            out = {}
            for k in (per if names is None else list(names) + [k for k in optional if k in per]):
                if k not in per:
                    return f"chunk file {p.name} has no digest for {k!r}", None
                a = z[k]
                if fileio.content_digest(None, {k: a}) != per[k]:
                    return (f"chunk file {p.name}: the content of {k!r} does not match its digest "
                            f"(modified or corrupted)"), None
                if names is not None:
                    out[k] = a
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        return f"chunk file {p.name} is unreadable ({e})", None
    return None, out


def _diff(a, b, prefix="") -> list:
    """Key paths where two JSON values differ, as 'key: store vs requested' strings."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            out += _diff(a.get(k), b.get(k), f"{prefix}.{k}" if prefix else str(k))
        return out
    if a != b:
        sa, sb = json.dumps(a), json.dumps(b)
        if len(sa) > 60:
            sa = sa[:57] + "..."
        if len(sb) > 60:
            sb = sb[:57] + "..."
        return [f"{prefix}: {sa} (store) vs {sb} (requested)"]
    return []


def store_status(store: str | Path) -> dict:
    """``{"hash", "n_chunks", "done", "complete", "config"}`` of an existing store."""
    store = Path(store)
    man = _read_manifest(store)
    n = int(man["config"]["n_chunks"])
    done = len(_done_chunks(store, n, man["hash"]))  # only chunks whose digests verify
    return {"hash": man["hash"], "n_chunks": n, "done": done, "complete": done == n, "config": man["config"]}



# ----------------------------------------------------------------------------------------
# Filling a store through an executor (collection, per-run sampling)
# ----------------------------------------------------------------------------------------

class FillResult(NamedTuple):
    """Outcome of :func:`fill_store`."""

    hash: str
    done: set            # chunk ids present and verified in the store now
    computed: int        # chunks computed by this call
    resumed_from: int    # chunks present (and verified) before this call
    finished: bool       # False: ``should_stop`` stopped it (the store stays resumable)


def check_fillable(store: str | Path, cfg: dict, fmt: str = STORE_FORMAT, what: str = "collection") -> None:
    """Refuse what :func:`fill_store` would refuse, without writing anything: ``store`` is a file, a
    non-empty folder that is no store, or a store of another configuration (the keys that differ
    are named). Callers that must not change anything before a refusal (``simgap run`` deleting an
    earlier run's results) check here first."""
    store = Path(store)
    if store.exists() and not store.is_dir():
        raise SimgapError(f"store {str(store)!r} exists and is not a directory")
    if not store.is_dir():
        return
    if not (store / MANIFEST).exists():
        if any(p.name != LOCK for p in store.iterdir()):
            if (store / LOCK).exists():
                with store_lock(store):  # a writer that has not written its manifest yet is refused here
                    pass
            raise SimgapError(f"{str(store)!r} is a non-empty directory without {MANIFEST}; refusing to write into it")
        return
    man = _read_manifest(store, fmt)
    if man["hash"] != config_hash(cfg):
        diffs = _diff(man["config"], cfg)
        raise SimgapError(f"store {str(store)!r} holds a {what} with a different configuration; refusing "
                          f"to resume. Differences: {'; '.join(diffs[:6])}"
                          f"{' ...' if len(diffs) > 6 else ''}. Use another output directory.")


def fill_store(store: str | Path, cfg: dict, fn, job, executor, *, on_start=None, on_chunk=None, should_stop=lambda: False,
               chunk_ids=None, resume: bool = True, fmt: str = STORE_FORMAT, what: str = "collection") -> FillResult:
    """Compute the chunks of the configuration ``cfg`` (``cfg["n_chunks"]`` of them, ``cfg["format"]`` =
    ``fmt``) missing from ``store`` with ``executor.map_chunks(fn, job, ...)`` and write each one as it
    arrives: atomically, with its content digests, under the store's lock.

    An existing store with the same configuration hash is resumed: chunks that verify are kept, the
    others recomputed. A store of another configuration is refused naming the keys that differ; a
    non-empty folder that is no store is refused. A store this call started that holds no finished chunk
    when it fails is removed again. ``on_chunk(c, arrays)`` is called in this thread after chunk c is
    stored, ``on_start(done)`` once with the chunks already there. Results never depend on the executor: ``fn`` must draw its randomness per chunk id.
    """
    store = Path(store)
    h = config_hash(cfg)
    n_chunks = int(cfg["n_chunks"])
    check_fillable(store, cfg, fmt, what)
    top = store.absolute()  # the outermost folder this call creates (removed again if nothing is stored)
    while not top.parent.exists():
        top = top.parent
    created = not store.exists()
    fresh = not (store / MANIFEST).exists()
    store.mkdir(parents=True, exist_ok=True)
    with store_lock(store, "written" if what != "collection" else "collected"):
        try:
            return _fill_locked(store, cfg, h, n_chunks, fn, job, executor, on_start, on_chunk, should_stop,
                                chunk_ids, resume, fmt, what)
        except BaseException:
            # a store this call started that holds no finished chunk is no resumable data: remove what
            # this call made while the lock is held (a store with finished chunks stays, to be resumed)
            if fresh and not _done_chunks(store, n_chunks):
                if created:
                    shutil.rmtree(top, ignore_errors=True)
                else:
                    shutil.rmtree(store / CHUNK_DIR, ignore_errors=True)
                    for name in (MANIFEST, LOCK):
                        (store / name).unlink(missing_ok=True)
            raise


def _fill_locked(store, cfg, h, n_chunks, fn, job, executor, on_start, on_chunk, should_stop, chunk_ids, resume,
                 fmt, what) -> FillResult:
    """The body of :func:`fill_store`, run while this process holds the store's lock."""
    if (store / MANIFEST).exists():
        check_fillable(store, cfg, fmt, what)
        if not resume:
            raise SimgapError(f"store {str(store)!r} already exists (resume disabled)")
    else:
        (store / CHUNK_DIR).mkdir(parents=True, exist_ok=True)
        from datetime import datetime, timezone
        man = {"hash": h, "config": cfg, "created": datetime.now(timezone.utc).isoformat(timespec="seconds")}
        _atomic_write_bytes(store / MANIFEST, (json.dumps(man, indent=1, sort_keys=True) + "\n").encode())
    (store / CHUNK_DIR).mkdir(exist_ok=True)
    for p in (store / CHUNK_DIR).glob(".*.tmp"):  # leftovers of a killed writer (not of a live one)
        if not _pid_alive(p.name.rsplit(".", 2)[-2]):
            p.unlink(missing_ok=True)
    present = _done_chunks(store, n_chunks)
    done = _done_chunks(store, n_chunks, h)  # a chunk that does not verify is recomputed
    for c in present - done:
        _chunk_path(store, c).unlink(missing_ok=True)
    resumed_from = len(done)
    wanted = range(n_chunks) if chunk_ids is None else sorted(set(int(c) for c in chunk_ids))
    for c in wanted:
        if not 0 <= c < n_chunks:
            raise SimgapError(f"chunk id {c} out of range 0..{n_chunks - 1}")
    todo = [c for c in wanted if c not in done]
    if on_start:
        on_start(set(done))
    computed = [0]

    def on_result(c, arrays):
        _write_chunk(store, c, h, arrays)
        done.add(c)
        computed[0] += 1
        if on_chunk:
            on_chunk(c, arrays)

    finished = executor.map_chunks(fn, job, todo, on_result, should_stop)
    return FillResult(hash=h, done=done, computed=computed[0], resumed_from=resumed_from, finished=finished)


def read_chunk(store: str | Path, c: int, h: str, names: Sequence[str]) -> dict:
    """The arrays ``names`` of chunk ``c`` of the store with configuration hash ``h``, verified."""
    why, out = _chunk_problem(Path(store), c, h, names)
    if why is not None:
        raise SimgapError(f"store {str(store)!r}: {why}; run the same command again to recompute it")
    return out


def _load_chunk(store: Path, c: int, h: str, rows: int, names: Sequence[str], optional: Sequence[str] = ()) -> dict:
    why, out = _chunk_problem(store, c, h, names, optional)
    if why is not None:
        raise SimgapError(f"store {str(store)!r}: {why}; run the same collection again to recompute it")
    p = _chunk_path(store, c)
    for k, a in out.items():
        if a.shape[0] != rows:
            raise SimgapError(f"store {str(store)!r}: chunk file {p.name} has {a.shape[0]} rows of {k}, expected {rows}")
    return out


def _check_store_complete(store: Path, cfg: dict) -> None:
    n = int(cfg["n_chunks"])
    done = _done_chunks(store, n)
    if len(done) < n:
        missing = sorted(set(range(n)) - done)
        raise SimgapError(f"store {str(store)!r} is incomplete: {len(missing)} of {n} chunks missing "
                          f"(first missing: {missing[0]}); resume the collection with the same configuration "
                          "(e.g. run the same `simgap collect` command again)")



class StoreContents(NamedTuple):
    """A complete store, read and verified: what :func:`simgap.dataset.load_store` makes a Dataset of."""

    system: System
    n_runs: int
    epsilon: float
    manifest: dict
    arrays: dict  # name -> (K, ...) array: x, u, f_nom, mean, var, lo, hi, cover_index, input_index[, absdev_top]


def read_store(path: str | Path, system: System | None = None) -> StoreContents:
    """Read and verify a complete collection store (:func:`simgap.dataset.load_store` wraps it in a Dataset).

    ``system`` is needed for user-defined systems and must match the recorded description;
    built-in systems are rebuilt from the manifest. The dataset's manifest holds the hashed
    configuration (``system``, ``simulator``, ``cover``, ``seed``, ``n_runs``, ...) plus
    ``hash`` and ``store``.

    Raises SimgapError for a missing, unreadable, modified, mismatched or incomplete store.
    """
    store = Path(path)
    man = _read_manifest(store)
    cfg, h = man["config"], man["hash"]
    steps = int(cfg["simulator"]["steps"])
    if system is None:
        try:
            system = system_from_config(cfg["system"], steps)
        except SimgapError as e:
            raise SimgapError(f"store {str(store)!r}: cannot rebuild its system ({e}); pass the System") from None
    diffs = _diff(cfg["system"], describe_system(system))
    if diffs:
        raise SimgapError(f"store {str(store)!r} was collected for a different system: {'; '.join(diffs[:4])}")
    _check_store_complete(store, cfg)
    names = ["x", "u", "f_nom", "mean", "var", "lo", "hi", "cover_index", "input_index"]
    K, S = int(cfg["n_pairs"]), int(cfg["chunk_size"])
    arrays = {}
    for c in range(int(cfg["n_chunks"])):  # fill preallocated arrays: peak memory = data set + one chunk
        a, b = c * S, min((c + 1) * S, K)
        # order statistics for the per-run gap: stores written before they existed lack them
        part = _load_chunk(store, c, h, b - a, names, optional=("absdev_top",))
        if not arrays:
            arrays = {k: np.empty((K,) + v.shape[1:], dtype=v.dtype) for k, v in part.items()}
        elif set(part) != set(arrays):
            arrays.pop("absdev_top", None)
            part.pop("absdev_top", None)
        for k, v in part.items():
            if v.shape[1:] != arrays[k].shape[1:]:
                raise SimgapError(f"store {str(store)!r}: chunk {c} has {k} of shape {v.shape}, "
                                  f"expected (.., {arrays[k].shape[1:]})")
            arrays[k][a:b] = v
    manifest = dict(cfg)
    manifest.update({"hash": h, "store": str(store.resolve()), "created": man.get("created")})
    return StoreContents(system=system, n_runs=int(cfg["n_runs"]), epsilon=float(cfg["epsilon"]),
                         manifest=manifest, arrays=arrays)


def load_samples(path: str | Path) -> np.ndarray:
    """The raw next states (K, N1hat, n) of a store collected with ``keep_samples``."""
    store = Path(path)
    man = _read_manifest(store)
    cfg, h = man["config"], man["hash"]
    if not cfg["keep_samples"]:
        raise SimgapError(f"store {str(store)!r} was collected without keep_samples; no raw samples stored")
    _check_store_complete(store, cfg)
    K, S = int(cfg["n_pairs"]), int(cfg["chunk_size"])
    return np.concatenate([_load_chunk(store, c, h, min((c + 1) * S, K) - c * S, ["samples"])["samples"]
                           for c in range(int(cfg["n_chunks"]))])

"""Data collection: N1hat simulator runs per (x_r, u) pair, chunked, resumable, executor-independent.

For every cover point x_r (:mod:`simgap.cover`) and every input u in U the nominal model gives
f(x_r, u) once and the simulator gives N1hat independent next states fhat(x_r, u, w_k),
k = 1..N1hat. Per pair only the statistics the certificate needs are kept (empirical mean,
unbiased variance (ddof=1), min and max; angle convention as in :mod:`simgap.dataset`) and the
largest ``min(N1hat, TOP_ORDER_STATS)`` absolute deviations |wrap(fhat_i - f_i)| per dimension
(order statistics for the per-run gap, :mod:`simgap.perrun.realization`), not the raw samples
unless ``keep_samples`` is set.

Work split. The K = N*M pairs (cover-major: row = r*M + j) are cut into chunks of
``chunk_size`` consecutive pairs. Chunk c draws all its randomness from its own generator
``default_rng(SeedSequence(seed, spawn_key=(c,)))`` (= ``SeedSequence(seed).spawn(n)[c]``),
so the data set does not depend on the executor, the number of workers, the order in which
chunks finish, or on interruptions. Inside a chunk the simulator is called on all
pairs*N1hat runs at once, in sub-batches of at most ``batch_runs`` runs (whole pairs) to
bound memory; ``batch_runs`` is part of the configuration because it fixes how the chunk's
random stream is consumed.

The store is a directory::

    manifest.json          full configuration (system, simulator, cover, N1hat, seed, chunking,
                           simgap version) and "hash" = sha256 of its canonical JSON
    chunks/c000000.npz     one file per chunk, written atomically (temp file + os.replace), no pickle;
                           it carries its chunk id, the configuration hash, the sha256 of every
                           array ("digests", JSON) and a digest over those ("digest")
    .lock                  locked by the one process collecting into the store (a second is refused)

A killed run leaves only complete chunk files; :func:`collect` on the same store verifies
each one's digests, recomputes the broken ones and the missing rest, giving a data set
bit-identical to an uninterrupted run. Loading verifies every chunk too: a chunk re-saved with
other numbers is refused. A store with a
different configuration hash is refused, naming the keys that differ.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import os
import shutil
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Optional, Sequence

import numpy as np

from . import fileio
from .cover import Cover, CoverSpec, make_cover
from .dataset import Dataset
from .errors import SimgapError
from .executors import Executor, make_executor
from .progress import StopCheck, as_stop_check
from .simulators.base import SimulatorConfig, make_simulator
from .systems import System, ref_of_description, resolve_system, wrap_angle

STORE_FORMAT = "simgap-store/1"
MANIFEST = "manifest.json"
LOCK = ".lock"  # held by the one process collecting into the store (see store_lock)
CHUNK_DIR = "chunks"
DEFAULT_BATCH_RUNS = 1 << 18  # simulator runs per step call: ~50 MB of float64 work arrays
TOP_ORDER_STATS = 32  # largest |fhat_i - f_i| kept per pair and dimension (per-run quantile bounds)


# ----------------------------------------------------------------------------------------
# Configuration
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


@dataclass(eq=False)
class CollectionPlan:
    """Everything that determines a data set (and so its hash).

    Parameters
    ----------
    system : System
        Nominal model f (its X, U, tau = steps * base_tau).
    simulator : SimulatorConfig
        The stochastic simulator fhat; its ``system``/``steps`` must match ``system``.
    cover : Cover
        The epsilon-cover of X (:func:`simgap.cover.make_cover`).
    n_runs : int
        N1hat >= 2 simulator runs per (x_r, u) pair.
    seed : int
        Root seed of the per-chunk generators.
    chunk_size : int, optional
        Pairs per chunk; default max(1, min(batch_runs // n_runs, ceil(K / 64))): one step call
        per chunk and enough chunks to keep every worker busy (it never depends on the executor).
    batch_runs : int
        Maximum simulator runs per ``step`` call (memory bound).
    keep_samples : bool
        Also store the raw (K, N1hat, n) next states (large!).
    """

    system: System
    simulator: SimulatorConfig
    cover: Cover
    n_runs: int
    seed: int = 0
    chunk_size: Optional[int] = None
    batch_runs: int = DEFAULT_BATCH_RUNS
    keep_samples: bool = False

    def __post_init__(self):
        if isinstance(self.simulator, dict):
            self.simulator = SimulatorConfig.from_dict(self.simulator)
        self.n_runs = _int(self.n_runs, "n_runs (N1hat)", 2, "N1hat must be >= 2 (the variance needs two runs)")
        self.seed = _int(self.seed, "seed", 0)
        self.batch_runs = _int(self.batch_runs, "batch_runs", 1)
        if self.chunk_size is None:
            # one step call per chunk, but at least ~64 chunks so that small jobs spread over workers
            self.chunk_size = max(1, min(self.batch_runs // self.n_runs, -(-self.n_pairs // 64)))
        self.chunk_size = _int(self.chunk_size, "chunk_size", 1)
        if self.cover.system is not self.system and describe_system(self.cover.system) != describe_system(self.system):
            raise SimgapError("collection: the cover was built for a different system")
        if self.simulator.system != self.system.name:
            raise SimgapError(f"collection: simulator simulates {self.simulator.system!r} "
                              f"but the system is {self.system.name!r}")
        if int(self.simulator.steps) != int(self.system.steps):
            raise SimgapError(f"collection: simulator steps={self.simulator.steps} but system steps="
                              f"{self.system.steps}; they must agree (tau = steps * base_tau)")
        self.system.check_states(self.cover.points, "cover points")
        # workers rebuild the cover from its spec: the points must be exactly what the spec gives
        if not np.array_equal(make_cover(self.system, self.cover.spec).points, self.cover.points):
            raise SimgapError("collection: the cover's points differ from what its spec produces; "
                              "build covers with simgap.cover.make_cover")

    @property
    def n_pairs(self) -> int:
        return self.cover.N * self.system.inputs.shape[0]

    @property
    def n_chunks(self) -> int:
        return -(-self.n_pairs // self.chunk_size)

    def config(self) -> dict:
        """The hashed configuration (JSON-ready). Executor and worker count are not part of it."""
        from . import __version__
        try:
            text = canonical_json({
            "format": STORE_FORMAT,
            "simgap_version": __version__,
            "system": describe_system(self.system),
            "simulator": self.simulator.to_dict(),
            "cover": self.cover.describe(),
            "epsilon": float(self.cover.epsilon),
            "n_runs": self.n_runs,
            "seed": self.seed,
            "chunk_size": self.chunk_size,
            "batch_runs": self.batch_runs,
            "keep_samples": bool(self.keep_samples),
            "n_pairs": self.n_pairs,
            "n_chunks": self.n_chunks,
            })
        except (ValueError, TypeError) as e:
            raise SimgapError(f"collection configuration is not JSON-able (NaN/inf or odd types): {e}") from None
        return json.loads(text)

    def hash(self) -> str:
        return config_hash(self.config())


def _int(v, name, lo, msg=None) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer, float)) or int(v) != v:
        raise SimgapError(f"{name} must be an integer, got {v!r}")
    if int(v) < lo:
        raise SimgapError(msg or f"{name} must be >= {lo}, got {v!r}")
    return int(v)


# ----------------------------------------------------------------------------------------
# Per-chunk work (runs in worker processes)
# ----------------------------------------------------------------------------------------

def pair_statistics(Y: np.ndarray, f_nom: np.ndarray, angle_dims: Sequence[int] = ()):
    """Per-pair statistics of runs Y (P, R, n) around the nominal f_nom (P, n).

    Returns mean, var (ddof=1), lo, hi, each (P, n). Angle dimensions use the wrapped
    deviation d = wrap(Y - f_nom): mean = wrap(f_nom + mean d), var = var d,
    lo = f_nom + min d, hi = f_nom + max d (see :mod:`simgap.dataset`).
    """
    mean = Y.mean(axis=1)
    var = Y.var(axis=1, ddof=1)
    lo = Y.min(axis=1)
    hi = Y.max(axis=1)
    if len(angle_dims):
        a = list(angle_dims)
        d = wrap_angle(Y[:, :, a] - f_nom[:, None, a])
        mean[:, a] = wrap_angle(f_nom[:, a] + d.mean(axis=1))
        var[:, a] = d.var(axis=1, ddof=1)
        lo[:, a] = f_nom[:, a] + d.min(axis=1)
        hi[:, a] = f_nom[:, a] + d.max(axis=1)
    return mean, var, lo, hi


def top_abs_deviations(Y: np.ndarray, f_nom: np.ndarray, angle_dims: Sequence[int] = (),
                       T: int = TOP_ORDER_STATS) -> np.ndarray:
    """The T = min(R, ``T``) largest |wrap(Y - f_nom)| per pair and dimension, descending: (P, T, n).

    Column j is the (R - j)-th order statistic of the R absolute deviations (j = 0: the maximum).
    """
    d = np.abs(Y - f_nom[:, None, :])
    if len(angle_dims):
        a = list(angle_dims)
        d[:, :, a] = np.abs(wrap_angle(Y[:, :, a] - f_nom[:, None, a]))
    T = min(d.shape[1], int(T))
    top = np.partition(d, d.shape[1] - T, axis=1)[:, d.shape[1] - T:, :]
    return -np.sort(-top, axis=1)


def chunk_rng(seed: int, chunk: int) -> np.random.Generator:
    """The generator of chunk ``chunk``: SeedSequence(seed).spawn(...)[chunk]."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(chunk),)))


# One simulator (and cover) per worker process, kept alive across chunks: PyBullet set-up is not free.
# Keyed to the process: a forked worker must not reuse the simulators its parent cached.
_WORKER_CACHE: dict = {}
_WORKER_PID = None


def _system_from_config(desc: dict, steps: int) -> System:
    """Rebuild a built-in, plugin, system-file or refined system (with its recorded input set) from a
    manifest description."""
    s = resolve_system(ref_of_description(desc), steps=steps, paths=False)
    U = np.asarray(desc["inputs"], dtype=float)
    if U.shape != s.inputs.shape or not np.array_equal(U, s.inputs):
        s = dataclasses.replace(s, inputs=U)
    return s


def _job(plan: CollectionPlan) -> dict:
    """Small picklable job description for workers; built-in systems are rebuilt by name."""
    cfg = plan.config()
    sysobj = None
    try:
        rebuilt = _system_from_config(cfg["system"], plan.system.steps)
        if describe_system(rebuilt) != cfg["system"]:
            sysobj = plan.system
    except SimgapError:
        sysobj = plan.system  # a user-defined system travels by pickle (define it at module level)
    return {"hash": config_hash(cfg), "config": cfg, "system": sysobj}


def _worker_state(job: dict) -> dict:
    global _WORKER_PID
    if _WORKER_PID != os.getpid():
        _WORKER_CACHE.clear()                 # the parent's (inherited by fork): not ours to close
        _WORKER_PID = os.getpid()
    h = job["hash"]
    st = _WORKER_CACHE.get(h)
    if st is None:
        for old in _WORKER_CACHE.values():
            old["sim"].close()
        _WORKER_CACHE.clear()
        cfg = job["config"]
        system = job["system"] or _system_from_config(cfg["system"], cfg["simulator"]["steps"])
        cv = cfg["cover"]
        cover = make_cover(system, CoverSpec(epsilon=cv["epsilon"], spacing=cv["spacing"],
                                             invariant_dims=tuple(cv["invariant_dims"]), fixed=cv["fixed"]))
        sim = make_simulator(cfg["simulator"], system)
        st = {"system": system, "cover": cover, "sim": sim}
        _WORKER_CACHE[h] = st
    return st


def run_chunk(job: dict, c: int) -> dict:
    """Compute chunk ``c``: pairs [c*S, min((c+1)*S, K)), N1hat runs each; returns arrays."""
    st = _worker_state(job)
    cfg = job["config"]
    system, cover, sim = st["system"], st["cover"], st["sim"]
    M = system.inputs.shape[0]
    K, S, R, n = cfg["n_pairs"], cfg["chunk_size"], cfg["n_runs"], system.n
    a, b = c * S, min((c + 1) * S, K)
    rows = np.arange(a, b, dtype=np.int64)
    ci, ui = rows // M, rows % M
    x, u = cover.points[ci], system.inputs[ui]
    f_nom = system.f(x, u)
    rng = chunk_rng(cfg["seed"], c)
    P = b - a
    mean, var, lo, hi = (np.empty((P, n)) for _ in range(4))
    top = np.empty((P, min(R, TOP_ORDER_STATS), n))
    samples = np.empty((P, R, n)) if cfg["keep_samples"] else None
    per = max(1, cfg["batch_runs"] // R)
    for s in range(0, P, per):
        e = min(P, s + per)
        xs = np.repeat(x[s:e], R, axis=0)
        us = np.repeat(u[s:e], R, axis=0)
        try:
            Y = np.asarray(sim.step(xs, us, rng), dtype=float)
        except SimgapError as err:
            raise SimgapError(f"chunk {c} (pairs {a + s}..{a + e - 1}): {err}") from None
        if Y.shape != xs.shape:
            raise SimgapError(f"simulator {cfg['simulator']['kind']!r} returned shape {Y.shape}, expected {xs.shape}")
        if not np.all(np.isfinite(Y)):
            bad = int((~np.isfinite(Y)).any(axis=1).sum())
            raise SimgapError(f"chunk {c}: simulator {cfg['simulator']['kind']!r} returned NaN/inf "
                              f"for {bad} of {len(Y)} runs")
        Y = Y.reshape(e - s, R, n)
        mean[s:e], var[s:e], lo[s:e], hi[s:e] = pair_statistics(Y, f_nom[s:e], system.angle_dims)
        top[s:e] = top_abs_deviations(Y, f_nom[s:e], system.angle_dims)
        if samples is not None:
            samples[s:e] = Y
    out = {"x": x, "u": u, "f_nom": f_nom, "mean": mean, "var": var, "lo": lo, "hi": hi,
           "cover_index": ci, "input_index": ui, "absdev_top": top}
    if samples is not None:
        out["samples"] = samples
    return out


# ----------------------------------------------------------------------------------------
# The store
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
def store_lock(store: Path):
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
        raise SimgapError(f"store {str(store)!r} is being collected by another process; wait for it to finish "
                          "(then run the same command to check it is complete) or collect into another "
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


def _read_manifest(store: Path) -> dict:
    mpath = store / MANIFEST
    if not store.is_dir():
        raise SimgapError(f"store {str(store)!r} does not exist or is not a directory")
    if not mpath.is_file():
        raise SimgapError(f"{str(store)!r} is not a simgap store (no {MANIFEST})")
    try:
        man = json.loads(mpath.read_text())
        cfg, h = man["config"], man["hash"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise SimgapError(f"store {str(store)!r}: {MANIFEST} is unreadable: {e}") from None
    if not isinstance(cfg, dict) or cfg.get("format") != STORE_FORMAT:
        raise SimgapError(f"store {str(store)!r}: unknown format {cfg.get('format') if isinstance(cfg, dict) else cfg!r}"
                          f" (expected {STORE_FORMAT})")
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


@dataclass
class CollectResult:
    """Outcome of :func:`collect`."""

    store: Path
    hash: str
    n_chunks: int
    done: int           # chunks present in the store now
    computed: int       # chunks computed by this call
    resumed_from: int   # chunks present (and verified) before this call
    cancelled: bool
    seconds: float
    runs: int           # simulator runs computed by this call

    @property
    def complete(self) -> bool:
        return self.done == self.n_chunks

    def dataset(self, system: System | None = None) -> Dataset:
        return load_store(self.store, system=system)


def collect(plan: CollectionPlan, store: str | Path, executor: str | Executor = "local",
            workers: Optional[int] = None, address: Optional[str] = None,
            on_progress: Optional[Callable[[int, int], None]] = None, should_stop: StopCheck = None,
            chunk_ids: Optional[Iterable[int]] = None, resume: bool = True) -> CollectResult:
    """Collect the data set of ``plan`` into the store directory ``store`` (see module docstring).

    Parameters
    ----------
    plan : CollectionPlan
    store : path
        Store directory; created if missing. An existing store with the same configuration
        hash is resumed (finished chunks are kept); a different configuration is refused.
    executor : "local" | "serial" | "ray" | Executor
    workers : int, optional
        Processes (local) or CPUs (local Ray instance); default all cores.
    address : str, optional
        Ray cluster address; default a local instance.
    on_progress : callable(done_pairs, total_pairs), optional
        Called in this thread after every stored chunk (and once at the start).
    should_stop : threading.Event or callable, optional
        Polled between chunks; when set, no new chunk starts and the call returns with
        ``cancelled=True`` (the store stays resumable).
    chunk_ids : iterable of int, optional
        Compute only these chunks (benchmarks, manual splitting across machines).
    resume : bool
        If False, an existing store is an error.
    """
    store = Path(store)
    stop = as_stop_check(should_stop)
    cfg = plan.config()
    h = config_hash(cfg)
    # the executor first: one that cannot start (e.g. an unreachable Ray cluster) leaves no store
    ex = executor if isinstance(executor, Executor) else make_executor(executor, workers, address)
    # the simulator next (an unknown kind or key, a bad value): a config that cannot build one leaves no store
    make_simulator(cfg["simulator"], plan.system).close()
    if store.exists() and not store.is_dir():
        raise SimgapError(f"store {str(store)!r} exists and is not a directory")
    if not (store / MANIFEST).exists() and store.is_dir() and any(p.name != LOCK for p in store.iterdir()):
        if (store / LOCK).exists():
            with store_lock(store):  # a collector that has not written its manifest yet is refused here
                pass
        raise SimgapError(f"{str(store)!r} is a non-empty directory without {MANIFEST}; refusing to write into it")
    top = store.absolute()  # the outermost folder this call creates (removed again if nothing is stored)
    while not top.parent.exists():
        top = top.parent
    created = not store.exists()
    fresh = not (store / MANIFEST).exists()
    store.mkdir(parents=True, exist_ok=True)
    with store_lock(store):
        try:
            return _collect_locked(plan, store, ex, cfg, h, on_progress, stop, chunk_ids, resume)
        except BaseException:
            # a store this call started that holds no finished chunk is no resumable data: remove what
            # this call made while the lock is held (a store with finished chunks stays, to be resumed)
            if fresh and not _done_chunks(store, plan.n_chunks):
                if created:
                    shutil.rmtree(top, ignore_errors=True)
                else:
                    shutil.rmtree(store / CHUNK_DIR, ignore_errors=True)
                    for name in (MANIFEST, LOCK):
                        (store / name).unlink(missing_ok=True)
            raise


def _collect_locked(plan, store, ex, cfg, h, on_progress, stop, chunk_ids, resume) -> CollectResult:
    """The body of :func:`collect`, run while this process holds the store's lock."""
    if (store / MANIFEST).exists():
        man = _read_manifest(store)
        if man["hash"] != h:
            diffs = _diff(man["config"], cfg)
            raise SimgapError(f"store {str(store)!r} holds a collection with a different configuration; refusing "
                              f"to resume. Differences: {'; '.join(diffs[:6])}"
                              f"{' ...' if len(diffs) > 6 else ''}. Use another output directory.")
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

    n_chunks = plan.n_chunks
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
    K, S = plan.n_pairs, plan.chunk_size

    def pairs_in(c):
        return min((c + 1) * S, K) - c * S

    done_pairs = sum(pairs_in(c) for c in done)
    if on_progress:
        on_progress(done_pairs, K)
    state = {"pairs": done_pairs, "computed": 0, "runs": 0}

    def on_result(c, arrays):
        _write_chunk(store, c, h, arrays)
        done.add(c)
        p = pairs_in(c)
        state["pairs"] += p
        state["computed"] += 1
        state["runs"] += p * plan.n_runs
        if on_progress:
            on_progress(state["pairs"], K)

    t0 = time.perf_counter()
    finished = ex.map_chunks(run_chunk, _job(plan), todo, on_result, stop)
    return CollectResult(store=store, hash=h, n_chunks=n_chunks, done=len(done), computed=state["computed"],
                         resumed_from=resumed_from, cancelled=not finished, seconds=time.perf_counter() - t0,
                         runs=state["runs"])


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


def load_store(path: str | Path, system: System | None = None) -> Dataset:
    """Load a complete collection store as a :class:`Dataset`.

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
            system = _system_from_config(cfg["system"], steps)
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
    return Dataset(system=system, n_runs=int(cfg["n_runs"]), epsilon=float(cfg["epsilon"]),
                   manifest=manifest, **arrays)


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

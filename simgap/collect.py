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

The store (:mod:`simgap.store`: a directory with a manifest and one verified file per chunk)
is written chunk by chunk, atomically. A killed run leaves only complete chunk files; :func:`collect`
on the same store verifies each one's digests, recomputes the broken ones and the missing rest,
giving a data set bit-identical to an uninterrupted run. A store with a different configuration
hash is refused, naming the keys that differ.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Optional, Sequence

import numpy as np

from .checks import check_disk, check_memory, check_seconds
from .cover import Cover, CoverSpec, make_cover, timed_rate
from .dataset import Dataset, load_store
from .errors import SimgapError
from .executors import Executor, make_executor
from .progress import StopCheck, as_stop_check
from .simulators import SimulatorConfig, make_simulator
# the store's format, writer and reader live in simgap.store; re-exported here, their old home
from .store import (CHUNK_DIR, LOCK, MANIFEST, STORE_FORMAT, _atomic_write_bytes, _chunk_digests,  # noqa: F401
                    _chunk_path, _diff, _done_chunks, _pid_alive, _read_manifest, _write_chunk, canonical_json,
                    config_hash, describe_system, fill_store, load_samples, portable_system, store_lock, store_status)
from .store import system_from_config as _system_from_config
from .systems import System, wrap_angle

DEFAULT_BATCH_RUNS = 1 << 18  # simulator runs per step call: ~50 MB of float64 work arrays
TOP_ORDER_STATS = 32  # largest |fhat_i - f_i| kept per pair and dimension (per-run quantile bounds)


# ----------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------

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


def _job(plan: CollectionPlan) -> dict:
    """Small picklable job description for workers; built-in systems are rebuilt by name."""
    cfg = plan.config()
    return {"hash": config_hash(cfg), "config": cfg, "system": portable_system(plan.system)}


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
                                             invariant_dims=tuple(cv["invariant_dims"]), fixed=cv["fixed"],
                                             region=cv.get("region") or {}, boxes=tuple(cv.get("boxes") or ())))
        sim = make_simulator(cfg["simulator"], system)
        st = {"system": system, "cover": cover, "sim": sim}
        _WORKER_CACHE[h] = st
    return st


def run_chunk(job: dict, c: int) -> dict:
    """Compute chunk ``c``: pairs [c*S, min((c+1)*S, K)), N1hat runs each; returns arrays."""
    cfg = job["config"]
    K, S = cfg["n_pairs"], cfg["chunk_size"]
    return _pairs(job, c, c * S, min((c + 1) * S, K), chunk_rng(cfg["seed"], c))


def _pairs(job: dict, c: int, a: int, b: int, rng: np.random.Generator) -> dict:
    """Pairs [a, b) of chunk ``c`` (``c`` names the chunk in error messages), N1hat runs each."""
    st = _worker_state(job)
    cfg = job["config"]
    system, cover, sim = st["system"], st["cover"], st["sim"]
    M = system.inputs.shape[0]
    R, n = cfg["n_runs"], system.n
    rows = np.arange(a, b, dtype=np.int64)
    ci, ui = rows // M, rows % M
    x, u = cover.points[ci], system.inputs[ui]
    f_nom = system.f(x, u)
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


def calibrate_chunk(job: dict, c: int, budget: float = 0.3, work: Optional[float] = None) -> dict:
    """In a worker: its set-up time and the pairs per second it computes (runs, statistics and all).

    The worker builds its simulator as for the collection (``setup_s``), then computes pairs of
    chunk ``c`` (drawn from a calibration generator: nothing is stored), timed by
    :func:`simgap.cover.timed_rate`: growing batches of pairs (x4 from 64 runs, until one takes
    half the budget) not timed for the rate, then repeated batches of the size reached (two at
    least) until ``budget`` seconds have passed, or a share of the time ``work`` (the pairs this
    worker will compute) takes. The rate is the one the collection's workers achieve, with the
    collection's own simulator settings (a noise-free collection has its own), on the machine's
    load at that moment (all workers calibrate at once)."""
    t0 = time.perf_counter()
    _worker_state(job)
    setup = time.perf_counter() - t0
    cfg = job["config"]
    K, S, R = cfg["n_pairs"], cfg["chunk_size"], cfg["n_runs"]
    a = min(c * S, K - 1)
    most = max(1, min(S, K - a))  # a chunk's pairs at most: a calibration costs no more than a chunk
    rng = np.random.default_rng(0)
    # growth up to batches of half the budget: a batched simulator's rate still grows with the batch
    # (the pendulum's: 64 pairs about 0.6x a whole chunk of 655), so small batches price it long
    rate = timed_rate(lambda p, timed: _pairs(job, c, a, a + p, rng), -(-64 // R), most, budget, grow=0.5,
                      work=work)
    return {"setup_s": setup, "pairs_per_s": rate, "pid": os.getpid(),
            "seconds": time.perf_counter() - t0}


# ----------------------------------------------------------------------------------------
# Collecting into a store
# ----------------------------------------------------------------------------------------

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
    K, S = plan.n_pairs, plan.chunk_size

    def pairs_in(c):
        return min((c + 1) * S, K) - c * S

    state = {"pairs": 0, "new": 0}

    def on_start(done):
        state["pairs"] = sum(pairs_in(c) for c in done)
        if on_progress:
            on_progress(state["pairs"], K)

    def on_chunk(c, arrays):
        state["pairs"] += pairs_in(c)
        state["new"] += pairs_in(c)
        if on_progress:
            on_progress(state["pairs"], K)

    t0 = time.perf_counter()
    r = fill_store(store, cfg, run_chunk, _job(plan), ex, on_start=on_start, on_chunk=on_chunk, should_stop=stop,
                   chunk_ids=chunk_ids, resume=resume)
    return CollectResult(store=store, hash=h, n_chunks=plan.n_chunks, done=len(r.done), computed=r.computed,
                         resumed_from=r.resumed_from, cancelled=not r.finished, seconds=time.perf_counter() - t0,
                         runs=state["new"] * plan.n_runs)


# ----- cost model: checked before any work (simgap run, simgap collect) ---------------------------

def collection_size(n_pairs: int, n_runs: int, n: int, m: int, steps: int, batch_runs: int, workers: int,
                    keep_samples: bool, rate_per_worker: Optional[float] = None) -> dict:
    """Estimated peak memory, disk and time of a collection (see :mod:`simgap.collect`).

    A worker steps at most max(batch_runs, N1hat) runs at once (whole pairs): states, inputs and
    next states in float64 plus the simulator's own work arrays (a factor 4 is allowed for them).
    With ``keep_samples`` a chunk also holds its raw samples. The store keeps 7 per-pair arrays.
    """
    per_call = max(int(batch_runs), int(n_runs))
    worker = per_call * (3 * n + m) * 8 * 4
    if keep_samples:
        worker += min(int(n_pairs), max(1, int(batch_runs) // int(n_runs))) * int(n_runs) * n * 8
    disk = n_pairs * (5 * n + m + 2) * 8 + (n_pairs * n_runs * n * 8 if keep_samples else 0)
    runs = n_pairs * n_runs
    secs = runs / (rate_per_worker * max(1, workers)) if rate_per_worker else None
    return {"memory": worker * max(1, workers), "disk": disk, "seconds": secs, "runs": runs,
            "sim_steps": runs * steps}


def check_collection(n_pairs: int, n_runs: int, n: int, m: int, steps: int, batch_runs: int, workers: int,
                     keep_samples: bool, store, rate_per_worker: Optional[float] = None) -> dict:
    """Refuse a collection that cannot fit in memory or on disk, or would take over a year."""
    est = collection_size(n_pairs, n_runs, n, m, steps, batch_runs, workers, keep_samples, rate_per_worker)
    what = f"collecting {n_pairs:,} pairs x N1hat={n_runs:,} runs ({est['sim_steps']:,} simulator steps)"
    hint = "lower --n-runs (N1hat) or raise --epsilon"
    check_memory(est["memory"], f"{what} on {workers} worker(s)", hint + " or use fewer --workers")
    check_disk(est["disk"], store, what, hint)
    check_seconds(est["seconds"], what, hint)
    return est


def collection_seconds(n_pairs: int, chunk_size: int, workers: int, pairs_per_s: float, setup_s: float = 0.0,
                       start_s: float = 0.0, write_s: float = 0.0) -> float:
    """Wall time of computing ``n_pairs`` pairs in chunks of ``chunk_size`` on ``workers`` workers.

    The chunks go round by round: ceil(chunks / workers) rounds of a chunk each per worker (a last
    round with fewer chunks than workers leaves some idle), a chunk of S pairs taking S / ``pairs_per_s``
    (one worker's measured rate); plus the pool's start ``start_s`` and a worker's simulator set-up
    ``setup_s`` (once per worker, in parallel), and ``write_s`` per chunk for the parent to verify and
    store it (in parallel with the workers but for the last round's: counted for ceil(chunks / workers)
    chunks, at least one)."""
    K, S, W = int(n_pairs), max(1, int(chunk_size)), max(1, int(workers))
    if K <= 0:
        return 0.0
    chunks = -(-K // S)
    W = min(W, chunks)
    rounds = -(-chunks // W)
    per_chunk = min(S, K) / float(pairs_per_s)
    return start_s + setup_s + rounds * per_chunk + max(1, rounds) * write_s


def estimate_collection(plan: CollectionPlan, executor: str | Executor = "local", workers: Optional[int] = None,
                        address: Optional[str] = None, chunks: Optional[int] = None, budget: float = 0.3) -> dict:
    """Measure what the collection of ``plan`` will cost, in the executor's own workers.

    One calibration task per worker (:func:`calibrate_chunk`: each builds its simulator, then times
    whole pairs, statistics included, on chunks spread over the plan) gives the pairs per second a
    worker achieves while the others run too, and the set-up of a worker; the pool's start is the
    calibration's wall time beyond its slowest task. A chunk's writing is priced at the parent's
    measured time to write a chunk of the same size (:func:`_write_seconds`). ``chunks``: the chunks
    to compute (a resumed store's missing ones), default all. Returns a dict with ``seconds`` (see
    :func:`collection_seconds`), ``pairs_per_s``, ``runs_per_s`` (one worker), ``setup_s``, ``start_s``,
    ``write_s`` and ``workers``."""
    ex = executor if isinstance(executor, Executor) else make_executor(executor, workers, address)
    W = max(1, int(getattr(ex, "workers", 1) or 1))
    n_chunks = plan.n_chunks if chunks is None else int(chunks)
    W_eff = max(1, min(W, plan.n_chunks))
    ids = sorted({int(i * plan.n_chunks // W_eff) for i in range(W_eff)})
    job = _job(plan)
    pairs = plan.n_pairs if chunks is None else min(plan.n_pairs, n_chunks * plan.chunk_size)
    res = []
    t0 = time.perf_counter()
    # each worker's timing: at most ``budget``, and a share of its part of the pairs
    ex.map_chunks(_calibrate_task, (job, budget, pairs / W_eff), ids, lambda c, r: res.append(r))
    wall = time.perf_counter() - t0
    rate = float(np.mean([r["pairs_per_s"] for r in res]))
    setup = float(max(r["setup_s"] for r in res))
    # the pool's start: the calibration's wall time beyond its slowest task (tasks run side by side;
    # a serial executor runs them one after another in this process: no pool)
    start = 0.0 if ex.name == "serial" else max(0.0, wall - max(r["seconds"] for r in res))
    write = _write_seconds(plan)
    secs = collection_seconds(pairs, plan.chunk_size, W, rate, setup, start, write)
    return {"seconds": secs, "pairs_per_s": rate, "runs_per_s": rate * plan.n_runs, "setup_s": setup,
            "start_s": start, "write_s": write, "workers": W, "executor": ex.name}


def _calibrate_task(job, c):
    j, budget, work = job
    return calibrate_chunk(j, c, budget, work)


def _write_seconds(plan: CollectionPlan) -> float:
    """The parent's time to store one chunk of ``plan``'s size (arrays of zeros; digests, atomic write)."""
    import tempfile
    S, n, m = plan.chunk_size, plan.system.n, plan.system.m
    R = plan.n_runs
    arrays = {"x": np.zeros((S, n)), "u": np.zeros((S, m)), "f_nom": np.zeros((S, n)), "mean": np.zeros((S, n)),
              "var": np.zeros((S, n)), "lo": np.zeros((S, n)), "hi": np.zeros((S, n)),
              "cover_index": np.zeros(S, np.int64), "input_index": np.zeros(S, np.int64),
              "absdev_top": np.zeros((S, min(R, TOP_ORDER_STATS), n))}
    if plan.keep_samples:
        arrays["samples"] = np.zeros((S, R, n))
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / CHUNK_DIR).mkdir()
        t0 = time.perf_counter()
        _write_chunk(Path(d), 0, "0" * 64, arrays)
        return time.perf_counter() - t0


def printed_collection_estimate(plan, store, executor, workers, address, rate, n_workers):
    """The printed estimate of a collection stage (a :class:`~simgap.cover.CostEstimate`).

    On a local (or serial) executor the rate is measured in the executor's own workers with the
    plan's own simulator settings (a noise-free collection has its own rate), whole pairs with
    their statistics, and the workers' start-up and the chunks' writing are priced
    (:func:`simgap.collect.estimate_collection`); a resumed store's stored chunks are left out.
    On Ray (a cluster's workers are not this machine's) ``rate`` measured here is used: runs /
    (rate x workers)."""
    import dataclasses
    from .cover import estimate_cost
    name = executor if isinstance(executor, str) else getattr(executor, "name", "")
    est = estimate_cost(plan.cover, plan.n_runs, rate_per_worker=rate, workers=n_workers,
                        rate_source="calibrated here; a resumed store's done chunks are skipped")
    if name not in ("local", "serial"):
        return est
    try:
        done = len(_done_chunks(Path(store), plan.n_chunks)) if (Path(store) / MANIFEST).exists() else 0
    except Exception:
        done = 0
    todo = plan.n_chunks - done
    if todo <= 0:
        return dataclasses.replace(est, seconds=0.0, rate_source="every chunk is stored already")
    # the workers' timing: at most 0.6 s, less for a small collection (timed_rate's share of the work)
    c = estimate_collection(plan, name, workers or None, address, chunks=todo, budget=0.6)
    src = (f"calibrated in the {name} workers with this collection's settings; + worker start {c['start_s'] + c['setup_s']:.1f} s, "
           f"{c['write_s'] * 1000:.0f} ms to store a chunk" + (f"; {done} of {plan.n_chunks} chunks stored already"
                                                                if done else ""))
    return dataclasses.replace(est, seconds=c["seconds"], rate_per_worker=c["runs_per_s"], workers=c["workers"],
                               rate_source=src)

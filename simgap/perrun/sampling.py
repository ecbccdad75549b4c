"""Interval-MDP sampling through the executors: chunked, resumable, the same bits on every executor.

The simulator work of :func:`build_imdp` runs as chunks of
:mod:`simgap.executors`, as a collection does (:mod:`simgap.collect`):

* phase ``lipschitz`` (when the constants are not given): chunk j = the common-random-number
  secants along state dimension j (:func:`simgap.perrun.imdp.secant_slopes`), drawn from
  ``SeedSequence(seed, spawn_key=(1, j))``; the Wood-Zhang estimates are made here from the slopes;
* phase ``runs``: chunk c = the pairs ``order[b[c] : b[c + 1]]`` of the sampling order, S units each
  (S = ``chunk_size`` pairs, or with shared runs S whole (anchor, input) groups; :class:`simgap.perrun.imdp.Layout`): their pilot runs from
  ``SeedSequence(seed, spawn_key=(2, c))``, their main runs from ``SeedSequence(seed, spawn_key=(3, c))``
  (:func:`simgap.perrun.imdp.count_pairs`). A chunk returns its pairs' support and counts only.

Every chunk's randomness is a function of (seed, phase, chunk id) alone, so the interval MDP does not
depend on the executor (serial, a local pool, Ray), the number of workers, the order in which chunks
finish, or on interruptions. ``chunk_size`` and ``batch_runs`` are part of the configuration because
they fix how the random streams are cut. The union bound's split depends on the pilot runs alone
(whether some pilot run ended in a single cell), which are independent of every main run: that a
chunk's main runs are simulated before another chunk's pilot does not change its validity.

With ``store`` (a folder) each phase keeps its chunks in a :mod:`simgap.store` folder
(``store/lipschitz``, ``store/runs``; format ``simgap-perrun/1``): a manifest with the hashed
configuration (system, simulator, spec, options and, for the runs, the widening constants the
secants gave) and one file per chunk with the sha256 of every array, written atomically under the
store's lock. The same call on the same folder verifies the chunks there, recomputes the missing
or broken ones and gives a bit-identical interval MDP (kill -9 included); a folder holding another
configuration is refused, naming the keys that differ.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..errors import SimgapError
from ..executors import Executor, SerialExecutor, make_executor
from ..progress import as_stop_check
from ..store import (MANIFEST, _read_manifest, config_hash, describe_system, fill_store, portable_system, read_chunk,
                     system_from_config)
from .imdp import (IMDP, Allocation, IMDPOptions, _bound_count, assemble_csr, count_pairs, layout,
                   lipschitz_from_slopes, secant_slopes)

FORMAT = "simgap-perrun/1"
SECANT_PAIRS, SECANT_RUNS = 300, 20   # common-random-number pairs per dimension x runs per pair
RUNS_ARRAYS = ("key", "n_hit", "n_in", "pairs", "n_sink", "single_seen", "simulated")


def chunk_rng(seed: int, phase: int, chunk: int) -> np.random.Generator:
    """The generator of chunk ``chunk`` of phase ``phase`` (1 secants, 2 pilot runs, 3 main runs)."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(phase), int(chunk))))


# ----------------------------------------------------------------------------------------------
# Configurations (hashed: a store is resumed only with the same one)
# ----------------------------------------------------------------------------------------------

def _base_config(sim, spec, o: IMDPOptions, lay) -> dict:
    from .. import __version__
    return {"format": FORMAT, "simgap_version": __version__, "system": describe_system(sim.system),
            "simulator": sim.config.to_dict(),
            # a string: the spec's boxes may be unbounded (inf), which canonical JSON refuses as numbers
            "spec": json.dumps(spec.to_dict(), sort_keys=True), "eta": lay.grid.eta.tolist(), "hold": int(o.hold),
            "seed": int(o.seed)}


def lipschitz_config(sim, spec, o: IMDPOptions, lay) -> dict:
    dims = list(range(sim.system.n))
    return {**_base_config(sim, spec, o, lay), "phase": "lipschitz", "half": (lay.grid.eta / 2).tolist(),
            "residual": lay.share is not None, "secant_pairs": SECANT_PAIRS, "secant_runs": SECANT_RUNS,
            "dims": dims, "n_chunks": len(dims)}


def runs_config(sim, spec, o: IMDPOptions, lay, widening: dict) -> dict:
    n_units = int(lay.starts.size)
    S = o.units_per_chunk(n_units, lay.unit_pairs)
    return {**_base_config(sim, spec, o, lay), "phase": "runs", "n_runs": int(o.n_runs),
            "pilot_runs": int(o.pilot_runs), "batch_runs": int(o.batch_runs),
            "share": None if lay.share is None else lay.share.tolist(), "widening": widening,
            "chunk_size": S, "chunk_unit": "pair" if lay.share is None else "(anchor, input) group",
            "n_pairs": lay.P, "n_units": n_units, "n_chunks": -(-n_units // S)}


# ----------------------------------------------------------------------------------------------
# Work in the workers
# ----------------------------------------------------------------------------------------------

# One simulator and layout per worker process and configuration, kept across chunks; keyed to the
# process (a forked worker must not reuse what its parent cached)
_CACHE: dict = {}
_PID = None


def _state(job: dict) -> dict:
    global _PID
    if _PID != os.getpid():
        _CACHE.clear()
        _PID = os.getpid()
    st = _CACHE.get(job["hash"])
    if st is None:
        _drop_cache()
        cfg = job["config"]
        if job["sim"] is not None:                      # the serial executor: the caller's simulator
            sim, own = job["sim"], False
        else:
            from ..simulators import make_simulator
            system = job["system"] or system_from_config(cfg["system"], cfg["simulator"]["steps"])
            sim, own = make_simulator(cfg["simulator"], system), True
        lay = layout(sim.system, job["spec"], job["options"]) if cfg["phase"] == "runs" else None
        st = _CACHE[job["hash"]] = {"sim": sim, "own": own, "layout": lay}
    return st


def _drop_cache() -> None:
    for old in _CACHE.values():
        if old["own"]:
            old["sim"].close()
    _CACHE.clear()


def secants_chunk(job: dict, c: int) -> dict:
    """Chunk c of the lipschitz phase: the secant slopes along dimension dims[c]."""
    st, cfg = _state(job), job["config"]
    j = int(cfg["dims"][c])
    return secant_slopes(st["sim"], int(cfg["hold"]), j, float(cfg["half"][j]), chunk_rng(cfg["seed"], 1, j),
                         int(cfg["secant_pairs"]), int(cfg["secant_runs"]), residual=bool(cfg["residual"]))


def runs_chunk(job: dict, c: int) -> dict:
    """Chunk c of the runs phase: pilot support and main-run counts of its pairs."""
    st, cfg = _state(job), job["config"]
    b = st["layout"].chunk_bounds(int(cfg["chunk_size"]))
    pp = st["layout"].order[b[c]:b[c + 1]]
    return count_pairs(st["sim"], job["spec"], st["layout"], cfg["widening"], pp, job["options"],
                       chunk_rng(cfg["seed"], 2, c), chunk_rng(cfg["seed"], 3, c))


def calibrate_sampling(sim, spec, options: IMDPOptions, runs: int = 8192, pairs: int = 8) -> Optional[dict]:
    """The interval-MDP sampling measured in this process on ``pairs`` pairs spread over the sampling
    order, with a one-cell widening (rho = eta / 2; the real one comes from the secants, and a wider
    one costs more and touches more cells): ``{"rate"}`` steps per second, bookkeeping included (box
    tests, touched cells and counts cost more than a cheap simulator itself), timed over the pilot's
    N0 runs and ``runs`` main runs in all, after one untimed warm-up pair; ``{"entries_per_row"}`` the
    support the N0 pilot runs gave plus the sink. A step is one (pair, run, period): with shared runs
    one anchor's run counts once per cell it serves, as in :func:`simgap.perrun.cost.perrun_size`. None: no
    live pair."""
    import dataclasses
    lay = layout(sim.system, spec, options)
    if lay.P == 0:
        return None
    L = np.eye(sim.system.n)
    widening = ({"Ln": L.tolist(), "Lr": (0 * L).tolist()} if lay.share is not None
                else {"rho": (lay.grid.eta / 2).tolist()})
    pp = lay.order[np.linspace(0, lay.P - 1, min(pairs, lay.P)).astype(np.int64)]
    per = max(2, runs // len(pp))
    o = dataclasses.replace(options, n_runs=per, lipschitz=None)
    rng = np.random.default_rng(0)
    count_pairs(sim, spec, lay, widening, pp[:1], dataclasses.replace(o, n_runs=2, pilot_runs=1), rng, rng)
    t = time.perf_counter()
    part = count_pairs(sim, spec, lay, widening, pp, o, rng, rng)
    dt = time.perf_counter() - t
    return {"rate": len(pp) * (per + int(o.pilot_runs)) * int(options.hold) / max(dt, 1e-9),
            "entries_per_row": part["key"].size / len(pp) + 1}


# ----------------------------------------------------------------------------------------------
# Orchestration
# ----------------------------------------------------------------------------------------------

def _run_phase(cfg: dict, fn, sim, spec, o, ex: Executor, folder: Optional[Path], stop, names,
               on_start: Optional[Callable] = None, on_chunk: Optional[Callable] = None, replace: bool = False,
               log=None) -> Callable:
    """Compute all chunks of ``cfg`` with ``ex`` (kept in ``folder`` and resumed from it); returns
    ``get(c, names)``, the arrays of chunk c (read back from ``folder`` and verified on each call, so
    the caller holds one chunk at a time). With ``replace`` a store of another configuration in
    ``folder`` is removed first (a results folder's own cache), else it is refused."""
    n = int(cfg["n_chunks"])
    h = config_hash(cfg)
    if replace and folder is not None and (folder / MANIFEST).is_file():
        try:
            stale = _read_manifest(folder, FORMAT)["hash"] != h
        except SimgapError:
            stale = True
        if stale:
            shutil.rmtree(folder)
            if log:
                log(f"removed the per-run samples of another configuration in {str(folder)!r}")
    serial = isinstance(ex, SerialExecutor)
    job = {"hash": h, "config": cfg, "spec": spec, "options": o, "sim": sim if serial else None,
           "system": None if serial else portable_system(sim.system)}
    try:
        if folder is None:
            out = {}

            def keep(c, arrays):
                out[c] = arrays
                if on_chunk:
                    on_chunk(c, arrays)

            if on_start:
                on_start(set())
            finished = ex.map_chunks(fn, job, range(n), keep, stop)
        else:
            r = fill_store(folder, cfg, fn, job, ex, on_start=on_start, on_chunk=on_chunk, should_stop=stop,
                           fmt=FORMAT, what=f"per-run sampling ({cfg['phase']})")
            finished = r.finished
    finally:
        _CACHE.pop(h, None)          # the serial executor cached the caller's simulator here
    if not finished:
        raise SimgapError("interval-MDP sampling cancelled" + (f"; the finished chunks are kept in {str(folder)!r}: "
                                                               "run the same command again to resume" if folder else ""))
    if folder is None:
        return lambda c, names=names: out[c]
    return lambda c, names=names: read_chunk(folder, c, h, names)


def build_imdp(sim, spec, options: IMDPOptions, log=None, on_progress=None, executor=None,
               workers: Optional[int] = None, address: Optional[str] = None, store=None,
               should_stop=None, replace_other: bool = False) -> IMDP:
    """Sample ``sim`` and build the interval MDP of ``spec`` (:mod:`simgap.perrun.imdp`).

    The simulator work (Lipschitz secants, pilot and main runs) is cut into chunks, each drawing
    from its own seeded generator, and run by ``executor``: a name (``serial``, ``local``, ``ray``),
    an :class:`~simgap.executors.Executor`, or None for ``serial`` in this process with ``sim``
    itself (``local`` and ``ray`` rebuild the simulator from its config in their workers). With
    ``store`` (a folder) every finished chunk is kept, verified and resumed. The interval MDP does
    not depend on the executor, the number of workers or interruptions. A store of another
    configuration is refused, or with ``replace_other`` (``simgap run`` after the ``[perrun]``
    options changed) removed first.

    ``on_progress(done, total)``: after every chunk, in (cell, input) pairs of both passes (2 x pairs)."""
    t0 = time.perf_counter()
    s, o = sim.system, options
    lay = layout(s, spec, o)
    ex = executor if isinstance(executor, Executor) else make_executor(executor or "serial", workers, address)
    stop = as_stop_check(should_stop)
    folder = None if store is None else Path(store)
    with ex.session():          # one Ray start-up for both phases
        return _sample(sim, spec, o, lay, ex, stop, folder, log, on_progress, t0, replace_other)


def _sample(sim, spec, o, lay, ex, stop, folder, log, on_progress, t0, replace) -> IMDP:
    s = sim.system
    half = lay.grid.eta / 2
    shared = lay.share is not None
    if o.lipschitz is None:
        cfg = lipschitz_config(sim, spec, o, lay)
        get = _run_phase(cfg, secants_chunk, sim, spec, o, ex, folder and folder / "lipschitz", stop,
                         ("nominal", "residual") if shared else ("slope",), replace=replace, log=log)
        est = lipschitz_from_slopes(s, {j: get(c) for c, j in enumerate(cfg["dims"])}, residual=shared)
        how = est[-1]
        if shared:
            Ln, Lr = est[0], est[1]
        else:
            L = est[0]
    elif shared:
        Ln, Lr = np.broadcast_to(np.asarray(o.lipschitz, float), (2, s.n, s.n)).copy()
        how = "given"
    else:
        L, how = np.broadcast_to(np.asarray(o.lipschitz, float), (s.n, s.n)).copy(), "given"
    widening = {"Ln": Ln.tolist(), "Lr": Lr.tolist()} if shared else {"rho": (L @ half).tolist()}
    t_lip = time.perf_counter() - t0

    cfg = runs_config(sim, spec, o, lay, widening)
    P, S = lay.P, int(cfg["chunk_size"])
    bounds = lay.chunk_bounds(S)
    done = [0]

    def pairs_in(c):
        return int(bounds[c + 1] - bounds[c])

    def on_start(have):
        done[0] = sum(pairs_in(c) for c in have)
        if on_progress and have:
            on_progress(2 * done[0], 2 * P)

    def on_chunk(c, arrays):
        done[0] += pairs_in(c)
        if on_progress:
            on_progress(2 * done[0], 2 * P)

    if log:
        log(f"imdp: {lay.cells.size} live cells x {lay.M} inputs = {P} pairs in {cfg['n_chunks']} chunks of "
            f"{S} {cfg['chunk_unit']}s on executor {ex.name}" + (f" ({ex.workers} workers)" if ex.name != "serial" else "")
            + (f", kept in {str(folder)!r}" if folder else ""))
    get = _run_phase(cfg, runs_chunk, sim, spec, o, ex, folder and folder / "runs", stop, RUNS_ARRAYS,
                     on_start, on_chunk, replace=replace, log=log)
    t_runs = time.perf_counter() - t0 - t_lip
    return _assemble(sim, spec, o, lay, get, widening, L if not shared else None,
                     (Ln, Lr) if shared else None, how, cfg, t0, t_lip, t_runs, log)


def _assemble(sim, spec, o, lay, get, widening, L, LnLr, how, cfg, t0, t_lip, t_runs, log) -> IMDP:
    """The interval MDP in CSR order straight from the chunks' supports and counts, one chunk in memory at
    a time (two passes: row lengths, then the entries): the driver's peak is the interval MDP itself plus
    one chunk and one block of bounds. Rows in pair order, each row's successors by cell, then the sink:
    the same whichever executor computed the chunks, in whatever order."""
    s = sim.system
    C, M, P, cells = lay.C, lay.M, lay.P, lay.cells
    n_chunks = int(cfg["n_chunks"])
    succ = np.zeros(P, np.int64)
    single_seen, simulated = False, 0
    for c in range(n_chunks):
        part = get(c, ("key", "single_seen", "simulated"))
        p, k = np.unique(part["key"] // (C + 1), return_counts=True)
        succ[p] += k
        single_seen |= bool(part["single_seen"])
        simulated += int(part["simulated"])
    row_of = cells.repeat(M) * M + np.tile(np.arange(M), cells.size)          # pair -> row (increasing)
    length = np.zeros(C * M, np.int64)
    length[row_of] = succ + 1                                                # + the sink entry
    row_ptr = np.zeros(C * M + 1, np.int64)
    np.cumsum(length, out=row_ptr[1:])
    nnz = int(row_ptr[-1])
    col, k_lo, k_hi = np.empty(nnz, np.int32), np.empty(nnz, np.int32), np.empty(nnz, np.int32)
    for c in range(n_chunks):
        part = get(c)
        key = part["key"]
        p = key // (C + 1)
        first = np.searchsorted(p, p)                                        # keys sorted: pairs grouped
        pos = row_ptr[row_of[p]] + (np.arange(p.size) - first)
        col[pos], k_lo[pos], k_hi[pos] = key % (C + 1), part["n_in"], part["n_hit"]
        end = row_ptr[row_of[part["pairs"]] + 1] - 1
        col[end], k_lo[end], k_hi[end] = C, -1, part["n_sink"]
    alloc = Allocation.of(o.split).after_pilot(single_seen)     # a function of the pilot runs alone
    if log:
        levels = alloc.levels(float(o.beta), P, nnz - P)
        log(f"imdp: support {nnz - P} entries; {_bound_count(alloc, P, nnz - P)} one-sided bounds, levels "
            + ", ".join(f"{f} {v:.3g}" for f, v in levels.items()))
    meta = {"pilot_runs": int(o.pilot_runs), "lipschitz_how": how, "live_cells": int(cells.size), "seed": int(o.seed),
            "simulator": sim.config.to_dict(), "spec": spec.to_dict(),
            "seconds": {"lipschitz": t_lip, "runs": t_runs, "intervals": time.perf_counter() - t0 - t_lip - t_runs},
            "samples": simulated * int(o.hold),
            "sampling": {"chunks": int(cfg["n_chunks"]), "chunk_size": int(cfg["chunk_size"]),
                         "batch_runs": int(o.batch_runs), "config_hash": config_hash(cfg),
                         "streams": "per chunk: SeedSequence(seed, spawn_key=(phase, chunk)), phases 1 secants "
                                    "(chunk = dimension), 2 pilot, 3 main runs"}}
    half = lay.grid.eta / 2
    if LnLr is None:
        meta.update(lipschitz=L.tolist(), rho=widening["rho"],
                    assumption="per realization: the k-period trajectory map is L-Lipschitz (common random numbers)")
    else:
        Ln, Lr = LnLr
        x_anchor = lay.grid.points(lay.anchor)
        rho_max = half @ Ln.T + (np.abs(s.diff(lay.centers, x_anchor)).max(axis=0) + half) @ Lr.T
        meta.update(lipschitz={"nominal": Ln.tolist(), "residual": Lr.tolist()}, rho=rho_max.tolist(),
                    share=lay.share.tolist(), anchors=int(np.unique(lay.anchor).size),
                    assumption="per realization: the residual y_t(x, w) - ynom_t(x) of the k-period run is "
                               "Lr-Lipschitz and the nominal k-period map Ln-Lipschitz (coordinate-wise, common "
                               "random numbers); the runs of one anchor cell per block serve every cell of the "
                               "block, shifted by the nominal model and widened by Ln eta/2 + Lr (|x_c - x_s| + eta/2)")
    return assemble_csr(lay.grid, s.inputs, int(o.hold), lay.live, lay.target, row_ptr, col, k_lo, k_hi, alloc,
                        int(o.n_runs), o.beta, meta)

"""The per-run stage's cost model: simulator steps, interval entries, memory and time, projected
before any work and refused over the limits (:mod:`simgap.checks`) with the numbers."""

from __future__ import annotations

import os
from typing import Optional

import numpy as np

from ..checks import available_memory, check_memory, human_seconds
from ..errors import SimgapError
from ..fileio import human_bytes


def perrun_size(o: dict, system, rate_per_worker: Optional[float] = None, workers: int = 1,
                n_controllers: int = 3, local_workers: int = 0, sampling_rate: Optional[float] = None,
                entries_per_row: Optional[float] = None) -> dict:
    """Estimated work, peak memory and time of the per-run stage for checked ``[perrun]`` options ``o``.

    Grid: C = prod ceil((x_hi - x_lo) / eta) cells (invariant dimensions collapse to one class),
    M inputs. The interval MDP samples n_runs + pilot_runs runs of ``hold`` periods per (cell, input)
    (``sampling_steps``; the Lipschitz secants add 2 x 6000 runs of ``hold`` periods per dimension)
    and keeps about ``entries_per_row`` (measured by the caller; default min(n_runs, C, 32)) intervals
    per pair (``entries``, about 20 bytes each while they are assembled: counts, bounds, column,
    :mod:`simgap.perrun.sampling`); value iteration keeps a policy and a value
    per cell and abstract step (horizon / hold); validation rolls ``n_rollouts`` runs of ``horizon``
    periods out from ``n_states`` states per controller (``rollout_steps``). A simulator step is one
    period of one run (one ``sim.step`` row); ``rate_per_worker`` is steps per second of one worker.
    ``sampling_rate`` (default ``rate_per_worker``) is the interval-MDP sampling's own rate in steps
    per second of one worker, bookkeeping included (:func:`simgap.perrun.sampling.calibrate_sampling`).
    ``local_workers`` sampling processes on this machine each hold one batch of runs
    (``batch_runs`` x hold states with shared runs). ``cpu_hours`` is the whole stage at those rates.
    """
    eta = np.broadcast_to(np.asarray(o["eta"], dtype=float), (system.n,))
    counts = np.ceil((system.x_hi - system.x_lo) / eta).astype(float)
    inv = [system.state_names.index(v) for v in (o.get("invariant") or [])]
    C = float(np.prod(counts))
    C_sampled = float(np.prod(np.delete(counts, inv))) if inv else C
    M = float(len(system.inputs))
    hold, horizon = int(o["hold"]), int(o["horizon"])
    steps = max(1, -(-horizon // hold))
    # successors per pair: a run lands in a few cells (not all n_runs apart), unless measured
    S = float(entries_per_row) if entries_per_row else min(float(o["n_runs"]), C, 32.0)
    entries = C * M * S
    batch = float(o.get("batch_runs", 1 << 19))
    worker = batch * (hold * system.n + 3 * system.n + system.inputs.shape[1]) * 8 * 2
    memory = entries * 20 + C * steps * 12 + float(o["n_rollouts"]) * (horizon + 1) * system.n * 8 * 2 \
        + max(0, int(local_workers)) * worker
    sampling = C_sampled * M * (float(o["n_runs"]) + float(o["pilot_runs"])) * hold + system.n * 12000.0 * hold
    rollouts = n_controllers * float(o["n_states"]) * float(o["n_rollouts"]) * horizon
    runs = sampling + rollouts
    cpu = sampling / (sampling_rate or rate_per_worker) + rollouts / rate_per_worker if rate_per_worker else None
    return {"cells": C, "inputs": M, "memory": memory, "runs": runs, "entries": entries,
            "seconds": cpu / max(1, workers) if cpu is not None else None,
            "sampling_steps": sampling, "rollout_steps": rollouts, "cpu_hours": cpu / 3600 if cpu is not None else None,
            "sampling_rate": sampling_rate or rate_per_worker, "rate": rate_per_worker,
            "entries_per_row": S, "entries_measured": bool(entries_per_row)}


def perrun_cost_text(e: dict, rate_per_worker: Optional[float], workers: int) -> str:
    """The projected cost of the per-run stage (:func:`perrun_size`) as one line for the log."""
    at = (f"{e['cpu_hours']:.3g} CPU-hours at {e['sampling_rate']:.3g} sampling / {rate_per_worker:.3g} rollout "
          f"steps/s per worker (calibrated here), about {human_seconds(e['seconds'])} on {workers} worker(s)"
          ) if rate_per_worker else "no rate measured"
    roll = f" + {e['rollout_steps']:.3g} for the validation rollouts" if e["rollout_steps"] else ""
    per = f"{e['entries_per_row']:.3g} per row, " + ("measured on a few pairs" if e["entries_measured"] else "guessed")
    return (f"per-run stage projected: {e['sampling_steps']:.3g} simulator steps to sample the interval MDP{roll}; "
            f"{at}; about {e['entries']:.3g} interval entries ({per}), peak memory about "
            f"{human_bytes(e['memory'])} ({human_bytes(available_memory())} available)")


#: the per-run stage estimated to take longer than this is refused (override: SIMGAP_NO_SIZE_CHECK=1)
MAX_PERRUN_SECONDS = 6 * 3600.0


def check_perrun(o: dict, system, rate_per_worker: Optional[float] = None, workers: int = 1,
                 local_workers: int = 0, sampling_rate: Optional[float] = None, n_controllers: int = 3,
                 entries_per_row: Optional[float] = None) -> dict:
    """Refuse a per-run stage that cannot fit in memory or would take over 6 hours, with the numbers
    (:func:`perrun_size`; the message carries the projection of :func:`perrun_cost_text`).
    ``SIMGAP_NO_SIZE_CHECK=1`` skips the time limit for users who know (never the memory one)."""
    e = perrun_size(o, system, rate_per_worker, workers, n_controllers, local_workers=local_workers,
                    sampling_rate=sampling_rate, entries_per_row=entries_per_row)
    what = (f"the per-run stage ({e['cells']:,.0f} cells x {e['inputs']:,.0f} inputs, n_runs {int(o['n_runs']):,}, "
            f"hold {int(o['hold'])}, horizon {int(o['horizon'])}, {int(o['n_states'])} states x "
            f"{int(o['n_rollouts']):,} rollouts: {e['runs']:.3g} simulator steps, about {e['entries']:.3g} interval "
            f"entries" + (f", {e['cpu_hours']:.3g} CPU-hours" if e["cpu_hours"] is not None else "") + ")")
    hint = "use a coarser [perrun] eta, fewer n_runs / n_rollouts / n_states or a shorter horizon"
    check_memory(e["memory"], what, hint + (" or fewer --workers" if local_workers > 1 else ""))
    if e["seconds"] is not None and e["seconds"] > MAX_PERRUN_SECONDS and not os.environ.get("SIMGAP_NO_SIZE_CHECK"):
        raise SimgapError(f"{what} would take about {human_seconds(e['seconds'])} on {workers} worker(s); {hint} "
                          "(more workers: --executor ray --address HOST:PORT; or set SIMGAP_NO_SIZE_CHECK=1 to run "
                          "it anyway)")
    return e


def calibrated_rate(sim_config, system) -> Optional[float]:
    """Simulator runs per second of one worker, measured in about 0.5 s (as collection does)."""
    from ..cover import calibrate_rate
    from ..simulators import make_simulator
    with make_simulator(sim_config, system) as sim:
        return calibrate_rate(sim, n_runs=65536, budget=0.3)  # per-run batches are large

"""Boundary checks shared by the commands: output paths, counts, network addresses, sizes.

Every command checks what it will write and how big the work is *before* doing any work, so
bad input ends with a :class:`~simgap.errors.SimgapError` that names the problem (and, for
sizes, the estimated numbers) instead of a traceback, a hang or a half-written file.
"""

from __future__ import annotations

import argparse
import ipaddress
import math
import os
import shutil
import socket
import tempfile
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .errors import SimgapError
from .fileio import human_bytes  # noqa: F401  (in fileio, whose write errors use it: fileio imports no checks)
from .memory import available_memory, check_memory  # noqa: F401  (light: stages import them directly)

#: work estimated to take longer than this is refused (the numbers are printed)
MAX_SECONDS = 365 * 24 * 3600.0
#: floating-point operations of a certify rank check + LP above which it is refused (~hours here)
MAX_CERTIFY_FLOPS = 2e12


# ----------------------------------------------------------------------------------------
# Output paths
# ----------------------------------------------------------------------------------------

def _probe_writable(folder: Path, what: str, path: Path) -> None:
    """Create and delete a temporary file in ``folder``: the only honest writability test
    (permissions, read-only mounts, root)."""
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".simgap-write-check.", suffix=".tmp")
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise SimgapError(f"{what} {str(path)!r}: cannot write in folder {str(folder)!r} "
                          f"({e.strerror or e})") from None


def output_file(path, what: str = "--out") -> Path:
    """Check that a result file can be written at ``path``: not a directory, its folder exists
    and is writable. Nothing is created. Returns ``Path(path)``."""
    p = Path(path)
    if p.is_dir():
        raise SimgapError(f"{what} {str(p)!r} is a folder; give a file name (e.g. {str(p / 'result')!r}"
                          " plus the extension)")
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.exists():
        raise SimgapError(f"{what} {str(p)!r}: folder {str(folder)!r} does not exist; create it first (mkdir -p "
                          f"{str(folder)!r}) or write into an existing folder")
    if not folder.is_dir():
        raise SimgapError(f"{what} {str(p)!r}: {str(folder)!r} is not a folder")
    _probe_writable(folder, what, p)
    return p


def output_dir(path, what: str = "--out") -> Path:
    """Check that a result folder can be used at ``path``: a writable folder, or a path whose
    nearest existing ancestor is a writable folder (it is created later). Nothing is created."""
    p = Path(path)
    if p.exists():
        if not p.is_dir():
            raise SimgapError(f"{what} {str(p)!r} exists and is not a folder")
        _probe_writable(p, what, p)
        return p
    anc = p.absolute().parent
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise SimgapError(f"{what} {str(p)!r}: {str(anc)!r} is a file, not a folder")
    _probe_writable(anc, what, p)
    return p


def check_outputs(args) -> None:
    """Check every output a parsed command declares (``set_defaults(outputs=..., output_dirs=...)``):
    writable (:func:`output_file`, :func:`output_dir`) and not over any input (:func:`not_over_inputs`)."""
    outs = []
    for name in getattr(args, "outputs", ()):
        v = getattr(args, name, None)
        if v is not None:
            outs.append(("--" + name.replace("_", "-"), output_file(v, "--" + name.replace("_", "-"))))
    for name in getattr(args, "output_dirs", ()):
        v = getattr(args, name, None)
        if v is not None:
            outs.append(("--" + name.replace("_", "-"), output_dir(v, "--" + name.replace("_", "-"))))
    not_over_inputs(outs, _input_paths(args))


def _input_paths(args) -> list:
    """(option, path) of every other argument value that names an existing file or folder: a
    command's inputs, found without each command listing them (a new option is covered too)."""
    skip = set(getattr(args, "outputs", ())) | set(getattr(args, "output_dirs", ())) | {"func", "command"}
    found = []
    for key, value in vars(args).items():
        if key in skip:
            continue
        for v in value if isinstance(value, (list, tuple)) else [value]:
            if isinstance(v, (str, os.PathLike)) and str(v) and os.path.lexists(v):
                found.append(("--" + key.replace("_", "-"), Path(v)))
    return found


def _same_or_inside(out: Path, inp: Path) -> bool:
    """True if ``out`` is ``inp`` (also through symlinks or hard links) or lies inside folder ``inp``."""
    o, i = out.resolve(), inp.resolve()
    if o == i or (i.is_dir() and i in o.parents):
        return True
    try:
        return out.exists() and os.path.samefile(out, inp)
    except OSError:
        return False


def not_over_inputs(outputs, inputs) -> None:
    """Refuse an output that is, or lies inside, an input: writing it would destroy what the
    command reads (e.g. ``certify STORE --out STORE/manifest.json``). Both are (option, path) lists."""
    for what, out in outputs:
        for src, inp in inputs:
            if _same_or_inside(Path(out), Path(inp)):
                where = "is" if Path(out).resolve() == Path(inp).resolve() or not Path(inp).is_dir() else "is inside"
                raise SimgapError(f"{what} {str(out)!r} {where} the input {str(inp)!r} ({src}): writing it would "
                                  "destroy the input; choose another output path")


# ----------------------------------------------------------------------------------------
# Command-line value types (argparse ``type=``): errors become "argument --x: message"
# ----------------------------------------------------------------------------------------

def _integer(text: str) -> int:
    """An integer from ``"12"`` or an integral float such as ``"1e6"``."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not math.isfinite(v) or v != int(v):
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}")
    return int(v)


def count(lo: int = 1):
    """argparse type: an integer >= ``lo`` (``1e6`` notation accepted)."""
    def parse(text: str) -> int:
        v = _integer(text)
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lo}, got {text!r}")
        return v
    parse.__name__ = f"integer >= {lo}"
    return parse


def port(text: str) -> int:
    """argparse type: a TCP port 0..65535 (0 = any free port)."""
    v = _integer(text)
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"port must be 0..65535, got {text!r}")
    return v


def host(text: str) -> str:
    """argparse type: an IP address to bind (or ``localhost``). Names are not resolved: no DNS."""
    if text == "localhost":
        return text
    try:
        return str(ipaddress.ip_address(text))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"not an IP address: {text!r} (e.g. 127.0.0.1 for this machine only, 0.0.0.0 for every "
            "interface, or localhost)") from None


def check_bindable(host_: str, port_: int = 0) -> None:
    """Bind and release ``(host, port)`` once (port 0: any), so a server that cannot start says
    why at once (e.g. an address that is not this machine's)."""
    family = socket.AF_INET6 if ":" in host_ else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host_, port_))
        except OSError as e:
            where = f"{host_}:{port_}" if port_ else host_
            raise SimgapError(f"cannot listen on {where}: {e.strerror or e}") from None


def reachable(address: str, timeout: float = 5.0, what: str = "server") -> None:
    """Open and close a TCP connection to ``host:port`` (``ray://`` prefix allowed) within
    ``timeout`` seconds, else SimgapError; ``auto`` is not checked."""
    a = address.strip()
    if a in ("", "auto", "local"):
        return
    for prefix in ("ray://", "http://", "https://"):
        if a.startswith(prefix):
            a = a[len(prefix):]
    h, sep, p = a.rpartition(":")
    if not sep or not h:
        raise SimgapError(f"{what} address {address!r}: expected HOST:PORT, e.g. 127.0.0.1:6379")
    try:
        pnum = int(p)
    except ValueError:
        raise SimgapError(f"{what} address {address!r}: port {p!r} is not a number") from None
    if not 0 < pnum <= 65535:
        raise SimgapError(f"{what} address {address!r}: port must be 1..65535")
    try:
        with socket.create_connection((h.strip("[]"), pnum), timeout=timeout):
            pass
    except OSError as e:
        raise SimgapError(f"cannot reach the {what} at {address} within {timeout:g} s ({e.strerror or e}); "
                          "is it running?") from None


# ----------------------------------------------------------------------------------------
# Sizes
# ----------------------------------------------------------------------------------------

def human_seconds(s: float) -> str:
    for unit, d in (("years", 365 * 86400.0), ("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if s >= d:
            return f"{s / d:.3g} {unit}"
    return f"{s:.3g} s"


def check_disk(need: float, folder, what: str, hint: str = "") -> None:
    """Refuse writing an estimated ``need`` bytes below ``folder`` (nearest existing ancestor)."""
    p = Path(folder).absolute()
    while not p.exists():
        p = p.parent
    free = shutil.disk_usage(p).free
    if need > free:
        raise SimgapError(f"{what} needs about {human_bytes(need)} of disk in {str(p)!r}, {human_bytes(free)} is free"
                          + (f"; {hint}" if hint else ""))


def check_seconds(seconds: Optional[float], what: str, hint: str = "") -> None:
    if seconds is not None and seconds > MAX_SECONDS:
        raise SimgapError(f"{what} would take about {human_seconds(seconds)}" + (f"; {hint}" if hint else ""))


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


def basis_terms(n_vars: int, degree: int) -> int:
    """Number of monomials of total degree <= ``degree`` in ``n_vars`` variables: C(v + d, d)."""
    return math.comb(n_vars + degree, degree) if degree >= 0 else 0


def check_basis(n_pairs: int, n_vars: int, degrees: Sequence[int], extra_terms: int = 0,
                what: str = "certify") -> None:
    """Refuse a certify basis whose design matrices or LP cannot be handled.

    Per state dimension the design matrix is K x P float64 (P = C(v + d, d) monomials plus the
    user's terms); the rank check and the linear program cost about K P^2 flops each. A basis
    with more terms than data pairs cannot have unique coefficients.
    """
    sizes = [basis_terms(n_vars, int(d)) + extra_terms for d in degrees]
    P = max(sizes)
    deg = max(int(d) for d in degrees)
    head = f"{what}: degree {deg} gives {P:,} basis terms per dimension"
    if P > n_pairs:
        raise SimgapError(f"{head} but the data have only {n_pairs:,} (x_r, u) pairs, so the coefficients "
                          "cannot be unique; use a smaller degree (the paper uses 1 or 2)")
    check_memory(8.0 * n_pairs * sum(sizes) * 2, f"{head}; with {n_pairs:,} pairs the design matrices",
                 "use a smaller degree")
    flops = 2.0 * n_pairs * float(P) ** 2 * len(sizes)
    if flops > MAX_CERTIFY_FLOPS:
        raise SimgapError(f"{head}; with {n_pairs:,} pairs the rank check and linear program need about "
                          f"{flops:.2g} floating-point operations (hours on this machine); use a smaller "
                          "degree (the paper uses 1 or 2) or name the terms you need")


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
    from .cover import calibrate_rate
    from .simulators import make_simulator
    with make_simulator(sim_config, system) as sim:
        return calibrate_rate(sim, n_runs=65536, budget=0.3)  # per-run batches are large


#: a single command's simulator work estimated above this is refused (override: SIMGAP_NO_SIZE_CHECK=1)
MAX_COMMAND_SECONDS = 6 * 3600.0


def check_sim_work(runs: float, memory: float, what: str, hint: str, rate_per_worker: Optional[float] = None,
                   workers: int = 1) -> None:
    """Refuse ``runs`` simulator periods that need more than the available memory, or (at the
    calibrated ``rate_per_worker``) more than :data:`MAX_COMMAND_SECONDS`, naming the numbers."""
    check_memory(memory, what, hint)
    if rate_per_worker and not os.environ.get("SIMGAP_NO_SIZE_CHECK"):
        secs = runs / (rate_per_worker * max(1, workers))
        if secs > MAX_COMMAND_SECONDS:
            raise SimgapError(f"{what} ({runs:.3g} simulator periods) would take about {human_seconds(secs)}; {hint} "
                              "(or set SIMGAP_NO_SIZE_CHECK=1 to run it anyway)")

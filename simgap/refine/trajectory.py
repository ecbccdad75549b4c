"""Measured trajectories -> transition data, when only positions are measured.

Given uniformly sampled time stamps t_k (period tau), measured positions q_k (T, p) and inputs
u_k (T, m), the velocity states are estimated as

1. q_f = zero-phase low-pass of q: Butterworth of order ``order`` and cutoff ``cutoff_hz``
   applied forwards and backwards (``scipy.signal.filtfilt``: no phase lag, effective order
   2 * order);
2. v_k = (q_f[k+1] - q_f[k-1]) / (2 tau) (central differences);
3. the first and last ``trim`` samples are dropped, where the filter's start-up transient and
   the one-sided differences live (default: max(20, ceil(2 fs / cutoff)) samples, i.e. two
   periods of the cutoff frequency);
4. by default the input is filtered with the same zero-phase filter (``filter_input``): the
   velocity update v_{k+1} - v_k then sees the filtered acceleration, and a dynamics
   M a = F(u, v) that is linear in u holds for the filtered signals exactly and for
   friction-type terms up to the (small) filtering error of smooth motions. Without it, the
   high-frequency part of a closed-loop input (the controller reacting to encoder
   quantization) appears in the residual as noise that no term can explain.

Transitions are x_k = (q_f[k], v_k), u_k, x_next = x_{k+1}: states ordered positions first,
then velocities (the order of the built-in ``emps`` system: q, qd).

Presets know the variable names of known records, e.g. ``emps`` (t, qm, vir in
``DATA_EMPS.mat``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import SimgapError
from .data import Transitions, make_transitions


@dataclass(frozen=True)
class TrajectoryPreset:
    """Variable names of a known record and the system it belongs to."""

    time: str
    positions: tuple
    inputs: tuple
    system: str
    default_cutoff: float


PRESETS = {
    # EMPS benchmark (DATA_EMPS.mat): t [s], qm motor position on the load side [m], vir [V]
    "emps": TrajectoryPreset(time="t", positions=("qm",), inputs=("vir",), system="emps",
                             default_cutoff=20.0),
}


def read_timeseries(path: str | Path, names: Sequence[str]) -> dict:
    """Read named 1-D variables from a .mat (MATLAB v5, scipy.io.loadmat), .npz or .csv file."""
    path = Path(path)
    from ..file_guard import regular_file
    regular_file(path, "trajectory file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".mat":
            import scipy.io
            raw = scipy.io.loadmat(str(path))
            data = {k: v for k, v in raw.items() if not k.startswith("__")}
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        elif suffix == ".csv":
            with open(path, newline="") as fh:
                header = [h.strip() for h in fh.readline().strip().split(",")]
            arr = np.atleast_2d(np.genfromtxt(path, delimiter=",", skip_header=1, dtype=float))
            if arr.shape[1] != len(header):
                raise SimgapError(f"{path}: {len(header)} header names but {arr.shape[1]} columns")
            data = {h: arr[:, i] for i, h in enumerate(header)}
        else:
            raise SimgapError(f"{path}: unknown trajectory format {suffix!r}; use .mat, .npz or .csv")
    except SimgapError:
        raise
    except Exception as e:  # scipy/numpy raise many error types for corrupt files
        raise SimgapError(f"{path}: unreadable {suffix} file: {e}") from None
    missing = [n for n in names if n not in data]
    if missing:
        raise SimgapError(f"{path}: missing variable(s) {missing}; the file holds: "
                          f"{', '.join(sorted(data))}")
    out = {}
    for n in names:
        v = np.asarray(data[n])
        if v.dtype.kind not in "fiu" or v.size == 0:
            raise SimgapError(f"{path}: variable {n!r} is not numeric")
        if v.ndim > 1 and sorted(v.shape)[:-1] != [1] * (v.ndim - 1):
            raise SimgapError(f"{path}: variable {n!r} has shape {v.shape}, expected a vector")
        out[n] = v.astype(float).reshape(-1)
    return out


def check_uniform_time(t: np.ndarray, rtol: float = 1e-3) -> float:
    """Sampling period tau of strictly increasing, uniform time stamps (deviation <= rtol tau)."""
    t = np.asarray(t, dtype=float).reshape(-1)
    if t.size < 3:
        raise SimgapError(f"time stamps: need at least 3, got {t.size}")
    if not np.all(np.isfinite(t)):
        raise SimgapError("time stamps contain NaN or inf")
    dt = np.diff(t)
    tau = float(np.median(dt))
    if tau <= 0 or np.any(dt <= 0):
        raise SimgapError("time stamps must be strictly increasing")
    dev = float(np.max(np.abs(dt - tau)))
    if dev > rtol * tau:
        k = int(np.argmax(np.abs(dt - tau)))
        raise SimgapError(f"non-uniform time stamps: step {k} is {dt[k]:g} s against a median of {tau:g} s "
                          f"(tolerance {rtol:g} relative); resample the record first")
    # the mean step is robust to clock jitter (EMPS: +-2e-8 s around 1 ms)
    return float((t[-1] - t[0]) / (t.size - 1))


def backward_transitions(t, positions, inputs, source: str = "", meta: Optional[dict] = None) -> Transitions:
    """Transitions with causal velocities, for fast lightly damped records: no filter, no trim.

    v_k = (q_k - q_{k-1}) / tau (backward differences of the raw positions), x_k = (q_k, v_k) for
    k = 1 .. T-2, x_next = x_{k+1}, u_k raw. A model whose position update uses the new velocity
    (semi-implicit Euler, q+ = q + tau v+) reproduces q exactly through this state; nothing is
    non-causal, so no filter phase is misread as input delays (the zero-phase path of
    :func:`trajectory_to_transitions` diverges on the Silverbox with an explicit-Euler model and its
    velocity reads as delays). Differentiation noise is not filtered.
    """
    t = np.asarray(t, dtype=float).reshape(-1)
    q = np.asarray(positions, dtype=float)
    u = np.asarray(inputs, dtype=float)
    q = q[:, None] if q.ndim == 1 else q
    u = u[:, None] if u.ndim == 1 else u
    if q.shape[0] != t.size or u.shape[0] != t.size:
        raise SimgapError(f"trajectory: {t.size} time stamps but {q.shape[0]} position and {u.shape[0]} input samples")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(u))):
        raise SimgapError("trajectory: positions or inputs contain NaN or inf")
    if t.size < 4:
        raise SimgapError(f"record too short: {t.size} samples")
    tau = check_uniform_time(t)
    v = np.vstack([np.full((1, q.shape[1]), np.nan), np.diff(q, axis=0) / tau])
    x = np.concatenate([q, v], axis=1)
    k = np.arange(1, t.size - 1)
    info = {"kind": "trajectory", "velocity": "backward differences", "fs_hz": 1.0 / tau,
            "samples_in": int(t.size)}
    info.update(meta or {})
    return make_transitions(x[k], u[k], x[k + 1], tau, t[k], source=source, meta=info)


def trajectory_to_transitions(t, positions, inputs, cutoff_hz: float, order: int = 4,
                              trim: Optional[int] = None, filter_input: bool = True,
                              source: str = "", meta: Optional[dict] = None) -> Transitions:
    """Transition data (x = (q, v), u, x_next) from a measured trajectory (module docstring).

    Parameters
    ----------
    t : (T,) time stamps [s], uniform.
    positions : (T,) or (T, p) measured positions.
    inputs : (T,) or (T, m) inputs.
    cutoff_hz : low-pass cutoff [Hz], 0 < cutoff < Nyquist = fs / 2.
    order : Butterworth order (applied twice by filtfilt).
    trim : samples dropped at each edge (default max(20, ceil(2 fs / cutoff))).
    filter_input : filter the inputs with the same zero-phase filter.
    """
    from scipy.signal import butter, filtfilt

    t = np.asarray(t, dtype=float).reshape(-1)
    q = np.asarray(positions, dtype=float)
    u = np.asarray(inputs, dtype=float)
    q = q[:, None] if q.ndim == 1 else q
    u = u[:, None] if u.ndim == 1 else u
    T = t.size
    if q.shape[0] != T or u.shape[0] != T:
        raise SimgapError(f"trajectory: {T} time stamps but {q.shape[0]} position and {u.shape[0]} input samples")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(u))):
        raise SimgapError("trajectory: positions or inputs contain NaN or inf")
    tau = check_uniform_time(t)
    fs = 1.0 / tau
    nyq = fs / 2.0
    if not (np.isfinite(cutoff_hz) and 0 < cutoff_hz < nyq):
        raise SimgapError(f"cutoff {cutoff_hz:g} Hz must be in (0, Nyquist = {nyq:g} Hz) for sampling "
                          f"at {fs:g} Hz")
    if int(order) != order or not 1 <= order <= 10:
        raise SimgapError(f"filter order must be an integer in 1..10, got {order}")
    if trim is None:
        trim = max(20, int(math.ceil(2.0 * fs / cutoff_hz)))
    if trim < 1:
        raise SimgapError(f"trim must be >= 1 sample, got {trim}")
    b, a = butter(int(order), cutoff_hz / nyq)
    padlen = 3 * max(len(a), len(b))
    min_len = 2 * trim + max(padlen, 1) + 100
    if T < min_len:
        raise SimgapError(f"record too short: {T} samples; need at least {min_len} for cutoff {cutoff_hz:g} Hz "
                          f"(2 x {trim} trimmed edge samples + 100 transitions)")
    # odd extension over 3 trim lengths: scipy's default (3 * filter length) leaves an edge
    # transient that outlives the trim (0.2 % velocity error at 20 Hz); this one does not
    pad = min(T - 1, 3 * trim)
    qf = filtfilt(b, a, q, axis=0, padlen=pad)
    uf = filtfilt(b, a, u, axis=0, padlen=pad) if filter_input else u
    v = np.gradient(qf, tau, axis=0)              # central differences inside
    x = np.concatenate([qf, v], axis=1)
    k = np.arange(trim, T - trim - 1)
    info = {"kind": "trajectory", "cutoff_hz": float(cutoff_hz), "order": int(order), "trim": int(trim),
            "filter_input": bool(filter_input), "fs_hz": fs, "samples_in": int(T)}
    info.update(meta or {})
    return make_transitions(x[k], uf[k], x[k + 1], tau, t[k], source=source, meta=info)


def from_trajectory_file(path: str | Path, preset: Optional[str] = None, time: Optional[str] = None,
                         positions: Optional[Sequence[str]] = None, inputs: Optional[Sequence[str]] = None,
                         cutoff_hz: Optional[float] = None, order: int = 4, trim: Optional[int] = None,
                         filter_input: bool = True) -> Transitions:
    """Read a trajectory file (with a preset or explicit variable names) and convert it."""
    p = None
    if preset is not None:
        if preset not in PRESETS:
            raise SimgapError(f"unknown preset {preset!r}; known: {', '.join(sorted(PRESETS))}")
        p = PRESETS[preset]
    time = time or (p.time if p else None)
    positions = list(positions or (p.positions if p else []))
    inputs = list(inputs or (p.inputs if p else []))
    if not time or not positions or not inputs:
        raise SimgapError("name the time, position and input variables (--time, --position, --input) "
                          "or use a --preset")
    if cutoff_hz is None:
        if p is None:
            raise SimgapError("give a low-pass --cutoff in Hz")
        cutoff_hz = p.default_cutoff
    d = read_timeseries(path, [time] + positions + inputs)
    q = np.stack([d[n] for n in positions], axis=1)
    u = np.stack([d[n] for n in inputs], axis=1)
    meta = {"file": str(path), "preset": preset, "time": time, "positions": positions, "inputs": inputs,
            "system": p.system if p else None}
    return trajectory_to_transitions(d[time], q, u, cutoff_hz, order=order, trim=trim,
                                     filter_input=filter_input, source=str(path), meta=meta)

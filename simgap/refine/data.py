"""Transition data for the refinement loop: K samples (x_k, u_k, x_next_k) taken tau apart.

Accepted inputs (see :func:`load_transitions`):

* ``.npz`` with arrays ``x`` (K,n), ``u`` (K,m), ``x_next`` (K,n) and scalar ``tau`` [s];
  optional ``t`` (K,) time stamps [s] and ``episode`` (K,) integer episode ids. When ``t`` is
  present the rows are a time series and held-out data are contiguous time segments
  (neighbouring samples are correlated). Several episodes whose clocks each start at 0 are kept
  apart (:func:`time_order`): by ``episode`` when given, otherwise as the runs of rows in file
  order along which ``t`` increases.
* ``.csv`` (comma separated, one header line) or ``.parquet`` with named columns: for each
  state ``i = 1..n`` a column ``x{i}`` (or the system's state name, e.g. ``theta``) and
  ``x{i}_next`` (or ``theta_next``), for each input ``u{j}`` (or its name, e.g. ``torque``),
  a column ``tau`` (constant) and optionally ``t`` and ``episode``.
* A collected simgap data set (``.npz`` written by :meth:`simgap.dataset.Dataset.save_npz` or a
  store directory): one transition per (x_r, u) row with x_next = the empirical mean of the
  N1hat simulator runs, tau = the system's sampling time. Rows are independent.

Rows with NaN/inf are counted; they are refused unless ``drop_nonfinite=True``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import BAD_FILE_ERRORS, SimgapError
from ..systems import System


@dataclass
class Transitions:
    """Transition samples x_next ~ fhat(x, u) after tau seconds.

    Attributes
    ----------
    x, x_next : (K, n) arrays
    u : (K, m) array
    tau : float
        Time between x and x_next [s].
    t : (K,) array or None
        Time stamps [s] for a time series (contiguous hold-out), None for independent rows.
    episode : (K,) int array or None
        Episode id of each row (time series of several episodes); None: inferred by
        :func:`time_order`.
    source : str
        Where the data came from (file name, "dataset", ...).
    n_dropped : int
        Rows removed because they held NaN/inf (only with ``drop_nonfinite``).
    meta : dict
        Free-form provenance (e.g. the trajectory conversion settings).
    se : (K, n) array or None
        Standard error of each x_next (collected data: sqrt(var / N1hat) of the runs' mean); the
        selection then weights row k of state i by 1 / se_ki (weighted least squares), so pairs
        whose runs scatter widely (a slipping robot at speed) count as little as they tell.
    """

    x: np.ndarray
    u: np.ndarray
    x_next: np.ndarray
    tau: float
    t: Optional[np.ndarray] = None
    source: str = ""
    n_dropped: int = 0
    meta: dict = field(default_factory=dict)
    episode: Optional[np.ndarray] = None
    se: Optional[np.ndarray] = None

    @property
    def K(self) -> int:
        return self.x.shape[0]

    @property
    def is_time_series(self) -> bool:
        return self.t is not None

    def save_npz(self, path: str | Path) -> Path:
        """Write ``x``, ``u``, ``x_next``, ``tau`` (and ``t``, ``meta`` as JSON) atomically."""
        from .. import fileio
        arrays = {"x": self.x, "u": self.u, "x_next": self.x_next, "tau": np.float64(self.tau),
                  "meta": np.array(json.dumps(self.meta))}
        if self.t is not None:
            arrays["t"] = self.t
        if self.episode is not None:
            arrays["episode"] = self.episode
        return fileio.savez(path, **arrays)


def episodes(data: Transitions) -> Optional[np.ndarray]:
    """Episode id (K,) of each row of a time series (None for independent rows).

    ``data.episode`` when given. Otherwise one clock is assumed unless the time stamps repeat:
    rows in file order with non-decreasing ``t``, or (shuffled rows) ``t`` without repeats, are one
    episode; with repeated time stamps (several episodes whose clocks each start at 0) an episode is
    a run of rows in file order along which ``t`` increases, and a new one starts where it does not.
    """
    if data.t is None:
        return None
    if data.episode is not None:
        return np.asarray(data.episode)
    t = data.t
    dt = np.diff(t)
    if np.all(dt >= 0) or np.unique(t).size == t.size:
        return np.zeros(t.size, dtype=np.int64)
    return np.concatenate([[0], np.cumsum(dt <= 0)]).astype(np.int64)


def time_order(data: Transitions) -> Optional[np.ndarray]:
    """Row indices in time order, episode by episode (:func:`episodes`); None for independent rows.

    Every function that looks along time (history, contiguous hold-out, multi-step predictions,
    time-chunked noise floor) walks the rows in this order, so rows of different episodes with the
    same time stamps never become each other's neighbours.
    """
    ep = episodes(data)
    if ep is None:
        return None
    return np.lexsort((data.t, ep))


def _continues(data: Transitions, order: np.ndarray) -> np.ndarray:
    """cont (K,) over the rows in ``order``: row j continues the trajectory of row j - 1 (x_next of the
    earlier row is the later row's x, the time step is tau, the same episode)."""
    ep = episodes(data)[order]
    x, xn, t = data.x[order], data.x_next[order], data.t[order]
    cont = np.zeros(data.K, dtype=bool)
    cont[1:] = np.all(np.isclose(xn[:-1], x[1:], rtol=0, atol=1e-9 * (1 + np.abs(x[1:]))), axis=1) \
        & np.isclose(np.diff(t), data.tau, rtol=1e-3, atol=0) & (ep[1:] == ep[:-1])
    return cont


def lagged_inputs(data: Transitions, periods) -> np.ndarray:
    """Inputs through first-order lags: (K, len(periods) m), column g m + j for lag periods[g], input j.

    a_k = a_{k-1} + (u_{k-1} - a_{k-1}) / L along time order (:func:`time_order`), restarted at
    a = u where a row does not continue the previous one: the exact discretisation of
    T_a a' = u - a with a held input, 1 / L = 1 - exp(-tau / T_a). Time series only.
    """
    order = time_order(data)
    cont = _continues(data, order)
    u = data.u[order]
    from scipy.signal import lfilter, lfilter_zi
    alpha = 1.0 / np.repeat(np.asarray(periods, dtype=float), u.shape[1])
    U = np.tile(u, (1, len(periods)))
    A = np.empty_like(U)
    starts = np.flatnonzero(~cont)
    ends = np.r_[starts[1:], data.K]
    for c, a in enumerate(alpha):             # per column and continuous segment, the recursion in C
        b, den = [0.0, a], [1.0, a - 1.0]
        zi = lfilter_zi(b, den)
        for s0, s1 in zip(starts, ends):
            A[s0:s1, c] = lfilter(b, den, U[s0:s1, c], zi=zi * U[s0, c])[0]
    out = np.empty_like(A)
    out[order] = A
    return out


def history(data: Transitions, lags: int) -> tuple:
    """Lagged values of a time series: (hist (K, lags (n + m)), valid (K,) bool).

    Row k's history is [x_{k-1}, u_{k-1}, x_{k-2}, u_{k-2}, ...]: the rows before it in time order
    (:func:`time_order`, episodes apart), as long as they continue one trajectory (x_next of the
    earlier row is the later row's x, and the time step is tau). ``valid`` is False where fewer than
    ``lags`` such rows exist (the start of each record segment); those rows hold NaN. Independent
    rows have no history.
    """
    K, w = data.K, data.x.shape[1] + data.u.shape[1]
    hist = np.full((K, lags * w), np.nan)
    valid = np.zeros(K, dtype=bool)
    if data.t is None or lags < 1:
        return hist, valid if lags >= 1 else np.ones(K, dtype=bool)
    order = time_order(data)
    cont = _continues(data, order)
    x, u = data.x[order], data.u[order]
    z = np.concatenate([x, u], axis=1)
    idx = np.arange(K)
    run = idx - np.maximum.accumulate(np.where(cont, 0, idx))     # continuing rows before j
    H = np.full((K, lags * w), np.nan)
    for lag in range(1, lags + 1):
        H[lag:, (lag - 1) * w: lag * w] = z[:-lag]
    ok = run >= lags
    H[~ok] = np.nan
    hist[order], valid[order] = H, ok
    return hist, valid


def subset(data: Transitions, rows: np.ndarray) -> Transitions:
    """The transitions of ``rows`` (a boolean mask or indices), provenance kept."""
    ep = episodes(data)            # made explicit: a subset may no longer show where episodes start
    return Transitions(x=data.x[rows], u=data.u[rows], x_next=data.x_next[rows], tau=data.tau,
                       t=None if data.t is None else data.t[rows], source=data.source,
                       n_dropped=data.n_dropped, meta=dict(data.meta),
                       episode=None if ep is None else ep[rows], se=None if data.se is None else data.se[rows])


def make_transitions(x, u, x_next, tau, t=None, *, system: Optional[System] = None,
                     drop_nonfinite: bool = False, source: str = "", meta: Optional[dict] = None,
                     episode=None) -> Transitions:
    """Validate arrays and build :class:`Transitions`.

    Checks shapes (x and x_next (K,n), u (K,m), t (K,), episode (K,) integers, only with t), that
    tau is a finite positive scalar, that the dimensions match ``system`` when given, and counts rows with NaN/inf in any of
    x, u, x_next (and t): refused with a SimgapError unless ``drop_nonfinite``.
    """
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    x_next = np.asarray(x_next, dtype=float)
    if u.ndim == 1:
        u = u[:, None]
    if x.ndim == 1 and system is not None and system.n == 1:
        x, x_next = x[:, None], x_next[:, None]
    if x.ndim != 2 or x_next.ndim != 2 or u.ndim != 2:
        raise SimgapError(f"transitions: x, u, x_next must be 2-D arrays, got shapes "
                          f"{x.shape}, {u.shape}, {x_next.shape}")
    K = x.shape[0]
    if x_next.shape != x.shape:
        raise SimgapError(f"transitions: x has shape {x.shape} but x_next has shape {x_next.shape}")
    if u.shape[0] != K:
        raise SimgapError(f"transitions: x has {K} rows but u has {u.shape[0]}")
    if system is not None:
        if x.shape[1] != system.n:
            raise SimgapError(f"transitions: {x.shape[1]} state columns but system {system.name!r} "
                              f"has n = {system.n} ({', '.join(system.state_names)})")
        if u.shape[1] != system.m:
            raise SimgapError(f"transitions: {u.shape[1]} input columns but system {system.name!r} "
                              f"has m = {system.m} ({', '.join(system.input_names)})")
    try:
        tau = float(np.asarray(tau, dtype=float).reshape(()))
    except (TypeError, ValueError):
        raise SimgapError(f"transitions: tau must be a scalar, got {np.shape(tau)}") from None
    if not (np.isfinite(tau) and tau > 0):
        raise SimgapError(f"transitions: tau must be a finite positive number of seconds, got {tau}")
    cols = [x, u, x_next]
    if t is not None:
        t = np.asarray(t, dtype=float).reshape(-1)
        if t.shape[0] != K:
            raise SimgapError(f"transitions: t has {t.shape[0]} entries for {K} rows")
        cols.append(t[:, None])
    if episode is not None:
        if t is None:
            raise SimgapError("transitions: episode ids need time stamps t")
        ep = np.asarray(episode, dtype=float).reshape(-1)
        if ep.shape[0] != K or not np.all(np.isfinite(ep)) or np.any(ep != np.round(ep)):
            raise SimgapError(f"transitions: episode must hold {K} integer ids, one per row")
        episode = ep.astype(np.int64)
    bad = ~np.all(np.isfinite(np.concatenate(cols, axis=1)), axis=1)
    n_bad = int(bad.sum())
    if n_bad:
        if not drop_nonfinite:
            raise SimgapError(f"transitions: {n_bad} of {K} rows contain NaN or inf; "
                              f"fix the data or pass --drop-nonfinite to drop them")
        keep = ~bad
        x, u, x_next = x[keep], u[keep], x_next[keep]
        t = t[keep] if t is not None else None
        episode = episode[keep] if episode is not None else None
    if x.shape[0] == 0:
        raise SimgapError("transitions: no rows")
    return Transitions(x=x, u=u, x_next=x_next, tau=tau, t=t, source=source, n_dropped=n_bad,
                       meta=dict(meta or {}), episode=episode)


def from_dataset(ds) -> Transitions:
    """Transitions from a collected :class:`simgap.dataset.Dataset`: x_next = empirical mean, with its
    standard error sqrt(var / N1hat) per pair and state."""
    tr = make_transitions(ds.x, ds.u, ds.mean, ds.system.tau, system=ds.system, source="dataset",
                          meta={"dataset_hash": ds.hash, "n_runs": int(ds.n_runs)})
    var = getattr(ds, "var", None)
    if var is not None and np.shape(var) == tr.x.shape and np.all(np.isfinite(var)):
        tr.se = np.sqrt(np.maximum(np.asarray(var, float), 0.0) / max(int(ds.n_runs), 1))
    return tr


def _columns_lookup(cols: dict, system: Optional[System], path: str):
    names = list(cols)

    def pick(options, what):
        for o in options:
            if o in cols:
                return np.asarray(cols[o], dtype=float)
        raise SimgapError(f"{path}: missing column for {what} (tried {', '.join(options)}); "
                          f"columns present: {', '.join(names)}")

    if system is not None:
        n, m = system.n, system.m
        snames, inames = system.state_names, system.input_names
    else:
        n = sum(1 for c in names if c.startswith("x") and c[1:].isdigit())
        m = sum(1 for c in names if c.startswith("u") and c[1:].isdigit())
        snames, inames = [f"x{i + 1}" for i in range(n)], [f"u{j + 1}" for j in range(m)]
    if n == 0 or m == 0:
        raise SimgapError(f"{path}: need columns x1.., x1_next.., u1.. and tau; got {', '.join(names)}")
    x = np.stack([pick([f"x{i + 1}", snames[i]], f"state {i + 1}") for i in range(n)], axis=1)
    xn = np.stack([pick([f"x{i + 1}_next", f"{snames[i]}_next"], f"next state {i + 1}")
                   for i in range(n)], axis=1)
    u = np.stack([pick([f"u{j + 1}", inames[j]], f"input {j + 1}") for j in range(m)], axis=1)
    tau_col = pick(["tau"], "tau")
    finite = tau_col[np.isfinite(tau_col)]
    if finite.size == 0 or np.ptp(finite) > 1e-12 * max(1.0, abs(finite[0])):
        raise SimgapError(f"{path}: column tau must hold one constant value")
    t = np.asarray(cols["t"], dtype=float) if "t" in cols else None
    ep = np.asarray(cols["episode"], dtype=float) if "episode" in cols else None
    return x, u, xn, float(finite[0]), t, ep


def _load_collected(path: Path, system: Optional[System]):
    """A collected data set as transitions; its own system (and steps) unless it is a user system."""
    from ..dataset import load_dataset
    try:
        ds = load_dataset(path)
    except SimgapError:
        if system is None:
            raise
        ds = load_dataset(path, system=system)
    tr = from_dataset(ds)
    tr.source = str(path)
    return tr


def load_transitions(path: str | Path, system: Optional[System] = None,
                     drop_nonfinite: bool = False) -> Transitions:
    """Load transition data from .npz / .csv / .parquet or a collected data set (see module doc)."""
    path = Path(path)
    if not path.exists():
        raise SimgapError(f"data file {str(path)!r} does not exist")
    if path.is_dir():
        return _load_collected(path, system)
    from ..file_guard import regular_file
    regular_file(path, "data file")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                keys = set(z.files)
                if {"mean", "f_nom", "meta"} <= keys:
                    is_dataset = True
                else:
                    is_dataset = False
                    missing = [k for k in ("x", "u", "x_next", "tau") if k not in keys]
                    if missing:
                        raise SimgapError(f"{path}: missing arrays {missing}; a transition file needs "
                                          f"x (K,n), u (K,m), x_next (K,n) and scalar tau "
                                          f"(found: {sorted(keys)})")
                    arr = {k: z[k] for k in ("x", "u", "x_next", "tau")}
                    t = z["t"] if "t" in keys else None
                    ep = z["episode"] if "episode" in keys else None
                    meta = json.loads(str(z["meta"])) if "meta" in keys else {}
        except BAD_FILE_ERRORS as e:
            if isinstance(e, SimgapError):
                raise
            raise SimgapError(f"{path}: unreadable .npz: {e}") from None
        if is_dataset:
            return _load_collected(path, system)
        return make_transitions(arr["x"], arr["u"], arr["x_next"], arr["tau"], t, system=system,
                                drop_nonfinite=drop_nonfinite, source=str(path), meta=meta, episode=ep)
    if suffix == ".csv":
        try:
            with open(path, newline="") as fh:
                header = fh.readline().strip().split(",")
            data = np.genfromtxt(path, delimiter=",", skip_header=1, dtype=float)
        except (OSError, ValueError) as e:
            raise SimgapError(f"{path}: unreadable CSV: {e}") from None
        data = np.atleast_2d(data)
        header = [h.strip() for h in header]
        if data.shape[1] != len(header):
            raise SimgapError(f"{path}: {len(header)} header names but {data.shape[1]} columns")
        cols = {h: data[:, i] for i, h in enumerate(header)}
    elif suffix == ".parquet":
        try:
            import pyarrow.parquet as pq
            table = pq.read_table(path)
        except ImportError:
            raise SimgapError("reading .parquet needs pyarrow (pip install pyarrow)") from None
        except Exception as e:  # pyarrow raises its own error types
            raise SimgapError(f"{path}: unreadable parquet: {e}") from None
        cols = {name: table.column(name).to_numpy() for name in table.column_names}
    else:
        raise SimgapError(f"{path}: unknown data format {suffix!r}; use .npz, .csv, .parquet "
                          f"or a collected data set")
    x, u, xn, tau, t, ep = _columns_lookup(cols, system, str(path))
    return make_transitions(x, u, xn, tau, t, system=system, drop_nonfinite=drop_nonfinite,
                            source=str(path), episode=ep)

"""Small in-memory data sets from the numpy simulator, for tests, benchmarks and examples.

This is NOT the collection stage (simgap.collect): it covers X with a regular grid, runs the
simulator N1hat times from every (x_r, u) and fills a :class:`~simgap.dataset.Dataset`
exactly as the Dataset docstring defines its fields (wrapped deviations for angles).
"""

from __future__ import annotations

import hashlib
import json

import numpy as np

from ..collect import TOP_ORDER_STATS, top_abs_deviations
from ..dataset import Dataset
from ..errors import SimgapError
from ..simulators import Simulator, SimulatorConfig, make_simulator


def grid_cover(x_lo, x_hi, epsilon: float) -> np.ndarray:
    """Grid points with spacing <= 2 eps / sqrt(n): every x in the box is within eps (Euclidean)."""
    x_lo, x_hi = np.asarray(x_lo, float), np.asarray(x_hi, float)
    n = x_lo.size
    h = 2.0 * epsilon / np.sqrt(n)
    axes = [np.linspace(l, u, int(np.ceil((u - l) / h)) + 1) for l, u in zip(x_lo, x_hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, n)


def synthetic_dataset(config: dict | SimulatorConfig | Simulator, epsilon: float, n_runs: int, seed: int = 0,
                      inputs: np.ndarray | None = None, chunk_samples: int = 2_000_000,
                      fixed: dict | None = None) -> Dataset:
    """Collect a Dataset on a grid cover of X with the (numpy or any) simulator ``config``.

    Rows are cover-major (cover point r, input j). ``inputs`` defaults to the system's U.
    ``fixed`` {dim: value}: declared-invariant dimensions, not covered but held at ``value``
    (recorded in the manifest's "cover" as the collection stage does).
    ``config`` may also be a built :class:`Simulator` (needed for user-defined systems).
    Randomness: one numpy Generator seeded with ``seed``; chunks of rows in order.
    """
    if isinstance(config, Simulator):  # e.g. a simulator of a user-defined system
        sim, cfg = config, config.config
    else:
        cfg = config if isinstance(config, SimulatorConfig) else SimulatorConfig.from_dict(config)
        sim = make_simulator(cfg)
    if int(n_runs) < 1:
        raise SimgapError(f"n_runs must be >= 1, got {n_runs}")
    s = sim.system
    U = s.inputs if inputs is None else np.atleast_2d(np.asarray(inputs, float))
    fixed = {int(k): float(v) for k, v in (fixed or {}).items()}
    cov = [j for j in range(s.n) if j not in fixed]
    Cc = grid_cover(s.x_lo[cov], s.x_hi[cov], epsilon)
    C = np.empty((len(Cc), s.n))
    C[:, cov] = Cc
    for j, v in fixed.items():
        C[:, j] = v
    N, M = len(C), len(U)
    ci = np.repeat(np.arange(N), M)
    ii = np.tile(np.arange(M), N)
    X, Uu = C[ci], U[ii]
    K = N * M
    fnom = s.f(X, Uu)
    mean = np.empty((K, s.n))
    var = np.zeros((K, s.n))
    lo = np.empty((K, s.n))
    hi = np.empty((K, s.n))
    top = np.empty((K, min(int(n_runs), TOP_ORDER_STATS), s.n))
    rng = np.random.default_rng(seed)
    rows = max(1, chunk_samples // int(n_runs))
    for a in range(0, K, rows):  # chunks of rows; each chunk fully vectorized over rows x runs
        b = min(K, a + rows)
        xr = np.repeat(X[a:b], n_runs, axis=0)
        ur = np.repeat(Uu[a:b], n_runs, axis=0)
        nxt = sim.step(xr, ur, rng).reshape(b - a, n_runs, s.n)
        d = s.diff(nxt, fnom[a:b, None, :])  # wrapped deviation from f
        mean[a:b] = s.wrap(fnom[a:b] + d.mean(axis=1))
        if n_runs > 1:
            var[a:b] = d.var(axis=1, ddof=1)
        lo[a:b] = fnom[a:b] + d.min(axis=1)
        hi[a:b] = fnom[a:b] + d.max(axis=1)
        top[a:b] = top_abs_deviations(nxt, fnom[a:b], s.angle_dims)
    manifest = {"simulator": cfg.to_dict(), "system": s.describe(), "cover": {"kind": "grid", "epsilon": epsilon,
                "points": int(N), "invariant_dims": [s.state_names[j] for j in sorted(fixed)]}, "seed": int(seed), "n_runs": int(n_runs), "source": "simgap.certify.synthetic"}
    manifest["hash"] = hashlib.sha256(json.dumps(manifest, sort_keys=True).encode()).hexdigest()[:16]
    return Dataset(system=s, x=X, u=Uu, f_nom=fnom, mean=mean, var=var, lo=lo, hi=hi, cover_index=ci,
                   input_index=ii, n_runs=int(n_runs), epsilon=float(epsilon), manifest=manifest, absdev_top=top)

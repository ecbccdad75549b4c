"""Dataset: the typed output of collection, per (x_r, u) pair statistics of N1hat simulator runs.

Rows are the K = N * M pairs (cover point r, input j), cover-major. For every row:

* ``x`` (K,n) the cover point x_r, ``u`` (K,m) the input;
* ``f_nom`` (K,n) the nominal next state f(x_r, u);
* ``mean`` (K,n) the empirical mean of the N1hat simulator next states fhat(x_r, u, w_k);
* ``var`` (K,n) their unbiased sample variance (ddof = 1);
* ``lo``/``hi`` (K,n) their minimum and maximum;
* ``absdev_top`` (K,T,n), optional: the T = min(N1hat, 32) largest absolute deviations
  |wrap(fhat_i - f_i)| per row and dimension, descending (order statistics for the per-run gap;
  None for data collected before they were kept).

Angle dimensions: every statistic is computed on the wrapped deviation d = wrap(fhat - f_nom)
and shifted back (mean = wrap(f_nom + mean d), lo = f_nom + min d, hi = f_nom + max d; lo/hi
are not wrapped), so the observed gap ``gap()`` = |wrap(mean - f_nom)| is meaningful across
the +-pi seam.

``manifest`` carries the full configuration, its hash (``manifest["hash"]``, the configuration
hash: what was asked for) and provenance. :attr:`Dataset.hash` is the CONTENT hash (what was
obtained): sha256 over every array, N1hat, epsilon, the system and the configuration hash.
Certificates record it, so data re-saved with other numbers no longer match their certificate.
"""

from __future__ import annotations

import dataclasses

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from . import fileio, store
from .errors import BAD_FILE_ERRORS, SimgapError
from .systems import System
from .system_ref import resolve_system, system_ref

ARRAYS = ("x", "u", "f_nom", "mean", "var", "lo", "hi", "cover_index", "input_index")


@dataclass
class Dataset:
    system: System
    x: np.ndarray
    u: np.ndarray
    f_nom: np.ndarray
    mean: np.ndarray
    var: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    cover_index: np.ndarray
    input_index: np.ndarray
    n_runs: int
    epsilon: float
    manifest: dict = field(default_factory=dict)
    absdev_top: Optional[np.ndarray] = None

    def __post_init__(self):
        K, n = self.x.shape
        if self.absdev_top is not None and (self.absdev_top.ndim != 3 or self.absdev_top.shape[0] != K
                                            or self.absdev_top.shape[2] != n):
            raise SimgapError(f"dataset: absdev_top has shape {self.absdev_top.shape}, expected ({K}, T, {n})")
        for name in ("f_nom", "mean", "var", "lo", "hi"):
            a = getattr(self, name)
            if a.shape != (K, n):
                raise SimgapError(f"dataset: {name} has shape {a.shape}, expected {(K, n)}")
        if self.u.shape[0] != K:
            raise SimgapError(f"dataset: u has {self.u.shape[0]} rows, expected {K}")
        if n != self.system.n:
            raise SimgapError(f"dataset: {n} state dims but system {self.system.name!r} has {self.system.n}")

    @property
    def K(self) -> int:
        return self.x.shape[0]

    @property
    def config_hash(self) -> str:
        """The configuration hash of the collection that produced this dataset (manifest "hash")."""
        return self.manifest.get("hash", "")

    @property
    def hash(self) -> str:
        """Content hash: sha256 of the arrays, N1hat, epsilon, system (name, steps) and configuration hash."""
        meta = {"n_runs": int(self.n_runs), "epsilon": float(self.epsilon), "system": self.system.name,
                "steps": int(self.system.steps), "config_hash": self.config_hash}
        arrays = {k: getattr(self, k) for k in ARRAYS}
        if self.absdev_top is not None:
            arrays["absdev_top"] = self.absdev_top
        return fileio.content_digest(meta, arrays)

    def gap(self) -> np.ndarray:
        """Observed gap |mean_k fhat(x_r,u,w_k) - f(x_r,u)| per row and dimension, (K,n), angles wrapped."""
        return np.abs(self.system.diff(self.mean, self.f_nom))

    def with_nominal(self, system: System) -> "Dataset":
        """The same simulator data against another nominal model f' (e.g. a refined system):
        f_nom = f'(x_r, u) at the data's steps; the empirical means, variances and extremes are
        unchanged, so the observed gap becomes |mean - f'|. f' must have the data's state
        variables and box X."""
        s, own = system.with_steps(self.system.steps), self.system
        if (s.state_names, s.input_names) != (own.state_names, own.input_names) \
                or not (np.array_equal(s.x_lo, own.x_lo) and np.array_equal(s.x_hi, own.x_hi)):
            raise SimgapError(f"system {s.name!r} does not fit the data of {own.name!r}: need the same state and "
                              f"input names and state box X = {own._box_str()}")
        s = dataclasses.replace(s, inputs=own.inputs)  # the input set the data cover
        # the kept per-run deviations are from the old f_nom: dropped, not silently reused
        return dataclasses.replace(self, system=s, f_nom=s.f(self.x, self.u), absdev_top=None)

    def check_finite(self) -> None:
        for name in ("x", "u", "f_nom", "mean", "var"):
            a = getattr(self, name)
            if not np.all(np.isfinite(a)):
                bad = int((~np.isfinite(a)).reshape(a.shape[0], -1).any(axis=1).sum())
                raise SimgapError(f"dataset: {bad} rows of {name} contain NaN or inf")

    # ----- single-file form (.npz, no pickle) -----------------------------------------
    def save_npz(self, path: str | Path) -> Path:
        """Write the dataset as one .npz (atomically: temp file, then rename)."""
        meta = {"n_runs": int(self.n_runs), "epsilon": float(self.epsilon), "manifest": self.manifest,
                "system": system_ref(self.system) or self.system.name, "steps": int(self.system.steps),
                "content_hash": self.hash}
        extra = {} if self.absdev_top is None else {"absdev_top": self.absdev_top}
        return fileio.savez(path, **{k: getattr(self, k) for k in ARRAYS}, **extra, meta=np.array(json.dumps(meta)))


def invariant_dims(dataset) -> list:
    """0-based state dimensions the collection declared invariant (not covered; manifest "cover")."""
    names = (dataset.manifest.get("cover") or {}).get("invariant_dims") or []
    out = []
    for d in names:
        if isinstance(d, int):
            out.append(d)
        elif d in dataset.system.state_names:
            out.append(dataset.system.state_names.index(d))
        else:
            raise SimgapError(f"dataset manifest: unknown invariant dimension {d!r}")
    return sorted(set(out))


def load_dataset(path: str | Path, system: System | None = None) -> Dataset:
    """Load a dataset from a single .npz or from a collection store directory.

    ``system`` overrides the system the file records (a built-in name or an embedded refined
    system; needed for user systems).
    """
    path = Path(path)
    if path.is_dir():
        return load_store(path, system=system)
    from .file_guard import loads_json, regular_file
    regular_file(path, "dataset")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ARRAYS}
            if "absdev_top" in z.files:
                arrays["absdev_top"] = z["absdev_top"]
            meta = loads_json(str(z["meta"]), f"dataset {str(path)!r}: its metadata")
    except (*BAD_FILE_ERRORS, KeyError) as e:
        raise SimgapError(f"dataset {str(path)!r} is unreadable or not a simgap dataset: {e}") from None
    try:
        sysobj = system or resolve_system(meta["system"], steps=meta.get("steps", 1), paths=False)
    except SimgapError as e:
        raise SimgapError(f"dataset {str(path)!r}: cannot rebuild its system ({e}); pass the System") from None
    ds = Dataset(system=sysobj, n_runs=int(meta["n_runs"]), epsilon=float(meta["epsilon"]),
                 manifest=meta.get("manifest", {}), **arrays)
    want = meta.get("content_hash")
    if want is None:
        raise SimgapError(f"dataset {str(path)!r} records no content hash (written by an older simgap); "
                          f"save it again from its collection store")
    if ds.hash != want:
        raise SimgapError(f"dataset {str(path)!r} was modified after it was written: its content hash is "
                          f"{ds.hash[:16]}... but the file records {str(want)[:16]}...")
    return ds


def load_store(path: str | Path, system: System | None = None) -> Dataset:
    """Load a complete collection store (:mod:`simgap.store`) as a :class:`Dataset`: what
    :func:`simgap.store.read_store` reads and verifies (``system``, manifest and refusals there)."""
    c = store.read_store(path, system)
    return Dataset(system=c.system, n_runs=c.n_runs, epsilon=c.epsilon, manifest=c.manifest, **c.arrays)

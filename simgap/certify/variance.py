"""The variance bound Mhat_i >= Var fhat_i(x, u, w) of Assumption 1 (units: state units squared).

* ``empirical`` (paper): Mhat_i = safety * max_r s_i^2(x_r, u), s^2 the unbiased sample variance
  of the N1hat runs at row r; safety defaults to 10 ("a conservative global bound is taken
  (e.g. 10 times)"). Carries no confidence of its own.
* ``maurer_pontil`` (beyond the paper): Maurer & Pontil (2009, Thm. 10): for i.i.d. variables
  with range b, with probability >= 1 - beta_v,  sigma <= s + b sqrt(2 ln(1/beta_v) / (N1hat - 1)).
  Applied to all K rows at once (union bound: beta_v / K per row), Mhat_i = max_r (that bound)^2
  and beta_v is added to dimension i's failure probability.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import SimgapError


@dataclass
class VarianceBound:
    M: np.ndarray              # (n,) Mhat_i
    method: str
    safety: float
    beta_v: float              # failure probability spent on Mhat per dimension (0 for empirical)
    max_sample_var: np.ndarray  # (n,) max_r s_i^2

    def to_dict(self):
        return {"M": self.M.tolist(), "method": self.method, "safety": self.safety, "beta_v": self.beta_v,
                "max_sample_var": self.max_sample_var.tolist()}


def variance_bound(var: np.ndarray, n_runs: int, method: str = "empirical", safety: float = 10.0,
                   value_range: Optional[float] = None, beta_v: float = 0.001) -> VarianceBound:
    """Mhat per dimension from the per-row sample variances ``var`` (K, n) of N1hat runs."""
    var = np.asarray(var, dtype=float)
    if var.ndim != 2 or not np.all(np.isfinite(var)) or np.any(var < 0):
        raise SimgapError("variance bound: sample variances must be a finite, non-negative (K, n) array")
    if n_runs < 2:
        raise SimgapError(f"variance bound: N1hat = {n_runs} runs per (x_r, u) give no variance estimate; "
                          f"the stochastic method needs N1hat >= 2 (use --method deterministic for one run)")
    smax = var.max(axis=0)
    if method == "empirical":
        if not (np.isfinite(safety) and safety >= 1):
            raise SimgapError(f"variance safety factor must be >= 1, got {safety}")
        return VarianceBound(M=safety * smax, method=method, safety=float(safety), beta_v=0.0, max_sample_var=smax)
    if method == "maurer_pontil":
        if not (value_range and value_range > 0):
            raise SimgapError("maurer_pontil variance bound needs the known range b > 0 of fhat_i (--range)")
        if not (0 < beta_v < 1):
            raise SimgapError(f"maurer_pontil: beta_v must be in (0, 1), got {beta_v}")
        K = var.shape[0]
        sig = np.sqrt(var.max(axis=0)) + value_range * np.sqrt(2.0 * np.log(K / beta_v) / (n_runs - 1))
        return VarianceBound(M=sig ** 2, method=method, safety=1.0, beta_v=float(beta_v), max_sample_var=smax)
    raise SimgapError(f"unknown variance method {method!r}; choose 'empirical' or 'maurer_pontil'")

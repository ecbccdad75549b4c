"""Probabilistic margins delta and confidences beta (paper: Lemma 1, Lemma 2, Theorems 1-2).

Paper (default, ``concentration="chebyshev"``, ``lemma2_factor=2``):

    Lemma 1:   beta_1i = Mhat_i / (delta_1i^2 N1hat)
    Lemma 2:   beta_2i = 2 Mhat_i / (delta_2i^2 N1hat)
    Theorem 1: P(|E fhat_i - f_i| <= gamma_i) >= 1 - beta_1i - beta_2i
    Theorem 2: joint confidence >= 1 - sum_i (beta_1i + beta_2i)

Mhat_i bounds Var fhat_i (units: state units squared), N1hat runs per (x_r, u), delta in
state units. Each direction is available: delta -> beta (:func:`beta_from_delta`) and a target
beta -> the smallest delta that achieves it (:func:`delta_from_beta`).

Options that go BEYOND the paper (off by default, each labelled in the certificate):

* ``lemma2_factor=4``: Lemma 2 bounds Var(fhat(x,u,w) - fhat(x_r,u,w)) by 2 Mhat assuming the
  two are independent; they share w, and in general Var(A - B) <= 4 Mhat.
* ``concentration="subgaussian"``: the empirical mean of N sub-Gaussian variables with
  variance proxy s^2 satisfies P(|mean - E| > delta) <= 2 exp(-N delta^2 / (2 s^2)); we take
  s^2 = Mhat (Lemma 1) and lemma2_factor * Mhat (Lemma 2). Assumes sub-Gaussian noise.
* ``concentration="bernstein"``: bounded variables (range b, known a priori) with variance
  <= s^2: P(|mean - E| > delta) <= 2 exp(-N delta^2 / (2 s^2 + 2 b delta / 3)).
  Lemma 2 uses range 2b.
* ``uniform=True``: one statement for ALL K cover rows at once instead of one per (x, u).
  Lemma 1 must hold at all K constraints of the scenario program for the solution to be
  feasible for SCP, and synthesis reads gamma at every cell, i.e. near every cover row, at
  once. A union bound over the K rows gives each row beta_1 / K in Lemma 1 AND beta_2 / K in
  Lemma 2 (Lemma 2 taken at one query point per cover row), so the stated (simultaneous)
  confidence 1 - beta_1 - beta_2 covers every row together.

Pointwise vs simultaneous. Without ``uniform`` beta_1, beta_2 are per (x, u): the confidence
is that of ONE query point. The simultaneous confidence over all K rows implied by the same
deltas is, by the union bound, 1 - K (beta_1 + beta_2); see :func:`scope_confidences`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..errors import SimgapError

CONCENTRATIONS = ("chebyshev", "subgaussian", "bernstein")


@dataclass(frozen=True)
class BoundOptions:
    """How delta and beta relate (see module docstring). Defaults are the paper's."""

    concentration: str = "chebyshev"
    lemma2_factor: float = 2.0
    uniform: bool = False
    value_range: Optional[float] = None   # b: known a-priori range of fhat_i (bernstein)

    def validate(self):
        if self.concentration not in CONCENTRATIONS:
            raise SimgapError(f"unknown concentration {self.concentration!r}; choose one of {', '.join(CONCENTRATIONS)}")
        if self.lemma2_factor not in (2.0, 4.0):
            raise SimgapError(f"lemma2_factor must be 2 (paper) or 4 (general), got {self.lemma2_factor}")
        if self.concentration == "bernstein" and not (self.value_range and self.value_range > 0):
            raise SimgapError("bernstein concentration needs a known range b > 0 of the simulator output (--range)")

    def beyond_paper(self) -> list:
        out = []
        if self.concentration != "chebyshev":
            out.append(f"concentration={self.concentration}")
        if self.concentration == "subgaussian":
            out.append("assumption: fhat_i is sub-Gaussian with variance proxy Mhat_i (Lemma 1) and "
                       f"{self.lemma2_factor:g} Mhat_i (Lemma 2); a variance bound alone does not imply it")
        if self.concentration == "bernstein":
            out.append(f"assumption: fhat_i has the known range b = {self.value_range:g}")
        if self.lemma2_factor != 2.0:
            out.append(f"lemma2_factor={self.lemma2_factor:g}")
        if self.uniform:
            out.append("uniform (union bound over the K cover rows in Lemma 1 and Lemma 2: simultaneous statement)")
        return out


def _check(M, N, what):
    M = np.asarray(M, dtype=float)
    if not np.all(np.isfinite(M)) or np.any(M < 0):
        raise SimgapError(f"{what}: Mhat must be finite and >= 0, got {M}")
    if int(N) != N or N < 1:
        raise SimgapError(f"{what}: N1hat must be an integer >= 1, got {N}")
    return M


def _tail(delta, var, N, opts: BoundOptions, rng_b):
    """P(|mean of N - E| > delta) bound for variables of variance <= var (range rng_b)."""
    with np.errstate(divide="ignore", over="ignore"):
        if opts.concentration == "chebyshev":
            return var / (delta ** 2 * N)
        if opts.concentration == "subgaussian":
            return 2.0 * np.exp(-N * delta ** 2 / (2.0 * var))
        return 2.0 * np.exp(-N * delta ** 2 / (2.0 * var + 2.0 * rng_b * delta / 3.0))


def _inv_tail(beta, var, N, opts: BoundOptions, rng_b):
    """Smallest delta with _tail(delta) <= beta."""
    if opts.concentration == "chebyshev":
        return np.sqrt(var / (beta * N))
    L = np.log(2.0 / beta)
    if opts.concentration == "subgaussian":
        return np.sqrt(2.0 * var * L / N)
    a = 2.0 * rng_b * L / 3.0  # N d^2 - a d - 2 var L = 0
    return (a + np.sqrt(a * a + 8.0 * N * var * L)) / (2.0 * N)


def beta_from_delta(M, delta1, delta2, N: int, K: int = 1, opts: BoundOptions = BoundOptions()):
    """(beta_1, beta_2) per dimension for given deltas (> 0). Paper: M/(d1^2 N), 2M/(d2^2 N)."""
    opts.validate()
    M = _check(M, N, "beta_from_delta")
    d1 = np.broadcast_to(np.asarray(delta1, float), M.shape)
    d2 = np.broadcast_to(np.asarray(delta2, float), M.shape)
    if np.any(~np.isfinite(d1)) or np.any(d1 <= 0) or np.any(~np.isfinite(d2)) or np.any(d2 <= 0):
        raise SimgapError(f"delta must be finite and > 0, got delta_1={np.asarray(delta1).tolist()}, "
                          f"delta_2={np.asarray(delta2).tolist()}")
    b = opts.value_range or 0.0
    k = K if opts.uniform else 1
    b1 = _tail(d1, M, N, opts, b) * k
    b2 = _tail(d2, opts.lemma2_factor * M, N, opts, 2.0 * b) * k
    return np.asarray(b1, float), np.asarray(b2, float)


def delta_from_beta(M, beta1, beta2, N: int, K: int = 1, opts: BoundOptions = BoundOptions()):
    """Smallest (delta_1, delta_2) per dimension achieving the target betas in (0, 1).

    Paper: delta_1 = sqrt(M / (beta_1 N)), delta_2 = sqrt(2 M / (beta_2 N)).
    """
    opts.validate()
    M = _check(M, N, "delta_from_beta")
    b1 = np.broadcast_to(np.asarray(beta1, float), M.shape)
    b2 = np.broadcast_to(np.asarray(beta2, float), M.shape)
    for name, b in (("beta_1", b1), ("beta_2", b2)):
        if np.any(~np.isfinite(b)) or np.any(b <= 0) or np.any(b >= 1):
            raise SimgapError(f"{name} must be in (0, 1), got {np.asarray(b).tolist()}")
    rb = opts.value_range or 0.0
    k = K if opts.uniform else 1
    d1 = _inv_tail(b1 / k, M, N, opts, rb)
    d2 = _inv_tail(b2 / k, opts.lemma2_factor * M, N, opts, 2.0 * rb)
    # Mhat = 0 would give delta = 0: the lemmas need delta > 0, keep a floor at machine scale
    return np.maximum(d1, 1e-12), np.maximum(d2, 1e-12)


def required_runs(M, delta1, delta2, beta1, beta2, K: int = 1, opts: BoundOptions = BoundOptions()) -> int:
    """Smallest N1hat such that the given deltas reach the target betas (max over dimensions)."""
    lo, hi = 1, 2
    while np.any(np.concatenate(beta_from_delta(M, delta1, delta2, hi, K, opts)) >
                 np.concatenate([np.broadcast_to(beta1, np.shape(M)), np.broadcast_to(beta2, np.shape(M))])):
        lo, hi = hi, hi * 2
        if hi > 2 ** 50:
            raise SimgapError("no N1hat reaches the requested beta at these deltas")
    while hi - lo > 1:  # tails are decreasing in N
        mid = (lo + hi) // 2
        ok = np.all(np.concatenate(beta_from_delta(M, delta1, delta2, mid, K, opts)) <=
                    np.concatenate([np.broadcast_to(beta1, np.shape(M)), np.broadcast_to(beta2, np.shape(M))]))
        lo, hi = (lo, mid) if ok else (mid, hi)
    return hi


def scope_confidences(beta1, beta2, beta_v, K: int, uniform: bool) -> dict:
    """Joint confidences of one certificate read both ways (Theorem 2 plus a union bound).

    ``beta1``, ``beta2`` are the stated per-dimension failure probabilities (per (x, u) when not
    ``uniform``, for all K rows together when ``uniform``); ``beta_v`` the variance bound's, which
    already holds for all rows at once. Returns {"pointwise": 1 - sum_i (b1p + b2p + bv),
    "simultaneous": 1 - sum_i (K (b1p + b2p) + bv)} with b1p, b2p the pointwise betas.
    A value <= 0 means that reading states nothing.
    """
    b = np.asarray(beta1, float) + np.asarray(beta2, float)
    bp = b / K if uniform else b
    bv = np.asarray(beta_v, float)
    return {"pointwise": 1.0 - float(np.sum(bp + bv)), "simultaneous": 1.0 - float(np.sum(K * bp + bv))}


def confidences(beta1, beta2):
    """Per-dimension confidence 1 - beta_1i - beta_2i (Theorem 1) and joint 1 - sum_i (...) (Theorem 2)."""
    b1, b2 = np.asarray(beta1, float), np.asarray(beta2, float)
    per = 1.0 - b1 - b2
    joint = 1.0 - float(np.sum(b1 + b2))
    return per, joint


def joint_from_per_dimension(per_dim) -> float:
    """Theorem 2 from per-dimension confidences c_i = 1 - beta_1i - beta_2i: 1 - sum_i (1 - c_i)."""
    c = np.asarray(per_dim, float)
    return 1.0 - float(np.sum(1.0 - c))


def compare_bounds(M, N: int, K: int, beta1: float, beta2: float, value_range: Optional[float] = None,
                   L_eps=0.0) -> list:
    """What each concentration option does to delta and to gamma's constant part, at the same betas.

    Returns a list of dict rows (one per option) with delta_1, delta_2 (per dimension) and the
    increase of gamma over the SCP fit that depends on the option: delta_1 + delta_2 (delta_1
    enters through the constraint q^T p >= g + delta_1, which raises q^T p by about delta_1).
    """
    rows = []
    variants = [("paper: chebyshev, 2 Mhat", BoundOptions()),
                ("chebyshev, 4 Mhat (general Lemma 2)", BoundOptions(lemma2_factor=4.0)),
                ("chebyshev, uniform over K rows", BoundOptions(uniform=True)),
                ("sub-Gaussian, 2 Mhat", BoundOptions(concentration="subgaussian")),
                ("sub-Gaussian, uniform over K rows", BoundOptions(concentration="subgaussian", uniform=True))]
    if value_range:
        variants += [("bernstein (range b), 2 Mhat", BoundOptions(concentration="bernstein", value_range=value_range)),
                     ("bernstein (range b), uniform", BoundOptions(concentration="bernstein", value_range=value_range,
                                                                   uniform=True))]
    for name, o in variants:
        d1, d2 = delta_from_beta(M, beta1, beta2, N, K, o)
        rows.append({"option": name, "delta1": np.atleast_1d(d1).tolist(), "delta2": np.atleast_1d(d2).tolist(),
                     "gamma_increase": np.atleast_1d(d1 + d2 + L_eps).tolist()})
    return rows

"""Distribution-free binomial bounds: quantiles from order statistics, Clopper-Pearson intervals.

Quantile bound. Let D_1..D_N be i.i.d. copies of a real random variable D and
D_(1) <= ... <= D_(N) their order statistics. For the (1 - alpha)-quantile
q* = inf{t : P(D <= t) >= 1 - alpha} we have P(D >= q*) >= alpha, so the number of samples
>= q* is Binomial(N, p) with p >= alpha and, for j exceedances allowed,

    P(D_(N-j) < q*) = P(#{D_k >= q*} <= j) <= P(Bin(N, alpha) <= j).

So D_(N-j) is an upper (1 - beta')-confidence bound on q* when P(Bin(N, alpha) <= j) <= beta'.
The largest such j gives the tightest bound; none exists when (1 - alpha)^N > beta', i.e.
alpha < alpha_min = 1 - beta'^(1/N): N runs cannot support a smaller alpha.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from ..errors import SimgapError


def alpha_min(n_runs: int, beta: float) -> float:
    """Smallest alpha for which N runs give a (1 - beta)-confidence bound on the (1-alpha)-quantile."""
    return float(-np.expm1(np.log(beta) / n_runs))


def order_index(n_runs: int, alpha: float, beta: float) -> int:
    """Largest j in [0, N-1] with P(Bin(N, alpha) <= j) <= beta, so D_(N-j) bounds the (1-alpha)-quantile.

    Raises SimgapError naming alpha_min when no j exists.
    """
    if not 0.0 < alpha < 1.0:
        raise SimgapError(f"alpha must be in (0, 1), got {alpha}")
    if not 0.0 < beta < 1.0:
        raise SimgapError(f"beta must be in (0, 1), got {beta}")
    a_min = alpha_min(n_runs, beta)
    if alpha < a_min:
        raise SimgapError(f"alpha = {alpha:g} is below what N1hat = {n_runs} runs per pair support at confidence "
                          f"1 - {beta:.3g} per pair: the smallest supported alpha is {a_min:.4g} (more runs lower it: "
                          f"alpha_min ~ ln(1/beta)/N1hat)")
    # the largest j with cdf(j) <= beta, found from the quantile function (no O(N) table: a data set
    # may claim billions of runs); cdf(0) = (1 - alpha)^N <= beta holds since alpha >= alpha_min
    j = int(min(max(stats.binom.ppf(beta, n_runs, alpha), 0), n_runs - 1))
    while j > 0 and stats.binom.cdf(j, n_runs, alpha) > beta:
        j -= 1
    while j + 1 < n_runs and stats.binom.cdf(j + 1, n_runs, alpha) <= beta:
        j += 1
    return j


def clopper_pearson(k, n, level: float = 0.95):
    """Two-sided Clopper-Pearson interval (lo, hi) of a binomial proportion, k successes of n (arrays ok)."""
    k = np.asarray(k, dtype=float)
    n = np.asarray(n, dtype=float)
    a = (1.0 - level) / 2
    lo = np.where(k > 0, stats.beta.ppf(a, np.maximum(k, 1e-300), n - k + 1), 0.0)
    hi = np.where(k < n, stats.beta.ppf(1 - a, k + 1, np.maximum(n - k, 1e-300)), 1.0)
    return lo, hi


def cp_upper(k, n, beta):
    """One-sided (1 - beta) Clopper-Pearson upper bound of a proportion (arrays ok); 1 - beta^(1/n) at k = 0."""
    k = np.asarray(k, dtype=float)
    n = np.asarray(n, dtype=float)
    return np.where(k < n, stats.beta.ppf(1 - beta, k + 1, np.maximum(n - k, 1e-300)), 1.0)


def cp_lower(k, n, beta):
    """One-sided (1 - beta) Clopper-Pearson lower bound of a proportion (arrays ok)."""
    k = np.asarray(k, dtype=float)
    n = np.asarray(n, dtype=float)
    return np.where(k > 0, stats.beta.ppf(beta, np.maximum(k, 1e-300), n - k + 1), 0.0)

"""Is anything left in a residual? A model-free noise floor and a flexible cross-validated fit.

Given the remaining residual e_k (rate units) of one state and the variables v_k it may depend on
(x_k, u_k and, for time-ordered data, the lagged inputs u_{k-1}, u_{k-2}, ...), two numbers:

* **noise floor** sigma_0^2: half the mean squared difference of e between each sample and its
  nearest neighbour in the standardized variables (angles as sin/cos),
  sigma_0^2 = mean_k (e_k - e_nn(k))^2 / 2. For noise e = s(v) eps with any smooth s
  (heteroscedastic too) this is the mean noise variance, whatever the model; exact repeats of
  (x, u) (repeated runs) give pure noise differences. For a time series the neighbour is taken
  from time chunks at least one correlation length away (chunks of length L, neighbours from the
  chunk class two apart modulo 4), so correlated noise does not look like a low floor.
* **structure R^2**: held-out R^2 of a k-nearest-neighbour regression of e on v (k chosen among
  5, 10, 20 by leave-one-out error on train rows) and of a full degree-2 polynomial; the
  larger one. A kNN fit sees interactions, thresholds and ripples that additive or low-degree
  fits miss.

* **memory R^2** (time-ordered data): held-out R^2 gained by a linear fit of e_k on its own lags
  e_{k-1..k-3} and the lagged states x_{k-1}, x_{k-2} over the linear fit on the current variables
  alone. Hysteresis, backlash or a state coupled with a delay leave a residual that follows its past.

Each R^2 comes with its significance (:func:`gain_z`): the paired statistic mean(d)/se(d) of the
held-out loss differences d_k = e_k^2 - (e_k - p_k)^2 (block means for a time series), judged by a
Student-t quantile with the number of (block) means less one degrees of freedom (:func:`critical`),
so a few held-out rows need a larger statistic than many: an R^2 of 0.1 on 45 held-out rows of
noise is common, on 6,000 it is not.

The residual variance above the floor, max(0, mean e^2 - sigma_0^2), is what a model could still
explain; :func:`select_state` flags a state whose structure R^2 (significant) and share above the
floor both clear their thresholds, or whose memory R^2 (significant) clears the R^2 threshold.
"""

from __future__ import annotations

import itertools
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import norm, t as student_t

KS = (5, 10, 20)
MAX_ROWS = 4000
MEMORY_LAGS = 3          # residual lags e_{k-1..k-3} of the memory test
STATE_LAGS = 2           # lagged states x_{k-1}, x_{k-2}


def block_length(y: np.ndarray) -> int:
    """Moving-block length for a time series: twice the lag where autocorrelation < 0.1."""
    K = y.size
    yc = y - y.mean()
    n = 1 << int(np.ceil(np.log2(2 * K)))
    f = np.fft.rfft(yc, n)
    ac = np.fft.irfft(f * np.conj(f), n)[:K]
    ac = ac / ac[0] if ac[0] > 0 else ac
    below = np.flatnonzero(ac < 0.1)
    lag = int(below[0]) if below.size else K // 10
    return int(np.clip(2 * lag, max(1, int(round(K ** (1 / 3)))), max(1, K // 10)))


def gain_z(e: np.ndarray, e_with: np.ndarray, series: bool = False, e_without: Optional[np.ndarray] = None,
           block: Optional[int] = None) -> tuple:
    """(z, dof): paired held-out statistic of the loss differences d_k = e_without,k^2 - e_with,k^2.

    ``e`` (the rows' values, in time order for a series) is the error without the fit unless
    ``e_without`` is given; for a time series d is averaged over consecutive blocks of ``block``
    rows, by default :func:`block_length` of the fit's own error e_with (structure the fit explains
    does not lengthen the blocks; correlated noise it leaves does), and z = mean / (sd / sqrt(b))
    over the b block means, dof = b - 1.
    """
    if block is None:
        block = block_length(e_with) if series else 1
    eo = e if e_without is None else e_without
    d = eo ** 2 - e_with ** 2
    nb = d.size // max(block, 1)
    means = d[: nb * block].reshape(nb, block).mean(axis=1) if nb >= 2 else d
    sd = float(means.std(ddof=1)) if means.size > 1 else 0.0
    if sd == 0.0:
        return (0.0 if means.mean() == 0 else float(np.inf * np.sign(means.mean()))), max(means.size - 1, 1)
    return float(means.mean() / (sd / np.sqrt(means.size))), means.size - 1


def critical(z: float, dof: int) -> float:
    """The statistic a paired test with ``dof`` degrees of freedom needs for the one-sided level of a
    normal ``z`` (Student-t quantile): 3.0 -> 3.01 at dof 1000, 3.08 at 100, 3.27 at 30, 6.6 at 4."""
    return float(student_t.ppf(norm.cdf(z), max(int(dof), 1)))


def features(V: np.ndarray, angle_cols: np.ndarray, train: np.ndarray) -> np.ndarray:
    """Standardized variables (train mean / std), angles replaced by (sin, cos)."""
    cols = []
    for j in range(V.shape[1]):
        if angle_cols[j]:
            cols += [np.sin(V[:, j]), np.cos(V[:, j])]
        else:
            cols.append(V[:, j])
    F = np.stack(cols, axis=1)
    mu, sd = F[train].mean(axis=0), F[train].std(axis=0)
    keep = sd > 0
    if not keep.any():                    # nothing varies: one constant column keeps the shapes valid
        return np.zeros((F.shape[0], 1))
    return (F[:, keep] - mu[keep]) / sd[keep]


class Probe:
    """Neighbour structure of the variables, computed once and reused for every state's residual.

    ``held`` marks held-out rows; ``order`` (time series: the rows in time order, episode by
    episode, :func:`simgap.refine.data.time_order`) enables the chunked floor neighbours.
    """

    def __init__(self, V: np.ndarray, angle_cols: np.ndarray, held: np.ndarray, order: Optional[np.ndarray],
                 rng: np.random.Generator, prev: Optional[np.ndarray] = None, lagged_x: Optional[np.ndarray] = None):
        self.held, self.order = held, order
        self.prev, self.lagged_x = prev, lagged_x     # memory test: previous row (-1: none), x_{k-1}, x_{k-2}
        tr = ~held
        self.F = F = features(V, angle_cols, tr)
        self.train_rows = np.flatnonzero(tr)
        tree = cKDTree(F[tr])
        self.sub = rng.choice(self.train_rows.size, min(2000, self.train_rows.size), replace=False)
        self.ks = tuple(k for k in KS if k < self.train_rows.size) or (1,)     # tiny data sets
        _, idx = tree.query(F[tr][self.sub], k=max(self.ks) + 1)
        self.loo_idx = idx[:, 1:]                          # leave-one-out: drop the point itself
        # R^2 on at most MAX_ROWS held-out rows and the floor from at most MAX_ROWS pairs per
        # chunk class: a few percent of precision for a bounded time (refine <= 2 s at 20k rows)
        hrows = np.flatnonzero(held)
        self.held_rows = np.sort(rng.choice(hrows, min(MAX_ROWS, hrows.size), replace=False))
        _, idx = tree.query(F[self.held_rows], k=max(self.ks))
        self.held_idx = idx.reshape(self.held_rows.size, -1)
        self._rng = rng
        self._pairs = {}

    def pairs(self, corr_len: int) -> tuple:
        """(rows, their nearest neighbours) for the noise floor (module docstring)."""
        if corr_len not in self._pairs:
            F, K = self.F, self.F.shape[0]
            if self.order is None or corr_len <= 1:
                src = np.sort(self._rng.choice(K, min(2 * MAX_ROWS, K), replace=False))
                _, idx = cKDTree(F).query(F[src], k=2)
                self._pairs[corr_len] = (src, idx[:, 1])
            else:
                cls = np.empty(K, dtype=int)
                cls[self.order] = (np.arange(K) // corr_len) % 4
                src_all, dst_all = [], []
                for a in range(4):
                    src, dst = np.flatnonzero(cls == a), np.flatnonzero(cls == (a + 2) % 4)
                    src = np.sort(self._rng.choice(src, min(MAX_ROWS // 2, src.size), replace=False))
                    if src.size and dst.size:
                        _, idx = cKDTree(F[dst]).query(F[src], k=1)
                        src_all.append(src), dst_all.append(dst[idx])
                self._pairs[corr_len] = (np.concatenate(src_all), np.concatenate(dst_all))
        return self._pairs[corr_len]

    def noise_floor(self, e: np.ndarray, corr_len: int = 1) -> float:
        """Model-free noise variance sigma_0^2 of e (module docstring)."""
        a, b = self.pairs(corr_len)
        return float(np.mean((e[a] - e[b]) ** 2) / 2.0)

    def knn_r2(self, e: np.ndarray, series: bool = False) -> tuple:
        """(held-out R^2, k, z, dof) of a kNN regression of e trained on the rows not held out
        (z, dof: :func:`gain_z` of the fit against predicting 0)."""
        et = e[self.train_rows]
        csum = np.cumsum(et[self.loo_idx], axis=1)
        loo = [float(np.mean((et[self.sub] - csum[:, k - 1] / k) ** 2)) for k in self.ks]
        k = self.ks[int(np.argmin(loo))]
        pred = et[self.held_idx[:, :k]].mean(axis=1)
        eh = e[self.held_rows]
        ss = float(eh @ eh)
        return (1.0 - float(np.sum((eh - pred) ** 2)) / ss if ss > 0 else 0.0), k, *gain_z(eh, eh - pred, series)

    def memory_r2(self, e: np.ndarray, series: bool = True) -> Optional[tuple]:
        """(held-out R^2 gain, z, dof) of e's own lags and the lagged states over the current variables
        (module docstring; linear fits on train rows); None without time order or too few rows."""
        if self.prev is None:
            return None
        lags, idx = [], np.arange(e.size)
        for _ in range(MEMORY_LAGS):
            idx = np.where(idx >= 0, self.prev[np.maximum(idx, 0)], -1)
            lags.append(idx)
        ok = lags[-1] >= 0
        X = [np.ones(e.size), *self.F.T]
        base = np.stack(X, axis=1)
        extra = [e[np.maximum(i, 0)] for i in lags]
        if self.lagged_x is not None and self.lagged_x.size:
            L = self.lagged_x
            ok &= np.all(np.isfinite(L), axis=1)
            sd = np.nanstd(L, axis=0)
            extra += [np.nan_to_num(L[:, j]) / sd[j] for j in range(L.shape[1]) if sd[j] > 0]
        full = np.column_stack([base] + extra)
        tr, he = ok & ~self.held, ok & self.held
        if tr.sum() < 5 * full.shape[1] or he.sum() < 10:
            return None

        def pred(A):
            G = A[tr].T @ A[tr]
            w = np.linalg.solve(G + 1e-10 * np.trace(G) / A.shape[1] * np.eye(A.shape[1]), A[tr].T @ e[tr])
            return A[he] @ w

        eh = e[he]
        ss = float(eh @ eh)
        r_base, r_full = eh - pred(base), eh - pred(full)
        gain = (float(r_base @ r_base) - float(r_full @ r_full)) / ss if ss > 0 else 0.0
        return gain, *gain_z(eh, r_full, series, e_without=r_base)

    def poly2_resid(self, M: np.ndarray) -> np.ndarray:
        """M (K,) or (K, b) minus its degree-2 polynomial fit in the variables (fitted on train rows)."""
        self.poly2_r2(np.zeros(self.F.shape[0]))
        tr = ~self.held
        return M - self._P @ np.linalg.solve(self._G, self._P[tr].T @ M[tr])

    def poly2_r2(self, e: np.ndarray, series: bool = False) -> tuple:
        """(held-out R^2, z, dof) of a full degree-2 polynomial (with interactions) of e."""
        F, held = self.F, self.held
        tr = ~held
        d = F.shape[1]
        if not hasattr(self, "_P"):
            cols = [np.ones(F.shape[0])] + [F[:, j] for j in range(d)]
            cols += [F[:, a] * F[:, b] for a, b in itertools.combinations_with_replacement(range(d), 2)]
            P = np.stack(cols, axis=1)
            Pt = P[tr]
            G = Pt.T @ Pt
            self._P, self._G = P, G + 1e-8 * np.trace(G) / P.shape[1] * np.eye(P.shape[1])
        w = np.linalg.solve(self._G, self._P[tr].T @ e[tr])
        eh = e[held]
        ss = float(eh @ eh)
        r = eh - self._P[held] @ w
        return (1.0 - float(r @ r) / ss if ss > 0 else 0.0), *gain_z(eh, r, series)

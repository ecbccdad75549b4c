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

The residual variance above the floor, max(0, mean e^2 - sigma_0^2), is what a model could still
explain; :func:`select_state` flags a state whose structure R^2 and share above the floor both
clear their thresholds.
"""

from __future__ import annotations

import itertools
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

KS = (5, 10, 20)
MAX_ROWS = 4000


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
                 rng: np.random.Generator):
        self.held, self.order = held, order
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

    def knn_r2(self, e: np.ndarray) -> tuple:
        """(held-out R^2, k) of a kNN regression of e trained on the rows not held out."""
        et = e[self.train_rows]
        csum = np.cumsum(et[self.loo_idx], axis=1)
        loo = [float(np.mean((et[self.sub] - csum[:, k - 1] / k) ** 2)) for k in self.ks]
        k = self.ks[int(np.argmin(loo))]
        pred = et[self.held_idx[:, :k]].mean(axis=1)
        eh = e[self.held_rows]
        ss = float(eh @ eh)
        return (1.0 - float(np.sum((eh - pred) ** 2)) / ss if ss > 0 else 0.0), k

    def poly2_resid(self, M: np.ndarray) -> np.ndarray:
        """M (K,) or (K, b) minus its degree-2 polynomial fit in the variables (fitted on train rows)."""
        self.poly2_r2(np.zeros(self.F.shape[0]))
        tr = ~self.held
        return M - self._P @ np.linalg.solve(self._G, self._P[tr].T @ M[tr])

    def poly2_r2(self, e: np.ndarray) -> float:
        """Held-out R^2 of a full degree-2 polynomial (with interactions) of e."""
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
        return 1.0 - float(np.sum((eh - self._P[held] @ w) ** 2)) / ss if ss > 0 else 0.0

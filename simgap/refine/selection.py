"""Sparse selection of effects: which candidate terms explain the residual of one state.

For state i the regression target is the residual rate y_k = r_ki / tau and the design is
Theta_kj = g_j(x_k, u_k) for the candidate effects g_j entering state i, so that
y ~ Theta c means x_i+ ~ f_i + tau * sum_j c_j g_j.

Procedure (all least squares through the Gram matrices G = Theta^T Theta, b = Theta^T y of
the column-standardized design, which makes every subset fit a tiny p x p solve):

1. Split the samples into train and held-out parts: random rows for independent samples,
   contiguous time segments for a time series (neighbouring samples are correlated).
2. Drop candidates that are zero or collinear with others on these data, with a note (e.g. an
   input that never varies makes its input_gain term collinear with bias; ``gravity`` of a refined
   model without drift is the friction it already holds); refuse too few samples (fewer than
   ``min_per_term`` train samples per candidate term).
3. Forward selection on train minimizing BIC = K ln(RSS/K) + |S| ln K, then backward
   elimination while BIC drops.
4. Held-out pruning: a term stays only if removing it (refitting the rest on train) raises
   the held-out RSS by at least ``min_explained`` of the held-out residual sum of squares of the
   nominal model, and significantly: the paired statistic mean(d)/se(d) of the per-sample loss
   differences d_k = e_without,k^2 - e_with,k^2 must reach the Student-t quantile of ``min_z``'s
   one-sided level with (block) means - 1 degrees of freedom (block means for a time series): the
   threshold grows as the held-out data shrink (3.0 -> 3.08 at 100 means, 3.27 at 30, 6.6 at 5). With step 3
   this keeps pure-noise data free of effects.
5. Coefficients on train; standard errors by bootstrap (rows resampled, or moving blocks for a
   time series) with a seeded generator.
6. Explained fraction of each effect: the drop of held-out RSS when it is added, in the forward
   order, divided by the nominal model's held-out RSS (they sum to the total explained).
7. Structure left (:mod:`simgap.refine.structure`): a model-free noise floor of the remaining
   residual (nearest-neighbour differences in the variables) and the held-out R^2 of a
   cross-validated kNN regression (and a degree-2 polynomial) of it, each with its paired held-out
   test (the same data-size aware threshold as step 4). If a significant R^2 reaches
   ``structure_threshold`` and the remaining variance above the floor is at least
   ``min_unexplained`` of what is left, or (time-ordered data) the residual's own lags and the lagged
   states explain a significant ``structure_threshold`` of it beyond the current variables (memory:
   hysteresis, a delayed coupling), a residual remains that no library term explains:
   ``unexplained = True``; the effects named beside it are the library's nearest reading.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..errors import SimgapError
from .structure import Probe, block_length as _block_length, critical, gain_z
from .timecheck import describe_time, segment_coefficients, time_structure


@dataclass
class SelectionOptions:
    """Tunables of :func:`select_state` (defaults are used by the CLI)."""

    holdout: float = 0.3            # fraction of samples held out
    n_segments: int = 5             # contiguous held-out segments for time series
    min_explained: float = 0.005    # held-out RSS fraction a term must explain to stay
    min_z: float = 3.0              # significance of a term's held-out improvement (paired z)
    min_per_term: int = 10          # train samples needed per candidate term
    n_boot: int = 100               # bootstrap resamples for standard errors
    structure_threshold: float = 0.05   # held-out R^2 of the structure fit of what remains
    min_unexplained: float = 0.01       # ... and that structured part as a fraction of the nominal residual
    seed: int = 0
    max_lag: Optional[int] = None   # periods of history (time series): input delays, lagged user terms
                                    # (None: chosen by the data, 3..16; report history.chosen)
    gate_steps: int = 100           # multi-step gate: horizons 10 and this on held-out data (time series; 0: 10 only)
    gate_tolerance: float = 0.01    # allowed mean squared ratio of k-step RMS f' / f above 1
    max_rounds: int = 5             # selection rounds on what is left (1: a single round)
    weighted: bool = False          # weight rows by 1 / standard error of x_next where the data carry it
                                    # (collected pair means: Transitions.se), i.e. weighted least squares


@dataclass
class StateFit:
    """Selection result for one state dimension (coefficients in rate units)."""

    state: int
    candidate_keys: list
    selected: list                  # indices into the candidates, in forward order
    coef: np.ndarray
    stderr: np.ndarray
    explained: np.ndarray
    rss0_heldout: float             # sum over held-out of y^2 (nominal model)
    rss_heldout: float              # with the selected effects
    structure_r2: float             # held-out R^2 of a flexible fit of the remaining residual
    unexplained: bool
    stderr_statistical: Optional[np.ndarray] = None   # bootstrap part of stderr
    stderr_misfit: Optional[np.ndarray] = None        # between-region spread part of stderr
    noise_floor_fraction: float = 0.0   # model-free noise floor / nominal held-out residual variance
    unexplained_fraction: float = 0.0   # remaining variance above the floor / nominal
    lag1_autocorr: Optional[float] = None
    notes: list = field(default_factory=list)
    refused: list = field(default_factory=list)     # terms with impossible signs: {key, coefficient, reason, flagged}
    time: Optional[dict] = None     # time in the remaining residual (timecheck.time_structure)
    segments: Optional[dict] = None     # per-segment coefficients over the record (timecheck.segment_coefficients)
    rounds: int = 1                 # selection rounds run (each on what the previous ones left)
    memory_r2: Optional[float] = None   # significant held-out R^2 gain of the residual's lags (time series)

    @property
    def explained_total(self) -> float:
        return 0.0 if self.rss0_heldout <= 0 else 1.0 - self.rss_heldout / self.rss0_heldout

    @property
    def remaining_fraction(self) -> float:
        return 0.0 if self.rss0_heldout <= 0 else self.rss_heldout / self.rss0_heldout


def split_heldout(K: int, t: Optional[np.ndarray], opts: SelectionOptions,
                  order: Optional[np.ndarray] = None) -> np.ndarray:
    """Boolean mask of held-out samples.

    Independent rows: a seeded random ``holdout`` fraction. Time series (``t`` given): order by
    time (``order``, the rows in time order episode by episode, default argsort of t), cut into
    ``n_segments`` equal chunks and hold out the last ``holdout`` part of each, so held-out data
    are contiguous segments spread over the record.
    """
    if not 0.05 <= opts.holdout <= 0.8:
        raise SimgapError(f"holdout fraction must be in [0.05, 0.8], got {opts.holdout}")
    mask = np.zeros(K, dtype=bool)
    if t is None:
        rng = np.random.default_rng(opts.seed)
        mask[rng.permutation(K)[: int(round(opts.holdout * K))]] = True
        return mask
    if order is None:
        order = np.argsort(t, kind="stable")
    pos = np.empty(K, dtype=int)
    pos[order] = np.arange(K)
    chunk = np.minimum(pos * opts.n_segments // K, opts.n_segments - 1)
    start = (chunk * K) // opts.n_segments
    end = ((chunk + 1) * K) // opts.n_segments
    mask = pos >= end - np.round(opts.holdout * (end - start)).astype(int)
    return mask


def _solve(G: np.ndarray, b: np.ndarray, S: list) -> np.ndarray:
    if not S:
        return np.zeros(0)
    Gs = G[np.ix_(S, S)]
    try:
        return np.linalg.solve(Gs, b[S])
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(Gs, b[S], rcond=None)[0]


def _rss(yy: float, G: np.ndarray, b: np.ndarray, S: list, c: np.ndarray) -> float:
    if not S:
        return float(yy)
    return float(max(yy - 2.0 * c @ b[S] + c @ G[np.ix_(S, S)] @ c, 0.0))


#: which of several collinear candidates is kept: the simplest physical reading first
PRIORITY = ("bias", "viscous_friction", "coulomb_friction", "drag", "cubic_stiffness", "input_gain", "deadband",
            "input_coupling", "input_cross", "input_cross_abs", None,
            "integration", "input_delay", "actuator_lag", "gravity")


def _priority(key: str) -> int:
    name = key.split(":")[0]
    return PRIORITY.index(name) if name in PRIORITY else PRIORITY.index(None)


def independent_columns(Theta: np.ndarray, keys: list, tol: float = 1e-6) -> tuple:
    """Candidates that are linearly independent on these data, and a note for each one dropped.

    Columns are taken in :data:`PRIORITY` order (then as given) and kept when the part of the
    standardized column orthogonal to the kept ones holds at least ``tol`` of its squared norm
    (Gram-Schmidt), i.e. when it is not explained to 1 - tol by the terms already kept. A term that
    is zero on every sample, or collinear with kept ones (an input that never varies next to
    ``bias``; ``gravity`` of a refined model without drift next to the friction it already holds),
    is dropped with a note naming the terms it duplicates.
    """
    K, p = Theta.shape
    notes, keep = [], []
    if p == 0:
        return keep, notes
    scale = np.sqrt(np.mean(Theta ** 2, axis=0))
    Z = Theta / np.where(scale > 0, scale, 1.0)
    G = Z.T @ Z / K                       # unit diagonal for non-zero columns
    for j in sorted(range(p), key=lambda j: (_priority(keys[j]), j)):
        if scale[j] == 0:
            notes.append(f"dropped {keys[j]}: zero on every sample (the variable never excites it)")
            continue
        # squared norm of the part of column j orthogonal to the kept columns
        w = np.linalg.lstsq(G[np.ix_(keep, keep)], G[keep, j], rcond=None)[0] if keep else np.zeros(0)
        if float(G[j, j] - G[keep, j] @ w) < tol:
            with_ = [keys[keep[i]] for i in np.flatnonzero(np.abs(w) > 0.05 * np.abs(w).max())]
            notes.append(f"dropped {keys[j]}: collinear with {', '.join(with_)} on these data")
            continue
        keep.append(j)
    return sorted(keep), notes


def bootstrap_stderr(Z: np.ndarray, y: np.ndarray, time_series: bool, n_boot: int,
                     rng: np.random.Generator, resid: np.ndarray) -> np.ndarray:
    """Bootstrap standard deviation of the least-squares coefficients of y ~ Z (train rows).

    Rows are resampled with replacement (independent samples) or in moving blocks of length
    :func:`_block_length` (time series). Each resample is a weight vector w (counts), and the
    weighted normal equations (Z^T W Z) c = Z^T W y are solved in a batch.
    """
    K, p = Z.shape
    if p == 0 or n_boot < 2:
        return np.full(p, np.nan)
    iu = np.triu_indices(p)
    P = np.concatenate([Z[:, iu[0]] * Z[:, iu[1]], Z * y[:, None]], axis=1)   # (K, p(p+1)/2 + p)
    coefs = []
    L = _block_length(resid) if time_series else 1
    nblk = int(np.ceil(K / L))
    for start in range(0, n_boot, 25):
        B = min(25, n_boot - start)
        if L == 1:
            idx = rng.integers(0, K, (B, K))
        else:
            starts = rng.integers(0, K - L + 1, (B, nblk))
            idx = (starts[:, :, None] + np.arange(L)[None, None, :]).reshape(B, -1)[:, :K]
        W = np.stack([np.bincount(row, minlength=K) for row in idx]).astype(float)   # (B, K)
        A = W @ P
        G = np.zeros((B, p, p))
        G[:, iu[0], iu[1]] = A[:, : iu[0].size]
        G[:, iu[1], iu[0]] = A[:, : iu[0].size]
        b = A[:, iu[0].size:]
        coefs.append(np.linalg.solve(G + 1e-12 * np.eye(p), b[:, :, None])[:, :, 0])
    return np.concatenate(coefs).std(axis=0, ddof=1)


def misfit_stderr(Z: np.ndarray, y: np.ndarray, F: np.ndarray, se_stat: np.ndarray, groups: int = 4) -> np.ndarray:
    """Standard deviation of the coefficients of y ~ Z between regions of the data (the misfit).

    For each variable (column of F) the rows are cut into ``groups`` quantile groups and the
    coefficients are refitted in each. A term of the right shape gives the same coefficient in
    every region up to sampling error; a wrong-shaped one (a sign term for a dead zone) does not.
    The between-group variance beyond sampling error is the random-effects estimate
    tau^2 = max(0, (Q - (G - 1)) / (sum w - sum w^2 / sum w)), Q = sum_g w_g (c_g - c_w)^2,
    w_g = 1 / se_g^2 (DerSimonian-Laird), with se_g the least-squares standard error in group g
    scaled by the ratio of the bootstrap to the least-squares standard error on all rows (so
    correlated noise does not pass for misfit). Returns max over variables of tau, per term.
    """
    K, p = Z.shape
    G0 = Z.T @ Z

    def ols(rows):
        Zg, yg = Z[rows], y[rows]
        Gg = Zg.T @ Zg
        if rows.sum() < 10 * p or np.linalg.cond(Gg) > 1e8:
            return None
        cg = np.linalg.solve(Gg, Zg.T @ yg)
        s2 = float(np.sum((yg - Zg @ cg) ** 2)) / max(rows.sum() - p, 1)
        return cg, np.sqrt(s2 * np.diag(np.linalg.inv(Gg)))

    full = ols(np.ones(K, dtype=bool))
    if full is None:
        return np.zeros(p)
    infl = np.maximum(1.0, se_stat / np.where(full[1] > 0, full[1], np.inf))
    out = np.zeros(p)
    for j in range(F.shape[1]):
        edges = np.quantile(F[:, j], np.linspace(0, 1, groups + 1)[1:-1])
        g = np.searchsorted(edges, F[:, j], side="right")
        fits = [ols(g == a) for a in range(groups)]
        fits = [f for f in fits if f is not None]
        if len(fits) < 2:
            continue
        C = np.stack([f[0] for f in fits])
        W = 1.0 / (np.stack([f[1] for f in fits]) * infl) ** 2
        cw = (W * C).sum(axis=0) / W.sum(axis=0)
        Q = (W * (C - cw) ** 2).sum(axis=0)
        den = W.sum(axis=0) - (W ** 2).sum(axis=0) / W.sum(axis=0)
        tau2 = np.maximum(0.0, (Q - (len(fits) - 1)) / np.where(den > 0, den, np.inf))
        out = np.maximum(out, np.sqrt(tau2))
    return out


def select_state(y: np.ndarray, Theta: np.ndarray, keys: list, held: np.ndarray,
                 probe: Probe, state: int, time_series: bool, opts: SelectionOptions,
                 rng: np.random.Generator, check=None, clock: Optional[tuple] = None) -> StateFit:
    """Select effects for one state: y (K,) residual rate, Theta (K, p) candidate terms.

    ``probe`` holds the variables' neighbour structure for the structure test (built on the same
    ``held`` mask). ``check(keys, coef, se)`` (:func:`simgap.refine.effects.sign_check`) names a
    selected term with an impossible coefficient; it is refused (``StateFit.refused``) and the
    selection repeated without it; one impossible beyond two standard errors flags the state.
    ``clock`` = (t, episode, tau) for rows in time order: the remaining residual and the selected
    coefficients are also checked along time (:mod:`simgap.refine.timecheck`).
    Returns coefficients in the units of y per unit of each term (see module docstring).
    """
    K, p = Theta.shape
    tr = ~held
    Kt, Kh = int(tr.sum()), int(held.sum())
    yt, yh = y[tr], y[held]
    rss0_h = float(yh @ yh)
    scale_y = float(np.sqrt(np.mean(y ** 2)))
    if scale_y == 0.0:
        return StateFit(state, keys, [], np.zeros(0), np.zeros(0), np.zeros(0), 0.0, 0.0, 0.0, False,
                        notes=["residual is exactly zero: nothing to explain"])
    if Kt < opts.min_per_term * max(p, 1) or Kh < 10:
        raise SimgapError(f"too few samples: {Kt} train / {Kh} held-out samples for {p} candidate terms of "
                          f"state {state} (need at least {opts.min_per_term} train samples per term and 10 "
                          f"held-out); collect more data or restrict --effects")
    cols, dropped = independent_columns(Theta[tr], keys)
    if len(cols) < p:
        all_keys = keys
        fit = select_state(y, Theta[:, cols], [keys[j] for j in cols], held, probe, state, time_series,
                           opts, rng, check, clock)
        fit.selected = [cols[j] for j in fit.selected]
        fit.candidate_keys = all_keys
        fit.notes = dropped + fit.notes
        return fit
    scale = np.sqrt(np.mean(Theta[tr] ** 2, axis=0)) if p else np.zeros(0)
    Zt, Zh = Theta[tr] / scale, Theta[held] / scale
    Gt, bt, yyt = Zt.T @ Zt, Zt.T @ yt, float(yt @ yt)
    Gh, bh = Zh.T @ Zh, Zh.T @ yh

    def bic(S):
        c = _solve(Gt, bt, S)
        rss = _rss(yyt, Gt, bt, S, c)
        return Kt * np.log(max(rss, 1e-300) / Kt) + len(S) * np.log(Kt)

    def rss_h(S):
        return _rss(rss0_h, Gh, bh, S, _solve(Gt, bt, S))

    # 4. held-out pruning: drop the weakest term while it explains too little or not significantly
    #    (paired test on the per-sample held-out loss differences, block means for a time series)
    blk = _block_length(yh) if time_series else 1

    def heldout_test(S_with, S_without):
        """(held-out RSS gain, paired statistic, the statistic needed for min_z with these many means)."""
        ew = yh - (Zh[:, S_with] @ _solve(Gt, bt, S_with) if S_with else 0.0)
        eo = yh - (Zh[:, S_without] @ _solve(Gt, bt, S_without) if S_without else 0.0)
        stat, dof = gain_z(yh, ew, e_without=eo, block=blk)
        return float(eo @ eo - ew @ ew), stat, critical(opts.min_z, dof)

    def choose(allowed, base, ref):
        """Steps 3-4 adding to the terms ``base`` of earlier rounds; ``ref``: held-out RSS they leave."""
        # 3. forward selection then backward elimination (of new terms) by BIC on train
        S = list(base)
        best = bic(S)
        while True:
            trials = [(bic(S + [j]), j) for j in allowed if j not in S]
            if not trials:
                break
            val, j = min(trials)
            if val >= best:
                break
            S, best = S + [j], val
        changed = True
        while changed and len(S) > len(base):
            changed = False
            trials = [(bic([k for k in S if k != j]), j) for j in S if j not in base]
            val, j = min(trials)
            if val < best:
                S, best, changed = [k for k in S if k != j], val, True
        # 4. held-out pruning of the new terms, relative to what the earlier rounds left
        while len(S) > len(base):
            tests = [(heldout_test(S, [k for k in S if k != j]), j) for j in S if j not in base]
            (gain, stat, crit), j = min(tests, key=lambda t: (t[0][1] >= t[0][2], t[0][0]))
            if gain >= opts.min_explained * ref and stat >= crit:
                break
            S = [k for k in S if k != j]
        return S

    def signs(S, allowed):
        """4b. physical signs: refuse a term with an impossible coefficient, select again without it."""
        nonlocal flag_refused
        while S and check is not None:
            c = _solve(Gt, bt, S)
            r = yt - Zt[:, S] @ c
            s2 = float(r @ r) / max(Kt - len(S), 1) * (_block_length(r) if time_series else 1)
            try:
                se_ols = np.sqrt(s2 * np.clip(np.diag(np.linalg.inv(Gt[np.ix_(S, S)])), 0, None)) / scale[S]
            except np.linalg.LinAlgError:
                se_ols = np.full(len(S), np.nan)
            bad = check([keys[j] for j in S], c / scale[S], se_ols)
            if bad is None:
                break
            key, reason, beyond = bad
            j = keys.index(key)
            refused.append({"key": key, "coefficient": float(c[S.index(j)] / scale[j]), "reason": reason,
                            "flagged": bool(beyond)})
            flag_refused |= bool(beyond)
            allowed = [a for a in allowed if a != j]
            base = [k for k in rounds_base if k in allowed]
            S = choose(allowed, base, rss_h(base))
        return S, allowed

    def structure(S):
        """7. structure left in the remaining residual: (residual, R^2, significant R^2, floor as held-out
        RSS, memory).

        R^2 is the larger of the kNN and polynomial fits'; the significant one the larger of those that
        pass their paired test (0 when neither does); memory the significant R^2 gain of the residual's
        own lags and lagged states (or None)."""
        c = _solve(Gt, bt, S)
        e = y - ((Theta[:, S] / scale[S]) @ c if S else 0.0)
        k_r2, _, *k_z = probe.knn_r2(e, time_series)
        fits = [(k_r2, *k_z), probe.poly2_r2(e, time_series)]
        sig = max([r for r, z, dof in fits if z >= critical(opts.min_z, dof)], default=0.0)
        mem = probe.memory_r2(e, time_series)
        mem = mem[0] if mem is not None and mem[1] >= critical(opts.min_z, mem[2]) else None
        floor = probe.noise_floor(e, _block_length(e) // 2 if time_series else 1)
        return e, float(max(r for r, _, _ in fits)), float(sig), floor * Kh, mem

    def remains(r2, cur, floor_rss, mem):
        """A residual no library term explains: structured beyond noise and above the floor, or with memory."""
        return ((r2 >= opts.structure_threshold and cur - floor_rss >= opts.min_unexplained * cur)
                or (mem is not None and mem >= opts.structure_threshold))

    # rounds: while a round named something and structure above the noise floor remains, select
    # again on what is left, with the thresholds relative to the remaining residual (a small effect
    # next to a large one explains little of the nominal residual but much of what is left)
    allowed, S, refused, flag_refused, rounds_base = list(range(p)), [], [], False, []
    ref, n_rounds = rss0_h, 0
    while True:
        n_rounds += 1
        rounds_base = list(S)
        S, allowed = signs(choose(allowed, S, ref), allowed)
        e, r2s, r2sig, floor_rss, mem = structure(S)
        cur = rss_h(S)
        new = [j for j in S if j not in rounds_base]
        left = remains(r2sig, cur, floor_rss, mem)
        if not new or not left or n_rounds >= opts.max_rounds:
            break
        ref = cur
    # 5. coefficients and bootstrap standard errors (original units: divide by the column scale)
    c = _solve(Gt, bt, S)
    coef = c / scale[S] if S else np.zeros(0)
    resid_t = yt - (Zt[:, S] @ c if S else 0.0)
    se_stat = bootstrap_stderr(Zt[:, S], yt, time_series, opts.n_boot, rng, resid_t) / scale[S] if S \
        else np.zeros(0)
    # regions of every variable and, for a time series, of the record (a drifting coefficient)
    Fm = np.column_stack([probe.F, np.arange(K)]) if clock is not None else probe.F
    misfit = misfit_stderr(Zt[:, S], yt, Fm[tr], se_stat * scale[S]) / scale[S] if S else np.zeros(0)
    se = np.sqrt(se_stat ** 2 + misfit ** 2)
    # 6. explained fractions in forward order on held-out data
    expl, prev = [], rss0_h
    for k in range(1, len(S) + 1):
        cur = rss_h(S[:k])
        expl.append((prev - cur) / rss0_h if rss0_h > 0 else 0.0)
        prev = cur
    rss_after_h = rss_h(S)
    # 7. structure left (computed in the last round), against the model-free noise floor
    floor_frac = floor_rss / rss0_h if rss0_h > 0 else 0.0
    above = max(0.0, rss_after_h / rss0_h - floor_frac) if rss0_h > 0 else 0.0
    # flagged relative to what is left, like the rounds (a structured residual under a large
    # explained one is still a residual the library has not named)
    left = remains(r2sig, rss_after_h, floor_rss, mem)
    floor_frac = min(floor_frac, rss_after_h / rss0_h) if rss0_h > 0 else floor_frac
    notes = [f"refused {r['key']} (coefficient {r['coefficient']:.4g}): {r['reason']}" for r in refused]
    if mem is not None and mem >= opts.structure_threshold:
        notes.append(f"the residual left follows its own past: its lags and the lagged states explain a further "
                     f"{100 * mem:.0f}% of it on held-out data (hysteresis, backlash, a delayed coupling: memory "
                     f"no library term holds)" + ("; the named effects are the library's nearest reading, not the "
                                                  "answer" if S else ""))
    tstruct, segs, time_flag = None, None, False
    if clock is not None:
        t, ep, tau = clock
        tstruct = time_structure(e, t, ep, tau, held, probe.poly2_resid, series=True)
        if tstruct["r2_gain"] >= opts.structure_threshold and tstruct["z"] >= critical(opts.min_z, tstruct["dof"]):
            time_flag = True
            notes.append("the residual left varies with time beyond a degree-2 polynomial in the variables "
                         "(a time-dependent disturbance, or state dependence that repeats with the motion): "
                         + describe_time(tstruct))
        if S:
            sg = segment_coefficients(Zt[:, S], yt, _block_length(resid_t))
            if sg is not None:
                segs = {"coef": (sg["coef"] / scale[S]).tolist(), "stderr": (sg["stderr"] / scale[S]).tolist(),
                        "q": sg["q"].tolist(), "varying": sg["varying"].tolist()}
                for k, j in enumerate(S):
                    if sg["varying"][k]:
                        time_flag = True
                        vals = ", ".join(f"{v:.4g}" for v in sg["coef"][:, k] / scale[j])
                        notes.append(f"{keys[j]} varies over the record: {vals} in {sg['coef'].shape[0]} "
                                     f"consecutive segments (Q = {sg['q'][k]:.3g})")
    lag1 = None
    if time_series:
        eh = e[held] - e[held].mean()
        den = float(eh @ eh)
        lag1 = float(eh[1:] @ eh[:-1] / den) if den > 0 else 0.0
    return StateFit(state=state, candidate_keys=keys, selected=list(S), coef=np.asarray(coef),
                    stderr=np.asarray(se), stderr_statistical=np.asarray(se_stat), stderr_misfit=misfit, explained=np.asarray(expl), rss0_heldout=rss0_h,
                    rss_heldout=rss_after_h, structure_r2=float(r2s), noise_floor_fraction=floor_frac,
                    unexplained_fraction=above,
                    unexplained=bool(left or flag_refused or time_flag), rounds=n_rounds, memory_r2=mem,
                    lag1_autocorr=lag1, refused=refused, notes=notes, time=tstruct, segments=segs)

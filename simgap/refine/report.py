"""The refinement loop end to end: residual -> selected effects -> refined model -> report.

:func:`refine` takes a system (built-in name, refined-system JSON path or System) and
transition data, and returns a :class:`RefineResult` whose ``report`` is the JSON of
``simgap refine`` (keys of issue 5):

* ``effects``: list of {name, state (0-based), state_name, variable or input, expr,
  coefficient, stderr (bootstrap), unit (model units), explained_fraction (of the nominal
  held-out residual variance of that state), physical (value in N, N s/m, ... or null)};
* ``rms_before``, ``rms_after``, ``max_before``, ``max_after``: per state, on held-out data,
  of r = x_next - f(x,u) (before) and x_next - f'(x,u) (after), in state units per tau;
* ``unexplained`` (bool) and per-state detail (``states``): remaining fraction of the
  residual, held-out R^2 of the structure test, lag-1 autocorrelation for time series;
* ``multistep`` (time series only): RMS error of 10- and 100-step open-loop predictions with
  the measured inputs from held-out states, for f and f';
* ``withdrawn``: effects the multi-step gate removed (f' predicted ``gate_steps`` steps ahead
  worse than f on held-out data), each with the reason; their states are flagged unexplained;
* ``refused``: selected terms with an impossible sign (friction that injects energy, a dead zone of
  negative width, a negative fraction delayed, ...), each with the reason; selection ran again
  without them, and a term impossible beyond two standard errors flags its state;
* ``history``: lags used (time series: ``input_delay`` candidates and lagged user terms);
  history effects are reported (``in_refined_system`` false) and counted in rms_after and the
  multi-step errors, but a memoryless f' cannot hold them;
* per effect ``stderr`` = sqrt(stderr_statistical^2 + stderr_misfit^2): the bootstrap part and
  the between-region spread of the coefficient (:func:`simgap.refine.selection.misfit_stderr`);
* per state ``noise_floor_fraction`` (model-free, :mod:`simgap.refine.structure`) and
  ``unexplained_fraction`` (remaining variance above the floor), both relative to the nominal
  model's held-out residual variance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from ..systems import System
from .data import Transitions, _continues, episodes, history, lagged_inputs, subset, time_order
from ..errors import SimgapError
from .effects import (LAG_PERIODS, Effect, candidate_effects, carry_matrix, coefficient_units,
                      integration_effect, physical, sign_check, velocity_dims)
from .refined import build_refined, load_system, refined_system
from .residual import Residuals, match_tau, residuals
from .selection import SelectionOptions, StateFit, select_state, split_heldout
from .structure import STATE_LAGS, Probe


@dataclass
class RefineResult:
    """Everything the loop produced (arrays for GUIs and recordings included)."""

    system: System                 # nominal, at the data's tau
    refined: System                # f' = f + tau * sum c g
    data: Transitions
    heldout: np.ndarray            # (K,) bool mask
    fits: list                     # StateFit per state
    effects: list                  # (Effect, coefficient, stderr, explained_fraction, stderr_stat., stderr_misfit)
    before: Residuals              # on all data
    after: Residuals
    report: dict


def refine(system, data: Transitions, effects: Optional[Sequence[str]] = None,
           user_terms: Sequence[Effect] = (), options: Optional[SelectionOptions] = None,
           name: Optional[str] = None) -> RefineResult:
    """Run the refinement loop (see module docstring and :mod:`simgap.refine.selection`).

    Parameters
    ----------
    system : str, path or System
        Nominal model f.
    data : Transitions
        Samples (x, u, x_next), tau apart.
    effects : list of str, optional
        Library effect names to consider (default: the whole library).
    user_terms : list of Effect
        Extra named terms (:func:`simgap.refine.effects.user_effect`).
    options : SelectionOptions
    """
    opts = options or SelectionOptions()
    sysobj = match_tau(load_system(system), data.tau)
    rng = np.random.default_rng(opts.seed)
    if data.is_time_series:           # rows in time order, episode by episode: blocks, segments, lags
        data = subset(data, time_order(data))
    max_lag, lag_note = (opts.max_lag, None) if opts.max_lag is not None else _choose_lags(sysobj, data)
    data, hist, lags, hist_info = _with_history(data, max_lag)
    if lag_note and lags:
        hist_info["chosen"] = lag_note
    if effects is not None and "input_delay" in effects and not lags:
        raise SimgapError(f"input_delay needs time-ordered data (time stamps t and x_next equal to the next "
                          f"row's x); {hist_info['reason']}")
    deep = [e.name for e in user_terms if e.lag > lags]
    if deep:
        raise SimgapError(f"user term(s) {deep} read lagged values, but "
                          + (f"only {lags} period(s) of history are used" if lags else
                             "the data carry no time order (transitions with time stamps t)"))
    before = residuals(sysobj, data)
    weighted = opts.weighted and data.se is not None
    cands = candidate_effects(sysobj, effects, user_terms, max_lag=lags)
    torder = time_order(data)
    held = split_heldout(data.K, data.t, opts, torder)
    # rows are in time order here: the clock lets selection look along time
    clock = (data.t, episodes(data), data.tau) if data.is_time_series else None
    # the structure test also sees the lagged inputs, so an unnamed delay or lag still shows as structure
    w = sysobj.n + sysobj.m
    lagged_u = [hist[:, d * w + sysobj.n: (d + 1) * w] for d in range(lags)]
    if lags:      # and the inputs through the longest library lag: memory beyond the lags shows too
        g = len(LAG_PERIODS) - 1
        lagged_u.append(hist[:, lags * w + g * sysobj.m: lags * w + (g + 1) * sysobj.m])
    V = np.concatenate([data.x, data.u] + lagged_u, axis=1)
    angle_cols = np.concatenate([sysobj.angle_mask, np.zeros(V.shape[1] - sysobj.n, dtype=bool)])
    # the memory test: each row's previous row along its trajectory, and the lagged states
    prev = None
    if lags:
        cont = _continues(data, torder)
        prev = np.full(data.K, -1)
        prev[torder[1:]] = np.where(cont[1:], torder[:-1], -1)
    lagged_x = np.concatenate([hist[:, d * w: d * w + sysobj.n] for d in range(min(lags, STATE_LAGS))], axis=1) \
        if lags else None
    probe = Probe(V, angle_cols, held, torder, rng, prev=prev, lagged_x=lagged_x)
    # velocity states first: the integration term of a position uses the refined velocity update
    vd = velocity_dims(sysobj)
    order = list(vd) + [i for i in range(sysobj.n) if i not in vd]
    K_carry = carry_matrix(sysobj)
    fits, chosen = {}, []
    for i in order:
        ci = [e for e in cands if e.state == i]
        if any(e.name == "integration" for e in ci) and chosen:
            interim = refined_system(sysobj, [c[0] for c in chosen if c[0].lag == 0],
                                     [c[1] for c in chosen if c[0].lag == 0])
            ci = [integration_effect(interim, i, sysobj.state_names.index(e.variable))
                  if e.name == "integration" else e for e in ci]
        Theta = np.stack([e(data.x, data.u, hist) for e in ci], axis=1) if ci else np.zeros((data.K, 0))
        if not np.all(np.isfinite(Theta)):
            bad = [e.key(sysobj) for e, col in zip(ci, Theta.T) if not np.all(np.isfinite(col))]
            raise SimgapError(f"candidate terms {bad} are not finite on the data")
        y = before.r[:, i] / data.tau
        if chosen and np.any(K_carry[i]):
            # a position that integrates a corrected velocity: what is left after the carried corrections
            interim = refined_system(sysobj, [c[0] for c in chosen if c[0].lag == 0],
                                     [c[1] for c in chosen if c[0].lag == 0])
            y = _after(interim, data, hist, chosen).r[:, i] / data.tau
        if weighted:
            # weighted least squares: row k counts 1 / se_ki (normalized to mean square 1)
            wt = row_weights(data.se[:, i])
            y, Theta = y * wt, Theta * wt[:, None]
        fit = select_state(y, Theta, [e.key(sysobj) for e in ci], held, probe, i,
                           data.is_time_series, opts, rng, sign_check(sysobj, ci, data.x), clock)
        fits[i] = fit
        for k, j in enumerate(fit.selected):
            chosen.append((ci[j], float(fit.coef[k]), float(fit.stderr[k]), float(fit.explained[k]),
                           float(fit.stderr_statistical[k]), float(fit.stderr_misfit[k])))
    fits = [fits[i] for i in range(sysobj.n)]
    chosen.sort(key=lambda c: c[0].state)
    chosen, withdrawn = _multistep_gate(sysobj, data, held, hist, chosen, fits, opts)
    base_spec = sysobj.params.get("_refined_json") or sysobj.params.get("_system_file") or sysobj.name
    now = [c for c in chosen if c[0].lag == 0]
    refined = build_refined(sysobj, base_spec, [c[0] for c in now], [c[1] for c in now],
                            [c[2] for c in now], name=name)
    after = _after(refined, data, hist, chosen)
    for fit in fits:      # after a withdrawal the remaining residual is larger than selection saw
        wt = row_weights(data.se[:, fit.state]) if weighted else 1.0
        fit.rss_heldout = float(np.sum(((after.r[:, fit.state] * wt)[held] / data.tau) ** 2))
        fit.unexplained_fraction = max(0.0, fit.remaining_fraction - fit.noise_floor_fraction)
    report = _report(sysobj, refined, data, held, fits, chosen, before, after, opts, hist, withdrawn, hist_info)
    return RefineResult(system=sysobj, refined=refined, data=data, heldout=held, fits=fits,
                        effects=chosen, before=before, after=after, report=report)


def row_weights(se: np.ndarray) -> np.ndarray:
    """Weights 1 / se (standard errors floored at 1 % of their median, so exact pairs do not take
    over), scaled to mean square 1; all ones when every se is zero (noise-free data)."""
    med = float(np.median(se))
    if not med > 0:
        return np.ones_like(se)
    w = 1.0 / np.maximum(se, 0.01 * med)
    return w / np.sqrt(np.mean(w ** 2))


def validate(res: RefineResult, data: Transitions) -> dict:
    """One-step and multi-step errors of f and f' on a record the fit never saw (all its rows).

    One step: RMS of x_next - f(x, u) and of x_next - f'(x, u) per state (history effects included
    when the record has the time order they need). Multi-step (time series): RMS of 10- and
    100-step open-loop predictions with the record's inputs, as in the report's ``multistep``.
    """
    lags = int(res.report.get("history", {}).get("lags", 0))
    data, hist, used, _ = _with_history(data, lags)
    chosen = list(res.effects)
    if used < lags:
        chosen = [c for c in chosen if c[0].lag == 0]
    s, f1 = match_tau(res.system, data.tau), match_tau(res.refined, data.tau)
    allrows = np.ones(data.K, dtype=bool)
    rb, ra = residuals(s, data).r, _after(f1, data, hist, chosen).r
    out = {"data": data.source, "samples": int(data.K),
           "rms_before": np.sqrt(np.mean(rb ** 2, axis=0)).tolist(),
           "rms_after": np.sqrt(np.mean(ra ** 2, axis=0)).tolist(), "multistep": {}}
    if len(chosen) < len(res.effects):
        out["note"] = "history effects left out: the record has no time order"
    if data.is_time_series:
        for k in (10, 100):
            b = multistep_rms(s, data, allrows, k)
            if b is not None:
                out["multistep"][str(k)] = {"rms_before": b.tolist(), "seconds": k * data.tau,
                                            "rms_after": multistep_rms(f1, data, allrows, k, hist, chosen).tolist()}
    return out


def format_validation(v: dict, names) -> str:
    """Table of :func:`validate`."""
    lines = ["", f"validation on {v['data']} ({v['samples']} samples, not used for fitting)",
             f"{'':<20}" + "".join(f"{n:>24}" for n in names)]
    lines.append(f"{'RMS 1-step f':<20}" + "".join(f"{x:>24.4g}" for x in v["rms_before"]))
    lines.append(f"{'RMS 1-step f' + chr(39):<20}" + "".join(f"{x:>24.4g}" for x in v["rms_after"]))
    for k, ms in v["multistep"].items():
        lines.append(f"{'RMS ' + k + '-step f':<20}" + "".join(f"{x:>24.4g}" for x in ms["rms_before"]))
        lines.append(f"{'RMS ' + k + '-step f' + chr(39):<20}" + "".join(f"{x:>24.4g}" for x in ms["rms_after"]))
    if "note" in v:
        lines.append(v["note"])
    return "\n".join(lines)


#: the deepest input delay the data may ask for (periods), and the least used
MAX_LAG_AUTO, MIN_LAG = 16, 3


def _choose_lags(s: System, data: Transitions, z_min: float = 5.0) -> tuple:
    """(lags, note): history depth chosen by the data, between MIN_LAG and MAX_LAG_AUTO periods.

    For every state i and input j the input enters, the nominal residual rate is regressed (rows
    with 16 periods of history) on 1, x and B_ij u, and then, by forward selection while the added
    term's |t| >= ``z_min`` (standard errors inflated by the residual's block length), on the
    library's first-order lag terms (memory they hold needs no deeper delays) and the delay terms
    B_ij (u_{k-d} - u_k), d = 1..16; the deepest delay selected sets the depth, at least MIN_LAG
    (the library's default).
    """
    if not data.is_time_series:
        return 0, None
    H, valid = history(data, MAX_LAG_AUTO)
    if valid.mean() < 0.5 or valid.sum() < 20 * (MAX_LAG_AUTO + s.n + 3):
        return MIN_LAG, None
    from .effects import _input_rate
    from .selection import _block_length
    lagged = lagged_inputs(data, LAG_PERIODS)[valid]
    x, u, H = data.x[valid], data.u[valid], H[valid]
    r = s.diff(data.x_next[valid], s.f(x, u)) / data.tau
    w = s.n + s.m
    deepest, where = 0, ""
    for i in range(s.n):
        for j in range(s.m):
            B = _input_rate(s, i, j)(x, u)
            if not np.any(np.abs(B) > 0):
                continue
            D = np.stack([B * (H[:, (d - 1) * w + s.n + j] - u[:, j]) for d in range(1, MAX_LAG_AUTO + 1)], axis=1)
            Lg = B[:, None] * (lagged[:, j::s.m] - u[:, [j]])       # first-order lags: memory they hold
            A = np.column_stack([np.ones(len(x)), x, B * u[:, j], Lg, D])
            sc = np.sqrt(np.mean(A ** 2, axis=0))
            A = A / np.where(sc > 0, sc, 1.0)
            y = r[:, i]
            G, b = A.T @ A, A.T @ y
            n_ctrl = A.shape[1] - MAX_LAG_AUTO - len(LAG_PERIODS)
            S = list(range(n_ctrl))                                            # controls, always in
            blk = _block_length(y - A[:, S] @ np.linalg.lstsq(A[:, S], y, rcond=None)[0])
            # forward selection among the lag and delay terms while the added term has |t| >= z_min
            while True:
                best = None
                for j2 in range(n_ctrl, A.shape[1]):
                    if j2 in S:
                        continue
                    T = S + [j2]
                    c = np.linalg.lstsq(G[np.ix_(T, T)], b[T], rcond=None)[0]
                    rss = float(y @ y - 2 * c @ b[T] + c @ G[np.ix_(T, T)] @ c)
                    if best is None or rss < best[0]:
                        best = (rss, j2, c, T)
                if best is None:
                    break
                rss, j2, c, T = best
                s2 = max(rss, 0.0) / max(len(y) - len(T), 1) * blk
                se = np.sqrt(s2 * max(float(np.linalg.pinv(G[np.ix_(T, T)])[-1, -1]), 0.0))
                if se <= 0 or abs(c[-1]) / se < z_min:
                    break
                S = T
            dsel = [j2 - (A.shape[1] - MAX_LAG_AUTO) + 1 for j2 in S if j2 >= A.shape[1] - MAX_LAG_AUTO]
            if dsel and max(dsel) > deepest:
                deepest, where = int(max(dsel)), f"{s.state_names[i]} / {s.input_names[j]}"
    lags = max(MIN_LAG, deepest)
    note = (f"chosen by the data: delayed-input terms significant up to {deepest} period(s) ({where})"
            if deepest > MIN_LAG else f"the default {MIN_LAG} (no delayed-input term significant deeper)")
    return lags, note


def _with_history(data: Transitions, max_lag: int) -> tuple:
    """(data restricted to rows with ``max_lag`` periods of history, history, lags used, info)."""
    if not data.is_time_series or max_lag < 1:
        return data, np.zeros((data.K, 0)), 0, {"lags": 0, "reason": "no time order" if max_lag else "disabled"}
    hist, valid = history(data, max_lag)
    if valid.mean() < 0.5:
        return data, np.zeros((data.K, 0)), 0, {
            "lags": 0, "reason": "fewer than half of the rows continue a trajectory (x_next = next x)"}
    info = {"lags": int(max_lag), "rows_without_history": int((~valid).sum())}
    # then the inputs through first-order lags (actuator_lag candidates) and the clock last (user terms
    # may read t): [x_{k-1}, u_{k-1}, .., x_{k-L}, u_{k-L}, lagged inputs, t]
    hist = np.concatenate([hist, lagged_inputs(data, LAG_PERIODS), data.t[:, None]], axis=1)
    if not valid.all():
        data, hist = subset(data, valid), hist[valid]
    return data, hist, int(max_lag), info


def _extra_rate(data: Transitions, hist: np.ndarray, chosen, x=None, rows=None, K=None) -> np.ndarray:
    """sum_k c_k g_k of the history effects (lag > 0) on rows (x default: the data's), carried into
    the positions by K (:func:`simgap.refine.effects.carry_matrix`) as the refined system does."""
    rows = slice(None) if rows is None else rows
    x = data.x[rows] if x is None else x
    out = np.zeros_like(x)
    for e, c, *_ in chosen:
        if e.lag:
            out[:, e.state] += c * e(x, data.u[rows], hist[rows])
    return out if K is None or not np.any(K) else out + out @ K.T


def _after(refined: System, data: Transitions, hist, chosen) -> Residuals:
    """Residuals of f' including the history effects (which the memoryless f' cannot hold)."""
    r = residuals(refined, data)
    if any(e.lag for e, *_ in chosen):
        K = carry_matrix(refined)
        r = Residuals(refined, data, r.r - data.tau * _extra_rate(data, hist, chosen, K=K))
    return r


def _multistep_gate(s: System, data: Transitions, held, hist, chosen, fits, opts) -> tuple:
    """Withdraw effects while f' predicts worse than f over 10 or ``opts.gate_steps`` steps (held-out).

    Worse means mean_i (rms'_i / rms_i)^2 > 1 + ``opts.gate_tolerance`` over the states, at either
    horizon. The effect whose removal helps most goes first; each withdrawn effect is reported with
    the numbers, and its state is flagged unexplained (the residual it seemed to fix is still there).
    """
    horizons = sorted({k for k in (10, opts.gate_steps) if k >= 2})
    if not data.is_time_series or not chosen or not horizons:
        return chosen, []
    base = {k: multistep_rms(s, data, held, k) for k in horizons}
    horizons = [k for k in horizons if base[k] is not None]
    if not horizons:
        return chosen, []
    b = {k: np.where(base[k] > 0, base[k], 1.0) for k in horizons}

    def score(ch):
        f1 = refined_system(s, [c[0] for c in ch if c[0].lag == 0], [c[1] for c in ch if c[0].lag == 0])
        return {k: multistep_rms(f1, data, held, k, hist, ch) for k in horizons}

    def ratios(sc):
        return {k: float(np.mean((sc[k] / b[k]) ** 2)) for k in horizons}

    def worse(sc):
        return max(ratios(sc).values()) > 1.0 + opts.gate_tolerance

    withdrawn = []
    cur = score(chosen)
    while chosen and worse(cur):
        trials = [(max(ratios(score(chosen[:j] + chosen[j + 1:])).values()), j) for j in range(len(chosen))]
        _, j = min(trials)
        e, c = chosen[j][0], chosen[j][1]
        before_rms = cur
        chosen = chosen[:j] + chosen[j + 1:]
        cur = score(chosen)
        k = max(horizons, key=lambda k: ratios(before_rms)[k])
        reason = (f"{k}-step held-out RMS with it {np.array2string(before_rms[k], precision=3)} is worse than the "
                  f"nominal model's {np.array2string(base[k], precision=3)}; without it "
                  f"{np.array2string(cur[k], precision=3)}")
        withdrawn.append({"name": e.name, "state": int(e.state), "state_name": s.state_names[e.state],
                          "key": e.key(s), "coefficient": c, "reason": reason, "horizon": int(k)})
        fit = fits[e.state]
        fit.selected = [i for i in fit.selected if fit.candidate_keys[i] != e.key(s)]
        fit.unexplained = True
        fit.notes.append(f"withdrew {e.key(s)} (coefficient {c:.4g}): {reason}")
    return chosen, withdrawn


def _in_time_order(data: Transitions, held: np.ndarray) -> tuple:
    """Rows in time order: (order, x, u, x_next, held, link), link[j] (K-1,) True when row j+1
    continues row j's trajectory (x_next[j] is x[j+1], within one episode)."""
    order = time_order(data)
    ep = episodes(data)[order]
    x, u, xn, h = data.x[order], data.u[order], data.x_next[order], held[order]
    link = np.all(np.isclose(xn[:-1], x[1:], rtol=0, atol=1e-12 * (1 + np.abs(x[1:]))), axis=1) \
        & (ep[:-1] == ep[1:])
    return order, x, u, xn, h, link


def multistep_rms(system: System, data: Transitions, held: np.ndarray, k: int,
                  hist: Optional[np.ndarray] = None, chosen=()) -> Optional[np.ndarray]:
    """RMS error (n,) of k-step open-loop predictions with the measured inputs (time series only).

    From every held-out sample s whose next k transitions are all held-out and consecutive
    (x_next[s+j] = x[s+j+1]), iterate x <- f(x, u[s+j]) for j < k and compare with x_next[s+k-1].
    History effects among ``chosen`` (lag > 0) add tau c g(x, u, hist) with the recorded lagged
    values ``hist``. None when no such start exists.
    """
    if data.t is None:
        return None
    K = data.K
    order, x, u, xn, h, link = _in_time_order(data, held)
    cont = np.zeros(K, dtype=bool)
    cont[:-1] = link
    # good[s] = h[s..s+k-1] all True and cont[s..s+k-2] all True (cumulative sums)
    bad = (~h).astype(int)
    brk = (~cont).astype(int)
    cb = np.concatenate([[0], np.cumsum(bad)])
    cc = np.concatenate([[0], np.cumsum(brk)])
    s = np.arange(K - k + 1)
    good = (cb[s + k] - cb[s] == 0) & ((cc[s + k - 1] - cc[s]) == 0 if k > 1 else True)
    starts = s[good]
    if starts.size == 0:
        return None
    z = x[starts]
    extra = [c for c in chosen if c[0].lag]
    hs = hist[order] if extra else None
    K = carry_matrix(system) if extra else None
    carried = K is not None and bool(np.any(K))
    for j in range(k):
        zn = system.f(z, u[starts + j])
        add = np.zeros_like(zn)
        for e, c, *_ in extra:
            add[:, e.state] += data.tau * c * e(z, u[starts + j], hs[starts + j])
        z = zn + (add + add @ K.T if carried else add)
    e = system.diff(z, xn[starts + k - 1])
    return np.sqrt(np.mean(e ** 2, axis=0))


def free_run_check(system: System, refined: System, data: Transitions, held: np.ndarray,
                   max_steps: int = 5000) -> Optional[dict]:
    """Free simulation of f and f' (memoryless) along every contiguous held-out stretch of a time series.

    From the first state of each stretch (consecutive rows, x_next = next x), both models are
    iterated with the recorded inputs for the stretch's length (at most ``max_steps``). A model
    diverges on a stretch when a state becomes non-finite or leaves X by more than 10 times its
    width. Returns {"stretches", "steps", "diverged_before", "diverged_after", "rms_before",
    "rms_after"} (RMS over the steps where both stay finite), None without time order.
    """
    if data.t is None:
        return None
    K = data.K
    _, x, u, xn, h, link = _in_time_order(data, held)
    cont = np.zeros(K, dtype=bool)
    cont[1:] = link & h[1:] & h[:-1]
    starts = np.flatnonzero(h & ~cont)
    if starts.size == 0:
        return None
    ends = np.r_[starts[1:], K]
    ends = np.array([s0 + int(np.argmin(np.r_[cont[s0 + 1:e0], False])) + 1 for s0, e0 in zip(starts, ends)])
    lengths = np.minimum(ends - starts, max_steps)
    span = system.x_hi - system.x_lo
    out = {"stretches": int(starts.size), "steps": int(lengths.sum())}
    for key, m in (("before", system), ("after", refined)):
        z = x[starts].copy()
        alive = np.ones(starts.size, dtype=bool)
        se, cnt = np.zeros(system.n), 0
        for j in range(int(lengths.max())):
            act = alive & (j < lengths)
            if not act.any():
                break
            zn = m.f(z[act], u[starts[act] + j])
            ok = np.all(np.isfinite(zn), axis=1) & np.all(np.abs(zn - system.x_lo - span / 2) <= 10.5 * span, axis=1)
            idx = np.flatnonzero(act)
            alive[idx[~ok]] = False
            z[idx[ok]] = zn[ok]
            good = idx[ok]
            se += np.sum(system.diff(z[good], xn[starts[good] + j]) ** 2, axis=0)
            cnt += good.size
        out[f"diverged_{key}"] = int((~alive).sum())
        out[f"rms_{key}"] = np.sqrt(se / max(cnt, 1)).tolist()
    return out


def _f(v) -> Optional[float]:
    v = float(v)
    return v if np.isfinite(v) else None


def _report(s: System, refined: System, data: Transitions, held, fits: Sequence[StateFit], chosen,
            before: Residuals, after: Residuals, opts: SelectionOptions, hist, withdrawn, hist_info) -> dict:
    rb, ra = before.r[held], after.r[held]
    free = free_run_check(s, refined, data, held) if data.is_time_series else None
    if free and free["diverged_after"] > free["diverged_before"]:
        msg = (f"the refined model diverges in free simulation on {free['diverged_after']} of "
               f"{free['stretches']} held-out stretches (the nominal on {free['diverged_before']})")
        for fit in fits:
            fit.unexplained = True
            fit.notes.append(msg)
        free["note"] = msg
    eff = []
    for e, c, se, ex, se_stat, se_mis in chosen:
        d = {"name": e.name, "state": int(e.state), "state_name": s.state_names[e.state]}
        if e.variable in s.input_names:
            d["input"] = e.variable
        elif e.variable is not None:
            d["variable"] = e.variable
        if "periods" in e.params:
            d["periods"] = float(e.params["periods"]) if e.name == "actuator_lag" else int(e.params["periods"])
        d["in_refined_system"] = e.lag == 0
        d.update({"expr": e.expr, "coefficient": c, "stderr": _f(se), "stderr_statistical": _f(se_stat),
                  "stderr_misfit": _f(se_mis), "unit": coefficient_units(s, e),
                  "explained_fraction": ex, "physical": physical(s, e, c, se)})
        if d["physical"] is not None:
            d["physical"] = {k: (_f(v) if isinstance(v, (float, np.floating)) else v)
                             for k, v in d["physical"].items()}
        fit = fits[e.state]
        sel = [fit.candidate_keys[j] for j in fit.selected]
        if fit.segments is not None and e.key(s) in sel:
            k = sel.index(e.key(s))
            d["segments"] = {"coefficient": [row[k] for row in fit.segments["coef"]],
                             "stderr": [row[k] for row in fit.segments["stderr"]],
                             "varying": bool(fit.segments["varying"][k])}
        eff.append(d)
    states = []
    for fit in fits:
        states.append({
            "state": fit.state, "state_name": s.state_names[fit.state],
            "candidates": list(fit.candidate_keys),
            "selected": [fit.candidate_keys[j] for j in fit.selected],
            "explained_fraction": fit.explained_total,
            "remaining_fraction": fit.remaining_fraction,
            "structure_r2": fit.structure_r2,
            "noise_floor_fraction": fit.noise_floor_fraction,
            "unexplained_fraction": fit.unexplained_fraction,
            "unexplained": fit.unexplained,
            "lag1_autocorr": fit.lag1_autocorr,
            "memory_r2": fit.memory_r2,
            "rounds": fit.rounds,
            "time": fit.time,
            "notes": list(fit.notes),
        })
    outside = int(np.any((data.x < s.x_lo) | (data.x > s.x_hi), axis=1).sum())
    multistep = {}
    if data.is_time_series:
        for k in (10, 100):
            b, a = multistep_rms(s, data, held, k), multistep_rms(refined, data, held, k, hist, chosen)
            if b is not None:
                multistep[str(k)] = {"rms_before": b.tolist(), "rms_after": a.tolist(),
                                     "seconds": k * data.tau}
    return {
        "system": s.name, "refined_system": refined.name, "data": data.source,
        "tau": data.tau, "samples": int(data.K), "train": int((~held).sum()), "heldout": int(held.sum()),
        "holdout_kind": "contiguous time segments" if data.is_time_series else "random rows",
        "weighted": bool(opts.weighted and data.se is not None),   # rows weighted by 1 / se of x_next
        "dropped_nonfinite": int(data.n_dropped), "outside_X": outside,
        "state_names": list(s.state_names),
        "effects": eff,
        "rms_before": np.sqrt(np.mean(rb ** 2, axis=0)).tolist(),
        "rms_after": np.sqrt(np.mean(ra ** 2, axis=0)).tolist(),
        "max_before": np.abs(rb).max(axis=0).tolist(),
        "max_after": np.abs(ra).max(axis=0).tolist(),
        "mean_before": rb.mean(axis=0).tolist(),
        "mean_after": ra.mean(axis=0).tolist(),
        "unexplained": bool(any(f.unexplained for f in fits)),
        "states": states,
        "multistep": multistep,
        "free_run": free,
        "withdrawn": withdrawn,
        "refused": [dict(r, state=int(f.state), state_name=s.state_names[f.state]) for f in fits for r in f.refused],
        "history": hist_info,
        "options": {"holdout": opts.holdout, "n_segments": opts.n_segments,
                    "min_explained": opts.min_explained, "n_boot": opts.n_boot,
                    "structure_threshold": opts.structure_threshold,
                    "min_unexplained": opts.min_unexplained, "seed": opts.seed, "max_lag": opts.max_lag,
                    "gate_steps": opts.gate_steps, "gate_tolerance": opts.gate_tolerance,
                    "max_rounds": opts.max_rounds},
        "data_meta": data.meta,
    }


def format_table(report: dict) -> str:
    """Readable terminal summary of a refine report."""
    names = report["state_names"]
    lines = [f"system {report['system']}  data {report['data']}  tau {report['tau']:g} s  "
             f"samples {report['samples']} (train {report['train']}, held-out {report['heldout']}, "
             f"{report['holdout_kind']})"]
    if report["dropped_nonfinite"]:
        lines.append(f"dropped {report['dropped_nonfinite']} rows with NaN/inf")
    lines.append("")
    if report["effects"]:
        lines.append(f"{'effect':<18}{'state':<8}{'var':<8}{'coefficient':>13}{'stderr':>11}  "
                     f"{'unit':<16}{'explained':>9}  physical")
        for e in report["effects"]:
            var = e.get("input", e.get("variable")) or "-"
            ph = e["physical"]
            phs = f"{ph['value']:.4g} {ph['unit']} ({ph['quantity']})" if ph else ""
            if not e.get("in_refined_system", True):
                phs += " [needs memory: not in the saved f']"
            if e.get("segments", {}).get("varying"):
                phs += " [VARIES over the record: " + ", ".join(f"{v:.3g}" for v in e["segments"]["coefficient"]) + "]"
            se = e["stderr"]
            lines.append(f"{e['name']:<18}{e['state_name']:<8}{var:<8}{e['coefficient']:>13.5g}"
                         f"{(se if se is not None else float('nan')):>11.2g}  {e['unit']:<16}"
                         f"{100 * e['explained_fraction']:>8.1f}%  {phs}")
    else:
        lines.append("no effect selected")
    for r in report.get("refused", []):
        lines.append(f"refused {r['key']} (coefficient {r['coefficient']:.4g}): {r['reason']}")
    for w in report.get("withdrawn", []):
        lines.append(f"withdrawn {w['key']} (coefficient {w['coefficient']:.4g}): {w['reason']}")
    hist = report.get("history", {})
    if hist.get("lags"):
        lines.append(f"history: {hist['lags']} periods of lagged inputs/states used "
                     f"({hist['rows_without_history']} rows at segment starts left out)")
    lines.append("")
    lines.append(f"{'held-out residual':<20}" + "".join(f"{n:>24}" for n in names))
    for key, label in (("rms_before", "RMS before (f)"), ("rms_after", "RMS after (f')"),
                       ("max_before", "max before (f)"), ("max_after", "max after (f')")):
        lines.append(f"{label:<20}" + "".join(f"{v:>24.4g}" for v in report[key]))
    ratio = [b / a if a > 0 else float("inf") for b, a in zip(report["rms_before"], report["rms_after"])]
    lines.append(f"{'RMS ratio':<20}" + "".join(f"{v:>24.3g}" for v in ratio))
    for k, ms in report.get("multistep", {}).items():
        lines.append(f"{'RMS ' + k + '-step f':<20}" + "".join(f"{v:>24.4g}" for v in ms["rms_before"]))
        lines.append(f"{'RMS ' + k + '-step f' + chr(39):<20}" + "".join(f"{v:>24.4g}" for v in ms["rms_after"]))
    lines.append("")
    for st in report["states"]:
        msg = (f"state {st['state_name']}: explained {100 * st['explained_fraction']:.1f}% of the residual "
               f"variance, noise floor {100 * st['noise_floor_fraction']:.1f}%, "
               f"structure left R^2 = {st['structure_r2']:.3f}")
        if st["lag1_autocorr"] is not None:
            msg += f", lag-1 autocorrelation {st['lag1_autocorr']:.2f}"
        if st.get("memory_r2") is not None:
            msg += f", memory R^2 = {st['memory_r2']:.3f}"
        if st.get("rounds", 1) > 1:
            msg += f", {st['rounds']} selection rounds"
        tm = st.get("time")
        if tm and tm["r2_gain"] >= 0.01:
            msg += f", time explains {100 * tm['r2_gain']:.0f}% of what is left"
        if st["unexplained"]:
            msg += (f"  -> UNEXPLAINED: {100 * st['remaining_fraction']:.1f}% of the residual variance remains, "
                    f"{100 * st['unexplained_fraction']:.1f}% above the noise floor")
        lines.append(msg)
        lines += [f"  {n}" for n in st["notes"] if "varies with time" in n or "varies over the record" in n]
    fr = report.get("free_run")
    if fr:
        lines.append(f"free run on {fr['stretches']} held-out stretches ({fr['steps']} steps): diverged f "
                     f"{fr['diverged_before']}, f' {fr['diverged_after']}" + (f"  -> {fr['note']}" if "note" in fr else ""))
    lines.append(f"unexplained: {'true' if report['unexplained'] else 'false'}")
    return "\n".join(lines)


def format_gap_comparison(c: dict, names) -> str:
    """Table of :func:`simgap.refine.compare.gap_comparison` (certified gap and winning domain)."""
    lines = ["", f"{'certified gap gamma':<22}" + "".join(f"{n:>16}" for n in names)]
    for key, label in (("gamma_max_before", "max over data, f"), ("gamma_max_after", "max over data, f'"),
                       ("gamma_mean_before", "mean over data, f"), ("gamma_mean_after", "mean over data, f'")):
        lines.append(f"{label:<22}" + "".join(f"{v:>16.4g}" for v in c[key]))
    if "winning_before" in c:
        lines.append(f"winning domain: {c['winning_before']} cells with f, {c['winning_after']} cells with f' "
                     f"(of {c['domain_cells']}; eta = {c['eta']}, hold = {c['hold']})")
    return "\n".join(lines)

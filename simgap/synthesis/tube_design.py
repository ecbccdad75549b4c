"""The box tube's design, chosen by the tool: the plan's pace among a few candidates, ranked by what each
proves, and, when none proves, the levers table (what each way out would need, computed from the
certificate's own formulas).

The pace is the plan's input weight w (:func:`~simgap.synthesis.box_tube.synthesize_box_tube`'s
``plan_input_weight``): the nominal plan is the saturated LQR loop with Bryson's weights over the safe box
and its input weight multiplied by w, so a larger w makes a slower plan (smaller velocities, more periods
T0) that leaves more room around it. Each candidate is designed and proved as a whole (plan, terminal box,
the tolerable gap factor s, the per-run noise bound lam); the ranking prefers, in order,

1. a proof at the certified gap (s >= 1),
   with a plan shorter than the rollouts' horizon (a plan of T0 >= T periods is ranked as not proved),
2. a per-run statement whose noise term beta_noise = 2 n T exp(-lam^2 / 2) is at most :data:`NOISE_TERM`
   (lam capped there: beyond it more lam buys nothing a user sees),
3. the largest margin s, then the fewest periods.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

#: the plan's input-weight factors tried (the pace, fastest first)
PACES = (1.0, 10.0, 100.0, 1000.0, 10000.0)
#: the per-run statement's noise term below which a larger lam is not preferred
NOISE_TERM = 1e-4


@dataclass
class Candidate:
    """One design tried (a pace and the tube's gain, ``gain`` = the exponent c of its LQR input weight, None
    when given): its plan length, whether the proof holds at the certified gap, the tolerable gap factor s
    (coarse), the per-run noise bound lam (coarse), or why it could not be designed."""

    pace: float
    gain: Optional[float] = None
    T0: Optional[int] = None
    proved: bool = False
    margin: Optional[float] = None
    lam: Optional[float] = None
    error: str = ""
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)

    def score(self, n: int, horizon: int) -> tuple:
        """(proved and the plan ends within the runs' horizon, capped lam, margin, -T0): larger is better."""
        if self.error:
            return (-1, 0.0, 0.0, 0)
        if horizon and self.T0 is not None and self.T0 >= horizon:  # runs would end before the plan does
            return (0, 0.0, 0.0, -self.T0)
        lam = 0.0 if self.lam is None else self.lam
        lam_cap = float(np.sqrt(2.0 * np.log(2.0 * n * max(horizon, 1) / NOISE_TERM)))
        margin = 0.0 if self.margin is None else min(self.margin, 1e12)
        return (int(self.proved), min(lam, lam_cap), margin, -(self.T0 or 0))

    def label(self) -> str:
        return f"pace x{self.pace:g}" + ("" if self.gain is None else f", K 10^{self.gain:g}")

    def row(self) -> str:
        if self.error:
            return f"{self.label()}: no plan ({self.error.split(': ')[0]})"
        s = "any" if self.margin is not None and not np.isfinite(self.margin) else \
            "-" if self.margin is None else f"{self.margin:.3g}"
        lam = "" if self.lam is None else f", per-run noise bound lam {self.lam:.3g}"
        if self.extra.get("horizon") and self.T0 >= self.extra["horizon"]:
            lam += f"; the plan outlasts the runs' horizon {self.extra['horizon']}"
        return (f"{self.label()}: T0 {self.T0}, {'proved' if self.proved else 'not proved'} at the certified "
                f"gap, margin {s}{lam} ({self.seconds:.1f} s)")

    def to_dict(self) -> dict:
        return {"pace": self.pace, "gain": self.gain, "T0": self.T0, "proved": self.proved,
                "margin": None if self.margin is None or not np.isfinite(self.margin) else self.margin,
                "lam": self.lam, "error": self.error, "seconds": round(self.seconds, 3)}


def best_candidate(cands: list, n: int, horizon: int) -> Candidate:
    """The candidate the ranking of the module docstring prefers."""
    return max(cands, key=lambda c: c.score(n, horizon))


def why_chosen(best: Candidate, cands: list) -> str:
    """One line: why this pace."""
    tried = ", ".join(f"x{c.pace:g}" for c in cands)
    if best.error:
        return f"no pace gave a plan (tried {tried})"
    if not best.proved:
        return f"no pace proves at the certified gap (tried {tried}); the closest (largest margin) is shown"
    others = [c for c in cands if c is not best and c.proved]
    if best.lam is not None and any(c.lam is not None and c.lam < best.lam for c in others):
        return f"the largest per-run noise bound among the paces that prove (tried {tried})"
    return f"the largest margin among the paces that prove (tried {tried})"


# ---------------------------------------------------------------------------------------
# the levers table
# ---------------------------------------------------------------------------------------

def _runs_for(cert, i: int, need_sum: float) -> Optional[int]:
    """The smallest N1hat whose delta_1 + delta_2 in dimension i at the certificate's betas is at most
    ``need_sum`` (None: no N up to 2^40 gets there)."""
    from ..certify.bounds import BoundOptions, delta_from_beta
    d = cert.dims[i]
    if d.beta1 is None or d.Mhat is None or need_sum <= 0 or d.Mhat <= 0 or d.beta1 <= 0 or d.beta2 <= 0:
        return None  # (a noise-free state has Mhat = 0 and no betas: more runs change nothing there)
    b = dict(cert.options.get("bounds") or {})
    opts = BoundOptions(**{k: v for k, v in b.items() if k in BoundOptions.__dataclass_fields__})
    M = np.array([d.Mhat])

    def total(N):
        d1, d2 = delta_from_beta(M, np.array([d.beta1]), np.array([d.beta2]), int(N), cert.K, opts)
        return float(d1[0] + d2[0])

    lo, hi = cert.n_runs, cert.n_runs
    while total(hi) > need_sum:
        lo, hi = hi, hi * 2
        if hi > 2 ** 40:
            return None
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if total(mid) <= need_sum else (mid, hi)
    return hi


def levers(cert, system, w_max, scale: float, cands: list, left: str = "") -> dict:
    """Per state: the certified gamma along the tube (max over periods, ``w_max`` (n,)) against the tolerable
    one (s x it, s = ``scale`` the largest factor the proof holds with), and for each lever what it would
    need. A reduction of gamma by (1 - s) max_t w_i(t) in every period suffices (w_i(t) - D <= s w_i(t)
    for every t when D >= (1 - s) w_i(t)); each lever's row says how much of gamma it can remove:

    * more runs: delta_1 + delta_2 shrink with N1hat (the certificate's own delta(beta, N) at its betas
      and Mhat); the N1hat whose deltas leave the reduction;
    * a finer cover / smaller region: the Lipschitz term is proportional to the cover's radius eps; the
      eps that removes the reduction (and the cover's growth, (eps / eps')^d points);
    * a refined model: the largest observed mean gap over the data (gap_max), what a model that explains
      it would remove at most;
    * another pace or gain: the designs tried and their margins;
    * a shorter period: not computed (it needs data at that period).
    ``left``: where the tube at the certified gap leaves the data's boxes (a cover along the tube), when it
    does: ``w_max`` is then the gap over the tube at the factor s (finite; at s = 1 the gap is not certified
    where the tube goes), and a larger ``[collect] tube_margin`` is a lever too.
    Returns {"states": [rows], "designs": [...], "text": lines}."""
    w = np.asarray(w_max, float)
    s = float(scale) if scale is not None and np.isfinite(scale) else 0.0
    n = system.n
    rows, lines = [], []
    stoch = cert is not None and getattr(cert, "method", "") == "stochastic"
    lip = cert.lipschitz_terms() if cert is not None else np.zeros(n)
    cov = int(np.count_nonzero(np.asarray(getattr(cert, "radii", None) if getattr(cert, "radii", None) is not None
                                          else np.ones(n)) > 0)) if cert is not None else 0
    lines.append(f"{'state':<10}{'gamma':>11}{'tolerable':>11}{'reduce by':>11}   levers (each alone)")
    for i in range(n):
        finite = bool(np.isfinite(w[i]))
        need = (1.0 - s) * w[i] if finite else np.inf
        row = {"state": system.state_names[i], "gamma": float(w[i]), "tolerable": float(s * w[i]) if finite else None,
               "reduce_by": float(max(need, 0.0)) if finite else None}
        txt = []
        if not finite:  # the tube leaves the data's boxes even at the smallest factor: no gamma there
            txt.append("gamma is not certified where the tube goes (it leaves the data's boxes at every gap factor): "
                       "no reduction of gamma helps; data along this plan (a larger [collect] tube_margin) do")
        elif need <= 0 or cert is None:
            txt.append("nothing to reduce" if need <= 0 else "no certificate (a constant gap)")
        else:
            if stoch:
                d = cert.dims[i]
                dsum = d.delta1 + d.delta2
                N = _runs_for(cert, i, dsum - need)
                row["n1hat"] = N
                txt.append(f"N1hat {N:,} (now {cert.n_runs:,}; delta1 + delta2 {dsum:.3g})" if N is not None else
                           "no N1hat: no noise in the runs here (Mhat 0)" if not d.Mhat else
                           f"no N1hat: delta1 + delta2 = {dsum:.3g} < {need:.3g}")
            L = float(lip[i])
            if L > need:
                f = (L - need) / L
                row["eps_factor"] = f
                txt.append(f"eps x{f:.3g} (Lipschitz term {L:.3g}; ~{(1 / f) ** max(cov, 1):.3g}x cover points)")
            else:
                row["eps_factor"] = None
                txt.append(f"no eps: Lipschitz term {L:.3g} < {need:.3g}")
            gm = float(cert.dims[i].gap_max)
            row["model_gap"] = gm
            txt.append(f"refined model removes <= {gm:.3g}" + (" (enough)" if gm >= need else " (not enough)"))
        row["text"] = "; ".join(txt)
        rows.append(row)
        cells = (w[i], s * w[i], max(need, 0.0)) if finite else (w[i], np.nan, np.nan)
        lines.append(f"{system.state_names[i]:<10}{cells[0]:>11.4g}{cells[1]:>11.4g}{cells[2]:>11.4g}   "
                     f"{row['text']}")
    if left:
        lines.append(f"at the certified gap the tube leaves the data's boxes ({left}); the gamma above is over the tube "
                     "at the tolerable factor: reducing it keeps the tube inside, and so does a larger [collect] "
                     "tube_margin (data over a wider tube)")
    tried = [c.row() for c in cands]
    lines.append("other designs (pace, K): " + ("; ".join(tried) if tried else "not searched (given)"))
    lines.append("shorter period: not computed (it needs data collected at that period)")
    return {"states": rows, "designs": [c.to_dict() for c in cands], "text": lines}

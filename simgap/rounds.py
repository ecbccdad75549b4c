"""Rounds of data, anytime-valid: collect more where the proof needs it until it holds or a budget ends.

When a proof fails for lack of data (the certified gamma is larger than the proof tolerates, and a
larger N1hat shrinks its confidence terms), ``simgap run`` collects again in rounds k = 1, 2, ...:

    round k:  N1hat_k = N1hat * 2^(k-1) runs per pair, in the same cover (the same region: fixed
              before any data, e.g. the cover along the tube of :mod:`simgap.tube_cover`), a fresh
              store and seed; certified with the betas beta / 2^k (beta1, beta2 and beta_v per
              dimension: ``CertifyOptions.round = k``); the synthesis proves again.

Why beta / 2^k. The rounds look at the data to decide whether to go on, so the certificate the
rounds stop at is chosen by the data; its own confidence 1 - beta / 2^k is not the statement's.
Every round's certificate holds with probability >= 1 - sum_i beta_i / 2^k; by the union bound ALL
rounds' certificates (k = 1, 2, ..., however many are run) hold at once with probability >= 1 -
sum_k sum_i beta_i / 2^k = 1 - sum_i beta_i: on that event the one stopped at holds too, whatever the
stopping rule. This is the confidence a proof with it states (:meth:`Certificate.sup_confidence` reads
its round k and gives 1 - 2^k (1 - its own simultaneous confidence)). Reusing one beta for every
round would make the statement 1 - k beta after k looks, not 1 - beta.

The budget (``[collect] budget_runs``: simulator runs over all the rounds after the first;
``budget_minutes``: minutes of the collections of the rounds after the first; certifying and proving
are not counted) is checked before each round from its
known size (pairs x N1hat_k runs) and the last round's rate: a round that would exceed it is not
started. Rounds stop early when the proof's tolerable factor did not grow (more data did not help:
the Lipschitz term or the gap itself limits the proof, not the confidence terms), or when, at the
last round's growth of the factor per round, reaching 1 would take more runs than the budget (a
projection, said as one).

Each round's store is resumable like any collection: running the same command again finds the
finished rounds' stores complete and their chunks verified.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from .errors import SimgapError


@dataclass(frozen=True)
class Budget:
    """What the rounds after the first may spend: simulator runs and/or wall minutes (None: no limit
    on that one; both None: no rounds)."""

    runs: Optional[int] = None
    minutes: Optional[float] = None

    def __post_init__(self):
        if self.runs is not None and (isinstance(self.runs, bool) or int(self.runs) != self.runs or self.runs < 1):
            raise SimgapError(f"[collect] budget_runs must be an integer >= 1, got {self.runs!r}")
        if self.minutes is not None and not (float(self.minutes) > 0):
            raise SimgapError(f"[collect] budget_minutes must be > 0, got {self.minutes!r}")

    @property
    def active(self) -> bool:
        return self.runs is not None or self.minutes is not None

    def refuses(self, runs_spent: int, runs_next: int, seconds_spent: float, seconds_next: Optional[float]) -> str:
        """'' when the next round fits, else why not (the budget named)."""
        if self.runs is not None and runs_spent + runs_next > self.runs:
            return (f"the next round's {runs_next:,} runs would bring the rounds to {runs_spent + runs_next:,} runs, "
                    f"over [collect] budget_runs = {self.runs:,}")
        if self.minutes is not None and seconds_next is not None and \
                seconds_spent + seconds_next > 60.0 * float(self.minutes):
            return (f"the next round (about {seconds_next / 60:.1f} min at the last round's rate) would bring the "
                    f"rounds to {(seconds_spent + seconds_next) / 60:.1f} min, over [collect] budget_minutes = "
                    f"{float(self.minutes):g}")
        return ""


def n_runs_of_round(n_runs: int, k: int) -> int:
    """N1hat of round k >= 1: the configured N1hat doubled each round after the first."""
    if k < 1:
        raise SimgapError(f"rounds count from 1, got {k}")
    return int(n_runs) * 2 ** (int(k) - 1)


def beta_share(k: int) -> float:
    """The share of the base betas round k >= 1 spends: 2^-k (summing to 1 over all rounds)."""
    return 0.5 ** int(k)


@dataclass
class Attempt:
    """One round's outcome: whether the proof holds, its tolerable factor of gamma (None: not searched,
    inf: any), the certificate, the runs and seconds the round's collection took."""

    proved: bool
    scale: Optional[float]
    cert: object
    runs: int
    seconds: float


@dataclass
class RoundsResult:
    """The rounds run: the last attempt, a row per round and why they stopped."""

    last: Attempt
    rows: list
    stopped: str

    def to_dict(self) -> dict:
        return {"rounds": self.rows, "stopped": self.stopped, "proved": bool(self.last.proved)}


def round_row(k: int, n_runs: int, a: Attempt) -> dict:
    """The summary's row of round k: N1hat, the betas' share, the certificate's own simultaneous confidence
    and every round's at once (what the proof states), the proof and its tolerable factor."""
    c = a.cert
    own = c.scope_confidences()["simultaneous"] if c is not None else None
    return {"round": k, "n_runs": int(n_runs), "beta_share": beta_share(k), "confidence_own": own,
            "confidence_all_rounds": None if c is None else c.all_rounds_confidence(), "proved": bool(a.proved),
            "gap_scale": a.scale, "runs": int(a.runs), "seconds": round(float(a.seconds), 3)}


def run_rounds(n_runs: int, n_pairs: int, budget: Budget, attempt: Callable[[int, int], Attempt],
               log: Callable[[str], None] = print, max_rounds: int = 12) -> RoundsResult:
    """Rounds k = 1, 2, ... of ``attempt(k, N1hat_k)`` (collect, certify with ``round = k``, prove) until
    one proves, the budget refuses the next round (its runs n_pairs x N1hat_k known in advance, its time
    from the last round's runs per second), the tolerable factor stops growing, or ``max_rounds``."""
    rows, spent_runs, spent_s = [], 0, 0.0
    prev_scale = None
    k = 1
    while True:
        n_k = n_runs_of_round(n_runs, k)
        a = attempt(k, n_k)
        rows.append(round_row(k, n_k, a))
        if k > 1:
            spent_runs += a.runs
            spent_s += a.seconds
        conf = rows[-1]["confidence_all_rounds"]
        log(f"[rounds] round {k}: N1hat {n_k:,}, betas / 2^{k}: " + ("proved" if a.proved else "not proved")
            + ("" if a.scale is None else f" (gamma tolerable up to {a.scale:.4g} x its bound)")
            + ("" if conf is None else f"; every round's certificate at once: confidence {conf:.4g}"))
        if a.proved:
            return RoundsResult(a, rows, f"proved in round {k}")
        if a.scale is None or a.scale <= 0:
            return RoundsResult(a, rows, f"round {k}: the proof fails for any gap (or no factor was searched): more "
                                         "data cannot help")
        if prev_scale is not None and a.scale <= prev_scale * (1 + 1e-3):
            return RoundsResult(a, rows, f"round {k}: the tolerable factor did not grow ({prev_scale:.4g} -> "
                                         f"{a.scale:.4g}): more data does not help; the gap itself or the Lipschitz "
                                         "term limits the proof")
        if k >= max_rounds:
            return RoundsResult(a, rows, f"stopped after {max_rounds} rounds")
        n_next = n_runs_of_round(n_runs, k + 1)
        runs_next = int(n_pairs) * n_next
        rate = a.runs / a.seconds if a.runs and a.seconds > 0 else None
        why = budget.refuses(spent_runs, runs_next, spent_s, None if rate is None else runs_next / rate)
        if why:
            return RoundsResult(a, rows, f"budget: {why}")
        if prev_scale is not None and a.scale < 1:
            # a projection, not a proof: the factor grows by g per round as in the last one; R more rounds reach 1
            g = a.scale / prev_scale
            R = min(int(np.ceil(np.log(1.0 / a.scale) / np.log(g))), 62)  # 62: beyond any budget already
            runs_R = int(n_pairs) * n_runs_of_round(n_runs, k + 1) * (2 ** R - 1)  # rounds k+1 .. k+R
            if R > max_rounds - k or (budget.runs is not None and spent_runs + runs_R > budget.runs):
                return RoundsResult(a, rows, (
                    f"round {k}: at the last round's growth of the tolerable factor (x {g:.4g} per round, "
                    f"{prev_scale:.4g} -> {a.scale:.4g}) the proof would need about {R} more rounds (N1hat "
                    f"{n_runs_of_round(n_runs, k + R):,}, {runs_R:,} more runs)"
                    + (f", beyond [collect] budget_runs = {budget.runs:,}" if budget.runs is not None and
                       spent_runs + runs_R > budget.runs else f", beyond {max_rounds} rounds")
                    + ": more data is not the lever here (a projection, not a proof)"))
        prev_scale = a.scale
        k += 1


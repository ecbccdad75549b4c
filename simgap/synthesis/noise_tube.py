"""A per-run statement for a box tube: the mean's tube widened by the noise's linear response.

The box tube (:mod:`.box_tube`) proves where the MEAN state goes (m_{t+1} = f(m_t, u_t(m_t)) + w_t,
|w_t| <= gamma). A single run of the simulator is

    x_{t+1} = f(x_t, u_t) + w_t + n_t,   n_t = fhat(x_t, u_t, xi_t) - E fhat(x_t, u_t, .),

with xi_t drawn afresh each period, independent of the past: given the run so far, n_t has mean
zero (a martingale difference). The certificate's Assumption 1 with its sub-Gaussian tail states
n_{t,i} sub-Gaussian with variance proxy Mhat_i at every (x, u).

**Split.** With e_t = x_t - x_nom(t) write e_t = a_t + z_t, where z is the noise's response through
fixed matrices (A_t the closed loop's Jacobian at the plan for t < T0, at x* after):

    z_{t+1} = A_t z_t + n_t,  z_0 = 0,      a_{t+1} = M_t a_t + (M_t - A_t) z_t + r_t + w_t,

with M_t the mean-value matrix of the closed loop (:mod:`.box_tube`). If |z_t| <= zbar_t, the a-part
is a tube proof with every box widened by zbar_t and the extra remainder (|Mc_t - A_t| + Mr_t) zbar_t
(:func:`~simgap.synthesis.box_tube.tube_phases`): the run stays in x_nom(t) +- (h_t + zbar_t) and,
after T0, in the terminal box x* +- H (H includes zbar).

**The noise bound.** z_{t,i} = sum_{s<t} (Phi(t, s+1) n_s)_i, Phi the products of the A's. Given
the past, (Phi n_s)_i is sub-Gaussian with proxy (sum_j |Phi_ij| sigma_j)^2, sigma_j = sqrt(Mhat_j)
(Hoelder's inequality: proxies add as standard deviations, whatever the noise's correlation), and
a sum of such martingale differences is sub-Gaussian with the sum of the proxies:

    proxy_{t,i} = sqrt( sum_{s<t} (|Phi(t, s+1)| sigma)_i^2 ),
    P(|z_{t,i}| > lam proxy_{t,i}) <= 2 exp(-lam^2 / 2).

(Stopped at the first exit from the tube, where Assumption 1 may no longer hold: before it the
stopped and the true process agree.) With zbar = lam proxy and a union bound over n states and
periods 1..T,

    P(a run leaves the noise tube within T periods) <= beta_noise(T) = 2 n T exp(-lam^2 / 2),

given the certificate holds (confidence 1 - beta_cert, the simultaneous one: the proof takes gamma's
sup over boxes). Over the data and the run together:

    p_run(T) = P(inside the noise tube, then its terminal box, for all T periods) >= 1 - beta_noise(T) - beta_cert.

Beyond the paper (whose guarantee is about the mean map only). Compared with bounding each
period's noise by a box and adding it to gamma, the response adds up as a root of a sum of squares
instead of a sum (on the reacher: 2.4 x less). :func:`~simgap.synthesis.box_tube.noise_tube` finds
the largest lam the proof tolerates; a simulator that draws parameters once per run (``randomize``)
makes n_t dependent across periods, and a certificate without Mhat (the deterministic baseline)
bounds no noise: both give no statement, with the reason.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

#: the assumption the statement rests on, in words (summary.json and the controller file carry it)
ASSUMPTION = ("noise drawn afresh each period, independent of the past (no per-run randomization); "
              "n_t,i sub-Gaussian with variance proxy Mhat_i at every (x, u) in the tube (the certificate's "
              "Assumption 1 with its sub-Gaussian tail)")


def noise_proxy(A_seq, sigma) -> np.ndarray:
    """(T + 1, n) proxy_t = sqrt(sum_{s<t} (|Phi(t, s+1)| sigma)^2) for z_{t+1} = A_t z_t + n_t
    (module docstring), A_seq (T, n, n), sigma (n,) the noise's proxy per state (state units per
    period). O(T^2 n^3): every Phi(t, s+1), s < t, is kept and multiplied by A_t each period."""
    A_seq = np.asarray(A_seq, float)
    sigma = np.asarray(sigma, float)
    T, n = A_seq.shape[0], sigma.size
    out = np.zeros((T + 1, n))
    P = np.zeros((0, n, n))
    S = np.zeros(n)
    for t in range(T):
        P = np.concatenate([np.matmul(A_seq[t], P), np.eye(n)[None]])  # Phi(t+1, s+1) for s <= t
        S = np.square(np.abs(P) @ sigma).sum(axis=0)
        out[t + 1] = np.sqrt(S)
    return out


#: horizon of the in-process calibration of :func:`noise_proxy` (about 0.1 s here)
CAL_HORIZON = 1000
#: horizons up to this are not priced (well under a second)
FREE_HORIZON = 2000


@functools.lru_cache(maxsize=None)
def _seconds_per_period_squared(n: int) -> float:
    """:func:`noise_proxy`'s time / T^2 for n states, measured here once at T = CAL_HORIZON."""
    A = np.repeat((0.5 * np.eye(n))[None], CAL_HORIZON, axis=0)
    t = time.perf_counter()
    noise_proxy(A, np.ones(n))
    return (time.perf_counter() - t) / CAL_HORIZON ** 2


def horizon_cost(horizon: int, n: int) -> dict:
    """Peak memory [bytes] and time [s] of the per-run statement for runs of ``horizon`` periods:
    :func:`noise_proxy` keeps every Phi(t, s) (T n^2 floats, about 5 copies at once with the
    Jacobians repeated after T0) and costs O(T^2 n^3) (calibrated here; 0 s below FREE_HORIZON)."""
    T = int(horizon)
    seconds = 0.0 if T <= FREE_HORIZON else _seconds_per_period_squared(int(n)) * float(T) ** 2
    return {"horizon": T, "memory": 5.0 * 8.0 * float(T) * n * n, "seconds": seconds}


def check_horizon(horizon, n: int, what: str = "horizon") -> dict:
    """Refuse a per-run horizon that is not an integer >= 1, or whose statement (:func:`horizon_cost`)
    needs more memory than is available or more time than a command may take
    (:data:`simgap.checks.MAX_COMMAND_SECONDS`), naming ``what``, the need and the limit; the cost."""
    from ..checks import MAX_COMMAND_SECONDS, check_memory, human_seconds
    from ..errors import SimgapError
    if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
        raise SimgapError(f"{what}: the per-run statement's horizon must be an integer >= 1 periods, got {horizon!r}")
    hint = "use a shorter horizon (the rollouts' default is 2 T0 + 1 periods)"
    c = horizon_cost(int(horizon), n)
    check_memory(c["memory"], f"{what} = {int(horizon):,}: the per-run statement (the noise's response over "
                 f"{int(horizon):,} periods)", hint)
    if c["seconds"] > MAX_COMMAND_SECONDS:
        raise SimgapError(f"{what} = {int(horizon):,}: the per-run statement (the noise's response over "
                          f"{int(horizon):,} periods, cost ~ T^2) would take about {human_seconds(c['seconds'])}, "
                          f"more than the {human_seconds(MAX_COMMAND_SECONDS)} a command may take; {hint}")
    return c


@dataclass
class NoiseTube:
    """The per-run statement (module docstring) for runs of up to ``horizon`` periods. ``lam``: zbar =
    lam proxy; ``sigma`` = sqrt(Mhat) (n,); ``radii`` (T0 + 1, n) and ``H`` (n,): the noise tube's
    half-widths around x_nom(t) and its terminal box around x*; ``beta_cert``: 1 - the certificate's
    simultaneous confidence."""

    lam: float
    sigma: np.ndarray
    radii: np.ndarray
    H: np.ndarray
    beta_cert: float
    horizon: int
    assumption: str = ASSUMPTION
    extra: dict = field(default_factory=dict)

    def beta_noise(self, T: int) -> float:
        """2 n T exp(-lam^2 / 2), at most 1 (T <= ``horizon``: the bound zbar was proved that far)."""
        T = int(T)
        if T > self.horizon:
            raise ValueError(f"the per-run statement holds for runs of up to {self.horizon} periods, not {T}")
        return float(min(1.0, 2.0 * self.sigma.size * T * np.exp(-0.5 * self.lam ** 2)))

    def p_run(self, T: int) -> float:
        """The lower bound 1 - beta_noise(T) - beta_cert on P(every period of a run of T periods inside
        the noise tube, then its terminal box), 0 when vacuous."""
        return float(max(0.0, 1.0 - self.beta_noise(T) - self.beta_cert))

    def to_dict(self) -> dict:
        return {"lam": self.lam, "sigma": self.sigma.tolist(), "horizon": self.horizon, "H": self.H.tolist(),
                "max_radius": self.radii.max(axis=0).tolist(), "beta_cert": self.beta_cert,
                "beta_noise": self.beta_noise(self.horizon), "p_run": self.p_run(self.horizon),
                "assumption": self.assumption, **self.extra}


def why_no_statement(gap) -> Optional[str]:
    """None when the certificate ``gap`` supports a per-run statement, else the reason in words."""
    if gap is None or not hasattr(gap, "dims"):
        return "no certificate (a constant or no gap states no noise)"
    if any(d.Mhat is None for d in gap.dims):
        return "the certificate bounds no noise variance (deterministic baseline)"
    if (gap.options.get("bounds") or {}).get("concentration") != "subgaussian":
        return ("the certificate's tail is Chebyshev's (no sub-Gaussian assumption): certify with "
                "concentration = \"subgaussian\" for a per-run statement")
    if _draws_per_run(((gap.provenance or {}).get("simulator") or {}).get("randomize")):
        return "the simulator draws parameters once per run (randomize): the noise is not independent across periods"
    if gap.sup_confidence() is None:
        return "the certificate's simultaneous confidence is vacuous"
    return None


def _draws_per_run(randomize) -> bool:
    """True when a simulator's ``randomize`` section varies anything (a value other than 0 or empty)."""
    if isinstance(randomize, dict):
        return any(_draws_per_run(v) for v in randomize.values())
    if isinstance(randomize, (list, tuple)):
        return any(_draws_per_run(v) for v in randomize)
    return bool(randomize)


__all__ = ["ASSUMPTION", "NoiseTube", "noise_proxy", "why_no_statement"]

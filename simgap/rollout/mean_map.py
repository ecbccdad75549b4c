"""The mean-map trajectory m+ = E fhat(m, u(m)): the sequence the controller's guarantee is about.

The certificate bounds |E_w fhat(x, u, w) - f(x, u)| <= gamma(x, u) for one known state x
(Theorem 1), and the abstraction places the next *mean* in f(m, u) + [-gamma, gamma]. The
controller's guarantee (reach-avoid or invariance, at the certificate's confidence) therefore
concerns the deterministic sequence

    m_0 = x0,    m_{k+1} = E_w fhat(m_k, u(m_k), w)          (one abstract step per k)

with the controller queried at the mean. It is *not* the average of closed-loop rollouts: there
every run's controller reacts to its own state, so runs apply different inputs, and the noise
enters through the nonlinear dynamics (cos/sin of a heading) step after step; E x(t) of the
closed loop differs from m_t in general.

Computed where it is reported: at every abstract step the simulator runs ``runs`` times from the
current mean m_k with the input u(m_k) held for ``hold`` simulator steps; m_{k+1} is the sample
mean (circular mean for angles), the reported trajectory. Two standard errors per row and dimension:

* ``std_error`` (propagated): in the same simulator calls, G = min(10, runs // 2) independent
  repetitions of the whole sequence with runs // G runs each, every one propagated from its OWN
  mean m^(g)_k with the same inputs u(m_k) (a continuous-input controller: with its own input
  u(m^(g)_k), since open-loop repetitions of an unstable plant drift apart exponentially);
  std_g(m^(g)_t) / sqrt(G) estimates the spread of m_t
  over repetitions of the sequence (the variance of a mean of runs // G runs is G times that of
  runs). Each repetition carries its own estimation error from step to step, so this includes
  the error propagated through the dynamics. It does not cover the bias of pushing a
  finite-sample mean through nonlinear dynamics (order 1 / runs, against 1 / sqrt(runs)). Cost:
  about twice the runs of the sequence alone.
* ``step_std_error`` (one step, conditional): s / sqrt(runs) of the last step's runs, given the
  state the step started from: the number reported earlier, which misses every error inherited
  from earlier steps (measured 2-5x too small on the PyBullet pendulum).

The means of the branches after j < hold simulator steps are recorded too (the trajectory has
one row per simulator step, like the rollouts), and the specification is judged on every row.
Rows inside a hold are means of j-step branches from the last abstract step's mean: Theorem 1
(one step from a known state) is about the rows at abstract-step boundaries only, and a
controller synthesized with ``compose_hold`` (a one-period gap composed over the hold) is outside
Theorem 1 altogether; :meth:`MeanMap.to_dict` says which.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import SimgapError
from ..synthesis.abstraction import COMPOSED_HOLD_LABEL
from ..synthesis.spec import Spec
from .judge import circular_mean, classify, judge_path


@dataclass
class MeanMap:
    """The mean-map trajectory of one controller from one x0 (module docstring).

    trajectory : (T+1, n)       mbar at every simulator step; after the run stopped the last row repeats
    std_error : (T+1, n)        propagated standard error of each row (0 at t = 0; module docstring)
    groups : int                G repetitions behind std_error
    step_std_error : (T+1, n)   one-step conditional standard error of each row (0 at t = 0)
    input_index : (T,)          input applied (row of the controller's inputs), -1 after stopping
    hold : int                  simulator steps per controller query (rows t % hold != 0 are inside a hold)
    composed_hold : bool        the controller composes a one-period gap over the hold (outside Theorem 1)
    """

    trajectory: np.ndarray
    std_error: np.ndarray
    input_index: np.ndarray
    length: int
    outcome: str
    verdict: dict
    left_domain_time: int
    runs: int
    robot_steps: int
    step_std_error: np.ndarray = None
    groups: int = 1
    hold: int = 1
    composed_hold: bool = False

    @property
    def satisfied(self) -> bool:
        return self.outcome == "success"

    def to_dict(self) -> dict:
        n = self.trajectory.shape[1]
        se = self.std_error[1:self.length + 1]
        st = self.step_std_error[1:self.length + 1]
        if self.composed_hold:
            theorem = ("none: the controller composes a one-period gap over its hold of "
                       f"{self.hold} periods (compose_hold), outside Theorem 1")
        elif self.hold > 1:
            theorem = (f"rows at multiples of the hold ({self.hold} simulator steps) only; the rows inside a hold "
                       "are means of branches from the last abstract step, outside Theorem 1")
        else:
            theorem = "every row (one simulator step per abstract step)"
        return {"what": "m+ = E fhat(m, u(m)) from the current mean m: the sequence the guarantee is about",
                "runs_per_step": self.runs, "groups": self.groups, "outcome": self.outcome,
                "satisfied": self.satisfied,
                "reach_time": self.verdict["reach_time"], "violation_time": self.verdict["violation_time"],
                "violation_kind": self.verdict["violation_kind"], "left_domain_time": self.left_domain_time,
                "length": self.length, "robot_steps": self.robot_steps,
                "max_std_error": (se.max(axis=0) if se.size else np.zeros(n)).tolist(),
                "std_error_what": f"propagated: std of m_t over {self.groups} independent repetitions of the sequence "
                                  f"({self.runs // self.groups} runs each, each from its own mean) / sqrt({self.groups}); "
                                  "excludes the bias of a finite-sample mean pushed through nonlinear dynamics",
                "max_step_std_error": (st.max(axis=0) if st.size else np.zeros(n)).tolist(),
                "step_std_error_what": "one step, conditional on the state the step started from: s / sqrt(runs); "
                                       "misses the error inherited from earlier steps",
                "hold": self.hold, "theorem1_rows": theorem}


def mean_map(controller, sim, spec: Spec, x0: np.ndarray, runs: int, T: int, hold: int,
             rng: np.random.Generator, on_exit: str = "hold", progress=None) -> MeanMap:
    """Run the mean map m_{k+1} = E fhat(m_k, u(m_k)) for T simulator steps (module docstring).

    ``runs`` simulator runs per abstract step (>= 4) estimate each mean, and G = min(10, runs // 2)
    repetitions of runs // G runs each the propagated standard error; ``hold`` simulator steps per controller query; ``on_exit`` as for
    rollouts ("hold": keep the previous input when m leaves the winning domain, "stop": stop with
    outcome left_domain). Stops at the first violation or (reach-avoid) when m reaches the target.
    ``progress(t, T)`` after every simulator step.
    """
    if int(runs) != runs or runs < 4:
        raise SimgapError(f"mean map: runs per step must be an integer >= 4 (at least two repetitions of two), got {runs!r}")
    runs = int(runs)
    G = min(10, runs // 2)
    rg = runs // G                                          # runs per repetition
    system = sim.system
    n, angle = system.n, system.angle_dims
    U = controller.system.inputs
    traj = np.empty((T + 1, n))
    se = np.zeros((T + 1, n))
    se1 = np.zeros((T + 1, n))
    uidx = np.full(T, -1, dtype=np.int32)
    traj[0] = m = np.asarray(x0, dtype=float)
    reps = np.repeat(m[None], G, axis=0)                    # m^(g): each repetition's own mean
    reach_avoid = spec.kind == "reach_avoid"
    t, cur, ltime, steps = 0, -1, -1, 0
    continuous = bool(getattr(controller, "continuous_input", False))
    timed = bool(getattr(controller, "time_varying", False))
    u_cur = None
    outcome = "success" if (not reach_avoid or spec.reached(m[None])[0]) else "timeout"
    done = reach_avoid and outcome == "success"
    B = runs + G * rg
    while t < T and not done:
        kw = {"t": t // hold} if timed else {}  # a time-varying controller: its period since x0
        q = int(np.asarray(controller.input_index(m[None], **kw)).reshape(-1)[0])
        if q < 0:
            ltime = t if ltime < 0 else ltime
            if on_exit == "stop" or cur < 0:
                outcome, done = "left_domain", True
                break
            q = cur
        else:
            # a continuous-input controller (invariant set): its value at the mean, held until the next query
            u_cur = controller.input(m[None], strict=False, **kw)[0] if continuous else U[q]
        cur = q
        X = np.concatenate([np.repeat(m[None], runs, axis=0), np.repeat(reps, rg, axis=0)])
        u = np.repeat(u_cur[None], B, axis=0)
        if continuous:
            # each repetition's own mean gets its own feedback value: held at u(m), the repetitions of an
            # open-loop unstable plant would drift apart exponentially (their spread is what the standard
            # error measures); outside the set a repetition keeps u(m)
            ur = controller.input(reps, strict=False, **kw)
            ur = np.where(np.isfinite(ur), ur, u_cur)
            u[runs:] = np.repeat(ur, rg, axis=0)
        for _ in range(min(hold, T - t)):
            X = np.asarray(sim.step_with_noise(X, u, sim.draw_noise(B, rng)), dtype=float)
            if not np.all(np.isfinite(X)):
                raise SimgapError(f"mean map: the simulator returned NaN/inf at step {t + 1}")
            t += 1
            steps += B
            if progress is not None:
                progress(t, T)
            mean = circular_mean(X[:runs], angle)
            reps = circular_mean(X[runs:].reshape(G, rg, n), angle, axis=1)
            traj[t], uidx[t - 1] = mean, q
            se1[t] = system.diff(X[:runs], mean).std(axis=0, ddof=1) / np.sqrt(runs)
            se[t] = system.diff(reps, circular_mean(reps, angle)).std(axis=0, ddof=1) / np.sqrt(G)
            kind = classify(spec, mean[None], system.x_lo, system.x_hi)[0]
            if kind:
                outcome, done = "violation", True
                break
            if reach_avoid and spec.reached(mean[None])[0]:
                outcome, done = "success", True
                break
        m = traj[t]
    traj[t + 1:], se[t + 1:], se1[t + 1:] = traj[t], se[t], se1[t]
    verdict = judge_path(spec, traj, system.x_lo, system.x_hi)
    composed = getattr(controller, "meta", {}).get("hold_mode") == COMPOSED_HOLD_LABEL
    return MeanMap(trajectory=traj, std_error=se, input_index=uidx, length=t, outcome=outcome, verdict=verdict,
                   left_domain_time=ltime, runs=runs, robot_steps=steps, step_std_error=se1, groups=G,
                   hold=int(hold), composed_hold=bool(composed))

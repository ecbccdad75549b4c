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

Computed where it is reported: at every abstract step the simulator runs ``runs`` times from
the current mean m_k with the input u(m_k) held for ``hold`` simulator steps; m_{k+1} is the sample
mean (circular mean for angles), reported with its standard error s / sqrt(runs) per dimension.
The means of the branches after j < hold simulator steps are recorded too (the trajectory has one
row per simulator step, like the rollouts), and the specification is judged on every row.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import SimgapError
from ..synthesis.spec import Spec
from .judge import circular_mean, classify, judge_path


@dataclass
class MeanMap:
    """The mean-map trajectory of one controller from one x0 (module docstring).

    trajectory : (T+1, n)   m at every simulator step; after the run stopped the last row repeats
    std_error : (T+1, n)    standard error of each row (0 at t = 0)
    input_index : (T,)      input applied (row of the controller's inputs), -1 after stopping
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

    @property
    def satisfied(self) -> bool:
        return self.outcome == "success"

    def to_dict(self) -> dict:
        se = self.std_error[1:self.length + 1]
        return {"what": "m+ = E fhat(m, u(m)) from the current mean m: the sequence the guarantee is about",
                "runs_per_step": self.runs, "outcome": self.outcome, "satisfied": self.satisfied,
                "reach_time": self.verdict["reach_time"], "violation_time": self.verdict["violation_time"],
                "violation_kind": self.verdict["violation_kind"], "left_domain_time": self.left_domain_time,
                "length": self.length, "robot_steps": self.robot_steps,
                "max_std_error": (se.max(axis=0) if se.size else np.zeros(self.trajectory.shape[1])).tolist()}


def mean_map(controller, sim, spec: Spec, x0: np.ndarray, runs: int, T: int, hold: int,
             rng: np.random.Generator, on_exit: str = "hold") -> MeanMap:
    """Run the mean map m_{k+1} = E fhat(m_k, u(m_k)) for T simulator steps (module docstring).

    ``runs`` simulator runs per abstract step estimate each mean; ``hold`` simulator steps per
    controller query; ``on_exit`` as for rollouts ("hold": keep the previous input when m leaves
    the winning domain, "stop": stop with outcome left_domain). Stops at the first violation or
    (reach-avoid) when m reaches the target.
    """
    if int(runs) != runs or runs < 2:
        raise SimgapError(f"mean map: runs per step must be an integer >= 2, got {runs!r}")
    runs = int(runs)
    system = sim.system
    n, angle = system.n, system.angle_dims
    U = controller.system.inputs
    traj = np.empty((T + 1, n))
    se = np.zeros((T + 1, n))
    uidx = np.full(T, -1, dtype=np.int32)
    traj[0] = m = np.asarray(x0, dtype=float)
    reach_avoid = spec.kind == "reach_avoid"
    t, cur, ltime, steps = 0, -1, -1, 0
    outcome = "success" if (not reach_avoid or spec.reached(m[None])[0]) else "timeout"
    done = reach_avoid and outcome == "success"
    while t < T and not done:
        q = int(np.asarray(controller.input_index(m[None])).reshape(-1)[0])
        if q < 0:
            ltime = t if ltime < 0 else ltime
            if on_exit == "stop" or cur < 0:
                outcome, done = "left_domain", True
                break
            q = cur
        cur = q
        X = np.repeat(m[None], runs, axis=0)
        u = np.repeat(U[q][None], runs, axis=0)
        for _ in range(min(hold, T - t)):
            X = np.asarray(sim.step_with_noise(X, u, sim.draw_noise(runs, rng)), dtype=float)
            if not np.all(np.isfinite(X)):
                raise SimgapError(f"mean map: the simulator returned NaN/inf at step {t + 1}")
            t += 1
            steps += runs
            mean = circular_mean(X, angle)
            traj[t], uidx[t - 1] = mean, q
            se[t] = system.diff(X, mean).std(axis=0, ddof=1) / np.sqrt(runs)
            kind = classify(spec, mean[None], system.x_lo, system.x_hi)[0]
            if kind:
                outcome, done = "violation", True
                break
            if reach_avoid and spec.reached(mean[None])[0]:
                outcome, done = "success", True
                break
        m = traj[t]
    traj[t + 1:], se[t + 1:] = traj[t], se[t]
    verdict = judge_path(spec, traj, system.x_lo, system.x_hi)
    return MeanMap(trajectory=traj, std_error=se, input_index=uidx, length=t, outcome=outcome, verdict=verdict,
                   left_domain_time=ltime, runs=runs, robot_steps=steps)

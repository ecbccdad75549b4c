"""Rollouts: a synthesized controller in the stochastic simulator, and the mean map.

* :mod:`~simgap.rollout.closed_loop`: R closed-loop rollouts at once (:func:`rollout`), the
  nominal model's run, their semantics (hold, spec checks, padding, seeds).
* :mod:`~simgap.rollout.mean_map`: m+ = E fhat(m, u(m)) from the current mean, the sequence
  the controller's guarantee is about (reported separately from the rollout average).
* :mod:`~simgap.rollout.result`: :class:`RolloutResult`, its JSON summary and .npz files.
* :mod:`~simgap.rollout.judge`: outcome codes and the specification verdict of states/paths.
"""

from .closed_loop import DEFAULT_HORIZON, default_horizon, resolve_hold, rollout
from .judge import OUTCOMES, VIOLATION_KINDS
from .mean_map import MeanMap, mean_map
from .result import RolloutResult, load_rollout

__all__ = ["DEFAULT_HORIZON", "OUTCOMES", "VIOLATION_KINDS", "MeanMap", "RolloutResult", "default_horizon",
           "load_rollout", "mean_map", "resolve_hold", "rollout"]

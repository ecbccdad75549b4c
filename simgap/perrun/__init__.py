"""Guarantees about each run: the realization-level gap and probabilistic synthesis.

* :mod:`.orderstats`  binomial order-statistic bounds on quantiles, Clopper-Pearson intervals;
* :mod:`.realization` gamma^alpha: P_w(|fhat_i - f_i| <= gamma^alpha_i(x,u)) >= 1 - alpha on X x U;
* :mod:`.run_audit`   empirical coverage of gamma^alpha at fresh points;
* :mod:`.imdp`        interval-MDP abstraction from simulator samples;
* :mod:`.value_iteration` pessimistic interval value iteration, controller and p_cert per cell.
"""

from .orderstats import alpha_min, clopper_pearson, order_index
from .realization import RunCertifyOptions, certify_run

__all__ = ["alpha_min", "order_index", "clopper_pearson", "certify_run", "RunCertifyOptions"]

"""The simulator factory: a config to a built simulator, in this process or spread over several.

Its own module because the parallel wrapper (:mod:`simgap.simulators.parallel`) is a Simulator
(:mod:`simgap.simulators.base`) and the factory builds it: factory -> parallel -> base, one way.
"""

from __future__ import annotations

import os

from ..errors import SimgapError
from ..systems import System
from .base import Simulator, SimulatorConfig, build_simulator
from .parallel import ParallelSimulator


def make_simulator(config: SimulatorConfig | dict, system: System | None = None, workers: int = 1) -> Simulator:
    """Build a simulator from its config (a :class:`SimulatorConfig` or its dict).

    ``workers`` > 1 (0 = all cores) serves each batch with that many processes
    (:class:`simgap.simulators.parallel.ParallelSimulator`); results are the same.
    """
    if workers != 1:
        n = (os.cpu_count() or 1) if workers in (0, None) else int(workers)
        if n < 1:
            raise SimgapError(f"simulator workers must be >= 1 (0 = all cores), got {workers!r}")
        inner = build_simulator(config, system)
        return ParallelSimulator(inner, n, system) if n > 1 else inner
    return build_simulator(config, system)

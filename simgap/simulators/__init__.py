"""Stochastic simulators: one batch interface, backends built from JSON-able configs."""

from . import base
from .base import Simulator, SimulatorConfig
from .factory import make_simulator

# the factory's old home: `from simgap.simulators.base import make_simulator` keeps working. base cannot
# import the factory (the factory wraps in ParallelSimulator, a base.Simulator); this package's
# __init__ always runs before anyone can import base, so the name is there whenever base is.
base.make_simulator = make_simulator

__all__ = ["Simulator", "SimulatorConfig", "make_simulator"]

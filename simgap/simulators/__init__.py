"""Stochastic simulators: one batch interface, backends built from JSON-able configs."""

from .base import Simulator, SimulatorConfig, make_simulator

__all__ = ["Simulator", "SimulatorConfig", "make_simulator"]

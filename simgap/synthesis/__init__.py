"""Symbolic controller synthesis: grid, abstraction, games, controller, rollouts.

The types and functions a new user needs::

    from simgap.synthesis import Box, Spec, synthesize

    spec = Spec(kind="invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    res = synthesize(system, spec, eta=(0.004, 0.01), gap=[1e-4, 1e-3])

See docs/synthesis.md.
"""

from .abstraction import Abstraction, ConstantGap, build_abstraction, state_independent
from .controller import Controller, SynthesisResult, label_cells, synthesize
from .games import GameResult, solve_invariance, solve_reach
from .grid import UniformGrid
from ..runge_kutta import rk4_growth, rk4_integrate, rk4_step
from .spec import Box, Spec

__all__ = [
    "Abstraction", "Box", "ConstantGap", "Controller", "GameResult", "Spec", "SynthesisResult",
    "UniformGrid", "build_abstraction", "label_cells", "rk4_growth", "rk4_integrate", "rk4_step",
    "solve_invariance", "solve_reach", "state_independent", "synthesize",
]

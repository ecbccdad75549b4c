"""simgap: certified sim-to-real gaps, controllers that respect them, and models that close them.

Pipeline: System -> Dataset -> Certificate -> Abstraction -> Controller -> Rollouts, plus Refinement.
"""

from .errors import SimgapError
from .systems import System, get_system, input_grid
from .system_ref import resolve_system

__version__ = "0.1.0"
__all__ = ["SimgapError", "System", "get_system", "input_grid", "resolve_system", "__version__"]

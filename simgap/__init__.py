"""simgap: certified sim-to-real gaps, controllers that respect them, and models that close them.

Pipeline: System -> Dataset -> Certificate -> Abstraction -> Controller -> Rollouts, plus Refinement.
"""

from .errors import SimgapError

__version__ = "0.1.0"
__all__ = ["SimgapError", "System", "get_system", "input_grid", "resolve_system", "__version__"]

# imported on first use (PEP 562): ``import simgap`` (every command, ``simgap --help``) does not
# pay for numpy and the system registry until they are needed
_LAZY = {"System": "systems", "get_system": "systems", "input_grid": "systems", "resolve_system": "system_ref"}


def __getattr__(name):
    if name in _LAZY:
        import importlib
        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'simgap' has no attribute {name!r}")

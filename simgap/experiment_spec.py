"""The specification an experiment asks for: its ``[synthesis]`` section as a Spec.

Shared by the comparison pipeline (:mod:`simgap.pipeline`), the per-run stage
(:mod:`simgap.perrun.stage`), the CLI and the GUI: a module of its own so that none of them has to
import another stage to read it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Optional

import numpy as np

from .errors import SimgapError
from .synthesis.spec import Box, Spec

if TYPE_CHECKING:
    from .config import ExperimentConfig


def experiment_spec(exp: ExperimentConfig) -> tuple[Spec, Optional[np.ndarray], object]:
    """(spec, x0 from the map or None, arena map or None) from ``[synthesis]``."""
    syn = exp.section("synthesis")
    system = exp.system
    kind = syn.get("spec", "invariance")
    if kind == "invariance":
        lo = np.asarray(syn.get("safe_lo", system.x_lo), dtype=float)
        hi = np.asarray(syn.get("safe_hi", system.x_hi), dtype=float)
        return Spec("invariance", safe=Box(lo, hi)), None, None
    if kind == "reach_avoid":
        from .maps import load_map  # only reach-avoid experiments read a map
        arena = load_map(syn.get("map", "arena"))
        return arena.spec(system), arena.x0(system), arena
    raise SimgapError(f"[synthesis] spec must be 'invariance' or 'reach_avoid', got {kind!r}")

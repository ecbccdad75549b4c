"""Model refinement: residuals, effect library, sparse selection, refined system, report.

The loop: transition data -> residual r = x_next - f(x,u) -> named effects (sparse selection on a
train / held-out split) -> refined system f' = f + tau * sum c_k g_k -> report before/after.
See docs/refine.md.
"""

from .compare import gap_comparison
from .data import Transitions, from_dataset, load_transitions, make_transitions
from .effects import (LIBRARY, Effect, candidate_effects, declare_velocity, library_candidates,
                      user_effect, velocity_dims)
from .refined import build_refined, load_refined, load_system, refined_system, save_refined
from .report import RefineResult, format_table, refine
from .residual import Residuals, residuals
from .selection import SelectionOptions
from .trajectory import PRESETS, from_trajectory_file, trajectory_to_transitions

__all__ = ["Transitions", "load_transitions", "make_transitions", "from_dataset", "Residuals", "residuals",
           "LIBRARY", "Effect", "candidate_effects", "library_candidates", "user_effect", "declare_velocity",
           "velocity_dims", "SelectionOptions", "refine", "RefineResult", "format_table", "refined_system",
           "build_refined", "save_refined", "load_refined", "load_system", "gap_comparison",
           "PRESETS", "from_trajectory_file", "trajectory_to_transitions"]

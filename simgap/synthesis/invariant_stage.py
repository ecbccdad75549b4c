"""The former name of :mod:`.set_synthesis` (the set-based methods' stage: ellipsoid and box tube),
kept so that existing imports keep working."""

from .set_synthesis import (METHOD_NAMES, SET_METHODS, check_method, check_section, is_set_method,  # noqa: F401
                            method_of, rollouts_in_set, states_in_set, synthesize)

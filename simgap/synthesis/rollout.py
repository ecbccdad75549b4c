"""Moved to :mod:`simgap.rollout`; this name keeps old imports working."""

from ..rollout import *  # noqa: F401,F403
from ..rollout import __all__  # noqa: F401

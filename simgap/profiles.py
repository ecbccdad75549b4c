"""The profile a command uses when it is not told one (light: the command line imports it).

``DEFAULT_PROFILE`` compares equal to ``"small"`` but is recognizable by its type: an experiment
that defines a ``small`` profile gets it, one without profiles (or without ``small``) runs with
its base settings. An explicit ``--profile small`` must exist in the file.
"""

from __future__ import annotations


class DefaultProfile(str):
    """The profile a command uses unless told: ``small`` when the file has one, else the base."""


DEFAULT_PROFILE = DefaultProfile("small")

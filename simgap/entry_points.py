"""Installed plugins' entry points: the names installed packages register, and loading one.

The discovery half of :mod:`simgap.plugins` (which describes plugins): it knows nothing of
systems or simulators, so the registries that own a group (:mod:`simgap.systems` for systems,
:mod:`simgap.simulators.base` for simulator kinds) ask it for their plugins without importing
each other or :mod:`simgap.plugins` (no import circle: tests/test_layout.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Collection

from .errors import SimgapError

SYSTEM_GROUP = "simgap.systems"
SIMULATOR_GROUP = "simgap.simulators"


@dataclass(frozen=True)
class Plugin:
    """One registered name: where it comes from (``module:attr`` and the distribution)."""

    name: str
    target: str
    package: str
    version: str

    def origin(self) -> str:
        return f"{self.package} {self.version} ({self.target})"


@lru_cache(maxsize=None)
def _registered(group: str) -> dict:
    from importlib import metadata  # imported on first use: it loads email, zipfile, csv, ... (about 40 ms)
    out = {}
    for ep in metadata.entry_points(group=group):
        dist = getattr(ep, "dist", None)
        out.setdefault(ep.name, (ep, Plugin(ep.name, ep.value, getattr(dist, "name", "?") if dist else "?",
                                            getattr(dist, "version", "?") if dist else "?")))
    return out


def refresh() -> None:
    """Forget the cached entry points (after installing a plugin in a running process)."""
    _registered.cache_clear()


def registered(group: str, builtin: Collection[str]) -> dict:
    """name -> :class:`Plugin` of ``group``'s installed plugins, the ``builtin`` names excluded (a built-in wins)."""
    return {k: p for k, (_, p) in _registered(group).items() if k not in builtin}


def shadowed(group: str, builtin: Collection[str]) -> list:
    """(group, Plugin) of ``group``'s plugins ignored because a built-in has the same name."""
    return [(group, p) for k, (_, p) in _registered(group).items() if k in builtin]


def load(group: str, name: str):
    """(the loaded entry point's object, its Plugin); a package that fails to load is a SimgapError naming it."""
    ep, plugin = _registered(group)[name]
    try:
        return ep.load(), plugin
    except Exception as e:  # a broken installed package: say which one, not a traceback
        raise SimgapError(f"plugin {name!r} ({plugin.origin()}) does not load: {type(e).__name__}: {e}") from None


def installed_note(group: str, names: Collection[str]) -> str:
    """', plugins: a, b' (or ', no plugins installed') for error messages listing names."""
    names = sorted(names)
    return f"; installed plugins: {', '.join(names)}" if names else f"; no {group} plugins installed"

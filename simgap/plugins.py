"""Plugins: systems and simulator backends that installed Python packages register by name.

A package declares entry points in its ``pyproject.toml``::

    [project.entry-points."simgap.systems"]
    double_integrator = "my_pkg.systems:double_integrator"      # () -> System (or a System)

    [project.entry-points."simgap.simulators"]
    my_backend = "my_pkg.sim:MySimulator"                       # a simgap Simulator subclass

Installed code is trusted; files are not: experiment files, system files, data sets,
certificates and controllers only ever refer to a registered *name*, never to a module, so a
file cannot make simgap import anything. A plugin name equal to a built-in's is ignored (the
built-in wins; ``simgap plugins`` says so). ``examples/plugin/`` is a complete example package.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from importlib import metadata
from typing import Optional

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
    out = {}
    for ep in metadata.entry_points(group=group):
        dist = getattr(ep, "dist", None)
        out.setdefault(ep.name, (ep, Plugin(ep.name, ep.value, getattr(dist, "name", "?") if dist else "?",
                                            getattr(dist, "version", "?") if dist else "?")))
    return out


def refresh() -> None:
    """Forget the cached entry points (after installing a plugin in a running process)."""
    _registered.cache_clear()


def system_plugins() -> dict:
    """name -> :class:`Plugin` of the installed system plugins (built-in names excluded)."""
    from .systems import BUILTIN
    return {k: p for k, (_, p) in _registered(SYSTEM_GROUP).items() if k not in BUILTIN}


def simulator_plugins() -> dict:
    """kind -> :class:`Plugin` of the installed simulator plugins (built-in kinds excluded)."""
    from .simulators.base import _BACKENDS
    return {k: p for k, (_, p) in _registered(SIMULATOR_GROUP).items() if k not in _BACKENDS}


def shadowed() -> list:
    """Plugin names ignored because a built-in has the same name: (group, Plugin)."""
    from .simulators.base import _BACKENDS
    from .systems import BUILTIN
    out = [(SYSTEM_GROUP, p) for k, (_, p) in _registered(SYSTEM_GROUP).items() if k in BUILTIN]
    return out + [(SIMULATOR_GROUP, p) for k, (_, p) in _registered(SIMULATOR_GROUP).items() if k in _BACKENDS]


def _load(group: str, name: str):
    ep, plugin = _registered(group)[name]
    try:
        return ep.load(), plugin
    except Exception as e:  # a broken installed package: say which one, not a traceback
        raise SimgapError(f"plugin {name!r} ({plugin.origin()}) does not load: {type(e).__name__}: {e}") from None


def load_system(name: str):
    """The System registered as ``name`` (the entry point is a System or a factory () -> System),
    or None when no installed plugin registers it."""
    from .systems import System
    if name not in system_plugins():
        return None
    obj, plugin = _load(SYSTEM_GROUP, name)
    if callable(obj) and not isinstance(obj, System):
        try:
            obj = obj()
        except SimgapError:
            raise
        except Exception as e:
            raise SimgapError(f"plugin system {name!r} ({plugin.origin()}) failed to build: "
                              f"{type(e).__name__}: {e}") from None
    if not isinstance(obj, System):
        raise SimgapError(f"plugin system {name!r} ({plugin.origin()}) is not a simgap System or a function "
                          f"returning one (got {type(obj).__name__})")
    if obj.name != name:
        raise SimgapError(f"plugin system {name!r} ({plugin.origin()}) builds a system named {obj.name!r}; "
                          f"the entry-point name and System.name must agree")
    return obj


def load_simulator(kind: str) -> Optional[type]:
    """The Simulator class registered as ``kind``, or None when no installed plugin registers it."""
    from .simulators.base import Simulator
    if kind not in simulator_plugins():
        return None
    cls, plugin = _load(SIMULATOR_GROUP, kind)
    if not (isinstance(cls, type) and issubclass(cls, Simulator)):
        raise SimgapError(f"plugin simulator {kind!r} ({plugin.origin()}) is not a subclass of "
                          f"simgap.simulators.Simulator")
    return cls


def installed_note(group: str) -> str:
    """', plugins: a, b' (or ', no plugins installed') for error messages listing names."""
    names = sorted(system_plugins() if group == SYSTEM_GROUP else simulator_plugins())
    return f"; installed plugins: {', '.join(names)}" if names else f"; no {group} plugins installed"

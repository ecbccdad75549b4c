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

This module is the one place that describes both groups (``simgap plugins``, the GUI). The
lookups live with the registries that own a group (:func:`simgap.systems.system_plugins`,
:func:`simgap.simulators.base.simulator_plugins`), on top of :mod:`simgap.entry_points`.
"""

from __future__ import annotations

from .entry_points import SIMULATOR_GROUP, SYSTEM_GROUP, Plugin, refresh  # noqa: F401
from .entry_points import installed_note as _note
from .entry_points import shadowed as _shadowed
from .simulators.base import _BACKENDS, simulator_plugins  # noqa: F401
from .simulators.base import load_plugin_simulator as load_simulator  # noqa: F401
from .systems import BUILTIN, system_plugins  # noqa: F401
from .systems import load_plugin_system as load_system  # noqa: F401


def shadowed() -> list:
    """Plugin names ignored because a built-in has the same name: (group, Plugin)."""
    return _shadowed(SYSTEM_GROUP, BUILTIN) + _shadowed(SIMULATOR_GROUP, _BACKENDS)


def installed_note(group: str) -> str:
    """', plugins: a, b' (or ', no plugins installed') for error messages listing names."""
    return _note(group, system_plugins() if group == SYSTEM_GROUP else simulator_plugins())

"""System references: what names a nominal model in files and on the command line, and how it resolves.

A reference is a built-in or plugin name (:mod:`simgap.systems`), a system file's path or its
embedded table (:mod:`simgap.system_file`), a refined system's JSON file or object
(:mod:`simgap.refine.refined`), or a :class:`~simgap.systems.System`. Data sets, certificates and
controllers record a reference and its digest, so every later command rebuilds the very model.
This module sits above both :mod:`simgap.systems` and :mod:`simgap.system_file`; the refined
system is built on top of it and is named in :data:`SYSTEM_BUILDERS` instead of imported.
"""

from __future__ import annotations

import importlib
import os
from typing import Callable, Optional

from . import system_file
from .errors import SimgapError
from .systems import BUILTIN, System, _plugins_note, get_system, is_named


#: Builders of the systems other modules define on top of :class:`System`, named ("module:function")
#: and imported only when a reference needs one, as the simulator backends are: the refined system
#: (:mod:`simgap.refine.refined`) is built on this module, so this module names it instead of importing
#: it (no import circle: tests/test_layout.py).
SYSTEM_BUILDERS = {
    "refined_object": "simgap.refine.refined:system_from_dict",  # an embedded refined-system JSON object
    "refined_file": "simgap.refine.refined:load_refined",        # the path of a refined-system JSON file
}


def system_builder(kind: str) -> Callable:
    """The builder :data:`SYSTEM_BUILDERS` names for ``kind``."""
    mod, fn = SYSTEM_BUILDERS[kind].split(":")
    return getattr(importlib.import_module(mod), fn)


def resolve_system(ref, steps: Optional[int] = None, paths: bool = True) -> System:
    """The one way to turn a system reference into a :class:`System`.

    ``ref`` is a built-in or plugin name (``pendulum``, ``turtlebot``, ``emps``, see ``simgap
    plugins``), an embedded system file or refined system (the JSON objects with ``format:
    simgap-system`` / ``simgap-refined-system`` recorded in manifests, data sets, certificates
    and controllers), the path of a system file (``.toml``) or refined-system JSON (command line,
    experiment TOML), or a System (returned as is). Files are parsed with the expression
    allow-list, never executed. ``steps`` (k base periods per sampling period) overrides the
    reference's own. ``paths=False`` for references read from a file: data never make simgap
    open another file.
    """
    if isinstance(ref, System):
        s = ref
    elif paths and isinstance(ref, (str, os.PathLike)) and str(ref).endswith(".toml") and os.path.isfile(ref):
        s = system_file.load_system_file(ref)  # before the plugins are listed (no name ends in .toml)
    elif is_named(ref):
        s = get_system(ref)
    elif system_file.is_spec(ref):
        s = system_file.system_from_spec(ref).with_steps(int(ref.get("steps", 1)))
    else:
        if isinstance(ref, dict):
            s = system_builder("refined_object")(ref)
        elif paths and isinstance(ref, (str, os.PathLike)) and os.path.isfile(ref):
            try:
                s = system_builder("refined_file")(ref)
            except SimgapError as e:  # the file the user named, then what is wrong in it
                msg = str(e)
                raise SimgapError(msg if str(ref) in msg else f"{str(ref)!r}: {msg}") from None
        else:
            raise SimgapError(f"unknown system {str(ref)[:200]!r}: not a built-in ({', '.join(sorted(BUILTIN))})"
                              + (", no such system file (.toml) or refined-system JSON file" if paths else
                                 " or an embedded system") + _plugins_note())
    return s.with_steps(steps) if steps is not None else s


def system_ref(system: System):
    """What :func:`resolve_system` rebuilds ``system`` from: the refined system's JSON object or
    the system file's table (self-contained, not tied to a file), or a built-in or plugin name;
    ``None`` for a system defined in Python only."""
    d = system.params.get("_refined_json")
    if d is not None:
        return dict(d, steps=int(system.steps), name=system.name)
    f = system.params.get("_system_file")
    if f is not None:
        return dict(f, steps=int(system.steps))
    return system.name if is_named(system.name) else None


def embedded_ref(system: System) -> Optional[dict]:
    """:func:`system_ref` when it is an embedded object (system file or refined system), else None:
    what certificates carry so that later commands rebuild the model without its file."""
    ref = system_ref(system)
    return ref if isinstance(ref, dict) else None


def ref_of_description(desc: dict):
    """The reference a manifest's system description (:meth:`System.describe`) rebuilds from."""
    params = desc.get("params") or {}
    return params.get("_refined_json") or params.get("_system_file") or desc.get("name")


def system_digest(system: System) -> Optional[str]:
    """sha256 of what the model computes: the built-in's (or plugin's) name, the system file's
    table (:func:`simgap.system_file.spec_digest`) or the refined system's JSON (base and effects
    with coefficients; name and steps are compared separately). Certificates record it, so a
    certificate is never used with a different model of the same name. ``None`` for a system
    defined in Python only."""
    from .fileio import content_digest
    ref = system_ref(system)
    if system_file.is_spec(ref):
        return system_file.spec_digest(ref)
    if isinstance(ref, dict):
        ref = {"base": ref.get("base"), "effects": ref.get("effects")}
    return None if ref is None else content_digest({"system": ref})

"""One typed reader for the options of the experiment, system and simulator sections.

The experiment sections are typed by :mod:`simgap.schema` (pydantic, strict: no coercion), whose
refusals use this module's :data:`SPELLING`; every built-in simulator backend declares the type of
each key it takes (:attr:`simgap.simulators.Simulator.TYPES`, ``{section: {key: kind}}``), and
:func:`check_section` refuses a value of another type before the backend reads it, naming the key
as written (``simulator.options.base_velocity``), the value, and the fix. The backends then read
the (already typed) values and check ranges and lengths.

Why: a value read with ``bool(...)`` turns the string ``"false"`` into True, so
``base_velocity = "false"`` silently switched velocity states on. A boolean here is a TOML
boolean and nothing else; the strings ``"true"``, ``"yes"``, ``"1"`` ... are refused with the
accepted spelling, never guessed.

Kinds (:data:`KINDS`): ``bool``; ``int`` (a whole number, not a boolean); ``number`` (an int or
a finite-or-not float, not a boolean: ranges are the backend's); ``numbers`` (a number or a flat
list of numbers); ``matrix`` (a list of equally long lists of numbers); ``name`` (a string);
``names`` (a string or a list of strings); ``boxes`` (a list of lists of numbers); ``any``.
"""

from __future__ import annotations

import numbers as _nums

from .errors import SimgapError

KINDS = ("bool", "int", "number", "numbers", "matrix", "name", "names", "boxes", "any")

#: what each kind accepts, as the refusal says it
SPELLING = {
    "bool": "true or false (a TOML boolean, without quotes: {key} = true or {key} = false)",
    "int": "a whole number, without quotes (e.g. {key} = 4)",
    "number": "a number, without quotes (e.g. {key} = 0.5)",
    "numbers": "a number or a list of numbers (e.g. {key} = 0.1 or {key} = [0.1, 0.2])",
    "matrix": "a list of equally long rows of numbers (e.g. {key} = [[1.0, 0.0], [0.0, 1.0]])",
    "name": "a string in quotes (e.g. {key} = \"name\")",
    "names": "a string or a list of strings (e.g. {key} = [\"joint_a\", \"joint_b\"])",
    "boxes": "a list of lists of numbers (e.g. {key} = [[0.0, 1.0, 0.0, 1.0]])",
    "any": "any value",
}


def _number(v) -> bool:
    return isinstance(v, _nums.Real) and not isinstance(v, bool)


def _numbers(v) -> bool:
    if _numeric_array(v):
        return v.ndim == 1
    return isinstance(v, (list, tuple)) and all(_number(x) for x in v)


def _numeric_array(v) -> bool:
    """A numpy array of numbers (what a Python caller may pass; a TOML or JSON file never holds one)."""
    import numpy as np
    return isinstance(v, np.ndarray) and v.dtype.kind in "iuf"


def is_kind(value, kind: str) -> bool:
    """True if ``value`` has the type ``kind`` names (see the module docstring)."""
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "int":
        return isinstance(value, _nums.Integral) and not isinstance(value, bool)
    if kind == "number":
        return _number(value)
    if kind == "numbers":
        return _number(value) or _numbers(value) or (_numeric_array(value) and value.ndim == 0)
    if kind == "matrix":
        if _numeric_array(value):
            return value.ndim == 2
        return (isinstance(value, (list, tuple)) and all(_numbers(r) for r in value)
                and len({len(r) for r in value}) <= 1)
    if kind == "name":
        return isinstance(value, str)
    if kind == "names":
        return isinstance(value, str) or (isinstance(value, (list, tuple)) and all(isinstance(x, str) for x in value))
    if kind == "boxes":
        return (_numeric_array(value) and value.ndim == 2) or (
            isinstance(value, (list, tuple)) and all(_numbers(r) for r in value))
    if kind == "any":
        return True
    raise ValueError(f"unknown option kind {kind!r} (kinds: {', '.join(KINDS)})")


#: said after a refused boolean: why the string is not guessed
NOT_GUESSED = "; a string such as \"false\" or \"yes\" (or a number) is never read as a boolean"


def spelling(key: str, kind: str) -> str:
    """How to write a ``kind`` value of ``key`` (and, for a boolean, why a string is not guessed)."""
    return SPELLING[kind].format(key=key) + (NOT_GUESSED if kind == "bool" else "")


def must_be(what: str, key: str, value, kind: str) -> str:
    """``<what> must be <spelling>, got <value>`` (and, for a boolean, why the value is not guessed)."""
    return f"{what} must be {SPELLING[kind].format(key=key)}, got {value!r}" + (NOT_GUESSED if kind == "bool" else "")


def refusal(where: str, key: str, value, kind: str) -> SimgapError:
    """The error for ``where.key = value`` not being a ``kind``: names the key, the value and the fix."""
    return SimgapError(must_be(f"{where}.{key}", key, value, kind))


def check_section(values: dict, types: dict, where: str) -> None:
    """Refuse the first key of ``values`` whose value is not of its declared kind in ``types``
    (keys without a declared kind are the backend's to check)."""
    for key, value in values.items():
        kind = types.get(key)
        if kind is not None and not is_kind(value, kind):
            raise refusal(where, key, value, kind)


def flag(values: dict, key: str, default: bool, where: str) -> bool:
    """``values[key]`` as a boolean (``default`` when absent); anything but true/false refused by name."""
    v = values.get(key, default)
    if not isinstance(v, bool):
        raise refusal(where, key, v, "bool")
    return v

"""Sub-systems of a system file: a chosen subset of the states, the others fixed at given values.

The diagnosis of an empty winning domain (docs/own-system.md, section 7) synthesizes the parts of
a system alone: the pole of a cart-pole with the cart at rest, the cart with the pole upright.
:func:`split_spec` makes such a part from a system file's table, as a system file of its own:

* the kept states keep their formulas, bounds, units and flags (``angles``, ``velocities``,
  ``translation_invariant``), in the original order;
* every other state becomes a parameter with its fixed value (the formulas read it by name, so
  nothing in them changes): it is held during the period too, so the part is the full model with
  those states' own dynamics switched off (what a diagnosis wants: "the pole with the cart at
  rest"); the value must lie in the state's range [x_lo, x_hi];
* a ``[bounds]`` matrix keeps the rows and columns of the kept states: a bound on |dF_i/dx_j|
  over X also bounds it over the slice where the others are fixed (sound, possibly loose);
* inputs, tau, steps, parameters and definitions are unchanged.

The result is checked like any system file (:func:`simgap.system_file.system_from_spec`) before it
is written; :func:`toml_text` writes it (round trip checked).
"""

from __future__ import annotations

import json
import math
import tomllib
from typing import Dict, List

from .errors import SimgapError

#: tables written after the top-level keys, in this order
TABLES = ("params", "definitions", "dynamics", "bounds")


def split_spec(spec: dict, keep: List[str], fixed: Dict[str, float], where: str = "system file") -> dict:
    """The system file table of the sub-system with states ``keep`` and the others at ``fixed``
    (module docstring). ``fixed`` must give a value for every state not kept."""
    states = list(spec.get("states", []))
    unknown = [s for s in keep if s not in states]
    if unknown:
        raise SimgapError(f"{where}: no state {', '.join(map(repr, unknown))}; its states: {', '.join(states)}")
    if not keep or len(set(keep)) != len(keep):
        raise SimgapError(f"{where}: name each kept state once (got {', '.join(keep) or 'none'})")
    if spec.get("dynamics", {}).get("kind") not in ("discrete", "continuous"):
        raise SimgapError(f"{where}: only formula systems ([dynamics] kind discrete or continuous) can be split")
    drop = [s for s in states if s not in keep]
    if not drop:
        raise SimgapError(f"{where}: keeping every state is the system itself; name a subset")
    extra = sorted(set(fixed) - set(drop))
    if extra:
        raise SimgapError(f"{where}: --fix names {', '.join(extra)}, which {'is' if len(extra) == 1 else 'are'} "
                          "kept or not a state; fix only the states left out")
    missing = [s for s in drop if s not in fixed]
    if missing:
        raise SimgapError(f"{where}: give a value for every state left out ({', '.join(missing)}), e.g. "
                          f"--fix {','.join(f'{s}=0' for s in missing)}")
    idx = [states.index(s) for s in states if s in keep]  # the original order
    lo, hi = spec["x_lo"], spec["x_hi"]
    for s in drop:
        j = states.index(s)
        v = float(fixed[s])
        if not (math.isfinite(v) and float(lo[j]) <= v <= float(hi[j])):
            raise SimgapError(f"{where}: {s} = {v:g} is outside its range [{lo[j]:g}, {hi[j]:g}]")
    params = dict(spec.get("params", {}))
    clash = [s for s in drop if s in params]
    if clash:
        raise SimgapError(f"{where}: parameter {clash[0]!r} has a state's name")
    out = {k: v for k, v in spec.items() if k not in ("states", "x_lo", "x_hi", "dynamics", "bounds", "params")}
    out["name"] = f"{spec.get('name', 'system')}_{'_'.join(states[i] for i in idx)}"
    out["description"] = (f"{spec.get('name', 'system')} with only {', '.join(states[i] for i in idx)}; fixed: "
                          + ", ".join(f"{s} = {float(fixed[s]):g}" for s in drop))
    out["states"] = [states[i] for i in idx]
    out["x_lo"] = [lo[i] for i in idx]
    out["x_hi"] = [hi[i] for i in idx]
    for key in ("angles", "velocities", "translation_invariant"):
        if key in spec:
            kept = [s for s in spec[key] if s in keep]
            if kept:
                out[key] = kept
            else:
                out.pop(key, None)
    if "units" in spec:
        out["units"] = {k: v for k, v in spec["units"].items() if k not in drop}
    params.update({s: float(fixed[s]) for s in drop})
    out["params"] = params
    dyn = spec["dynamics"]
    out["dynamics"] = {k: v for k, v in dyn.items() if k not in drop}
    if "bounds" in spec:
        out["bounds"] = {k: [[row[j] for j in idx] for row in (m[i] for i in idx)] for k, m in spec["bounds"].items()}
    return out


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string: JSON's escapes are TOML's
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    raise SimgapError(f"cannot write {type(v).__name__} to a system file")


def _key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() and k.isascii() else json.dumps(k)


def toml_text(spec: dict, header: str = "") -> str:
    """A system file table as TOML text (top-level keys, then ``[params]``, ``[definitions]``,
    ``[dynamics]``, ``[bounds]``); reading it back gives ``spec`` (checked)."""
    lines = [f"# {h}" for h in header.splitlines()] if header else []
    lines += [f"{_key(k)} = {_value(v)}" for k, v in spec.items() if k not in TABLES]
    for t in TABLES:
        if t in spec:
            lines += ["", f"[{t}]"] + [f"{_key(k)} = {_value(v)}" for k, v in spec[t].items()]
    text = "\n".join(lines) + "\n"
    if tomllib.loads(text) != json.loads(json.dumps(spec)):
        raise SimgapError("internal: the sub-system's TOML does not read back as written")
    return text

"""``simgap plugins``: the systems and simulator kinds this installation offers, with their keys.

Lists the built-ins and what installed packages register through the entry-point groups
``simgap.systems`` and ``simgap.simulators`` (:mod:`simgap.plugins`): per system its states,
inputs, X, |U| and tau; per simulator kind the keys of its ``noise``, ``randomize``,
``effects`` and ``options`` config sections. A plugin that fails to load is listed with the
reason (exit status 1), never a traceback.
"""

from __future__ import annotations

import argparse


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "plugins", help="list systems and simulator kinds (built-in and from installed plugins) with their keys",
        description="List the systems and simulator kinds this installation offers: the built-ins and those "
                    "installed packages register (entry-point groups simgap.systems, simgap.simulators), "
                    "with each simulator's config keys.")
    p.add_argument("--json", action="store_true", help="print the listing as JSON")
    p.set_defaults(func=run)


def listing() -> dict:
    """{"systems": [...], "simulators": [...], "shadowed": [...]}, every entry a JSON-ready dict."""
    from .. import plugins
    from ..errors import SimgapError
    from ..simulators.base import _BACKENDS, simulator_class
    from ..systems import BUILTIN, get_system

    sys_plugins, sim_plugins = plugins.system_plugins(), plugins.simulator_plugins()
    systems = []
    for name in sorted(BUILTIN) + sorted(sys_plugins):
        entry = {"name": name, "source": "built-in" if name in BUILTIN else sys_plugins[name].origin()}
        try:
            s = get_system(name)
            entry.update(states=list(s.state_names), inputs=list(s.input_names), x_lo=s.x_lo.tolist(),
                         x_hi=s.x_hi.tolist(), n_inputs=int(s.inputs.shape[0]), tau=s.tau)
        except SimgapError as e:
            entry["error"] = str(e)
        systems.append(entry)
    simulators = []
    for kind in sorted(_BACKENDS) + sorted(sim_plugins):
        entry = {"kind": kind, "source": "built-in" if kind in _BACKENDS else sim_plugins[kind].origin()}
        try:
            cls = simulator_class(kind)
            entry.update({sec: list(getattr(cls, attr, ())) for sec, attr in
                          (("noise", "NOISE_KEYS"), ("randomize", "RANDOMIZE_KEYS"), ("effects", "EFFECT_KEYS"),
                           ("options", "OPTION_KEYS"))})
            doc = (cls.__doc__ or "").strip().splitlines()
            entry["about"] = doc[0] if doc else ""
        except (SimgapError, ImportError) as e:  # an optional dependency of a built-in backend
            entry["error"] = str(e) if isinstance(e, SimgapError) else f"{type(e).__name__}: {e}"
        simulators.append(entry)
    shadowed = [{"group": g, "name": p.name, "source": p.origin()} for g, p in plugins.shadowed()]
    return {"systems": systems, "simulators": simulators, "shadowed": shadowed}


def run(args) -> int:
    import json

    d = listing()
    if args.json:
        print(json.dumps(d, indent=2))
    else:
        print("systems (use as [system] name, --system NAME):")
        for e in d["systems"]:
            if "error" in e:
                print(f"  {e['name']:<20} {e['source']}\n    ERROR: {e['error']}")
                continue
            box = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in zip(e["x_lo"], e["x_hi"]))
            print(f"  {e['name']:<20} {e['source']}\n    states {', '.join(e['states'])}; inputs "
                  f"{', '.join(e['inputs'])} (|U| = {e['n_inputs']}); X = {box}; tau = {e['tau']:g} s")
        print("simulator kinds (use as [simulator] kind):")
        for e in d["simulators"]:
            print(f"  {e['kind']:<20} {e['source']}")
            if "error" in e:
                print(f"    ERROR: {e['error']}")
                continue
            if e.get("about"):
                print(f"    {e['about']}")
            for sec in ("noise", "randomize", "effects", "options"):
                print(f"    {sec + ':':<11}{', '.join(e[sec]) or '-'}")
        for e in d["shadowed"]:
            print(f"ignored: plugin {e['name']!r} ({e['source']}) in {e['group']} has a built-in's name")
        print("system files (.toml) are accepted wherever a system is: docs/system-files.md")
    bad = any("error" in e for e in d["systems"] + d["simulators"])
    return 1 if bad else 0

"""``simgap split SYSTEM.toml --keep A,B --fix C=0,D=0 --out part.toml``: a sub-system file.

Keeps the named states of a system file, fixes the others at the given values (they become
parameters) and writes the result as a system file of its own (:mod:`simgap.system_split`), for
synthesizing the parts of a system alone when its winning domain is empty (docs/own-system.md,
section 7):

    simgap split cartpole.toml --keep theta,omega --fix p=0,v=0 --out pole.toml
    simgap synthesize --system pole.toml --no-gap --safe=-0.1,0.1,-1,1 --eta 0.01,0.05 --out pole.npz
"""

from __future__ import annotations

import argparse

from ..errors import SimgapError


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("split", help="a system file with a subset of its states, the others fixed",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("system", metavar="SYSTEM", help="a system file (.toml)")
    p.add_argument("--keep", required=True, help="the states to keep, comma separated (in any order)")
    p.add_argument("--fix", default="", help="values of the other states, NAME=VALUE comma separated "
                                             "(default: the middle of each one's range)")
    p.add_argument("--out", required=True, help="the sub-system file to write (.toml)")
    p.set_defaults(func=run, outputs=("out",), formats={"out": (".toml",)})


def _fixed(text: str) -> dict:
    """{state: value} from ``NAME=VALUE,NAME=VALUE``; a state given two different values is refused."""
    import math

    out = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            v = float(value)
        except ValueError:
            raise SimgapError(f"--fix {item!r}: expected NAME=VALUE, e.g. p=0") from None
        if not math.isfinite(v):
            raise SimgapError(f"--fix {item!r}: the value must be a finite number")
        key = name.strip()
        if key in out and out[key] != v:  # one value per state: never keep the last silently
            raise SimgapError(f"--fix gives {key} twice ({key}={out[key]:g} and {key}={v:g}): give each state one "
                              f"value, e.g. --fix {key}={out[key]:g}")
        out[key] = v
    return out


def run(args) -> int:
    import tomllib
    from pathlib import Path

    from .. import fileio
    from ..system_file import system_from_spec
    from ..system_split import split_spec, toml_text

    path = Path(args.system)
    if path.suffix != ".toml" or not path.is_file():
        raise SimgapError(f"{args.system!r} is not a system file (.toml) that exists")
    try:
        spec = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
        raise SimgapError(f"system file {str(path)!r} is unreadable: {e}") from None
    if "states" not in spec or "dynamics" not in spec:
        named = spec.get("system")
        named = named.get("name") if isinstance(named, dict) else named
        hint = f" (an experiment? split its system file, {named!r})" if isinstance(named, str) else ""
        raise SimgapError(f"{str(path)!r} is not a system file: no states or [dynamics]{hint}")
    system_from_spec(dict(spec), str(path))  # the original must be a valid system first
    keep = [s.strip() for s in args.keep.split(",") if s.strip()]
    fixed = _fixed(args.fix)
    states, lo, hi = spec["states"], spec["x_lo"], spec["x_hi"]
    mid = {s: (float(lo[j]) + float(hi[j])) / 2 for j, s in enumerate(states) if s not in keep and s not in fixed}
    part = split_spec(spec, keep, {**mid, **fixed}, str(path))
    sub = system_from_spec(dict(part), f"the sub-system of {path.name}")  # checked before it is written
    text = toml_text(part, header=f"made by: simgap split {path.name} --keep {','.join(keep)} --fix "
                                  + ",".join(f"{k}={v:g}" for k, v in part["params"].items() if k in states))
    with fileio.atomic_file(args.out) as fh:
        fh.write(text)
    for s, v in mid.items():
        print(f"note: {s} fixed at {v:g}, the middle of its range (--fix {s}=VALUE to choose)")
    print(f"sub-system {sub.name}: states {', '.join(sub.state_names)}; fixed "
          + ", ".join(f"{s} = {float(part['params'][s]):g}" for s in states if s not in keep))
    print(f"wrote {args.out}")
    return 0

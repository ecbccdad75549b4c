"""Installed size of the dependency closures of `pip install -e .` and `pip install -e ".[dev]"`.

    python bench/install_size.py

Counts, for the distributions installed in this environment, every file each one recorded
(importlib.metadata), over the closure of pyproject.toml's requirements (environment markers
evaluated here, extras of dependencies not followed). No network: it measures what is installed,
not a fresh download into a clean venv.
"""

from __future__ import annotations

import re
import tomllib
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


DISTS = {_norm(d.metadata["Name"]): d for d in metadata.distributions()}


def size(dist) -> int:
    """Bytes of every file the distribution recorded (missing files count 0)."""
    total = 0
    for f in dist.files or []:
        try:
            total += f.locate().stat().st_size
        except OSError:
            pass
    return total


def closure(requirements) -> set:
    """Installed distributions reachable from ``requirements`` (markers evaluated without extras)."""
    seen, todo = set(), [Requirement(r) for r in requirements]
    while todo:
        req = todo.pop()
        if req.marker and not req.marker.evaluate({"extra": ""}):
            continue
        name = _norm(req.name)
        if name in seen or name not in DISTS:
            continue
        seen.add(name)
        todo += [Requirement(r) for r in DISTS[name].requires or []]
    return seen


def main() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    base = closure(project["dependencies"])
    dev = closure(project["dependencies"] + project["optional-dependencies"]["dev"])
    for label, names in (("pip install -e .", base), ('pip install -e ".[dev]"', dev)):
        print(f"{label}: {len(names)} distributions, {sum(size(DISTS[n]) for n in names) / 1e9:.2f} GB installed")
    for label, names in (("largest of the plain install", base), ("largest added by [dev]", dev - base)):
        top = sorted(((size(DISTS[n]), n) for n in names), reverse=True)[:6]
        print(f"{label}: " + ", ".join(f"{n} {s / 1e6:.0f} MB" for s, n in top))


if __name__ == "__main__":
    main()

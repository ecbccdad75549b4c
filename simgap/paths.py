"""Where simgap's bundled assets are: URDF files, arena maps and experiment files.

In a source checkout (and an editable install) they are the repository's ``assets/`` folder; a
regular install puts the same files under ``<prefix>/share/simgap/assets`` (pyproject.toml,
``tool.setuptools.data-files``).
"""

from __future__ import annotations

import sys
from pathlib import Path


def _assets_dir() -> Path:
    checkout = Path(__file__).resolve().parents[1] / "assets"
    for cand in (checkout, Path(sys.prefix) / "share" / "simgap" / "assets"):
        if (cand / "experiments").is_dir():
            return cand
    return checkout  # missing everywhere: later lookups name this path in their errors


#: the folder holding ``urdf/``, ``maps/`` and ``experiments/``
ASSETS_DIR = _assets_dir()


def install_command(extra: str | None, cwd: Path | None = None) -> str:
    """The pip command that adds ``extra`` (None: simgap's own dependencies) to the install at hand.
    From a source checkout (an editable install: simgap's package folder sits next to its
    pyproject.toml) it installs the checkout again with the extra, spelled ``".[extra]"`` from
    inside it; an installed package names the registry's ``'simgap[extra]'``."""
    root = Path(__file__).resolve().parents[1]
    pyproject = root / "pyproject.toml"
    if pyproject.is_file() and 'name = "simgap"' in pyproject.read_text(errors="replace"):
        here = Path.cwd() if cwd is None else cwd
        where = "." if here.resolve() == root else str(root)
        return f"pip install -e {where}" if extra is None else f'pip install -e "{where}[{extra}]"'
    return "pip install simgap" if extra is None else f"pip install 'simgap[{extra}]'"

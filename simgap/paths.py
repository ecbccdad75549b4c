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

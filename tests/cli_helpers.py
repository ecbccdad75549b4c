"""What the command-line tests share: run `python -m simgap` on this checkout in a subprocess (what a
user sees), list a folder's files, and check a refusal (non-zero exit, no traceback, the message)."""

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def simgap(*args, cwd, timeout=120):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "simgap", *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)


def files(folder: Path) -> set:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def refused(r, *words):
    """Non-zero exit, no traceback, and every word in the message."""
    assert r.returncode != 0, r.stdout + r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    for w in words:
        assert w in r.stderr, (w, r.stderr)

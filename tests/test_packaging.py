"""Everyday polish: quiet third-party libraries, ordinary file permissions, declared Pythons."""

import os
import stat
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from simgap.fileio import savez, write_json

REPO = Path(__file__).resolve().parents[1]


def test_collect_prints_no_pybullet_banner(tmp_path):
    """PyBullet prints a build banner on import (stderr) and argv[0]= on connect (stdout)."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-m", "simgap", "collect", "pendulum", "--out", str(tmp_path / "d"),
                        "--epsilon", "0.05", "--n-runs", "4", "--workers", "2"],
                       capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    both = p.stdout + p.stderr
    assert "collected" in p.stdout  # the command did run its simulators
    assert "pybullet build time" not in both and "argv[0]" not in both, both


def test_urdf_meshes_print_nothing(capfd):
    from simgap.simulators._bullet import urdf_path
    from simgap_viz.layers.bodies import urdf_meshes

    assert urdf_meshes(urdf_path("pendulum.urdf"))
    out, err = capfd.readouterr()
    assert "argv[0]" not in out + err and "pybullet build time" not in out + err


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_result_files_respect_umask(tmp_path, mask):
    old = os.umask(mask)
    try:
        a = write_json(tmp_path / "a.json", {"x": 1})
        b = savez(tmp_path / "b.npz", x=[1, 2])
        ref = tmp_path / "ref.txt"
        ref.write_text("plain open()")
    finally:
        os.umask(old)
    want = stat.S_IMODE(ref.stat().st_mode)
    assert want == 0o666 & ~mask
    assert stat.S_IMODE(a.stat().st_mode) == want and stat.S_IMODE(b.stat().st_mode) == want
    assert not list(tmp_path.glob(".*.tmp"))


def test_running_python_is_a_declared_one():
    spec = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["requires-python"]
    lo = tuple(int(v) for v in spec.split(",")[0].removeprefix(">=").split("."))
    assert sys.version_info[:len(lo)] >= lo, (spec, sys.version)

"""Messages about a missing extra name the pip command for the install at hand (issue 54): an editable
clone reinstalls itself with the extra, an installed package names the registry's extra."""

import subprocess
import sys
from pathlib import Path

import pytest

from simgap import paths
from simgap.errors import SimgapError

ROOT = Path(__file__).resolve().parents[1]


def test_clone_and_installed_package(tmp_path, monkeypatch):
    assert paths.install_command("mujoco", cwd=ROOT) == 'pip install -e ".[mujoco]"'
    assert paths.install_command("ray", cwd=tmp_path) == f'pip install -e "{ROOT}[ray]"'  # outside the clone
    assert paths.install_command(None, cwd=ROOT) == "pip install -e ."
    # an installed package: site-packages/simgap/paths.py, no pyproject.toml beside the package
    site = tmp_path / "site-packages" / "simgap"
    site.mkdir(parents=True)
    monkeypatch.setattr(paths, "__file__", str(site / "paths.py"))
    assert paths.install_command("mujoco", cwd=tmp_path) == "pip install 'simgap[mujoco]'"
    assert paths.install_command(None, cwd=tmp_path) == "pip install simgap"
    # a pyproject.toml of another project next to it is not a simgap clone
    (tmp_path / "site-packages" / "pyproject.toml").write_text('[project]\nname = "other"\n')
    assert paths.install_command("sign", cwd=tmp_path) == "pip install 'simgap[sign]'"


def test_missing_mujoco_names_the_clone_command(monkeypatch):
    """The real message: MuJoCo hidden from the import system, from this clone's root."""
    from simgap.simulators.mujoco_sim import mujoco_module

    monkeypatch.setitem(sys.modules, "mujoco", None)
    monkeypatch.chdir(ROOT)
    with pytest.raises(SimgapError, match=r'pip install -e "\.\[mujoco\]"'):
        mujoco_module()


def test_missing_extra_from_the_command_line(tmp_path):
    """Through `simgap run` on the reacher with MuJoCo hidden: exit 1, one line naming the command, no
    traceback."""
    hide = tmp_path / "hide"
    hide.mkdir()
    (hide / "mujoco.py").write_text("raise ImportError('hidden for this test')\n")
    env = {"PYTHONPATH": f"{hide}:{ROOT}", "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    r = subprocess.run([sys.executable, "-m", "simgap", "run", "reacher", "--out", str(tmp_path / "out")],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "Traceback" not in r.stderr, r.stderr
    assert 'pip install -e ".[mujoco]"' in r.stderr, r.stderr


"""Bad system files, names and plugins through the real command line (subprocesses): a message
naming the problem, a non-zero exit, no traceback, nothing written; hostile formulas are refused
while parsing, never run."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cli_helpers import files, refused, simgap

REPO = Path(__file__).resolve().parents[1]

GOOD = """
name = "osc"
states = ["x", "v"]
inputs = ["F"]
x_lo = [-1.0, -1.0]
x_hi = [1.0, 1.0]
tau = 0.1
input_grid = {lo = [-1.0], hi = [1.0], counts = [3]}
[params]
k = 1.0
[dynamics]
kind = "continuous"
substeps = 2
x = "v"
v = "-k*x + F"
"""

EXP = """
system = "osc.toml"
[simulator]
kind = "numpy"
[collect]
epsilon = 0.2
n_runs = 4
executor = "serial"
"""


BAD_FILES = {
    "unknown name": (GOOD.replace('"-k*x + F"', '"-k*x + G"'), ["dynamics.v", "unknown variable 'G'", "known: F"]),
    "state count": (GOOD.replace("x_lo = [-1.0, -1.0]", "x_lo = [-1.0, -1.0, 0.0]"), ["x_lo has 3 entries for 2 states"]),
    "formula missing": (GOOD.replace('x = "v"\n', ""), ["[dynamics] needs one formula per state", "missing ['x']"]),
    "input count": (GOOD.replace("counts = [3]", "counts = [3, 2]"), ["input_grid.counts", "1 numbers"]),
    "non-finite bound": (GOOD.replace("x_hi = [1.0, 1.0]", "x_hi = [1.0, inf]"), ["x_hi must be finite"]),
    "empty bound": (GOOD.replace("x_hi = [1.0, 1.0]", "x_hi = [1.0, -1.0]"), ["X is empty in 'v'"]),
    "NaN on X": (GOOD.replace('"-k*x + F"', '"sqrt(x) + F"'), ["not finite on X", "is nan after one period"]),
    "bad tau": (GOOD.replace("tau = 0.1", "tau = 0"), ["tau (the base period [s])"]),
    "unknown key": (GOOD.replace("tau = 0.1", "tau = 0.1\nangels = [\"x\"]"), ["unknown key 'angels'", "'angles'"]),
    "angle name": (GOOD.replace("tau = 0.1", "tau = 0.1\nangles = [\"theta\"]"), ["angles must list state names"]),
    "bad jacobian": (GOOD.replace("[dynamics]", "[bounds]\njacobian = [[1, 0.1]]\n[dynamics]"),
                     ["bounds.jacobian must be an 2 x 2 matrix"]),
    "reserved name": (GOOD.replace('states = ["x", "v"]', 'states = ["x", "sin"]'), ["'sin' is reserved"]),
    "huge input grid": (GOOD.replace("counts = [3]", "counts = [1000000000]"), ["input_grid has 1e+09 inputs",
                                                                           "at most 100,000"]),
}

HOSTILE = {
    "import": "__import__('os').system('touch pwned')",
    "attribute": "x.__class__",
    "call of a call": "(lambda: 1)()",
    "eval": "eval('1')",
    "subscript": "F[0]",
    "comprehension": "[F for F in (1,)]",
    "string": "'touch pwned'",
}


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "exp.toml").write_text(EXP)
    return tmp_path


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_system_file_is_refused_by_collect(folder, case):
    text, words = BAD_FILES[case]
    (folder / "osc.toml").write_text(text)
    before = files(folder)
    r = simgap("collect", "exp.toml", "--profile", "base", "--no-progress", cwd=folder)
    refused(r, "osc.toml", *words)
    assert files(folder) == before  # no store, no runs/ folder


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_formula_is_refused_and_never_run(folder, case):
    (folder / "osc.toml").write_text(GOOD.replace('"-k*x + F"', json.dumps(HOSTILE[case])))  # a TOML string
    before = files(folder)
    r = simgap("synthesize", "--system", "osc.toml", "--no-gap", "--safe=-1,1,-1,1", "--eta", "0.1",
               "--out", "c.npz", cwd=folder)
    refused(r, "dynamics.v")
    assert "is not allowed" in r.stderr or "unknown variable" in r.stderr or "not a number" in r.stderr, r.stderr
    assert files(folder) == before and not (folder / "pwned").exists()


def test_system_file_outside_the_experiment_folder(tmp_path):
    (tmp_path / "osc.toml").write_text(GOOD)
    (tmp_path / "exp").mkdir()
    (tmp_path / "exp" / "exp.toml").write_text(EXP.replace('"osc.toml"', '"../osc.toml"'))
    r = simgap("collect", "exp/exp.toml", "--profile", "base", cwd=tmp_path)
    refused(r, "../osc.toml", "outside the experiment's folder")
    (tmp_path / "exp" / "exp.toml").write_text(EXP.replace('"osc.toml"', f'"{tmp_path / "osc.toml"}"'))
    r = simgap("collect", "exp/exp.toml", "--profile", "base", cwd=tmp_path)
    refused(r, "outside the experiment's folder")
    (tmp_path / "exp" / "exp.toml").write_text(EXP.replace('"osc.toml"', '"missing.toml"'))
    r = simgap("collect", "exp/exp.toml", "--profile", "base", cwd=tmp_path)
    refused(r, "'missing.toml' does not exist")
    assert files(tmp_path) == {"osc.toml", "exp", "exp/exp.toml"}


def test_names_that_are_not_installed_list_what_is(folder):
    (folder / "osc.toml").write_text(GOOD)
    (folder / "e2.toml").write_text(EXP.replace('"osc.toml"', '"no_such_system"'))
    before = files(folder)
    r = simgap("collect", "e2.toml", "--profile", "base", cwd=folder)
    refused(r, "unknown system 'no_such_system'", "built-in systems: emps, pendulum, turtlebot")
    assert "plugins" in r.stderr
    (folder / "e3.toml").write_text(EXP.replace('kind = "numpy"', 'kind = "no_such_backend"'))
    before = files(folder)
    r = simgap("collect", "e3.toml", "--profile", "base", cwd=folder)
    refused(r, "simulator.kind", "unknown simulator kind 'no_such_backend'", "numpy, pybullet_pendulum")
    assert "plugins" in r.stderr
    r = simgap("synthesize", "--system", "no_such_system", "--no-gap", "--safe=-1,1,-1,1", "--eta", "0.1",
               "--out", "c.npz", cwd=folder)
    refused(r, "unknown system 'no_such_system'")
    assert files(folder) == before

"""Hostile input, third pass (issue 45): typed options that cannot flip, results folders a forged
list cannot empty, rollout files that prove their content, no hang on a huge step count, no
traceback, resumable plots, and messages that name the option, its value and the fix.

Each case runs what a user runs (mostly the real command line in a subprocess) and asserts the
exit code, the words of the message, no traceback and, where files are at stake, that no file
changed. Every case failed on the tree before issue 45's fixes (a silently flipped setting, a
deleted user file, a drawn forged rollout, a hang, a traceback, or a message naming the wrong
thing)."""

import copy
import dataclasses
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import refused, simgap
from test_bad_input import EXP, run_folder, work  # noqa: F401  (module fixtures reused)
from test_hostile_probe import damped, digests  # noqa: F401

REPO = Path(__file__).resolve().parents[1]


def _husky(tmp_path, edit) -> Path:
    """examples/husky (the robot from the installed pybullet_data) with its experiment edited."""
    pytest.importorskip("pybullet_data")
    d = tmp_path / "husky"
    shutil.copytree(REPO / "examples" / "husky", d)
    text = (d / "experiment.toml").read_text()
    (d / "experiment.toml").write_text(edit(text))
    return d


def _write(folder: Path, name: str, text: str) -> str:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(text)
    return name


# ----- 1. typed options: booleans are booleans, every field refuses a wrong type ---------------------------

@pytest.mark.parametrize("value", ['"false"', '"yes"', "0"])
def test_base_velocity_string_is_refused_by_name_not_turned_on(tmp_path, value):
    """`base_velocity = "false"` used to switch velocity states ON (bool("false") is True)."""
    d = _husky(tmp_path, lambda t: t.replace("base_pose = true", f"base_pose = true\nbase_velocity = {value}"))
    before = digests(d)
    r = simgap("collect", "experiment.toml", "--profile", "base", "--dry-run", cwd=d, timeout=300)
    refused(r, "simulator.options.base_velocity", value.replace('"', "'"), "true or false", "without quotes")
    assert "state has" not in r.stderr  # not reported as a state-count mismatch
    assert digests(d) == before


@pytest.mark.parametrize("key", ["base_pose", "fixed_base", "ground", "cone_friction"])
def test_every_urdf_flag_refuses_the_string_false(tmp_path, key):
    import re
    d = _husky(tmp_path, lambda t: re.sub(rf"(?m)^{key} = .*$", "", t)
               .replace("[simulator.options]\n", f'[simulator.options]\n{key} = "false"\n'))
    r = simgap("collect", "experiment.toml", "--profile", "base", "--dry-run", cwd=d, timeout=300)
    refused(r, f"simulator.options.{key}", "'false'", "true or false")


#: a value of the wrong type for each kind of simgap.typed
WRONG = {"bool": "false", "int": "4", "number": "0.5", "numbers": "0.1", "matrix": [[1.0], "x"], "name": 3,
         "names": [1, 2], "boxes": "box"}
BACKENDS = {"numpy": "pendulum", "pybullet_pendulum": "pendulum", "pybullet_turtlebot": "turtlebot",
            "pybullet_urdf": "pendulum", "mujoco": "pendulum"}


@pytest.mark.parametrize("kind", sorted(BACKENDS))
def test_every_simulator_key_has_a_type_and_refuses_a_wrong_one(kind):
    """The walk: every key every built-in backend accepts is typed (Simulator.TYPES) and a wrong type is
    refused by its full name before the backend reads it (no model file is even opened)."""
    from simgap.errors import SimgapError
    from simgap.simulators.base import SimulatorConfig, simulator_class
    cls = simulator_class(kind)
    types = getattr(cls, "TYPES", {})
    for section, keys in (("noise", cls.NOISE_KEYS), ("randomize", cls.RANDOMIZE_KEYS),
                          ("effects", cls.EFFECT_KEYS), ("options", cls.OPTION_KEYS)):
        for key in keys:
            t = types.get(section, {}).get(key)
            assert t is not None, f"{kind}: {section}.{key} has no declared type"
            if t == "any":
                continue
            cfg = SimulatorConfig(kind=kind, system=BACKENDS[kind], **{section: {key: WRONG[t]}})
            with pytest.raises(SimgapError) as e:
                cls(cfg)
            msg = str(e.value)
            assert f"simulator.{section}.{key}" in msg and repr(WRONG[t]) in msg and "must be" in msg, msg
            if t == "bool":
                assert "true or false" in msg


def _wrong_values():
    return ["not-a-value", 12345.5, {"nested": "table"}, [[["deep"]]], True]


def _fields(model, path=()):
    """(path of section/key names, field) of every field of the experiment schema, nested tables included."""
    from pydantic import BaseModel
    from typing import get_args
    for name, f in model.model_fields.items():
        sub = [a for a in (f.annotation, *get_args(f.annotation)) if isinstance(a, type) and issubclass(a, BaseModel)]
        if sub:
            yield from _fields(sub[0], path + (name,))
        else:
            yield path + (name,), f


def test_every_schema_field_refuses_a_wrong_type_by_name():
    """The walk over the experiment schema: every field refuses a value of a wrong type with a message
    naming its section and key; a boolean field refuses the string "false" with the accepted spelling."""
    from simgap import schema
    from simgap.errors import SimgapError
    base = {"system": {"name": "pendulum"}, "simulator": {"kind": "numpy"}, "collect": {"epsilon": 0.1, "n_runs": 10}}
    schema.validate(base, "exp")
    checked = 0
    for path, f in _fields(schema.Experiment):
        if path == ("description",):
            continue
        refusals = []
        for wrong in _wrong_values():
            d = copy.deepcopy(base)
            node = d
            for p in path[:-1]:
                node = node.setdefault(p, {})
            node[path[-1]] = wrong
            try:
                schema.validate(d, "exp")
            except SimgapError as e:
                refusals.append(str(e))
        assert refusals, f"{'.'.join(path)} takes a value of every type"
        key = path[-1]
        assert any(key in m and f"[{path[0]}" in m for m in refusals), (path, refusals)
        if f.annotation is bool:
            d = copy.deepcopy(base)
            d.setdefault(path[0], {})[key] = "false"
            with pytest.raises(SimgapError, match="true or false"):
                schema.validate(d, "exp")
        checked += 1
    assert checked > 60  # every section's every key


def test_an_epsilon_list_of_the_wrong_length_is_named_as_epsilon(tmp_path):
    _write(tmp_path, "exp.toml", EXP.replace("epsilon = 0.1", "epsilon = [0.1, 0.1, 0.1]"))
    r = simgap("collect", "exp.toml", "--profile", "base", "--dry-run", cwd=tmp_path)
    refused(r, "[collect] epsilon", "[0.1, 0.1, 0.1]", "3 radii", "2 covered", "theta, omega")
    assert "spacing" not in r.stderr  # the key the user did not write (with doubled values) is not named


# ----- 2. results folders: a list simgap did not write never licenses a delete -------------------------------

def _forged_journal(res: Path, victims) -> None:
    files = {n: {"sha256": hashlib.sha256((res / n).read_bytes()).hexdigest()} for n in victims}
    (res / ".simgap-files.json").write_text(json.dumps({"run_id": "forged", "files": files}))


def test_a_forged_hidden_file_list_deletes_nothing(tmp_path):
    """The user's result-named files, listed by hand with their sha256 in a hidden run journal, survive a
    run into the folder; the log names no summary.json that is not there."""
    res = tmp_path / "res"
    res.mkdir()
    (res / "cert_mine.json").write_text('{"my": "certificate"}')
    (res / "rollouts_mine.npz").write_bytes(b"my rollouts")
    _forged_journal(res, ["cert_mine.json", "rollouts_mine.npz"])
    _write(tmp_path, "exp.toml", EXP)
    mine = {n: (res / n).read_bytes() for n in ("cert_mine.json", "rollouts_mine.npz")}
    r = simgap("run", "exp.toml", "--profile", "base", "--out", "res", "--no-record", cwd=tmp_path, timeout=300)
    assert r.returncode == 0, r.stderr
    for n, b in mine.items():
        assert (res / n).read_bytes() == b, f"{n} was changed or deleted"
    assert "removed" not in r.stderr
    assert "left 2 file(s) simgap did not write untouched" in r.stderr


def test_a_forged_list_naming_a_file_the_run_writes_refuses_the_run(tmp_path):
    from simgap import results_folder as rf
    from simgap.errors import SimgapError
    (tmp_path / "cert_stochastic.json").write_text('{"mine": 1}')
    _forged_journal(tmp_path, ["cert_stochastic.json"])
    before = digests(tmp_path)
    with pytest.raises(SimgapError, match=r"cert_stochastic.json \(not listed in a file list simgap can verify"):
        rf.claim(tmp_path, ["cert_stochastic.json"])
    assert digests(tmp_path) == before
    # the same list sealed as simgap seals its own: the file is the earlier run's
    j = json.loads((tmp_path / ".simgap-files.json").read_text())
    (tmp_path / ".simgap-files.json").write_text(json.dumps(rf.seal(j)))
    assert rf.claim(tmp_path, ["cert_stochastic.json"]).owned == ["cert_stochastic.json"]


def test_mutation_an_unsealed_list_would_delete(tmp_path, monkeypatch):
    """The check that protects the user's file is the seal: without it (the old reading) the forged list
    deletes the file. (Guards the test above against passing for another reason.)"""
    from simgap import results_folder as rf
    (tmp_path / "cert_mine.json").write_text("mine")
    _forged_journal(tmp_path, ["cert_mine.json"])
    assert rf.claim(tmp_path, []).owned == []
    monkeypatch.setattr(rf, "files_digest", lambda run_id, files: None)  # every list "verifies"
    j = json.loads((tmp_path / ".simgap-files.json").read_text())
    j["files_digest"] = None
    (tmp_path / ".simgap-files.json").write_text(json.dumps(j))
    assert rf.claim(tmp_path, []).owned == ["cert_mine.json"]


# ----- 3. rollout files prove their content; non-finite trajectories refused ---------------------------------

@pytest.fixture(scope="module")
def rollouts(work, tmp_path_factory):  # noqa: F811
    """A rollout file `simgap rollout --trajectories` wrote (the work controller, 5 rollouts)."""
    d = tmp_path_factory.mktemp("rollouts")
    r = simgap("rollout", "--controller", work / "ctrl.npz", "--simulator", work / "exp.toml", "--profile", "base",
               "--x0", "0.05,0.1", "--n", "5", "--horizon", "5", "--out", "r.json", "--trajectories", "r.npz",
               cwd=d, timeout=300)
    assert r.returncode == 0, r.stderr
    return d / "r.npz"


def _edit_rollouts(src: Path, dst: Path, edit, reseal: bool) -> None:
    from simgap import fileio
    with np.load(src) as z:
        a = {k: z[k] for k in z.files}
    meta = json.loads(str(a.pop("meta_json")))
    edit(meta, a)
    if reseal and "digest" in meta:  # a consistent digest: only the value checks can refuse it
        meta.pop("digest")
        meta["digest"] = fileio.content_digest(meta, a)
    np.savez_compressed(dst, **a, meta_json=np.array(json.dumps(meta)))


def test_rollouts_with_another_controllers_digest_are_refused(rollouts, tmp_path):
    _edit_rollouts(rollouts, tmp_path / "r.npz",
                   lambda m, a: m.update(controller_digest="0" * 64), reseal=False)
    before = digests(tmp_path)
    r = simgap("plot", "--rollouts", "r.npz", "--out", "figs", cwd=tmp_path)
    refused(r, "r.npz", "modified after it was written")
    assert digests(tmp_path) == before and not (tmp_path / "figs").exists()


def test_all_nan_trajectories_are_refused_by_name(rollouts, tmp_path):
    def nan(m, a):
        a["trajectories"] = np.full_like(a["trajectories"], np.nan)
    _edit_rollouts(rollouts, tmp_path / "r.npz", nan, reseal=True)
    r = simgap("plot", "--rollouts", "r.npz", "--out", "figs", cwd=tmp_path)
    refused(r, "r.npz", "trajectories", "NaN")
    assert not (tmp_path / "figs").exists()


def test_a_rollout_file_without_a_digest_is_refused(rollouts, tmp_path):
    from simgap.errors import SimgapError
    from simgap.rollout import load_rollout
    _edit_rollouts(rollouts, tmp_path / "r.npz", lambda m, a: m.pop("digest", None), reseal=False)
    with pytest.raises(SimgapError, match="records no content digest"):
        load_rollout(tmp_path / "r.npz")
    load_rollout(rollouts)  # the file as written loads


# ----- 4. work bounded before it starts: a huge step count is refused at once ---------------------------------

def _refined_steps(damped, d) -> str:  # noqa: F811
    r = json.loads((damped / "refined.json").read_text())
    r["steps"] = 10 ** 9
    (d / "steps.json").write_text(json.dumps(r))
    shutil.copy(damped / "damped.npz", d / "damped.npz")
    return "steps.json"


def test_refined_system_with_1e9_steps_is_refused_within_10_s(damped, tmp_path):  # noqa: F811
    name = _refined_steps(damped, tmp_path)
    t0 = time.monotonic()
    r = simgap("refine", "--system", name, "--data", "damped.npz", "--quiet", cwd=tmp_path, timeout=10)
    refused(r, "steps.json", '"steps"', "1,000,000,000", "10,000")
    assert time.monotonic() - t0 < 10


def test_dataset_embedding_1e9_steps_is_refused_within_10_s(work, tmp_path):  # noqa: F811
    from simgap.dataset import load_dataset
    ds = load_dataset(work / "data.npz")
    s = copy.copy(ds.system)
    object.__setattr__(s, "steps", 10 ** 9)  # what an edited file holds (System's own check bypassed)
    dataclasses.replace(ds, system=s).save_npz(tmp_path / "forged.npz")  # its content hash recomputed
    t0 = time.monotonic()
    r = simgap("certify", "forged.npz", "--out", "c.json", cwd=tmp_path, timeout=10)
    refused(r, "forged.npz", "steps", "1,000,000,000")
    assert time.monotonic() - t0 < 10 and not (tmp_path / "c.json").exists()


# ----- 5. no traceback -------------------------------------------------------------------------------------

def test_nul_byte_in_a_pybullet_data_path(tmp_path):
    d = _husky(tmp_path, lambda t: t.replace('urdf = "pybullet_data:husky/husky.urdf"',
                                             'urdf = "pybullet_data:husky/hu\\u0000sky.urdf"'))
    r = simgap("collect", "experiment.toml", "--profile", "base", "--dry-run", cwd=d, timeout=120)
    refused(r, "simulator.options.urdf", "NUL byte", "\\x00")


INVARIANT = """
[synthesis]
method = "invariant_set"
{extra}
"""


@pytest.mark.parametrize("extra,words", [
    ("K = [[1.0], [2.0, 3.0]]", ["[synthesis] K must have shape 1 x 2", "[[1.0], [2.0, 3.0]]", "rows of lengths 1, 2"]),
    ("lqr_q = [1.0, 2.0, 3.0]", ["[synthesis] lqr_q", "[1.0, 2.0, 3.0]", "one weight or 2", "theta, omega"]),
    ('spec = "reach_avoid"\nmap = "arena"', ['method = "invariant_set"', 'spec = "invariance" only', "reach_avoid",
                                             'method = "grid"']),
])
def test_invariant_set_options_of_the_wrong_shape(tmp_path, extra, words):
    _write(tmp_path, "exp.toml", EXP.replace("[synthesis]\neta = [0.004, 0.01]\n", "")
           + INVARIANT.format(extra=extra))
    r = simgap("run", "exp.toml", "--profile", "base", "--out", "res", cwd=tmp_path, timeout=120)
    refused(r, *words)
    assert "x0" not in r.stderr  # (the reach-avoid case was reported as an initial-state length)
    assert not (tmp_path / "res").exists()


def test_ragged_gain_through_the_api():
    from simgap.errors import SimgapError
    from simgap.synthesis.invariant_set import _parse_matrix, _weights
    with pytest.raises(SimgapError, match="rows of equal length"):
        _parse_matrix([[1.0], [2.0, 3.0]], 2, 2)
    with pytest.raises(SimgapError, match="lqr_q .* need one finite weight or 2, got 3"):
        _weights([1.0, 2.0, 3.0], 2, "lqr_q")
    assert _weights(2.0, 3, "lqr_q").tolist() == [2.0, 2.0, 2.0]


# ----- 6. resumable plot, unfinished runs --------------------------------------------------------------------

KILL_AFTER_FIRST_FIGURE = """
import os, signal, sys
import simgap_viz.figures as F
orig = F.save
def save(fig, out_dir, name):
    paths = orig(fig, out_dir, name)
    os.kill(os.getpid(), signal.SIGKILL)   # kill -9 right after the first figure is in place
F.save = save
from simgap.cli import main
main(["plot", "res", "--out", "figs"])
"""

KILL_WHILE_DRAWING = """
import os, signal
import matplotlib.figure
orig = matplotlib.figure.Figure.savefig
def savefig(self, *a, **k):
    orig(self, *a, **k)
    os.kill(os.getpid(), signal.SIGKILL)   # kill -9 with the first figure half-written (temporary name)
matplotlib.figure.Figure.savefig = savefig
from simgap.cli import main
main(["plot", "res", "--out", "figs"])
"""


@pytest.mark.parametrize("script", [KILL_AFTER_FIRST_FIGURE, KILL_WHILE_DRAWING])
def test_plot_resumes_after_kill_9(run_folder, tmp_path, script):  # noqa: F811
    shutil.copytree(run_folder[0] / "res", tmp_path / "res")
    (tmp_path / "kill.py").write_text(script)
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    k = subprocess.run([sys.executable, "kill.py"], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert k.returncode == -signal.SIGKILL, k.stderr
    figs = tmp_path / "figs"
    # a user's file under a figure name is still refused (resuming does not make every figure name
    # simgap's), and only it is named: the killed plot's own figure is not
    own = [p.name for p in figs.iterdir() if not p.name.startswith(".")]
    assert script is KILL_WHILE_DRAWING or own, "the kill came before any figure was in place"
    (figs / "p_cert.png").write_bytes(b"my picture")
    before = digests(figs)
    r = simgap("plot", "res", "--out", "figs", cwd=tmp_path, timeout=300)
    refused(r, "p_cert.png", "did not write")
    assert not [n for n in own if n in r.stderr] and digests(figs) == before, (own, r.stderr)
    (figs / "p_cert.png").unlink()
    r = simgap("plot", "res", "--out", "figs", cwd=tmp_path, timeout=300)
    assert r.returncode == 0, r.stderr
    assert not [p.name for p in figs.iterdir() if ".tmp." in p.name]  # its own leftovers removed
    listed = json.loads((figs / ".simgap-figures.json").read_text())["files"]
    drawn = sorted(p.name for p in figs.iterdir() if not p.name.startswith("."))
    assert drawn and sorted(listed) == drawn
    from simgap.results_folder import file_digest
    assert all(listed[n] == file_digest(figs / n) for n in drawn)


def test_an_unfinished_run_folder_is_named_with_the_command_that_finishes_it(run_folder, tmp_path):  # noqa: F811
    shutil.copytree(run_folder[0] / "res", tmp_path / "res")
    (tmp_path / "res" / "summary.json").unlink()  # stopped before its summary
    r = simgap("plot", "res", "--out", "figs", cwd=tmp_path)
    refused(r, "'res'", "did not finish", "simgap run", "exp.toml", "--profile base", "--out")
    assert "data set" not in r.stderr
    r = simgap("view", "res", "--web-port", "0", "--grpc-port", "0", "--exit-after", "0", cwd=tmp_path)
    refused(r, "did not finish")


# ----- 7. messages that name what the user wrote --------------------------------------------------------------

def test_split_fix_given_twice_is_refused(tmp_path):
    shutil.copy(REPO / "assets" / "experiments" / "cartpole" / "cartpole.toml", tmp_path / "cartpole.toml")
    r = simgap("split", "cartpole.toml", "--keep", "theta,omega", "--fix", "p=0,p=0.5,v=0", "--out", "pole.toml",
               cwd=tmp_path)
    refused(r, "--fix", "p twice", "p=0", "p=0.5")
    assert not (tmp_path / "pole.toml").exists()


def test_audit_with_another_systems_experiment_is_refused(work, tmp_path):  # noqa: F811
    r = simgap("audit", work / "cert.json", "--data", work / "data", "--experiment", "turtlebot", "--points", "5",
               "--runs", "20", "--out", tmp_path / "a.json", cwd=tmp_path, timeout=120)
    refused(r, "--experiment 'turtlebot'", "'turtlebot'", "'pendulum'", "another experiment")
    assert not (tmp_path / "a.json").exists()


def test_an_overflowing_refined_coefficient_is_named(damped, tmp_path):  # noqa: F811
    r = json.loads((damped / "refined.json").read_text())
    r["effects"][0]["coefficient"] = 1e300
    (tmp_path / "big.json").write_text(json.dumps(r))
    shutil.copy(damped / "damped.npz", tmp_path)
    p = simgap("refine", "--system", "big.json", "--data", "damped.npz", "--quiet", cwd=tmp_path, timeout=60)
    refused(p, "big.json", "effect 'viscous_friction'", "state 'omega'", '"coefficient": 1e+300')
    assert "RuntimeWarning" not in p.stderr


def test_experiment_steps_above_the_bound_are_refused_by_the_schema(tmp_path):
    _write(tmp_path, "exp.toml", EXP.replace('name = "pendulum"', 'name = "pendulum"\nsteps = 1000000000'))
    r = simgap("collect", "exp.toml", "--profile", "base", "--dry-run", cwd=tmp_path, timeout=10)
    refused(r, "[system] steps", "10000", "1000000000")

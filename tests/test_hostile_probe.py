"""Hostile input and reused folders, in the style of an outside probe: each case runs the real
command line in a subprocess and asserts the exit code, a keyword of the message, that no file
in the case's folder changed (sha256 before and after) and that no traceback reached the user.

Every case failed before the fixes of issue 35 (a deleted earlier run, a hang, a traceback, a
silent exit 0 or a message that did not name the flag or field at fault)."""

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import refused, simgap
from test_bad_input import EXP, run_cert, run_folder, work  # noqa: F401  (module fixtures reused)

REPO = Path(__file__).resolve().parents[1]


def digests(folder: Path) -> dict:
    """{relative path: sha256} of every regular file below ``folder`` (FIFOs and links not followed)."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_symlink() or not p.is_file():
            continue
        out[str(p.relative_to(folder))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def simgap_capped(*args, cwd, memory: int, timeout=120):
    """``simgap`` with its address space capped (a command that tries to allocate gigabytes fails fast
    instead of taking the shared machine's memory)."""
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (memory, memory))

    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "simgap", *map(str, args)], cwd=cwd, env=env, preexec_fn=limit,
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def damped(tmp_path_factory):
    """Transitions of a damped pendulum (refine's input) and a refined system saved from them."""
    from simgap.cli import main
    from simgap.simulators.base import make_simulator
    from simgap.systems import get_system

    d = tmp_path_factory.mktemp("damped")
    s = get_system("pendulum")
    rng = np.random.default_rng(21)
    x = s.x_lo + rng.random((2000, 2)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, len(s.inputs), 2000)]
    with make_simulator({"kind": "numpy", "system": "pendulum", "noise": {"process_std": 1e-4},
                         "effects": {"linear": [[0, 0], [0, -0.5]]}}) as sim:
        xn = sim.step(x, u, rng)
    np.savez(d / "damped.npz", x=x, u=u, x_next=xn, tau=s.tau)
    assert main(["refine", "--system", "pendulum", "--data", str(d / "damped.npz"), "--quiet",
                 "--save-system", str(d / "refined.json")]) == 0
    return d


# ----- each case: (prepare(ctx, folder) -> command-line args, words the message must hold, timeout) ------------

def _copy(src: Path, d: Path, name: str = None) -> str:
    dst = d / (name or src.name)
    (shutil.copytree if src.is_dir() else shutil.copy)(src, dst)
    return dst.name


def _results(ctx, d):
    """A copy of a finished run's folder (summary.json, results, stores, run.rrd) in ``d/res``."""
    shutil.copytree(ctx["run"], d / "res")
    return d / "res"


def _forged_dataset(ctx, d, **change):
    import dataclasses

    from simgap.dataset import load_dataset
    ds = load_dataset(ctx["work"] / "data.npz")
    ds = dataclasses.replace(ds, **{k: (v(ds) if callable(v) else v) for k, v in change.items()})
    ds.save_npz(d / "forged.npz")  # the content hash recomputed: only the checks on the values can refuse it
    return "forged.npz"


def _forged_controller(ctx, d):
    from simgap import fileio
    with np.load(ctx["work"] / "ctrl.npz") as z:
        a = {k: z[k] for k in z.files}
    meta = json.loads(str(a.pop("meta")))
    a["chosen"] = np.where(a["chosen"] >= 0, 999, a["chosen"]).astype(np.int32)
    assert (a["chosen"] == 999).any()
    meta.pop("digest")
    meta["digest"] = fileio.content_digest(meta, a)  # a consistent digest: only the index check can refuse it
    np.savez(d / "ctrl999.npz", **a, meta=np.array(json.dumps(meta)))
    return "ctrl999.npz"


def _refined(ctx, d, name, edit):
    r = json.loads((ctx["damped"] / "refined.json").read_text())
    edit(r)
    (d / name).write_text(json.dumps(r))
    return name


def _deep(d, name, depth=100_000):
    (d / name).write_text("[" * depth + "]" * depth)
    return name


def _stray_recording(ctx, d):
    import rerun as rr
    res = _results(ctx, d)
    rec = rr.RecordingStream("simgap", recording_id="another-run")
    rec.save(str(res / "run.rrd"))
    rec.log("points", rr.Points3D(np.zeros((3, 3))))
    rec.flush()
    del rec
    return ["view", "res", "--web-port", "0", "--grpc-port", "0", "--exit-after", "0"]


def _missing_listed(ctx, d):
    res = _results(ctx, d)
    assert "audit_deterministic.json" in json.loads((res / "summary.json").read_text())["files"]
    (res / "audit_deterministic.json").unlink()
    return ["plot", "res", "--out", "figs"]


def _deep_summary(ctx, d):
    res = _results(ctx, d)
    _deep(res, "summary.json")
    return ["plot", "res", "--out", "figs"]


def _fifo(d, name):
    os.mkfifo(d / name)
    return name


def _loop(d, name):
    os.symlink(name, d / name)
    return name


PERRUN = """
[perrun]
alpha = 0.8
eta = [0.1, 0.2]
hold = 1
horizon = 5
n_runs = 20
pilot_runs = 5
n_rollouts = 10
n_states = 2
"""

CASES = {
    # a refused run keeps the earlier run's results (it used to delete them first)
    "run_of_another_config_keeps_earlier_results": (
        lambda c, d: ["run", _write(d, "other.toml", EXP.replace("seed = 5", "seed = 6")), "--profile", "base",
                      "--out", _results(c, d).name],
        ["different configuration", "seed"], 120),
    # a user's summary.json is not a run's: refused, not overwritten
    "user_summary_json_is_not_overwritten": (
        lambda c, d: ["run", _write(d, "exp.toml", EXP), "--profile", "base", "--out",
                      _write(d / "res", "summary.json", '{"mine": true}') and "res"],
        ["simgap did not write", "summary.json"], 120),
    # readers verify the folder against its summary
    "view_refuses_a_recording_of_another_run": (_stray_recording, ["run.rrd", "differs from the file this run wrote"],
                                                120),
    "plot_names_a_listed_file_that_is_missing": (_missing_listed, ["audit_deterministic.json is missing", "summary.json"], 120),
    "plot_refuses_deeply_nested_summary": (_deep_summary, ["summary.json", "levels"], 120),
    # data sets
    "cover_point_outside_X": (
        lambda c, d: ["certify", _forged_dataset(c, d, x=lambda ds: np.where(np.arange(ds.K)[:, None] == 0,
                                                                              ds.x + [3.0, 0.0], ds.x)),
                      "--out", "c.json"],
        ["cover points", "outside X"], 120),
    "dataset_claiming_1e9_runs": (
        lambda c, d: ["certify", _forged_dataset(c, d, n_runs=10 ** 9), "--level", "run", "--alpha", "0.8",
                      "--out", "c.json"],
        ["n_runs", "manifest"], 120),
    # --alpha at every level
    "audit_run_certificate_alpha_zero": (
        lambda c, d: ["audit", _copy(c["run_cert"], d), "--data", _copy(c["work"] / "data", d), "--alpha", "0",
                      "--points", "5", "--runs", "20"],
        ["--alpha", "(0, 1)"], 120),
    "audit_run_certificate_alpha_nan": (
        lambda c, d: ["audit", _copy(c["run_cert"], d), "--data", _copy(c["work"] / "data", d), "--alpha", "nan",
                      "--points", "5", "--runs", "20"],
        ["--alpha", "(0, 1)"], 120),
    "audit_run_certificate_alpha_ignored": (
        lambda c, d: ["audit", _copy(c["run_cert"], d), "--data", _copy(c["work"] / "data", d), "--alpha", "0.3",
                      "--points", "5", "--runs", "20"],
        ["--alpha", "run-level certificate"], 120),
    # names from files
    "refined_name_with_terminal_escapes": (
        lambda c, d: ["refine", "--system", _refined(c, d, "evil.json", lambda r: r.update(name="x\x1b[2J\x1b[31m")),
                      "--data", _copy(c["damped"] / "damped.npz", d)],
        ["control characters", "\\x1b"], 120),
    # files that are not files
    "cert_is_a_fifo": (
        lambda c, d: ["audit", _fifo(d, "cert.json"), "--data", _copy(c["work"] / "data", d)],
        ["FIFO", "not a regular file"], 30),
    "cert_is_dev_zero": (
        lambda c, d: ["audit", "/dev/zero", "--data", _copy(c["work"] / "data", d)],
        ["character device"], 30),
    "input_is_a_symlink_loop": (lambda c, d: ["certify", _loop(d, "data"), "--out", "c.json"], ["symlink loop"], 60),
    "cert_deeply_nested": (
        lambda c, d: ["audit", _deep(d, "cert.json"), "--data", _copy(c["work"] / "data", d)],
        ["cert.json", "levels"], 60),
    # sizes and shapes before any work
    "run_level_eta_of_wrong_length": (
        lambda c, d: ["synthesize", "--level", "run", "--spec", _write(d, "exp.toml", EXP + PERRUN), "--profile", "base",
                      "--eta", "0.1,0.1,0.1", "--out", "c.npz"],
        ["--eta", "need one cell width or 2"], 120),
    "run_level_degree_40": (
        lambda c, d: ["certify", _copy(c["work"] / "data", d), "--level", "run", "--alpha", "0.8", "--degree", "40",
                      "--out", "c.json"],
        ["--degree", "basis terms"], 60),
    # values checked on load
    "controller_input_index_999": (
        lambda c, d: ["rollout", "--controller", _forged_controller(c, d), "--simulator", _write(d, "exp.toml", EXP),
                      "--profile", "base", "--x0", "0.05", "0.1", "--n", "5", "--horizon", "5", "--out", "r.json"],
        ["input index", "999"], 120),
    "refined_model_overflowing_to_inf": (  # finite on X, its residuals overflow: refused on load, the coefficient named
        lambda c, d: ["refine", "--system", _refined(c, d, "big.json", lambda r: r["effects"][0].update(
            coefficient=1e308)), "--data", _copy(c["damped"] / "damped.npz", d), "--out", "rep.json"],
        ["big.json", "viscous_friction", "coefficient", "1e+308"], 120),
    # messages that name the flag or field at fault
    "refined_steps_not_a_number": (
        lambda c, d: ["refine", "--system", _refined(c, d, "steps.json", lambda r: r.update(steps="many")),
                      "--data", _copy(c["damped"] / "damped.npz", d), "--quiet"],
        ['"steps"', "'many'"], 120),
    "safe_box_inverted": (
        lambda c, d: ["synthesize", "--no-gap", "--system", "pendulum", "--safe=0.2,-0.2,-0.5,0.5",
                      "--eta", "0.004,0.01", "--out", "c.npz"],
        ["--safe", "lo = 0.2 > hi = -0.2"], 60),
}


def _write(folder: Path, name: str, text: str) -> str:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / name).write_text(text)
    return name


@pytest.fixture(scope="module")
def ctx(work, run_cert, run_folder, damped):  # noqa: F811  (the fixtures imported above)
    return {"work": work, "run_cert": run_cert, "run": run_folder[0] / "res", "damped": damped}


@pytest.mark.parametrize("case", sorted(CASES))
def test_hostile_case(case, ctx, tmp_path):
    prepare, words, timeout = CASES[case]
    args = prepare(ctx, tmp_path)
    before = digests(tmp_path)
    run = simgap_capped if case == "dataset_claiming_1e9_runs" else None
    r = (run(*args, cwd=tmp_path, memory=3 << 30, timeout=timeout) if run else
         simgap(*args, cwd=tmp_path, timeout=timeout))
    refused(r, *words)
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "\x1b" not in r.stdout + r.stderr  # nothing from a file reaches the terminal unescaped
    assert digests(tmp_path) == before  # nothing written, nothing deleted, nothing changed


def test_a_folder_keeps_an_earlier_run_and_foreign_files_through_a_refused_and_a_successful_run(ctx, tmp_path):
    """The issue's "done when": an earlier run plus the user's own files whose names look like results
    survive, byte for byte, a refused run (another configuration); a successful run then replaces
    only the earlier run's listed files and leaves the user's untouched."""
    res = _results(ctx, tmp_path)
    (res / "cert_final.json").write_text('{"mine": 1}')
    shutil.copy(ctx["work"] / "ctrl.npz", res / "controller_good.npz")
    (res / "notes.txt").write_text("my notes")
    _write(tmp_path, "exp.toml", EXP)
    _write(tmp_path, "other.toml", EXP.replace("seed = 5", "seed = 6"))
    before = digests(tmp_path)

    r = simgap("run", "other.toml", "--profile", "base", "--out", "res", cwd=tmp_path, timeout=300)
    refused(r, "different configuration")
    assert digests(tmp_path) == before

    earlier = json.loads((res / "summary.json").read_text())
    r = simgap("run", "exp.toml", "--profile", "base", "--out", "res", "--no-record", cwd=tmp_path, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    after = digests(tmp_path)
    mine = ("res/cert_final.json", "res/controller_good.npz", "res/audit_old.json", "res/notes.txt")
    for name in mine:
        assert after[name] == before[name]
    # notes.txt does not look like a result; the other three are named
    assert "left 3 file(s) simgap did not write untouched" in r.stderr
    summary = json.loads((res / "summary.json").read_text())
    assert summary["run_id"] != earlier["run_id"]
    assert not {"cert_final.json", "controller_good.npz", "audit_old.json"} & set(summary["files"])
    # the earlier run's recording (listed, digest matching) was removed: this run wrote none
    assert "run.rrd" in earlier["files"] and not (res / "run.rrd").exists()
    from simgap_viz.results import load_run
    load_run(res)  # the new run's folder opens beside the user's files


def test_a_stopped_runs_files_are_its_own_to_replace_while_unchanged(tmp_path):
    """A run killed before its summary: the journal lists what it wrote, so the next run may replace
    those files (and only while their digests match); a file it never recorded stays foreign."""
    from simgap import results_folder as rf
    from simgap.errors import SimgapError

    rf.claim(tmp_path, ["cert_stochastic.json"]).release("stopped-run")
    (tmp_path / "cert_stochastic.json").write_text("{}")
    rf.record(tmp_path, ["cert_stochastic.json"])
    (tmp_path / "audit_stochastic.json").write_text("{}")  # written, but killed before it was recorded
    c = rf.claim(tmp_path, ["cert_stochastic.json"])
    assert c.owned == ["cert_stochastic.json"] and set(c.foreign) == {"audit_stochastic.json"}
    with pytest.raises(SimgapError, match="audit_stochastic.json .not listed"):
        rf.claim(tmp_path, ["cert_stochastic.json", "audit_stochastic.json"])
    (tmp_path / "cert_stochastic.json").write_text('{"edited": 1}')
    with pytest.raises(SimgapError, match="changed since simgap wrote it"):
        rf.claim(tmp_path, ["cert_stochastic.json"])


def test_a_manifest_never_owns_a_file_simgap_does_not_write(tmp_path):
    """A forged summary.json listing the user's notes.txt with its exact sha256 still cannot get it deleted;
    a sealed one (files_digest matching, as simgap writes it) owns itself but never a name simgap does not write."""
    from simgap import results_folder as rf
    from simgap.errors import SimgapError
    (tmp_path / "notes.txt").write_text("mine")
    digest = hashlib.sha256(b"mine").hexdigest()
    forged = {"run_id": "x", "methods": {}, "files": {"notes.txt": {"sha256": digest}}}
    (tmp_path / "summary.json").write_text(json.dumps(forged))
    with pytest.raises(SimgapError, match="summary.json .not a summary simgap can verify"):
        rf.claim(tmp_path, ["summary.json"])  # unverifiable (issue 45): kept, the run refused
    (tmp_path / "summary.json").write_text(json.dumps(rf.seal(forged)))
    c = rf.claim(tmp_path, ["summary.json"])
    assert c.owned == ["summary.json"]
    c.release("new-run")
    assert (tmp_path / "notes.txt").read_text() == "mine" and not (tmp_path / "summary.json").exists()

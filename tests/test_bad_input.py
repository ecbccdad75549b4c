"""Bad input through the real command line: every case exits non-zero with a message naming the
problem, no traceback, and leaves no file behind (subprocesses, so what a user sees is tested)."""

import fcntl
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from simgap import checks, file_guard
from simgap.collect import check_collection, collection_size
from simgap.perrun import cost
from simgap.errors import SimgapError

from cli_helpers import files, refused, simgap

REPO = Path(__file__).resolve().parents[1]

EXP = """
[system]
name = "pendulum"
[simulator]
kind = "numpy"
noise = { actuation_std = 0.05 }
[collect]
epsilon = 0.1
n_runs = 8
seed = 5
executor = "serial"
[certify]
beta1 = 0.01
beta2 = 0.01
[synthesis]
eta = [0.004, 0.01]
[rollout]
x0 = [0.05, 0.1]
n = 10
horizon = 20
[audit]
points = 5
runs = 20
[profiles.small.collect]
n_runs = 4
"""


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A folder with an experiment, its collected store, a single-file data set, a certificate
    and a controller (numpy simulator, 504 pairs: seconds)."""
    from simgap.certify import CertifyOptions, certify
    from simgap.collect import collect
    from simgap.config import load_experiment
    from simgap.synthesis.controller import synthesize
    from simgap.synthesis.spec import Box, Spec

    d = tmp_path_factory.mktemp("bad")
    (d / "exp.toml").write_text(EXP)
    exp = load_experiment(d / "exp.toml", None)
    res = collect(exp.plan(), d / "data", executor="serial")
    ds = res.dataset()
    ds.save_npz(d / "data.npz")
    certify(ds, CertifyOptions(beta1=0.01, beta2=0.01)).save(d / "cert.json")
    s = exp.system
    synthesize(s, Spec("invariance", safe=Box(s.x_lo, s.x_hi)), [0.004, 0.01]).controller.save(d / "ctrl.npz")
    for name in ("data.npz", "ctrl.npz", "cert.json"):
        b = (d / name).read_bytes()
        (d / f"trunc_{name}").write_bytes(b[: len(b) // 2])
    (d / "adir").mkdir()
    return d


# ----- output paths: one check before any work ------------------------------------------------

OUT_CASES = {
    "certify": ["certify", "data", "--out", "{out}"],
    "audit": ["audit", "cert.json", "--data", "data", "--points", "5", "--runs", "20", "--out", "{out}"],
    "synthesize": ["synthesize", "--no-gap", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5",
                   "--eta", "0.004,0.01", "--out", "{out}"],
    "synthesize-json": ["synthesize", "--no-gap", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5",
                        "--eta", "0.004,0.01", "--out", "c.npz", "--json", "{out}"],
    "rollout": ["rollout", "--controller", "ctrl.npz", "--simulator", "exp.toml", "--profile", "base",
                "--x0", "0.05,0.1", "--n", "5", "--out", "{out}"],
    "rollout-traj": ["rollout", "--controller", "ctrl.npz", "--simulator", "exp.toml", "--profile", "base",
                     "--x0", "0.05,0.1", "--n", "5", "--out", "r.json", "--trajectories", "{out}"],
    "refine": ["refine", "--system", "pendulum", "--data", "data", "--bootstrap", "2", "--out", "{out}"],
    "refine-system": ["refine", "--system", "pendulum", "--data", "data", "--bootstrap", "2",
                      "--save-system", "{out}"],
    "collect": ["collect", "exp.toml", "--out", "{out}"],
    "run": ["run", "exp.toml", "--out", "{out}"],
}


BAD_OUTS = [
    ("adir", ["'adir'", "is a folder"]),         # a folder where a file goes
    ("exp.toml", ["'exp.toml'", "not a folder"]),  # a file where a folder goes
    ("exp.toml/x", ["exp.toml", "folder"]),      # a path below a file
    ("missing/deeper/x.json", ["missing"]),      # a file in a folder that does not exist
]
FOLDER_OUTPUTS = ("collect", "run")  # result folders: an existing folder is fine, parents are created


@pytest.mark.parametrize("case,out,words", [
    (case, out, words) for case in sorted(OUT_CASES) for out, words in BAD_OUTS
    if (out == "exp.toml") == (case in FOLDER_OUTPUTS) or out == "exp.toml/x"])
def test_unusable_output_is_refused_before_any_work(work, case, out, words):
    args = [a.replace("{out}", out) for a in OUT_CASES[case]]
    before = files(work)
    r = simgap(*args, cwd=work)
    refused(r, *words)
    assert files(work) == before  # nothing written, no *.tmp left


def test_unwritable_output_folder(work):
    """A read-only folder (root may write anywhere, so a read-only mount stands in: /proc)."""
    r = simgap("certify", "data", "--out", "/proc/cert.json", cwd=work)
    refused(r, "/proc/cert.json", "cannot write")


def test_refine_writes_no_tmp(work, tmp_path):
    r = simgap("refine", "--system", "pendulum", "--data", "data", "--bootstrap", "2", "--quiet",
               "--out", tmp_path / "rep.json", cwd=work)
    assert r.returncode == 0, r.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["rep.json"]


def test_output_checks_unit(tmp_path):
    assert file_guard.output_file(tmp_path / "a.json") == tmp_path / "a.json"
    assert file_guard.output_dir(tmp_path / "new" / "deeper") == tmp_path / "new" / "deeper"
    assert list(tmp_path.iterdir()) == []  # checking creates nothing
    with pytest.raises(SimgapError, match="is a folder"):
        file_guard.output_file(tmp_path)
    (tmp_path / "f").write_text("x")
    with pytest.raises(SimgapError, match="not a folder"):
        file_guard.output_dir(tmp_path / "f")
    with pytest.raises(SimgapError, match="is a file, not a folder"):
        file_guard.output_dir(tmp_path / "f" / "sub")


# ----- hangs ------------------------------------------------------------------------------------

@pytest.mark.parametrize("args,words", [
    (["--port", "99999"], ["--port", "0..65535", "99999"]),
    (["--port", "-1"], ["--port", "0..65535"]),
    (["--port", "http"], ["--port", "integer"]),
    (["--host", "999.1.1.1"], ["--host", "999.1.1.1", "IP address"]),
    (["--host", "example.com"], ["--host", "example.com"]),
    (["--host", "10.255.255.254", "--port", "0"], ["cannot listen on 10.255.255.254"]),
])
def test_gui_bad_address_exits_at_once(tmp_path, args, words):
    r = simgap("gui", *args, "--exit-after", "0", cwd=tmp_path, timeout=60)
    refused(r, *words)


def test_ray_unreachable_address_fails_fast_and_writes_nothing(work, tmp_path):
    import time
    t0 = time.monotonic()
    r = simgap("collect", work / "exp.toml", "--profile", "base", "--executor", "ray", "--address", "127.0.0.1:1",
               "--out", tmp_path / "store", "--no-progress", cwd=tmp_path)
    refused(r, "Ray cluster", "127.0.0.1:1")
    assert time.monotonic() - t0 < 60
    assert not (tmp_path / "store").exists()  # no manifest left behind


def test_reachable_checks_address_form():
    for bad, word in [("127.0.0.1", "HOST:PORT"), ("h:x", "not a number"), ("h:0", "1..65535")]:
        with pytest.raises(SimgapError, match=word):
            checks.reachable(bad)
    checks.reachable("auto")  # left to Ray


def test_certify_huge_degree_is_refused_with_sizes(work):
    r = simgap("certify", "data", "--degree", "40", cwd=work, timeout=60)
    refused(r, "degree 40", "12,341 basis terms", "504")
    r = simgap("certify", "data", "--degree", "-5", cwd=work)
    refused(r, "--degree", ">= 0")


def test_basis_size_limits():
    assert checks.basis_terms(3, 2) == 10 and checks.basis_terms(3, 40) == 12341
    checks.check_basis(43239, 3, [2, 2])  # the pendulum's small profile: fine
    with pytest.raises(SimgapError, match="floating-point operations|of memory"):  # which comes first
        checks.check_basis(43239, 3, [40, 40])                                    # depends on free memory
    with pytest.raises(SimgapError, match="cannot be unique"):
        checks.check_basis(50, 3, [5, 5])  # 56 terms


# ----- sizes ------------------------------------------------------------------------------------

def test_collect_too_many_runs_is_refused_with_numbers(work, tmp_path):
    r = simgap("collect", work / "exp.toml", "--profile", "base", "--n-runs", "1e11", "--out", tmp_path / "s",
               cwd=tmp_path)
    refused(r, "N1hat=100,000,000,000", "of memory", "available")
    assert not (tmp_path / "s").exists()
    r = simgap("collect", work / "exp.toml", "--n-runs", "100000000000", "--dry-run", cwd=tmp_path)
    refused(r, "100,000,000,000", "TB")
    r = simgap("collect", work / "exp.toml", "--n-runs", "-3", cwd=tmp_path)
    refused(r, "--n-runs", ">= 2")


def test_collection_estimates():
    e = collection_size(504, 8, 2, 1, 1, 1 << 18, 2, False, rate_per_worker=1e5)
    assert e["runs"] == 4032 and e["seconds"] == pytest.approx(4032 / 2e5)
    with pytest.raises(SimgapError, match="would take about"):
        check_collection(10 ** 6, 1000, 2, 1, 1, 1 << 18, 1, False, ".", rate_per_worker=10.0)
    with pytest.raises(SimgapError, match="of disk"):
        check_collection(10 ** 8, 10 ** 5, 3, 2, 1, 1 << 18, 1, True, ".", rate_per_worker=1e12)


def test_rollout_too_many_is_refused_with_numbers(work, tmp_path):
    r = simgap("rollout", "--controller", work / "ctrl.npz", "--simulator", work / "exp.toml", "--profile", "base",
               "--x0", "0.05,0.1", "--n", "1e9", "--horizon", "100", "--out", tmp_path / "r.json", cwd=tmp_path)
    refused(r, "1,000,000,000 rollouts", "of memory")
    assert list(tmp_path.iterdir()) == []


# ----- truncated files --------------------------------------------------------------------------

@pytest.mark.parametrize("args,words", [
    (["certify", "trunc_data.npz"], ["trunc_data.npz", "not a zip file"]),
    (["rollout", "--controller", "trunc_ctrl.npz", "--simulator", "exp.toml", "--profile", "base",
      "--out", "r.json"], ["trunc_ctrl.npz", "not a zip file"]),
    (["synthesize", "--cert", "trunc_cert.json", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5",
      "--eta", "0.004,0.01", "--out", "c.npz"], ["trunc_cert.json", "JSON"]),
    (["refine", "--system", "pendulum", "--data", "trunc_data.npz"], ["trunc_data.npz"]),
])
def test_truncated_files(work, args, words):
    before = files(work)
    refused(simgap(*args, cwd=work), *words)
    assert files(work) == before


# ----- concurrent collectors --------------------------------------------------------------------

def test_second_collector_into_one_store_is_refused(work, tmp_path):
    store = tmp_path / "s"
    r = simgap("collect", work / "exp.toml", "--profile", "base", "--out", store, "--no-progress", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    manifest = (store / "manifest.json").read_bytes()
    with open(store / ".lock", "a") as fh:  # a collector running into the store holds this lock
        fcntl.lockf(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        r = simgap("collect", work / "exp.toml", "--profile", "base", "--out", store, "--no-progress",
                   cwd=tmp_path)
        refused(r, "being collected by another process", str(store))
    assert (store / "manifest.json").read_bytes() == manifest
    # released (as when the first collector exits or is killed): the same command resumes
    r = simgap("collect", work / "exp.toml", "--profile", "base", "--out", store, "--no-progress", cwd=tmp_path)
    assert r.returncode == 0 and "already done" in r.stdout, r.stderr


def test_concurrent_collectors_compute_each_chunk_once(tmp_path):
    """Two real collectors started together into one store: every chunk is computed once; the
    later one is refused while the first runs (or, if it started after the end, finds all done)."""
    import re
    (tmp_path / "exp.toml").write_text(EXP.replace("epsilon = 0.1", "epsilon = 0.02"))
    env = dict(os.environ, PYTHONPATH=str(REPO))
    cmd = [sys.executable, "-m", "simgap", "collect", "exp.toml", "--profile", "base", "--out", "s", "--no-progress"]
    procs = [subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    computed = 0
    for p, (out, err) in zip(procs, outs):
        assert "Traceback" not in err, err
        if p.returncode == 2:
            assert "being collected by another process" in err, err
        else:
            assert p.returncode == 0, err
            computed += int(re.search(r"collected (\d+) chunks", out).group(1))
    from simgap.collect import store_status
    st = store_status(tmp_path / "s")
    assert st["complete"] and computed == st["n_chunks"], outs


# ----- the experiment file: schema, typos, paths ------------------------------------------------

def _exp(tmp_path, text, name="exp.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("edit,profile,words", [
    (lambda t: t + "\n[colect]\nepsilon = 0.1\n", "small", ["unknown section [colect]", "did you mean [collect]"]),
    (lambda t: t + "\n[profiles.small.colect]\nn_runs = 3\n", "small",
     ["unknown section [profiles.small.colect]", "did you mean [profiles.small.collect]"]),
    (lambda t: t + "\n[profiles.paper.colect]\nn_runs = 3\n", "small",  # a profile not in use
     ["[profiles.paper.colect]", "[profiles.paper.collect]"]),
    (lambda t: t.replace("seed = 5", "seed = 5\nepsilom = 3"), "base",
     ["unknown key 'epsilom' in [collect]", "did you mean 'epsilon'"]),
    (lambda t: t.replace("[profiles.small.collect]\nn_runs = 4", "[profiles.small.collect]\nn_run = 4"), "small",
     ["unknown key 'n_run' in [profiles.small.collect]", "did you mean 'n_runs'"]),
    (lambda t: t.replace("[rollout]", "[rollout]\nhorizn = 3"), "small", ["'horizn'", "'horizon'"]),
    (lambda t: "descripton = 'x'\n" + t, "small", ["[descripton]", "[description]"]),
    (lambda t: t.replace("epsilon = 0.1", "epsilon = -0.1"), "base", ["[collect] epsilon", "greater than 0"]),
    (lambda t: t.replace("epsilon = 0.1", "epsilon = inf"), "base", ["[collect] epsilon", "finite"]),
    (lambda t: t.replace("epsilon = 0.1", "epsilon = '0.1'"), "base", ["[collect] epsilon", "valid number"]),
    (lambda t: t.replace("[profiles.small.collect]\nn_runs = 4", "[profiles.small.collect]\nn_runs = 1"), "small",
     ["[profiles.small.collect] n_runs (N1hat)", "greater than or equal to 2"]),
    (lambda t: t.replace("beta1 = 0.01", "beta1 = 2.0"), "small", ["[certify] beta1", "less than 1"]),
    (lambda t: t.replace("beta1 = 0.01", "beta1 = [0.01, 5]"), "small", ["[certify] beta1[1]", "less than 1"]),
    (lambda t: t.replace("beta1 = 0.01", "beta1 = 0.01\nconcentration = 'hoeffding'"), "small",
     ["[certify] concentration", "'chebyshev'"]),
    (lambda t: t.replace("beta1 = 0.01", "beta1 = 0.01\nterms = { x = ['sin(x1)'] }"), "small", ["terms", "'x'"]),
    (lambda t: t.replace("eta = [0.004, 0.01]", "eta = [0.004, -0.01]"), "small", ["[synthesis] eta[1]"]),
    (lambda t: t.replace("eta = [0.004, 0.01]", "eta = [0.004, 0.01]\nspec = 'reach'"), "small",
     ["[synthesis] spec", "'reach_avoid'"]),
    (lambda t: t.replace("n = 10", "n = -3"), "small", ["[rollout] n", "greater than or equal to 1"]),
    (lambda t: t.replace("points = 5", "points = 5.5"), "small", ["[audit] points", "valid integer"]),
    (lambda t: t.replace("executor = \"serial\"", "executor = \"dask\""), "small", ["[collect] executor", "'ray'"]),
    (lambda t: t + "\n[profiles.x]\ncollect = 3\n", "small", ["[profiles.x.collect] must be a table"]),
    (lambda t: t, "smal", ["no profile 'smal'", "small"]),
    # paths written in the file stay in the experiment's folder; URDFs are files under assets/urdf
    (lambda t: t.replace("seed = 5", "seed = 5\nout = '../../..'"), "small", ["[collect] out", "'../../..'"]),
    (lambda t: t.replace("seed = 5", "seed = 5\nout = '/tmp/x'"), "small", ["[collect] out", "relative path"]),
    (lambda t: t.replace("eta = [0.004, 0.01]", "eta = [0.004, 0.01]\nmap = '../arena.toml'"), "small",
     ["synthesis.map", "outside the experiment's folder"]),
    (lambda t: t.replace('kind = "numpy"', 'kind = "numpy"\noptions = { urdf = "/etc/passwd" }'), "small",
     ["[simulator] options.urdf", "assets/urdf"]),
    (lambda t: t.replace('kind = "numpy"', 'kind = "numpy"\noptions = { urdf = "../../x.urdf" }'), "small",
     ["[simulator] options.urdf"]),
])
def test_experiment_file_errors_name_the_place(tmp_path, edit, profile, words):
    from simgap.config import load_experiment
    p = _exp(tmp_path, edit(EXP))
    with pytest.raises(SimgapError) as e:
        load_experiment(p, profile)
    for w in words:
        assert w in str(e.value), (w, str(e.value))


def test_profile_typo_never_falls_back_to_the_base_scale(tmp_path):
    """The issue's case: a misspelled section in the small profile ran the paper-scale base."""
    text = EXP.replace("[profiles.small.collect]", "[profiles.small.colect]")
    p = _exp(tmp_path, text)
    r = simgap("collect", p, "--dry-run", cwd=tmp_path)
    refused(r, "[profiles.small.colect]", "did you mean [profiles.small.collect]")
    assert "cover:" not in r.stdout  # nothing was planned, let alone collected
    assert files(tmp_path) == {"exp.toml"}


def test_paths_in_the_file_resolve_against_it(tmp_path):
    from simgap.config import load_experiment
    sub = tmp_path / "cases"
    sub.mkdir()
    p = _exp(sub, EXP.replace("seed = 5", "seed = 5\nout = 'results/data'"))
    assert load_experiment(p, None).store_dir() == sub.resolve() / "results" / "data"
    # the command line's --out is the user's own choice, taken as given
    e = load_experiment(p, None, overrides={"collect": {"out": str(tmp_path / "elsewhere")}})
    assert e.store_dir() == tmp_path / "elsewhere"
    (sub / "link").symlink_to(tmp_path)  # a symlink out of the folder is caught after resolving
    with pytest.raises(SimgapError, match="outside the experiment's folder"):
        load_experiment(_exp(sub, EXP.replace("seed = 5", "seed = 5\nout = 'link/data'"), "link.toml"), None)
    r = simgap("collect", p, "--profile", "base", "--no-progress", cwd=tmp_path)  # cwd is not the file's folder
    assert r.returncode == 0, r.stderr
    assert f"data: {sub.resolve() / 'results' / 'data'}" in r.stdout  # says where the data went
    assert (sub / "results" / "data" / "manifest.json").is_file()


def test_simulator_refuses_urdf_outside_assets():
    pytest.importorskip("pybullet")
    from simgap.simulators.base import make_simulator
    for bad in ("/etc/passwd", "../../pyproject.toml"):
        with pytest.raises(SimgapError, match="under"):
            make_simulator({"kind": "pybullet_pendulum", "system": "pendulum", "options": {"urdf": bad}})


# ----- simgap run validates the whole experiment before any stage -------------------------------

@pytest.mark.parametrize("edit,args,words", [
    (lambda t: t, ["--rollouts", "-3"], ["--rollouts", ">= 1"]),
    (lambda t: t.replace("beta1 = 0.01", "beta1 = 2.0"), [], ["[certify] beta1"]),
    (lambda t: t.replace("beta1 = 0.01", "beta1 = [0.01, 0.01, 0.01]"), [], ["[certify] beta1", "one value or 2"]),
    (lambda t: t.replace("beta1 = 0.01", "beta1 = 0.01\ndegree = 40"), [], ["[certify] degree", "12,341"]),
    (lambda t: t.replace("beta1 = 0.01", "beta1 = 0.01\nterms = { \"0\" = [\"__import__('os')\"] }"), [],
     ["__import__", "not allowed"]),
    (lambda t: t.replace("beta1 = 0.01", "beta1 = 0.01\nterms = { \"5\" = [\"x1\"] }"), [], ["terms key '5'", "not 0..1 or -1"]),
    (lambda t: t.replace("eta = [0.004, 0.01]", "eta = [0.004, 0.01, 0.1]"), [], ["[synthesis] eta"]),
    (lambda t: t.replace("eta = [0.004, 0.01]", "hold = 1"), [], ["[synthesis] eta", "required"]),
    (lambda t: t.replace("x0 = [0.05, 0.1]", "x0 = [5.0, 0.1]"), [], ["[rollout] x0", "outside X"]),
    (lambda t: t.replace("x0 = [0.05, 0.1]", "x0 = [0.05]"), [], ["[rollout] x0", "need 2"]),
    (lambda t: t.replace("horizon = 20", "horizon = 0"), [], ["[rollout] horizon"]),
    (lambda t: t.replace("eta = [0.004, 0.01]", "eta = [0.004, 0.01]\nsafe_lo = [0.1]"), [], ["safe_lo"]),
    (lambda t: t.replace("eta = [0.004, 0.01]", "eta = [0.004, 0.01]\nspec = 'reach_avoid'\nmap = 'nomap'"), [],
     ["nomap"]),
    (lambda t: t.replace("actuation_std = 0.05", "actuation_std = -0.05"), [], ["actuation_std"]),
    (lambda t: t.replace("n_runs = 8", "n_runs = 100000000000"), [], ["N1hat=100,000,000,000", "memory"]),
])
def test_run_validates_before_any_stage(tmp_path, capsys, edit, args, words):
    """In this process (one import of the engine for all cases): an exception other than the
    CLI's own error exit would fail the test, so no traceback reaches the user either."""
    from simgap.cli import main
    p = _exp(tmp_path, edit(EXP))
    try:
        rc = main(["run", str(p), "--profile", "base", "--out", str(tmp_path / "res"), "--no-record", *args])
    except SystemExit as e:  # argparse's own refusal
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2, err
    for w in words:
        assert w in err, (w, err)
    assert "[collect/" not in err  # no stage started
    assert files(tmp_path) == {"exp.toml"}  # no partial results


# ----- messages that named the wrong problem -----------------------------------------------------

def test_negative_numbers_are_values():
    from simgap.cli import build_parser
    p = build_parser()
    a = p.parse_args(["synthesize", "--no-gap", "--system", "pendulum", "--safe", "-0.2,0.2,-0.5,0.5",
                      "--eta", "0.004,0.01", "--x0", "-0.05,0.1", "--out", "c.npz"])
    assert a.x0 == "-0.05,0.1" and a.safe == "-0.2,0.2,-0.5,0.5"
    a = p.parse_args(["rollout", "--controller", "c.npz", "--simulator", "s.json", "--x0", "-0.05", "-1e-3",
                      "--out", "r.json"])
    assert a.x0 == ["-0.05", "-1e-3"]
    with pytest.raises(SystemExit):  # an option that does not exist is still an error
        p.parse_args(["rollout", "--controller", "c.npz", "--simulator", "s.json", "--out", "r.json", "-x"])


def test_unknown_spec_is_named(tmp_path):
    r = simgap("synthesize", "--no-gap", "--spec", "nosuchspec", "--eta", "0.1", "--out", "c.npz", cwd=tmp_path)
    refused(r, "unknown map 'nosuchspec'")
    assert list(tmp_path.iterdir()) == []


# ----- a wider probe, in process (main() is what the console script calls) -------------------

def _cert_edit(fn):
    def make(d: Path) -> str:
        import json
        c = json.loads((d / "cert.json").read_text())
        fn(c)
        (d / "edited.json").write_text(json.dumps(c))
        return "edited.json"
    return make


def _set(path, value):
    def edit(c):
        obj = c
        for k in path[:-1]:
            obj = obj[k]
        obj[path[-1]] = value
    return edit


CERT_EDITS = [  # (edit, words): every reader must refuse, naming the problem
    (_set(["system"], "pendulum"), ["'system' must be an object", "string"]),
    (_set(["system"], None), ["'system' must be an object", "null"]),
    (_set(["dims"], 5), ["'dims' must be a list", "number"]),
    (_set(["dims"], {}), ["'dims' must be a list", "object"]),
    (lambda c: c["dims"].__setitem__(0, "x"), ["dims[0] must be an object"]),
    (lambda c: c["dims"][0].pop("terms"), ["dims[0]", "'terms'"]),
    (lambda c: c["system"].pop("state_names"), ["'state_names'"]),
    (_set(["system", "x_lo"], "0"), ["'x_lo' must be a list"]),
    (lambda c: c["dims"].pop(), ["dimension entries"]),
    (_set(["dims", 0, "q"], [1.0]), ["q does not match"]),
    (_set(["dims", 0, "terms"], ["__import__('os')"]), ["not allowed"]),
    (_set(["dims", 0, "delta1"], "big"), ["malformed"]),
    (_set(["format"], "other"), ["not a simgap certificate"]),
    (_set(["version"], 1), ["version 1"]),
    (_set(["joint_confidence"], 0.999999), ["joint_confidence"]),
    (lambda c: c["dims"][0].__setitem__("q", [0.0] * len(c["dims"][0]["q"])), ["digest"]),
    (_set(["digest"], "0" * 64), ["digest"]),
    (_set(["epsilon"], 1e-9), ["digest"]),
]


@pytest.mark.parametrize("edit,words", CERT_EDITS, ids=[f"cert{i}" for i in range(len(CERT_EDITS))])
@pytest.mark.parametrize("command", ["synthesize", "audit"])
def test_edited_certificates_are_refused_by_every_reader(work, capsys, edit, words, command):
    from simgap.cli import main

    name = _cert_edit(edit)(work)
    args = {"synthesize": ["synthesize", "--cert", name, "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5",
                           "--eta", "0.004,0.01", "--out", str(work / "never.npz")],
            "audit": ["audit", name, "--data", str(work / "data"), "--points", "5", "--runs", "20",
                      "--out", str(work / "never.json")]}[command]
    cwd = os.getcwd()
    os.chdir(work)
    try:
        rc = main(args)
    finally:
        os.chdir(cwd)
    err = capsys.readouterr().err
    assert rc != 0 and err.startswith("error:"), err
    for w in words:
        assert w in err, (w, err)
    assert not (work / "never.npz").exists() and not (work / "never.json").exists()


CLI_CASES = [  # (args, words); "{w}" is the work folder
    (["certify", "{w}/data", "--delta", "1e300"], ["delta1", "1e6 times the size"]),
    (["certify", "{w}/data", "--delta", "-0.1"], ["delta must be > 0"]),
    (["certify", "{w}/data", "--delta", "0.1,0.1,0.1"], ["delta1", "one value or 2 values"]),
    (["certify", "{w}/data", "--delta", "nan"], ["delta1", "NaN"]),
    (["certify", "{w}/data", "--delta", "abc"], ["delta"]),
    (["certify", "{w}/data", "--beta", "1.5"], ["beta"]),
    (["certify", "{w}/data", "--beta", "0"], ["beta"]),
    (["certify", "{w}/data", "--degree", "-5"], ["degree"]),
    (["certify", "{w}/data", "--term", "1:lambda: 0"], ["not allowed"]),
    (["certify", "{w}/data", "--term", "9:theta"], ["9"]),
    (["certify", "{w}/data", "--term", "1:os.system"], ["not allowed"]),
    (["certify", "{w}/data", "--safety", "-1"], ["safety"]),
    (["certify", "{w}/data", "--level", "run", "--alpha", "1.5"], ["alpha"]),
    (["certify", "{w}/data", "--level", "run", "--alpha", "0"], ["alpha"]),
    (["certify", "{w}/nowhere"], ["nowhere"]),
    (["certify", "{w}/exp.toml"], ["exp.toml"]),
    (["synthesize", "--no-gap", "--system", "nosuch", "--safe=-0.2,0.2,-0.5,0.5", "--eta", "0.004,0.01",
      "--out", "{w}/never.npz"], ["nosuch"]),
    (["synthesize", "--no-gap", "--system", "pendulum", "--safe=-0.2,0.2", "--eta", "0.004,0.01",
      "--out", "{w}/never.npz"], ["safe"]),
    (["synthesize", "--no-gap", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5", "--eta", "0,0.01",
      "--out", "{w}/never.npz"], ["eta"]),
    (["synthesize", "--no-gap", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5", "--eta", "0.004,0.01,1",
      "--out", "{w}/never.npz"], ["eta"]),
    (["synthesize", "--no-gap", "--system", "pendulum", "--safe=0.2,-0.2,-0.5,0.5", "--eta", "0.004,0.01",
      "--out", "{w}/never.npz"], ["lo <= hi"]),
    (["synthesize", "--no-gap", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5", "--eta", "0.004,0.01",
      "--x0", "9,9", "--out", "{w}/never.npz"], ["x0"]),
    (["rollout", "--controller", "{w}/ctrl.npz", "--simulator", "{w}/exp.toml", "--profile", "base",
      "--x0", "0.05", "--out", "{w}/never.json"], ["x0"]),
    (["rollout", "--controller", "{w}/ctrl.npz", "--simulator", "{w}/exp.toml", "--profile", "base",
      "--x0", "0.05,0.1", "--n", "0", "--out", "{w}/never.json"], ["--n"]),
    (["rollout", "--controller", "{w}/ctrl.npz", "--simulator", "{w}/exp.toml", "--profile", "base",
      "--x0", "0.05,0.1", "--horizon", "0", "--out", "{w}/never.json"], ["horizon"]),
    (["rollout", "--controller", "{w}/exp.toml", "--simulator", "{w}/exp.toml", "--profile", "base",
      "--out", "{w}/never.json"], ["exp.toml"]),
    (["rollout", "--controller", "{w}/ctrl.npz", "--simulator", "nosuchsim", "--out", "{w}/never.json"],
     ["nosuchsim"]),
    (["rollout", "--controller", "{w}/ctrl.npz", "--simulator", "{w}/exp.toml", "--profile", "nosuch",
      "--out", "{w}/never.json"], ["nosuch"]),
    (["collect", "{w}/exp.toml", "--profile", "nosuch", "--out", "{w}/never"], ["nosuch"]),
    (["collect", "{w}/exp.toml", "--epsilon", "-1", "--out", "{w}/never"], ["epsilon"]),
    (["collect", "{w}/exp.toml", "--n-runs", "0", "--out", "{w}/never"], ["n-runs"]),
    (["collect", "{w}/exp.toml", "--workers", "0", "--out", "{w}/never"], ["workers"]),
    (["collect", "{w}/nosuch.toml", "--out", "{w}/never"], ["nosuch"]),
    (["refine", "--system", "nosuch", "--data", "{w}/data"], ["nosuch"]),
    (["refine", "--system", "pendulum", "--data", "{w}/nowhere.npz"], ["nowhere"]),
    (["refine", "--system", "pendulum", "--data", "{w}/data", "--term", "t:omega:__import__('os')"], ["not allowed"]),
    (["refine", "--system", "pendulum", "--data", "{w}/data", "--term", "t:omega:[x for x in u]"], ["not allowed"]),
    (["refine", "--system", "pendulum", "--data", "{w}/data", "--term", "1:theta"], ["NAME:STATE:EXPR"]),
    (["refine", "--system", "pendulum", "--data", "{w}/data", "--effects", "nosuch_effect"], ["nosuch_effect"]),
    (["data", "from-trajectory", "{w}/exp.toml", "--preset", "emps", "--out", "{w}/never.npz"], ["exp.toml"]),
    (["data", "from-trajectory", "{w}/data.npz", "--preset", "nosuch", "--out", "{w}/never.npz"], ["nosuch"]),
    (["data", "from-trajectory", "{w}/data.npz", "--preset", "emps", "--out", "{w}/never.txt"], [".npz"]),
]


@pytest.mark.parametrize("args,words", CLI_CASES, ids=[f"cli{i}" for i in range(len(CLI_CASES))])
def test_more_bad_values_are_named(work, capsys, args, words):
    from simgap.cli import main

    before = files(work)
    try:
        rc = main([a.replace("{w}", str(work)) for a in args])
    except SystemExit as e:  # argparse's own refusal (exit 2 with usage on stderr)
        rc = e.code
    err = capsys.readouterr().err
    assert rc not in (0, None), err
    assert "Traceback" not in err
    for w in words:
        assert w in err, (w, err)
    assert files(work) == before


# ----- outputs over inputs (one shared check, simgap.file_guard.not_over_inputs) ----------------------

def _digests(folder: Path) -> dict:
    import hashlib
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


OVER_INPUTS = {
    "certify-store-manifest": ["certify", "data", "--out", "data/manifest.json"],
    "certify-run-store": ["certify", "data", "--level", "run", "--alpha", "0.1", "--out", "data/manifest.json"],
    "refine-data": ["refine", "--system", "pendulum", "--data", "data.npz", "--bootstrap", "2", "--out", "data.npz"],
    "refine-record": ["refine", "--system", "pendulum", "--data", "data", "--bootstrap", "2",
                      "--record", "data/x.rrd"],
    "synthesize-cert": ["synthesize", "--cert", "cert.json", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5",
                        "--eta", "0.004,0.01", "--out", "cert.json"],
    "synthesize-json": ["synthesize", "--cert", "cert.json", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5",
                        "--eta", "0.004,0.01", "--out", "c.npz", "--json", "cert.json"],
    "audit-cert": ["audit", "cert.json", "--data", "data", "--points", "5", "--runs", "20", "--out", "cert.json"],
    "rollout-controller": ["rollout", "--controller", "ctrl.npz", "--simulator", "exp.toml", "--profile", "base",
                           "--x0", "0.05,0.1", "--n", "5", "--out", "ctrl.npz"],
    "rollout-simulator": ["rollout", "--controller", "ctrl.npz", "--simulator", "exp.toml", "--profile", "base",
                          "--x0", "0.05,0.1", "--n", "5", "--out", "r.json", "--trajectories", "exp.toml"],
    "record-dataset": ["record", "--experiment", "exp.toml", "--dataset", "data", "--upto", "collect",
                       "--out", "data/chunks/x.rrd"],
    "collect-into-toml-folder": ["collect", "exp.toml", "--out", "exp.toml"],
}


@pytest.mark.parametrize("case", sorted(OVER_INPUTS))
def test_output_over_an_input_is_refused(work, case):
    before = _digests(work)
    r = simgap(*OVER_INPUTS[case], cwd=work)
    refused(r)
    assert "destroy the input" in r.stderr or "not a folder" in r.stderr, r.stderr
    assert _digests(work) == before  # every input intact, nothing new


def test_output_over_an_input_through_a_link(work, tmp_path):
    (tmp_path / "link.json").symlink_to(work / "cert.json")
    os.link(work / "data.npz", tmp_path / "hard.npz")
    refused(simgap("audit", work / "cert.json", "--data", work / "data", "--points", "5", "--runs", "20",
                   "--out", tmp_path / "link.json", cwd=tmp_path), "destroy the input")
    refused(simgap("refine", "--system", "pendulum", "--data", work / "data.npz", "--out", tmp_path / "hard.npz",
                   cwd=tmp_path), "destroy the input", "hard.npz")
    # a sibling of an input is fine
    assert file_guard.not_over_inputs([("--out", work / "cert2.json")], [("--cert", work / "cert.json")]) is None


# ----- a full disk: a file-size limit stands in (RLIMIT_FSIZE; SIGXFSZ ignored so writes fail
# with EFBIG, the path a full disk's ENOSPC takes too) -----------------------------------------

def simgap_limited(*args, cwd, fsize: int, timeout=180):
    import resource
    import signal

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               PYTHONDONTWRITEBYTECODE="1")
    return subprocess.run([sys.executable, "-m", "simgap", *map(str, args)], cwd=cwd, env=env, preexec_fn=limit,
                          capture_output=True, text=True, timeout=timeout)


def no_temp_files(folder: Path) -> None:
    left = [str(p) for p in folder.rglob("*") if ".tmp" in p.name]
    assert not left, left


FULL_DISK = {  # case: (args with {w} = the work folder, size limit in bytes, the file named)
    "certify": (["certify", "{w}/data", "--out", "cert.json"], 2000, "cert.json"),
    "synthesize": (["synthesize", "--no-gap", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5", "--eta",
                    "0.004,0.01", "--out", "c.npz", "--json", "s.json"], 1000, "c.npz"),
    "refine": (["refine", "--system", "pendulum", "--data", "{w}/data.npz", "--bootstrap", "2", "--quiet",
                "--out", "rep.json"], 500, "rep.json"),
    "collect": (["collect", "{w}/exp.toml", "--profile", "base", "--out", "st", "--no-progress"], 5000,
                "c000000.npz"),
    "record": (["record", "--experiment", "{w}/exp.toml", "--profile", "base", "--dataset", "{w}/data",
                "--certificate", "{w}/cert.json", "--controller", "{w}/ctrl.npz", "--upto", "synthesize",
                "--out", "x.rrd"], 60000, "x.rrd"),
}


@pytest.mark.parametrize("case", sorted(FULL_DISK))
def test_full_disk_is_an_error_naming_the_path(work, tmp_path, case):
    args, fsize, name = FULL_DISK[case]
    r = simgap_limited(*[a.replace("{w}", str(work)) for a in args], cwd=tmp_path, fsize=fsize)
    refused(r, "cannot write", name, "needs about", "ulimit -f")
    no_temp_files(tmp_path)
    assert not list(tmp_path.rglob(name)), "a result announced or left under its final name"


def test_full_disk_run_never_announces_a_truncated_recording(work, tmp_path):
    """Every stage's files fit; the 157 KB recording does not: the run fails naming it (it used
    to exit 0 announcing a truncated run.rrd), leaving neither it nor a temporary file."""
    r = simgap_limited("run", work / "exp.toml", "--profile", "base", "--out", tmp_path / "res", cwd=tmp_path,
                       fsize=100_000)
    refused(r, "cannot write", "run.rrd", "needs about")
    assert "recording:" not in r.stdout
    assert not (tmp_path / "res" / "run.rrd").exists()
    no_temp_files(tmp_path)


# ----- results folders: their own list of files; self-contained -------------------------------

@pytest.fixture(scope="module")
def run_folder(work, tmp_path_factory):
    """A finished `simgap run` of the work experiment, made from a copy of its TOML, in a folder that
    already held two files of the user's whose names look like results."""
    d = tmp_path_factory.mktemp("runs")
    (d / "exp").mkdir()
    (d / "exp" / "exp.toml").write_text(EXP)
    (d / "res").mkdir()
    (d / "res" / "controller_good.npz").write_bytes((work / "ctrl.npz").read_bytes())  # the user's own
    (d / "res" / "audit_old.json").write_text("{}")
    r = simgap("run", "exp/exp.toml", "--profile", "base", "--out", "res", cwd=d, timeout=300)
    assert r.returncode == 0, r.stderr
    return d, r


def test_a_reused_results_folder_lists_only_what_the_run_wrote(run_folder, work):
    import json
    d, r = run_folder
    res = d / "res"
    assert "left 2 file(s) simgap did not write untouched" in r.stderr
    assert (res / "audit_old.json").read_text() == "{}"  # the user's files stay, byte for byte
    assert (res / "controller_good.npz").read_bytes() == (work / "ctrl.npz").read_bytes()
    s = json.loads((res / "summary.json").read_text())
    assert len(s["run_id"]) == 32
    on_disk = {p.name for p in res.iterdir() if p.is_file() and not p.name.startswith(".")} - {"summary.json"}
    assert set(s["files"]) == on_disk - {"audit_old.json", "controller_good.npz"} and "run.rrd" in on_disk
    from simgap.results_folder import file_digest
    for name, e in s["files"].items():
        assert e["sha256"] == file_digest(res / name) and e["run_id"] == s["run_id"]


def test_results_readers_refuse_files_of_another_run(run_folder, tmp_path, work):
    import shutil

    from simgap_viz.results import load_run
    d, _ = run_folder
    res = tmp_path / "res"
    shutil.copytree(d / "res", res)
    load_run(res)  # as written: loads
    (res / "rollouts_stochastic.npz").write_bytes((work / "ctrl.npz").read_bytes())  # copied in
    with pytest.raises(SimgapError, match="rollouts_stochastic.npz is not part of this run"):
        load_run(res)
    refused(simgap("gui", res, "--port", "0", "--exit-after", "0", cwd=tmp_path), "not part of this run")
    (res / "rollouts_stochastic.npz").unlink()
    shutil.copy(work / "cert.json", res / "cert_stochastic.json")  # a valid certificate, another run's
    with pytest.raises(SimgapError, match="cert_stochastic.json differs from the file this run wrote"):
        load_run(res)


def test_results_folder_opens_anywhere_without_its_toml(run_folder, tmp_path):
    """Moved, its TOML deleted, opened from another folder: the summary's embedded configuration."""
    import shutil
    d, _ = run_folder
    moved = tmp_path / "moved" / "res"
    shutil.copytree(d / "res", moved)
    shutil.copytree(d / "exp", tmp_path / "exp_copy")
    toml = d / "exp" / "exp.toml"
    saved = toml.read_text()
    toml.unlink()
    try:
        elsewhere = tmp_path / "elsewhere"
        elsewhere.mkdir()
        r = simgap("gui", moved, "--port", "0", "--exit-after", "0", cwd=elsewhere, timeout=120)
        assert r.returncode == 0, r.stderr
        assert "open http" in r.stdout
    finally:
        toml.write_text(saved)


def test_a_second_run_into_one_folder_is_refused(run_folder, tmp_path):
    d, _ = run_folder
    res = tmp_path / "res"
    res.mkdir()
    with open(res / ".run.lock", "a") as fh:  # a run writing into the folder holds this lock
        fcntl.lockf(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        r = simgap("run", d / "exp" / "exp.toml", "--profile", "base", "--out", res, cwd=tmp_path, timeout=300)
    refused(r, "another simgap run is writing into")
    assert not (res / "summary.json").exists()


# ----- run-level certificates and options -------------------------------------------------------

@pytest.fixture(scope="module")
def run_cert(work):
    r = simgap("certify", "data", "--level", "run", "--alpha", "0.8", "--out", "cert_run.json", cwd=work)
    assert r.returncode == 0, r.stderr
    return work / "cert_run.json"


def test_run_level_certificate_is_not_a_mean_gap(work, run_cert, tmp_path):
    r = simgap("synthesize", "--cert", run_cert, "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5",
               "--eta", "0.004,0.01", "--out", tmp_path / "c.npz", cwd=tmp_path)
    refused(r, "run-level certificate", "gamma^alpha", "mean-map guarantee")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("extra,words", [
    (["--degree", "1.7"], ["--degree '1.7'", "one integer"]),
    (["--degree", "1,2"], ["--degree '1,2'", "one integer"]),
    (["--method", "deterministic"], ["--method", "not used at --level run"]),
    (["--delta", "0.1"], ["--delta", "not used at --level run"]),
    (["--uniform"], ["--uniform", "not used at --level run"]),
    (["--compare"], ["--compare", "not used at --level run"]),
])
def test_run_level_refuses_options_it_would_ignore(work, extra, words):
    before = files(work)
    refused(simgap("certify", "data", "--level", "run", "--alpha", "0.8", *extra, "--out", "never.json", cwd=work),
            *words)
    assert files(work) == before


def _forge(top):
    t = top.copy()
    return {"negative": lambda: t.__setitem__((0, 0, 0), -t[0, 0, 0] - 1.0) or t,
            "unsorted": lambda: t[:, ::-1, :].copy(),
            "nan": lambda: t.__setitem__((3, 1, 1), np.nan) or t,
            "zero": lambda: np.zeros_like(t),
            "inflated": lambda: t * 3.0}


@pytest.mark.parametrize("how,words", [("negative", "negative"), ("unsorted", "not sorted"), ("nan", "NaN"),
                                       ("zero", "own extreme"), ("inflated", "own extreme")])
def test_forged_per_run_deviations_are_refused(work, tmp_path, how, words):
    """A data set whose deviations were forged and its digest recomputed (save_npz does that)."""
    import dataclasses

    from simgap.dataset import load_dataset
    ds = load_dataset(work / "data")
    forged = dataclasses.replace(ds, absdev_top=_forge(ds.absdev_top)[how]())
    forged.save_npz(tmp_path / "forged.npz")
    refused(simgap("certify", tmp_path / "forged.npz", "--level", "run", "--alpha", "0.8", cwd=tmp_path),
            "per-run deviations", words, "refused")


def test_genuine_per_run_deviations_pass_the_plausibility_check(work):
    from simgap.dataset import load_dataset
    from simgap.perrun.realization import check_deviations
    check_deviations(load_dataset(work / "data"))


# ----- signatures: forgery, not only accidents (simgap[sign]) ---------------------------------------

def _forge_zero_gap(src: Path, dst: Path) -> None:
    """The forgery a digest cannot stop: gamma's coefficients set to 0, derived fields and the
    digest recomputed exactly as simgap does (whoever has the code can do it)."""
    import json

    from simgap import fileio
    from simgap.certify.certificate import Certificate
    d = json.loads(src.read_text())
    for e in d["dims"]:
        e["q"] = [0.0] * len(e["q"])
    d.pop("signature", None)
    body = Certificate._from_dict(d).to_dict()  # derived fields and digest from the forged parts
    body["signature"] = json.loads(src.read_text()).get("signature")  # the genuine signature, reused
    dst.write_text(json.dumps(body))


def test_signed_certificates_refuse_forgery(work, tmp_path):
    pytest.importorskip("cryptography")
    r = simgap("key", "new", "--out", tmp_path / "me", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "me").stat().st_mode & 0o077 == 0 and (tmp_path / "me.pub").is_file()
    refused(simgap("key", "new", "--out", tmp_path / "me", cwd=tmp_path), "never overwritten")
    simgap("key", "new", "--out", tmp_path / "other", cwd=tmp_path)
    r = simgap("certify", work / "data", "--sign-key", tmp_path / "me", "--out", tmp_path / "signed.json", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _forge_zero_gap(tmp_path / "signed.json", tmp_path / "forged.json")
    synth = ["synthesize", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5", "--eta", "0.004,0.01",
             "--out", tmp_path / "c.npz", "--cert"]

    def run(cert, trusted):
        env = dict(os.environ, PYTHONPATH=str(REPO))
        if trusted:
            env["SIMGAP_TRUSTED_KEYS"] = os.pathsep.join(str(tmp_path / k) for k in trusted)
        return subprocess.run([sys.executable, "-m", "simgap", *map(str, synth), cert], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=120)

    r = run(tmp_path / "forged.json", None)  # without a trusted key the forgery passes its digest check
    assert "modified" not in r.stderr and "digest" not in r.stderr, r.stderr
    refused(run(tmp_path / "forged.json", ["me.pub"]), "signature does not match its content", "forged")
    refused(run(work / "cert.json", ["me.pub"]), "is not signed")
    refused(run(tmp_path / "signed.json", ["other.pub"]), "not among SIMGAP_TRUSTED_KEYS")
    r = run(tmp_path / "signed.json", ["other.pub", "me.pub"])
    assert r.returncode in (0, 1) and "error" not in r.stderr, r.stderr  # genuine: accepted (1 = empty domain)


# ----- sizes and times checked before work: per-run stage, audit, mean map, fine grids ------------

PERRUN_HUGE = EXP + """
[perrun]
alpha = 0.9
eta = [0.0004, 0.001]
hold = 20
horizon = 2000
n_runs = 4000
pilot_runs = 400
n_rollouts = 10000
n_states = 20
"""


def test_run_with_a_huge_perrun_section_is_refused_before_any_work(tmp_path):
    (tmp_path / "exp.toml").write_text(PERRUN_HUGE)
    r = simgap("run", "exp.toml", "--profile", "base", "--out", tmp_path / "res", cwd=tmp_path)
    refused(r, "the per-run stage", "1,000,000 cells", "[perrun] eta")
    assert "of memory" in r.stderr or "would take about" in r.stderr
    assert not (tmp_path / "res").exists()


@pytest.mark.parametrize("args,words", [
    (["synthesize", "--level", "run", "--spec", "pendulum", "--profile", "perrun", "--eta", "2e-3,5e-3",
      "--out", "never.npz"], ["the per-run stage", "40,000 cells", "would take about", "SIMGAP_NO_SIZE_CHECK"]),
    (["synthesize", "--no-gap", "--system", "pendulum", "--safe=-0.2,0.2,-0.5,0.5", "--eta", "1e-5,1e-5",
      "--out", "never.npz"], ["4,000,140,001 cells", "of memory", "--eta"]),
    (["audit", "cert.json", "--data", "data", "--points", "1e6", "--runs", "1e6"],
     ["auditing 1,000,000 points x 1,000,000 runs", "would take about"]),
    (["rollout", "--controller", "ctrl.npz", "--simulator", "exp.toml", "--profile", "base", "--x0", "0.05,0.1",
      "--n", "5", "--horizon", "100", "--mean-map-runs", "1e9", "--out", "never.json"],
     ["mean map with 1,000,000,000 runs per step", "of memory"]),
])
def test_long_or_large_work_is_refused_with_numbers(work, args, words):
    import time
    before = files(work)
    t0 = time.monotonic()
    refused(simgap(*args, cwd=work), *words)
    assert time.monotonic() - t0 < 60  # refused up front, not after the work
    assert files(work) == before


def test_perrun_estimate_counts_the_work():
    from simgap.systems import get_system
    s = get_system("pendulum")
    o = {"eta": [0.04, 0.1], "hold": 20, "horizon": 400, "n_runs": 4000, "pilot_runs": 400, "n_rollouts": 10000,
         "n_states": 20}
    e = cost.perrun_size(o, s, rate_per_worker=1e5, workers=2)
    C = np.prod(np.ceil((s.x_hi - s.x_lo) / np.array([0.04, 0.1])))
    assert e["cells"] == C
    assert e["runs"] == C * len(s.inputs) * 4400 * 20 + s.n * 12000 * 20 + 3 * 20 * 10000 * 400   # + the secants
    assert e["seconds"] == pytest.approx(e["runs"] / 2e5)


def _terminal_sigint():
    """In the child before exec: SIGINT handled and unblocked, as in a terminal, whatever this test
    process inherited or was left with by an earlier test (SIG_IGN survives exec)."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def test_ctrl_c_during_collection_prints_no_worker_traceback(work, tmp_path):
    """SIGINT to the whole process group, as a terminal's Ctrl-C sends it: the parent says
    "interrupted"; the pool's workers print nothing (they printed KeyboardInterrupt tracebacks)."""
    import signal
    import time
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.Popen([sys.executable, "-m", "simgap", "collect", str(work / "exp.toml"), "--profile", "base",
                          "--epsilon", "0.002", "--n-runs", "2", "--chunk-size", "64", "--executor", "local",
                          "--workers", "2",
                          "--out", str(tmp_path / "st"), "--no-progress"], cwd=tmp_path, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=_terminal_sigint)
    try:
        deadline = time.monotonic() + 60
        while not list((tmp_path / "st" / "chunks").glob("c*.npz")) and time.monotonic() < deadline:
            time.sleep(0.2)  # the workers are running once the first chunk is written; small
        time.sleep(1.0)     # chunks: they often wait for the next one, where SIGINT used to hit them
        os.killpg(p.pid, signal.SIGINT)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, err
    assert "interrupted" in err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err


def test_sigterm_during_collection_exits_cleanly_and_says_how_to_resume(work, tmp_path):
    """SIGTERM to simgap alone (as `kill PID` sends it) while its worker pool runs: exit status 143,
    a message that the same command resumes, and no "leaked semaphore objects" warning from the
    resource tracker (the default SIGTERM killed the parent before the pool was shut down)."""
    import signal
    import time
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.Popen([sys.executable, "-m", "simgap", "collect", str(work / "exp.toml"), "--profile", "base",
                          "--epsilon", "0.002", "--n-runs", "2", "--chunk-size", "64", "--executor", "local",
                          "--workers", "2", "--out", str(tmp_path / "st"), "--no-progress"], cwd=tmp_path, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=_terminal_sigint)
    try:
        deadline = time.monotonic() + 60
        while not list((tmp_path / "st" / "chunks").glob("c*.npz")) and time.monotonic() < deadline:
            time.sleep(0.2)
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 143, err
    assert "run the same command again to resume" in err
    assert "leaked semaphore" not in err and "Traceback" not in err, err


def test_gui_malformed_websocket_messages_print_one_line_each(tmp_path):
    import asyncio
    import re

    import viser
    import websockets
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.Popen([sys.executable, "-m", "simgap", "gui", "--port", "0", "--exit-after", "60", "--system",
                          "pendulum"], cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = None
        for line in p.stdout:
            m = re.search(r"open (http://\S+)", line)
            if m:
                url = m.group(1).rstrip("/")
                break
        assert url, "the app did not start"

        async def send_all():
            for payload in (b"\x00\x01garbage", b"\xc1", "a text frame", b"\x81\xa4type\xa7Nothing"):
                async with websockets.connect(url.replace("http", "ws"), origin=url,
                                              subprotocols=[f"viser-v{viser.__version__}"]) as ws:
                    await ws.send(payload)
                    try:
                        await asyncio.wait_for(ws.recv(), 5)
                        while True:
                            await asyncio.wait_for(ws.recv(), 5)
                    except (websockets.exceptions.ConnectionClosed, asyncio.TimeoutError):
                        pass
        asyncio.run(send_all())
    finally:
        p.terminate()
        _, err = p.communicate(timeout=30)
    assert "Traceback" not in err, err
    assert err.count("dropped a client connection after a malformed message") == 4, err


def test_a_reader_that_goes_away_gets_no_traceback(tmp_path):
    """`simgap plugins | head`: the reader closes the pipe before the command writes; it stops
    without a traceback (exit 141, as a tool killed by SIGPIPE)."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.Popen([sys.executable, "-m", "simgap", "plugins"], cwd=tmp_path, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    p.stdout.close()       # before the interpreter has started: every write meets a closed pipe
    err = p.stderr.read()
    assert p.wait(timeout=120) == 141, err
    assert "Traceback" not in err, err

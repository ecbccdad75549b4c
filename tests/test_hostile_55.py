"""Hostile input, fourth pass (issue 55): the box-tube, local-certificate and fit surfaces.

By class: every count a command takes is priced before work and refused with the key, the need and
the limit (and a long rollout prints its estimate first); files carry what their proof assumed and
the commands that apply them check it (hold, the certificate's region against its data's); two
options that set the same thing are refused together by one function in `run` and in the stage
commands; output formats come from the extension and no output lands on another; messages name the
key and the method the user wrote; a read-only results folder and a folder holding another run's
results are said. Each case asserts the exit, the words, no traceback and, where files are at stake,
that nothing changed. Every case here failed before issue 55's fixes (a traceback, a hang without an
estimate, a forged file applied, a silently dropped option, a lost report, a message naming the
wrong thing)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import REPO, refused, simgap
from test_box_tube import EXPERIMENT
from test_fit import EXPERIMENT as FIT_EXPERIMENT, SYSTEM as LEAKY
from test_hostile_probe import digests
from test_invariant_set import CUBIC

from simgap.errors import SimgapError

#: the box-tube experiment of tests/test_box_tube.py over a [collect] region (a local certificate)
LOCAL = (EXPERIMENT.replace("epsilon = 0.2\n", "epsilon = 0.2\nregion = { th = [-0.5, 0.5], w = [-1.0, 1.0] }\n", 1)
         .replace('method = "box_tube"\n', 'method = "box_tube"\nsafe_lo = [-0.5, -1.0]\nsafe_hi = [0.5, 1.0]\n'))


def _edit(text: str, add: str, drop: str = "") -> str:
    """The [synthesis] section with ``add`` after its method line (and ``drop`` removed)."""
    return text.replace(drop, "").replace('method = "box_tube"\n', f'method = "box_tube"\n{add}\n', 1)


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A folder with the cubic pendulum's system file, its box-tube experiments, and one finished
    `simgap run` of the local one (a certificate with a region, its data, a box-tube controller)."""
    d = tmp_path_factory.mktemp("h55")
    (d / "cubic.toml").write_text(CUBIC)
    (d / "exp.toml").write_text(EXPERIMENT)
    (d / "local.toml").write_text(LOCAL)
    (d / "leaky.toml").write_text(LEAKY)
    (d / "fit.toml").write_text(FIT_EXPERIMENT)
    for argv in (["run", "local.toml", "--out", "run", "--no-record"],
                 ["synthesize", "--method", "box_tube", "--system", "cubic.toml", "--gamma", "0.002,0.02", "--safe",
                  "-1,1,-2,2", "--x0", "0.5,0", "--out", "tube.npz"],
                 ["synthesize", "--system", "cubic.toml", "--no-gap", "--safe", "-1,1,-2,2", "--eta", "0.05",
                  "--out", "grid.npz"]):
        rc, _, err = _quiet(argv, d)
        assert rc == 0, err
    return d


def _quiet(argv, cwd):
    """``simgap ARGV`` in this process with its output captured: (exit status, stdout, stderr)."""
    import contextlib
    import io
    from simgap.cli import main
    out, err, old = io.StringIO(), io.StringIO(), os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = main([str(a) for a in argv])
            except SystemExit as e:  # argparse's own refusal
                rc = e.code
    finally:
        os.chdir(old)
    return rc, out.getvalue(), err.getvalue()


def _cubic():
    import tomllib
    from simgap.system_file import system_from_spec
    return system_from_spec(tomllib.loads(CUBIC))


def cli(*args, cwd=None):
    """``simgap ARGS`` in this process (faster than a subprocess): (exit status, stdout, stderr), no traceback."""
    rc, out, err = _quiet(args, cwd or os.getcwd())
    assert "Traceback" not in err, err
    return rc, out, err


# ----- 1. sizes priced before work -------------------------------------------------------------------------

@pytest.mark.parametrize("horizon,words", [
    ("1000000000", ["--horizon = 1,000,000,000", "memory", "is available"]),
    ("5000000", ["--horizon = 5,000,000", "would take about", "more than the 6 h"]),
])
def test_box_tube_horizon_is_priced_before_any_work(work, horizon, words):
    """Used to die allocating 29.8 GiB (traceback), or run past 120 s without a word."""
    before = digests(work)
    t = time.perf_counter()
    rc, _, err = cli("synthesize", "--spec", "local.toml", "--cert", "run/cert_stochastic.json", "--horizon",
                     horizon, "--out", "never.npz", cwd=work)
    assert rc == 2 and all(w in err for w in words), err
    assert time.perf_counter() - t < 60 and digests(work) == before


@pytest.mark.parametrize("option", ["--horizon", "--steps", "--hold"])
@pytest.mark.parametrize("value", ["0", "-5"])
def test_non_positive_counts_are_refused_by_name(work, option, value):
    """--horizon 0 / -5 used to be replaced by the plan's length without a word."""
    rc, _, err = cli("synthesize", "--spec", "exp.toml", "--no-gap", option, value, "--out", "never.npz",
                     cwd=work)
    assert rc == 2 and f"argument {option}" in err and "integer >= 1" in err
    assert not (work / "never.npz").exists()


def test_run_prices_the_box_tubes_horizon_before_collecting(work, tmp_path):
    (tmp_path / "cubic.toml").write_text(CUBIC)
    (tmp_path / "exp.toml").write_text(EXPERIMENT.replace("[rollout]\n", "[rollout]\nhorizon = 5000000\n"))
    rc, _, err = cli("run", "exp.toml", "--out", "res", "--no-record", "--rollouts", "1", cwd=tmp_path)
    assert rc == 2 and all(w in err for w in ("[rollout] horizon = 5,000,000", "per-run statement", "would take")), err
    assert not (tmp_path / "res").exists()  # refused before the collection


def test_horizon_cost_model_refuses_what_cannot_fit():
    from simgap.synthesis.noise_tube import check_horizon, horizon_cost
    small, big = horizon_cost(1000, 2), horizon_cost(4000, 2)
    assert small["seconds"] == 0 and big["seconds"] > 0 and big["memory"] == 4 * small["memory"]
    assert horizon_cost(8000, 2)["seconds"] == pytest.approx(4 * big["seconds"])  # T^2
    for bad in (0, -5, 2.5, True, "7"):
        with pytest.raises(SimgapError, match="horizon must be an integer >= 1"):
            check_horizon(bad, 2)
    check_horizon(100, 2)


@pytest.mark.parametrize("argv,words", [
    (["--points", "1000000000"], ["--points 1000000000", "5,000,000,000 transitions", "of memory"]),
    (["--points", "30000000"], ["--points 30000000", "of memory"]),
    (["--grid", "1000000000"], ["--grid 1000000000", "of memory"]),
])
def test_fit_sizes_are_priced_before_any_state_is_drawn(work, argv, words, monkeypatch):
    """Used to die on memory. The available memory is pinned so the refusal does not depend on the
    machine (the leaky integrator: 1 state, 5 inputs)."""
    monkeypatch.setattr("simgap.memory.available_memory", lambda: 8e9)
    rc, _, err = cli("fit", "fit.toml", "--profile", "base", "--params", "a", "--out", "never.toml", *argv,
                     cwd=work)
    assert rc == 2 and all(w in err for w in words), err
    assert not (work / "never.toml").exists()


def test_fit_grid_counts_every_free_state(work):
    """A grid of 100,000 values over the cubic pendulum's two states is 10^10 states (np.prod of the
    sizes once overflowed silently): refused by its size."""
    rc, _, err = cli("fit", "exp.toml", "--params", "a", "--grid", "100000", "--out", "never.toml", cwd=work)
    assert rc == 2 and "--grid 100000: 10,000,000,000 states x 9 inputs" in err, err


def test_fit_time_beyond_a_commands_limit_is_refused(work, monkeypatch):
    """The least-squares fit's iterations count (one model evaluation pinned at 1 h: 5 iterations of
    4 evaluations are 20 h, more than the 6 h a command may take)."""
    monkeypatch.setattr("simgap.fit.seconds_per_evaluation", lambda *a, **k: 3600.0)
    rc, _, err = cli("fit", "fit.toml", "--profile", "base", "--params", "a", "b", "c", "--points", "50",
                     "--out", "never.toml", cwd=work)
    assert rc == 2 and "--points 50: the fit's transitions and its first 5 iterations would take about 20" in err, err
    assert not (work / "never.toml").exists()


def test_fit_estimate_prices_the_least_squares_too(work):
    rc, out, _ = cli("fit", "fit.toml", "--profile", "base", "--params", "a", "b", "c", "--points", "50",
                     "--out", "fitted.toml", cwd=work)
    assert rc == 0
    line = out.splitlines()[0]
    assert line.startswith("estimate: 50 states x 5 inputs = 250") and "per iteration (4 model evaluations" in line


def test_refine_bootstrap_is_priced_and_counts_are_typed(work):
    rc, _, err = cli("refine", "--system", "cubic.toml", "--data", "run/data", "--bootstrap", "1000000000",
                     "--quiet", "--out", "never.json", cwd=work)
    assert rc == 2 and "--bootstrap 1,000,000,000" in err and "more than the 6 h" in err, err
    for option, value in (("--bootstrap", "1"), ("--segments", "0"), ("--hold", "-5")):
        rc, _, err = cli("refine", "--system", "cubic.toml", "--data", "run/data", option, value,
                         "--out", "never.json", cwd=work)
        assert rc == 2 and f"argument {option}" in err, err
    assert not (work / "never.json").exists()


def test_rollouts_beyond_a_commands_limit_are_refused(work, monkeypatch):
    """Estimated, then refused: 1 rollout x 2 x 10^8 steps is days here (memory pinned large so that
    time, not memory, is what refuses it)."""
    monkeypatch.setattr("simgap.memory.available_memory", lambda: 1e13)
    rc, out, err = cli("rollout", "--controller", "grid.npz", "--simulator", "exp.toml", "--x0", "0.1,0",
                       "--n", "1", "--horizon", "200000000", "--mean-map-runs", "0", "--out", "never.json", cwd=work)
    assert "estimate: 1 rollouts x 200,000,000 steps" in out
    assert rc == 2 and "rollout: 1 rollouts x horizon 200,000,000 would take about" in err and "6 h" in err, err
    assert not (work / "never.json").exists()


def test_long_rollout_prints_its_estimate_before_the_work(work):
    """`simgap rollout --horizon 5000000` of an invariance controller used to step the nominal path to
    the horizon (a model in formulas, ~1 ms a step) before the estimate: no line for over an hour."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.Popen([sys.executable, "-m", "simgap", "rollout", "--controller", "grid.npz", "--simulator",
                          "exp.toml", "--x0", "0.1,0", "--n", "1", "--horizon", "5000000", "--mean-map-runs", "0",
                          "--out", "long.json"], cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                         text=True, start_new_session=True)
    lines = []
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            line = p.stdout.readline()
            if not line:
                break
            lines.append(line)
            if "nominal model's path" in line:
                break
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    text = "".join(lines)
    assert "estimate: 1 rollouts x 5,000,000 steps" in text, text
    assert "then the nominal model's path, 1 run x up to 5,000,000 steps" in text, text
    assert not (work / "long.json").exists()


# ----- 2. files carry what their proof assumed --------------------------------------------------------------

def _forge(src: Path, dst: Path, **meta_changes) -> Path:
    """``src``'s controller file with meta keys changed and its content digest recomputed (a digest is no
    signature: only the checks on the values can refuse it)."""
    from simgap import fileio
    with np.load(src) as z:
        a = {k: z[k] for k in z.files}
    meta = json.loads(str(a.pop("meta")))
    meta.update(meta_changes)
    meta.pop("digest")
    meta["digest"] = fileio.content_digest(meta, a)
    np.savez(dst, **a, meta=np.array(json.dumps(meta)))
    return dst


def test_box_tube_controller_with_another_hold_is_refused(work):
    """A box-tube file edited to hold = 7 (digest recomputed) was applied with inputs held 7 periods."""
    forged = _forge(work / "tube.npz", work / "tube_hold7.npz", hold=7)
    rc, _, err = cli("rollout", "--controller", forged, "--simulator", "exp.toml", "--n", "5",
                     "--out", "never.json", cwd=work)
    assert rc == 2 and "box-tube controller: hold = 7" in err and "hold = 1" in err, err
    assert not (work / "never.json").exists()


def test_box_tube_rollout_from_another_x0_is_refused(work):
    """The tube's proof starts at its own x0; rollouts from elsewhere reported "spec held" for a tube
    that proves nothing there."""
    rc, _, err = cli("rollout", "--controller", "tube.npz", "--simulator", "exp.toml", "--x0", "0.4,0",
                     "--n", "5", "--out", "never.json", cwd=work)
    assert rc == 2 and "outside the controller's box at period 0" in err and "x0 = [0.5, 0.0]" in err, err
    rc, _, err = cli("rollout", "--controller", "tube.npz", "--simulator", "exp.toml", "--n", "5",
                     "--out", "tube_rollouts.json", cwd=work)
    assert rc == 0, err


def test_set_controllers_refuse_a_hold_other_than_one():
    from simgap.synthesis.ellipsoid_controller import EllipsoidController
    from simgap.synthesis.tube_controller import TubeController
    from simgap.synthesis.box_tube import TubePlan
    with pytest.raises(SimgapError, match="invariant-set controller: hold = 2"):
        EllipsoidController([0, 0], [0], [[-1, -1]], np.eye(2), hold=2)
    plan = TubePlan(np.zeros((2, 2)), np.zeros((1, 1)), np.zeros((1, 2)), np.zeros(2), np.zeros(1), np.ones(2))
    with pytest.raises(SimgapError, match="box-tube controller: hold = 3"):
        TubeController(plan, np.ones((2, 2)), hold=3)


@pytest.mark.parametrize("ctrl", ["tube.npz", "grid.npz"])
def test_rollout_hold_other_than_the_controllers_is_refused(work, ctrl):
    rc, _, err = cli("rollout", "--controller", ctrl, "--simulator", "exp.toml", "--x0", "0.5,0", "--n", "5",
                     "--hold", "7", "--out", "never.json", cwd=work)
    assert rc == 2 and "hold = 7" in err and "proved with its input held 1 step(s)" in err, err
    assert not (work / "never.json").exists()


@pytest.mark.parametrize("change,words", [
    (lambda r: [[-1.0, r[0][1]], r[1]], ["th [-1, 0.5]", "collected over th [-0.5, 0.5]"]),   # widened
    (lambda r: [[-0.25, r[0][1]], r[1]], ["th [-0.25, 0.5]"]),                               # narrowed
    (lambda r: None, ["claims gamma over X (no region)"]),                                  # removed
])
def test_audit_compares_the_certificates_region_with_the_datas(work, change, words):
    """A local certificate whose region was widened (digest recomputed) passed `audit CERT --data DATA`."""
    from simgap import fileio
    d = json.loads((work / "run" / "cert_stochastic.json").read_text())
    region = change(d["region"])
    if region is None:
        d.pop("region")
    else:
        d["region"] = region
    d.pop("digest")
    d.pop("signature", None)
    d["digest"] = fileio.content_digest(d)
    (work / "forged_cert.json").write_text(json.dumps(d))
    rc, _, err = cli("audit", "forged_cert.json", "--data", "run/data", "--points", "5", "--runs", "20",
                     "--out", "never_audit.json", cwd=work)
    assert rc == 2 and "forged_cert.json" in err and all(w in err for w in words), err
    assert not (work / "never_audit.json").exists()
    rc, _, err = cli("audit", "run/cert_stochastic.json", "--data", "run/data", "--points", "5", "--runs",
                     "20", cwd=work)
    assert rc in (0, 1) and "claims gamma" not in err  # the certificate as written: audited


# ----- 3. one rule for conflicting options, one check in run and in the stage commands -----------------------

CONFLICTS = {
    "hold": ("hold = 2", ['[synthesis] method = "box_tube" applies u(x) every period', "[synthesis] hold = 2"]),
    "K_lqr_q": ("K = [[-3.0, -2.0]]\nlqr_q = [1.0, 1.0]",
                ["[synthesis] K = [[-3.0, -2.0]] and [synthesis] lqr_q = [1.0, 1.0] both set the feedback gain"]),
    "K_lqr_r": ("K = [[-3.0, -2.0]]\nlqr_r = [2.0]", ["[synthesis] K = [[-3.0, -2.0]] and [synthesis] lqr_r = [2.0]"]),
    "reach_avoid": ("", ['[synthesis] method = "box_tube" handles spec = "invariance" only',
                         '[synthesis] spec = "reach_avoid"']),
}


@pytest.mark.parametrize("case", sorted(CONFLICTS))
def test_synthesize_and_run_refuse_the_same_conflict_with_the_same_words(work, tmp_path, case):
    """`hold = 2` with box_tube was ignored by synthesize (run refused it); K with lqr_q dropped lqr_q; a
    box tube with reach_avoid named the arena's initial_state: now one check, the same message."""
    add, words = CONFLICTS[case]
    text = _edit(EXPERIMENT, add)
    if case == "reach_avoid":
        text = text.replace('spec = "invariance"', 'spec = "reach_avoid"')
    (tmp_path / "cubic.toml").write_text(CUBIC)
    (tmp_path / "e.toml").write_text(text)
    rc, _, err_syn = cli("synthesize", "--spec", "e.toml", "--no-gap", "--out", "never.npz", cwd=tmp_path)
    assert rc == 2 and all(w in err_syn for w in words), err_syn
    assert "initial_state" not in err_syn and "invariant set:" not in err_syn
    rc, _, err_run = cli("run", "e.toml", "--out", "res", "--no-record", cwd=tmp_path)
    assert rc == 2 and err_run.splitlines()[-1] == err_syn.splitlines()[-1]  # one function, the same words
    assert not (tmp_path / "never.npz").exists() and not (tmp_path / "res").exists()


def test_command_line_values_are_named_as_written(work):
    rc, _, err = cli("synthesize", "--spec", "exp.toml", "--no-gap", "--method", "box_tube", "--hold", "2",
                     "--out", "never.npz", cwd=work)
    assert rc == 2 and "--method box_tube applies u(x) every period, but --hold 2" in err, err
    rc, _, err = cli("synthesize", "--system", "cubic.toml", "--safe", "-1,1,-2,2", "--eta", "0.1", "--no-gap",
                     "--horizon", "5", "--out", "never.npz", cwd=work)
    assert rc == 2 and "--horizon is for --level run and --method box_tube" in err and "grid" in err, err
    rc, _, err = cli("synthesize", "--spec", "exp.toml", "--no-gap", "--eta", "0.1", "--out", "never.npz",
                     cwd=work)
    assert rc == 2 and '--eta is a grid option, but [synthesis] method = "box_tube" builds no grid' in err, err
    assert not (work / "never.npz").exists()


def test_the_engines_refuse_k_with_lqr_weights_too():
    from simgap.synthesis.box_tube import synthesize_box_tube
    from simgap.synthesis.invariant_set import synthesize_invariant_set
    from simgap.synthesis.spec import Box, Spec
    s = _cubic()
    spec = Spec(kind="invariance", safe=Box(s.x_lo, s.x_hi))
    with pytest.raises(SimgapError, match="K and lqr_q both set the feedback gain"):
        synthesize_box_tube(s, spec, None, x0=[0.5, 0], K=[[-3, -2]], lqr_q=[1, 1])
    with pytest.raises(SimgapError, match="K and lqr_r both set the feedback gain"):
        synthesize_invariant_set(s, spec, None, K=[[-3, -2]], lqr_r=[2])


@pytest.mark.parametrize("argv,words", [
    (["--grid", "5", "--points", "10"], ["--points and --grid both set the states"]),
    (["--bounds", "keep=0:1"], ["--bounds keep: not among --params a", "a bound only applies to a fitted parameter"]),
])
def test_fit_conflicts_are_refused(work, argv, words):
    rc, _, err = cli("fit", "fit.toml", "--profile", "base", "--params", "a", "--out", "never.toml", *argv,
                     cwd=work)
    assert rc == 2 and all(w in err for w in words), err
    assert not (work / "never.toml").exists()


def test_fit_start_outside_the_bounds_and_a_worse_fit_are_said(work):
    """`fit --bounds b=2.5:3` (the file's b = 1, the simulator's 1.5) wrote a worse model without a word."""
    rc, _, err = cli("fit", "fit.toml", "--profile", "base", "--params", "b", "--bounds", "b=2.5:3",
                     "--points", "50", "--out", "worse.toml", cwd=work)
    assert rc == 0
    assert "--bounds b=2.5:3 excludes the file's b = 1" in err
    assert "match the transitions WORSE than the file's own" in err and "do not replace the system file" in err


# ----- 4. output formats from the extension; no output over another --------------------------------------------

@pytest.mark.parametrize("argv,words", [
    (["fit", "fit.toml", "--profile", "base", "--params", "a", "--out", "f.json"], ["--out 'f.json'", "TOML"]),
    (["synthesize", "--system", "cubic.toml", "--safe", "-1,1,-2,2", "--eta", "0.1", "--no-gap", "--out", "c.json"],
     ["--out 'c.json'", "NPZ", ".npz"]),
    (["synthesize", "--system", "cubic.toml", "--safe", "-1,1,-2,2", "--eta", "0.1", "--no-gap", "--out", "c.npz",
      "--json", "s.npz"], ["--json 's.npz'", "JSON"]),
    (["rollout", "--controller", "grid.npz", "--simulator", "exp.toml", "--x0", "0.1,0", "--out", "r.npz"],
     ["--out 'r.npz'", "JSON"]),
    (["rollout", "--controller", "grid.npz", "--simulator", "exp.toml", "--x0", "0.1,0", "--out", "r.json",
      "--trajectories", "t.json"], ["--trajectories 't.json'", "NPZ"]),
    (["certify", "run/data", "--out", "c.toml"], ["--out 'c.toml'", "JSON"]),
    (["audit", "run/cert_stochastic.json", "--data", "run/data", "--out", "a"], ["--out 'a'", "has no extension"]),
    (["refine", "--system", "cubic.toml", "--data", "run/data", "--save-system", "o.npz"],
     ["--save-system", "JSON or TOML"]),
    (["refine", "--system", "cubic.toml", "--data", "run/data", "--save-system", "o.json", "--out", "o.json"],
     ["--out and --save-system are both 'o.json'"]),
])
def test_outputs_named_for_another_format_or_twice_are_refused(work, argv, words):
    before = digests(work)
    rc, _, err = cli(*argv, cwd=work)
    assert rc == 2 and all(w in err for w in words), err
    assert digests(work) == before


def test_two_outputs_at_one_path_by_other_spellings(work, tmp_path):
    """As a user runs it (a subprocess): the report no longer lost to the refined system."""
    (tmp_path / "sub").mkdir()
    r = simgap("refine", "--system", str(work / "cubic.toml"), "--data", str(work / "run" / "data"), "--save-system",
               "sub/../o.json", "--out", "o.json", cwd=tmp_path)
    refused(r, "--out and --save-system are both")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sub"]


# ----- 5. messages name the key and the method ------------------------------------------------------------------

def test_plan_input_weight_is_named(work, tmp_path):
    """`plan_input_weight = 1e300` said "invariant set: the discrete Riccati equation has no stabilizing
    solution" (or that K_plan does not stabilize) without the key."""
    (tmp_path / "cubic.toml").write_text(CUBIC)
    (tmp_path / "e.toml").write_text(_edit(EXPERIMENT, "plan_input_weight = 1e300",
                                           "x_star = [0.0, 0.0]\nu_star = [0.0]\n"))
    rc, _, err = cli("synthesize", "--spec", "e.toml", "--no-gap", "--out", "never.npz", cwd=tmp_path)
    assert rc == 2 and "plan_input_weight = 1e+300" in err and err.startswith("error: box tube:"), err


@pytest.mark.parametrize("kw,words", [
    ({"x_star": [0.9, 0.0], "u_star": [0.0]}, ["x* = [0.9, 0.0]", "not an equilibrium"]),
    ({"x_star": [0.0, 0.0]}, ["x_star and u_star"]),                      # half given
    ({"K": [[1.0]]}, ["K must have shape 1 x 2"]),                        # K's shape
    ({"lqr_q": [1.0, 2.0, 3.0]}, ["lqr_q", "need one finite weight or 2"]),  # a traceback before
])
def test_box_tube_messages_name_the_box_tube(kw, words):
    """The helpers shared with the invariant-set method said "invariant set:" for the box tube."""
    from simgap.synthesis.box_tube import synthesize_box_tube
    from simgap.synthesis.spec import Box, Spec
    s = _cubic()
    with pytest.raises(SimgapError) as e:
        synthesize_box_tube(s, Spec(kind="invariance", safe=Box(s.x_lo, s.x_hi)), None, x0=[0.5, 0.0],
                            margin_search=False, **kw)
    msg = str(e.value)
    assert msg.startswith("box tube:") and "invariant set" not in msg and all(w in msg for w in words), msg


# ----- 6. results folders -----------------------------------------------------------------------------------------

def test_run_into_another_runs_folder_names_what_it_replaces(work):
    """`simgap run` with another profile replaced a finished run's summary, certificates and controllers
    without a word."""
    before = digests(work / "run")
    rc, _, err = cli("run", "local.toml", "--profile", "base", "--out", "run", "--no-record", cwd=work)
    assert rc == 2 and all(w in err for w in (
        "holds the finished run of experiment 'local' (profile small)", "(profile base)", "summary.json",
        "cert_stochastic.json", "controller_nominal.npz", "--force")), err
    assert digests(work / "run") == before


def _read_only(folder: Path, monkeypatch):
    """Make ``folder`` read-only: a read-only bind mount where the machine allows one (root writes
    through permissions), else every temporary file refused there as a read-only mount refuses it."""
    import errno
    import tempfile
    r = subprocess.run(["mount", "--bind", "-o", "ro", str(folder), str(folder)], capture_output=True)
    if r.returncode == 0:
        return lambda: subprocess.run(["umount", str(folder)], check=True)
    real = tempfile.mkstemp

    def mkstemp(*a, dir=None, **kw):
        if dir is not None and Path(folder).resolve() in [Path(dir).resolve(), *Path(dir).resolve().parents]:
            raise OSError(errno.EROFS, "Read-only file system")
        return real(*a, dir=dir, **kw)
    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
    return lambda: None


@pytest.mark.parametrize("draw", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_plot_on_a_read_only_results_folder_offers_out(work, tmp_path, monkeypatch, draw):
    """`simgap plot RUN` on a read-only folder died with OSError on mkdir figures; the --out it offers
    draws the figures elsewhere (drawing them takes matplotlib ~10 s of CPU: the slow suite)."""
    pytest.importorskip("matplotlib")
    before = digests(work / "run")
    undo = _read_only(work / "run", monkeypatch)
    try:
        rc, _, err = cli("plot", work / "run")
        assert rc == 2 and "not writable" in err and "--out FOLDER" in err, err
        if draw:
            rc, out, err = cli("plot", work / "run", "--out", tmp_path / "fig")
            assert rc == 0 and (tmp_path / "fig").is_dir() and any((tmp_path / "fig").iterdir()), err
    finally:
        undo()
    assert digests(work / "run") == before

"""``simgap run`` with a [perrun] section: every controller validated next to p_cert; bad input writes nothing."""

import json
from pathlib import Path

import numpy as np
import pytest

from simgap.cli import main
from simgap.perrun.value_iteration import PerRunController

TOML = Path(__file__).parent / "data" / "perrun_tiny.toml"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("perrun") / "out"
    assert main(["run", str(TOML), "--out", str(out), "--no-record"]) == 0
    return out, json.loads((out / "summary.json").read_text())


def test_summary_has_p_cert_and_p_emp_per_controller_and_state(run):
    out, s = run
    pr = s["per_run"]
    assert set(pr["controllers"]) == {"deterministic", "stochastic", "run_baseline", "perrun"}
    for name, c in pr["controllers"].items():
        assert len(c["states"]) >= 1
        for st in c["states"]:
            assert {"x0", "p_cert", "p_emp", "ci95", "n_rollouts", "horizon"} <= set(st)
            assert st["n_rollouts"] == 500 and st["horizon"] == 40
            assert st["ci95"][0] <= st["p_emp"] <= st["ci95"][1]
            if st["p_cert"] is not None:   # soundness at every tested initial state
                assert st["p_emp"] >= st["p_cert"] - 3 * max(np.sqrt(st["p_emp"] * (1 - st["p_emp"]) / 500), 1 / 500)
    per = pr["controllers"]["perrun"]["states"]
    assert len(per) == 6 and per[0]["x0"] == [0.0, 0.0] and per[0]["p_cert"] > 0.5
    # the union-bound baseline certifies nothing at this horizon: 1 - 40 * 2 * 0.1 < 0
    assert pr["controllers"]["run_baseline"]["states"][0]["p_cert"] == 0.0
    ctl = PerRunController.load(out / "controller_perrun.npz")
    assert ctl.certified(np.array([[0.0, 0.0]]))[0] == pytest.approx(per[0]["p_cert"])
    assert (out / "cert_run.json").stat().st_size > 0
    # p_cert says what it rests on, in the summary, the controller file and the printed table
    assert "estimated Lipschitz constants" in pr["p_cert_conditional_on"]
    assert ctl.meta["p_cert_conditional_on"] == pr["p_cert_conditional_on"]
    c = pr["imdp"]["containment"]
    assert c["passed"] is True and c["runs"] == c["rows_checked"] * c["states_per_row"] > 0
    assert ctl.meta["containment"]["passed"] is True
    assert pr["randomization"].startswith("per period") and ctl.meta["randomization"] == pr["randomization"]
    from simgap.perrun.stage import table
    assert "conditional on the estimated Lipschitz constants" in table(pr).splitlines()[1]
    assert "containment check: passed" in table(pr).splitlines()[1]


def test_table_judges_only_stated_probabilities(run):
    """The printed table: a controller without p_cert gets no soundness verdict, and one state below
    p_cert - 3 SE is counted as unsound."""
    from simgap.perrun.stage import table
    _, s = run
    pr = json.loads(json.dumps(s["per_run"]))
    rows = {line.split()[0]: line.split() for line in table(pr).splitlines()[3:]}
    assert rows["deterministic"][-1] == "-" and rows["stochastic"][-1] == "-"
    n = len(pr["controllers"]["perrun"]["states"])
    assert rows["perrun"][-1] == f"{n}/{n}"
    worst = pr["controllers"]["perrun"]["states"][-1]
    worst.update(p_cert=1.0, p_emp=0.5, se=0.02)
    rows = {line.split()[0]: line.split() for line in table(pr).splitlines()[3:]}
    assert rows["perrun"][-1] == f"{n - 1}/{n}" and float(rows["perrun"][-2]) == 0.5


@pytest.mark.parametrize("old, new, msg", [
    ("alpha = 0.1", "alpha = 1.5", "alpha must be in (0, 1)"),
    ("alpha = 0.1", "alpha = 0.01", "smallest supported alpha is"),
    ("n_states = 5", "n_states = 5\nhorizon = 0", "horizon must be >= 1"),
    ("x0 = [0.0, 0.0]", "x0 = [0.5, 0.0]", "x0"),
    ("n_states = 5", "n_states = 5\nsplit = [0.9, 0.1, 0.1]", "sums to 1.1 > 1"),
    ("n_states = 5", "n_states = 5\nsplit = 0.9", "split: input should be a valid list"),
    ("n_states = 5", "n_states = 5\nsplit = [0.9, 0.1]", "three shares (sink, lo, hi)"),
])
def test_bad_input_is_refused_before_anything_is_written(tmp_path, capsys, old, new, msg):
    toml = tmp_path / "bad.toml"
    toml.write_text(TOML.read_text().replace(old, new))
    out = tmp_path / "out"
    assert main(["run", str(toml), "--out", str(out), "--no-record"]) == 2
    assert msg in capsys.readouterr().err
    assert not out.exists()


def test_cli_synthesize_level_run(tmp_path, capsys):
    out = tmp_path / "c.npz"
    assert main(["synthesize", "--level", "run", "--spec", str(TOML), "--out", str(out), "--horizon", "20"]) == 0
    txt = capsys.readouterr().out
    assert "p_cert(x0 = [0.0, 0.0])" in txt and "one-sided Clopper-Pearson bounds" in txt
    ctl = PerRunController.load(out)
    assert ctl.horizon == 20 and ctl.steps == 2 and 0 < ctl.p_cert.max() <= 1
    def rc(args):  # a bad count is refused by the parser (SystemExit 2), other bad input by main (2)
        try:
            return main(args)
        except SystemExit as e:
            return e.code

    for extra, msg in ((["--horizon", "0"], "--horizon: must be an integer >= 1"), (["--x0", "0.5,0"], "outside X"),
                       (["--no-gap"], "drop --cert/--gamma/--no-gap")):
        bad = tmp_path / "bad.npz"
        assert rc(["synthesize", "--level", "run", "--spec", str(TOML), "--out", str(bad), *extra]) == 2
        assert msg in capsys.readouterr().err and not bad.exists()


def test_rerun_recording_of_the_per_run_results(run, tmp_path):
    from simgap_viz.record import read_back
    from simgap_viz.record_perrun import record_per_run

    out, s = run
    ctl = PerRunController.load(out / "controller_perrun.npz")
    info = record_per_run(tmp_path / "perrun.rrd", ctl, s["per_run"])
    back = read_back(tmp_path / "perrun.rrd")
    assert info["cells"] == ctl.grid.size
    for ent in ("/perrun/p_cert", "/perrun/perrun/p_emp", "/perrun/deterministic/p_emp", "/perrun/summary"):
        assert ent in back, sorted(back)
    assert back["/perrun/perrun/p_emp"]["rows"] >= 1


def test_pendulum_perrun_profile_is_valid():
    from simgap.config import load_experiment
    from simgap.perrun.stage import check_section

    e = load_experiment("pendulum", "perrun")
    o = check_section(e.section("perrun"), e.system, e.plan().n_pairs, e.collect.n_runs,
                      e.section("rollout").get("horizon"))
    assert o["horizon"] == 400 and o["n_rollouts"] == 10000 and o["alpha"] == 0.05
    assert load_experiment("pendulum", "noisy").section("perrun") == {}   # the other profiles are unchanged


def test_share_in_an_experiment(tmp_path, capsys):
    """`[perrun] share` reaches the interval MDP (fewer simulator runs, recorded), and its bad values are
    refused before any sampling (with invariant, not a whole number of cells)."""
    import re
    text = TOML.read_text()
    shared = tmp_path / "shared.toml"
    shared.write_text(text.replace("[perrun]\n", "[perrun]\nshare = 3\n"))
    out = tmp_path / "ctl.npz"
    assert main(["synthesize", "--level", "run", "--spec", str(shared), "--out", str(out)]) == 0
    meta = PerRunController.load(out).meta
    assert meta["share"] == [3, 3] and meta["anchors"] < meta["live_cells"]
    assert "residual" in meta["lipschitz"] and re.search(r"p_cert\(x0", capsys.readouterr().out)
    for line, msg in (("share = 3\ninvariant = [\"theta\"]\n", "exclude each other"), ("share = 0\n", "share"),
                      ("share = [2, 2, 2]\n", "share")):
        bad = tmp_path / "bad.toml"
        bad.write_text(text.replace("[perrun]\n", "[perrun]\n" + line))
        dest = tmp_path / "bad.npz"
        assert main(["synthesize", "--level", "run", "--spec", str(bad), "--out", str(dest)]) == 2
        assert msg in capsys.readouterr().err and not dest.exists()

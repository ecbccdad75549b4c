"""Experiment TOML loading and the `simgap collect` command, including every bad input (exit 2, no data)."""

import numpy as np
import pytest

from simgap.cli import main
from simgap.config import load_experiment
from simgap.dataset import load_dataset
from simgap.errors import SimgapError

BASE = """
[system]
name = "pendulum"
{system_extra}
[simulator]
kind = "numpy"
noise = {{ actuation_std = 0.05 }}
[collect]
epsilon = 0.1
n_runs = 8
seed = 5
{collect_extra}
[certify]
delta1 = 0.05
[profiles.tiny.collect]
n_runs = 4
"""


def write(tmp_path, system_extra="", collect_extra="", text=None):
    p = tmp_path / "exp.toml"
    p.write_text(text if text is not None else BASE.format(system_extra=system_extra, collect_extra=collect_extra))
    return p


def test_builtin_experiments_load():
    for name, M, n_pts in [("pendulum", 21, 12567), ("turtlebot", 441, 185)]:
        e = load_experiment(name, "paper")
        assert e.system.name == name and e.system.inputs.shape[0] == M
        assert e.cover().N == n_pts and e.collect.n_runs == 1000
        s = load_experiment(name, "small")
        plan = s.plan()
        assert plan.n_pairs * plan.n_runs * s.system.steps < 3e7  # the small profile stays small
    t = load_experiment("turtlebot", "paper")
    assert t.collect.epsilon == 0.017 and t.cover().covered == (2,)
    assert load_experiment("pendulum", "paper").collect.epsilon == 0.004


def test_profiles_overrides_and_other_sections(tmp_path):
    p = write(tmp_path)
    e = load_experiment(p, "tiny")
    assert e.collect.n_runs == 4 and e.collect.epsilon == 0.1
    assert e.section("certify") == {"delta1": 0.05} and e.section("synthesis") == {}
    e = load_experiment(p, None, overrides={"collect": {"n_runs": 9, "seed": None}})
    assert e.collect.n_runs == 9 and e.collect.seed == 5
    assert e.store_dir().as_posix() == "results/exp-base/data"  # where simgap run collects


def test_cli_collect_runs_and_resumes(tmp_path, capsys):
    p = write(tmp_path)
    out = tmp_path / "store"
    assert main(["collect", str(p), "--profile", "base", "--out", str(out), "--executor", "serial",
                 "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "cover: 24 points" in text and "504 (x_r,u) pairs" in text and "4,032 simulator steps" in text
    assert "estimated time" in text and str(out) in text
    ds = load_dataset(out)
    assert ds.K == 504 and ds.n_runs == 8
    assert main(["collect", str(p), "--profile", "base", "--out", str(out), "--executor", "local",
                 "--workers", "2", "--no-progress"]) == 0
    assert "already done" in capsys.readouterr().out
    # flags override the TOML; a different configuration into the same store is refused
    assert main(["collect", str(p), "--profile", "base", "--out", str(out), "--n-runs", "9", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and "n_runs: 8 (store) vs 9 (requested)" in err
    np.testing.assert_array_equal(load_dataset(out).mean, ds.mean)


def test_cli_dry_run_writes_nothing(tmp_path, capsys):
    p = write(tmp_path)
    out = tmp_path / "store"
    assert main(["collect", str(p), "--profile", "tiny", "--out", str(out), "--dry-run", "--epsilon", "0.05"]) == 0
    text = capsys.readouterr().out
    assert "dry run" in text and "x 4 runs" in text
    assert not out.exists()


@pytest.mark.parametrize("args,toml_kw,match", [
    (["--epsilon", "0"], {}, "\\[collect\\] epsilon: input should be greater than 0"),
    (["--epsilon", "-0.5"], {}, "\\[collect\\] epsilon: input should be greater than 0"),
    ([], {"text": BASE.format(system_extra="", collect_extra="").replace("n_runs = 8", "n_runs = 1")},
     "n_runs \\(N1hat\\): input should be greater than or equal to 2"),
    (["--profile", "nope"], {}, "no profile 'nope'"),
    ([], {"system_extra": "inputs = []"}, "input"),
    ([], {"system_extra": 'inputs = [[1.0, 2.0]]'}, "components"),
    ([], {"system_extra": 'inputs = "abc"'}, "\\[system\\] inputs"),
    ([], {"system_extra": 'input_grid = { lo = [-1.0], hi = [1.0], counts = [0] }'}, "input_grid.counts\\[0\\]"),
    ([], {"system_extra": "colour = 3"}, "unknown key 'colour' in \\[system\\]"),
    ([], {"collect_extra": 'invariant_dims = ["theta", "omega"]'}, "nothing left to cover"),
    ([], {"collect_extra": 'invariant_dims = ["omega"]\nfixed = { omega = 9.0 }'}, "outside X"),
    ([], {"collect_extra": 'executor = "dask"'}, "executor"),
    ([], {"text": "[system\nname="}, "not valid TOML"),
    ([], {"text": BASE.format(system_extra="", collect_extra="").replace('"pendulum"', '"segway"')},
     "unknown system 'segway'"),
    ([], {"text": BASE.format(system_extra="", collect_extra="").replace('"numpy"', '"gazebo"')},
     "unknown simulator kind"),
])
def test_cli_bad_input_exits_2(tmp_path, capsys, args, toml_kw, match):
    p = write(tmp_path, **toml_kw)
    out = tmp_path / "store"
    profile = [] if "--profile" in args else ["--profile", "base"]
    rc = main(["collect", str(p), *profile, "--out", str(out), "--no-progress", *args])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.startswith("error:")
    import re
    assert re.search(match, err), err
    assert not out.exists()


def test_cli_unknown_experiment_and_bad_store(tmp_path, capsys):
    assert main(["collect", "no_such_experiment"]) == 2
    assert "unknown experiment" in capsys.readouterr().err
    assert main(["collect", str(tmp_path / "missing.toml")]) == 2
    assert "does not exist" in capsys.readouterr().err
    with pytest.raises(SimgapError, match=r"\[collect\] n_runs \(N1hat\): input should be a valid integer, got 1.5"):
        load_experiment(write(tmp_path, text=BASE.format(system_extra="", collect_extra="").replace(
            "n_runs = 8", "n_runs = 1.5")), None)

"""simgap fit: a system file's parameters fitted to noise-free simulator transitions."""

import tomllib

import numpy as np
import pytest

from simgap.cli import main
from simgap.errors import SimgapError

SYSTEM = '''format = "simgap-system"
name = "leaky"
description = "a leaky integrator"
states = ["x"]
inputs = ["F"]
x_lo = [-2.0]
x_hi = [2.0]
tau = 0.1
input_grid = { lo = [-1.0], hi = [1.0], counts = [5] }

[params]
# the leak rate [1/s]
a = 0.5   # a guess
b = 1.0
c = 0.0
keep = 3.0

[dynamics]
kind = "discrete"
x = "x + dt*(-a*x + b*F + c + 0*keep)"
'''

# the simulator: the file's model with its input scaled by 1.5, an extra leak 0.2 x and a drift 0.1,
# so the true one-step map is the model's with a = 0.5 + 0.2, b = 1.5, c = 0.1 exactly
EXPERIMENT = '''description = "fit test"
system = "leaky.toml"
[simulator]
kind = "numpy"
noise = { actuation_std = 0.3 }
effects = { input_gain = 1.5, linear = [[-0.2]], bias = [0.1] }
[collect]
epsilon = 0.1
n_runs = 5
'''


@pytest.fixture
def folder(tmp_path):
    (tmp_path / "leaky.toml").write_text(SYSTEM)
    (tmp_path / "exp.toml").write_text(EXPERIMENT)
    return tmp_path


def test_fit_recovers_the_simulators_parameters_and_writes_only_them(folder, capsys):
    out = folder / "fitted.toml"
    assert main(["fit", str(folder / "exp.toml"), "--profile", "base", "--params", "a", "b", "c",
                 "--points", "50", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.splitlines()[0].startswith("estimate: 50 states x 5 inputs = 250 noise-free simulator runs")
    new = tomllib.loads(out.read_text())
    assert new["params"]["a"] == pytest.approx(0.7, abs=1e-5)
    assert new["params"]["b"] == pytest.approx(1.5, abs=1e-5)
    assert new["params"]["c"] == pytest.approx(0.1, abs=1e-5)
    assert new["params"]["keep"] == 3.0
    # comments and every other line are kept; the noise-free gap after the fit is ~0
    assert "# the leak rate [1/s]" in out.read_text() and "# a guess" in out.read_text()
    old_lines = SYSTEM.splitlines()
    new_lines = out.read_text().splitlines()
    assert [i for i, (p, q) in enumerate(zip(old_lines, new_lines)) if p != q] == [12, 13, 14]
    from simgap.system_file import load_system_file
    s = load_system_file(out)
    x = np.linspace(-2, 2, 9)[:, None]
    u = np.full((9, 1), 0.5)
    assert np.allclose(s.f(x, u), x + 0.1 * (-0.7 * x + 1.5 * 0.5 + 0.1), atol=1e-6)


def test_fit_params_engine_matches_the_cli_and_reports_the_gap(folder):
    from simgap.config import load_experiment
    from simgap.fit import fit_params, sample_states, transitions
    from simgap.simulators import make_simulator
    import dataclasses

    exp = load_experiment(folder / "exp.toml", "base")
    s = exp.system
    rng = np.random.default_rng(1)
    x = sample_states(s, 7, rng, grid=True)
    assert np.allclose(x[:, 0], -2 + (np.arange(7) + 0.5) * 4 / 7)
    with make_simulator(dataclasses.replace(exp.simulator, noise={}, randomize={}), s) as sim:
        X, U, Y = transitions(sim, x, s.inputs, rng)
    res = fit_params(s, ["a", "b"], X, U, Y)  # c left at 0: the drift stays in the gap
    assert res.max_after[0] < res.max_before[0]
    assert res.max_after[0] == pytest.approx(0.1 * 0.1, rel=0.3)  # about dt x the drift left out
    full = fit_params(s, ["a", "b", "c"], X, U, Y)
    assert full.max_after[0] < 1e-6 < res.max_after[0]


@pytest.mark.parametrize("argv, words", [
    (["--params", "nope"], ["--params/--bounds nope", "not in leaky.toml's [params]"]),
    (["--params", "a", "--fix", "x"], ["--fix 'x'", "NAME=VALUE"]),
    (["--params", "a", "--fix", "x=9"], ["--fix x=9", "outside X"]),
    (["--params", "a", "--bounds", "a=1:0"], ["--bounds 'a=1:0'", "LO:HI"]),
])
def test_bad_input_is_refused_by_name_and_writes_nothing(folder, capsys, argv, words):
    out = folder / "fitted.toml"
    assert main(["fit", str(folder / "exp.toml"), "--profile", "base", "--out", str(out)] + argv) == 2
    err = capsys.readouterr().err
    assert all(w in err for w in words), err
    assert "Traceback" not in err and not out.exists()


def test_the_experiments_own_file_and_a_built_in_system_are_refused(folder, tmp_path, capsys):
    assert main(["fit", str(folder / "exp.toml"), "--profile", "base", "--params", "a",
                 "--out", str(folder / "leaky.toml")]) == 2
    assert "the experiment's own system file" in capsys.readouterr().err
    assert (folder / "leaky.toml").read_text() == SYSTEM
    assert main(["fit", "pendulum", "--params", "m", "--out", str(tmp_path / "p.toml")]) == 2
    assert "not from a system file" in capsys.readouterr().err


def test_fitted_text_changes_only_the_named_lines():
    from simgap.fit import fitted_text
    new = fitted_text(SYSTEM, {"a": 0.123456789, "c": -2})
    assert "a = 0.123457   # a guess" in new and "c = -2.0" in new and "b = 1.0" in new
    with pytest.raises(SimgapError, match="no \\[params\\] table"):
        fitted_text(SYSTEM.replace("[params]", "params = { a = 1 }\n[other]"), {"a": 1.0})
    with pytest.raises(SimgapError, match="not name = value lines"):
        fitted_text(SYSTEM, {"zz": 1.0})

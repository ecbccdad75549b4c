"""The rollout CLI's argument handling (the end-to-end run with a synthesized controller is in
test_rollout_synth.py)."""

import json

import numpy as np
import pytest

from simgap.cli import main
from simgap.cli.rollout import parse_vector, simulator_config
from simgap.errors import SimgapError


def test_parse_vector():
    np.testing.assert_allclose(parse_vector(["3.5", "2", "1.5"], "--x0"), [3.5, 2, 1.5])
    np.testing.assert_allclose(parse_vector(["3.5,2,1.5"], "--x0"), [3.5, 2, 1.5])
    with pytest.raises(SimgapError, match="--x0: expected numbers"):
        parse_vector(["a", "b"], "--x0")


def test_simulator_config_from_json_file_inline_and_experiment(tmp_path):
    cfg = {"kind": "numpy", "system": "turtlebot", "noise": {"actuation_std": [0.1, 0.1]}}
    p = tmp_path / "sim.json"
    p.write_text(json.dumps(cfg))
    assert simulator_config(str(p))["noise"] == cfg["noise"]
    assert simulator_config(json.dumps(cfg))["kind"] == "numpy"
    assert simulator_config(json.dumps({"simulator": cfg}))["system"] == "turtlebot"
    d = simulator_config("turtlebot")  # the built-in experiment's [simulator] section
    assert d["system"] == "turtlebot" and d["kind"]
    with pytest.raises(SimgapError, match="not readable JSON"):
        simulator_config("{kind: numpy")
    with pytest.raises(SimgapError, match="unknown keys"):
        simulator_config(json.dumps(dict(cfg, colour=1)))
    with pytest.raises(SimgapError, match="does not exist"):
        simulator_config(str(tmp_path / "none.json"))
    with pytest.raises(SimgapError, match="unknown experiment"):
        simulator_config("no_such_experiment")


def test_cli_errors_exit_2(tmp_path, capsys):
    rc = main(["rollout", "--controller", str(tmp_path / "missing.npz"), "--simulator", "turtlebot",
               "--out", str(tmp_path / "r.json")])
    assert rc == 2
    assert "error: controller file" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()

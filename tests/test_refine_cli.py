"""``simgap refine`` end to end: table, report JSON keys, refined system file, error exits."""

import json

import numpy as np
import pytest

from simgap.cli import main
from simgap.refine.refined import load_system
from simgap.simulators.base import make_simulator
from simgap.systems import get_system


@pytest.fixture
def damped_npz(tmp_path):
    s = get_system("pendulum")
    rng = np.random.default_rng(21)
    K = 8000
    x = s.x_lo + rng.random((K, 2)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, 21, K)]
    with make_simulator({"kind": "numpy", "system": "pendulum", "noise": {"process_std": 1e-4},
                         "effects": {"linear": [[0, 0], [0, -0.5]]}}) as sim:
        xn = sim.step(x, u, rng)
    path = tmp_path / "damped.npz"
    np.savez(path, x=x, u=u, x_next=xn, tau=s.tau)
    return path


def test_refine_cli_report_and_saved_system(damped_npz, tmp_path, capsys):
    out, sysf = tmp_path / "report.json", tmp_path / "refined.json"
    rc = main(["refine", "--system", "pendulum", "--data", str(damped_npz), "--out", str(out),
               "--save-system", str(sysf)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "viscous_friction" in text and "RMS before (f)" in text and "unexplained: false" in text
    rep = json.loads(out.read_text())
    for key in ("effects", "rms_before", "rms_after", "max_before", "max_after", "unexplained"):
        assert key in rep
    assert len(rep["rms_before"]) == 2 and len(rep["max_after"]) == 2
    (e,) = rep["effects"]
    assert {"name", "state", "variable", "coefficient", "stderr", "explained_fraction"} <= set(e)
    assert e["name"] == "viscous_friction" and e["state"] == 1 and e["variable"] == "omega"
    assert e["coefficient"] == pytest.approx(-0.5, abs=0.01)
    assert rep["rms_after"][1] < rep["rms_before"][1] / 5
    ref = load_system(str(sysf))
    assert ref.params["refinement"][0]["name"] == "viscous_friction"
    # the refined system is accepted where a system is expected: refine against it again
    rc = main(["refine", "--system", str(sysf), "--data", str(damped_npz), "--quiet", "--out", str(out)])
    assert rc == 0 and json.loads(out.read_text())["effects"] == []


def test_refine_cli_effect_subset_and_user_term(damped_npz, tmp_path):
    out = tmp_path / "r.json"
    assert main(["refine", "--system", "pendulum", "--data", str(damped_npz), "--effects", "bias,gravity",
                 "--term", "damp:omega:omega", "--quiet", "--out", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert [(e["name"], e["state"]) for e in rep["effects"]] == [("damp", 1)]


@pytest.mark.parametrize("args,msg", [
    (["--effects", "bias,stiction"], "unknown effect name"),
    (["--term", "bad"], "expected NAME:STATE:EXPR"),
    (["--system", "cartpole"], "unknown system"),
])
def test_refine_cli_bad_arguments(damped_npz, capsys, args, msg):
    argv = ["refine", "--system", "pendulum", "--data", str(damped_npz)] + args
    if "--system" in args:
        argv = ["refine", "--data", str(damped_npz)] + args
    assert main(argv) == 2
    assert msg in capsys.readouterr().err


def test_refine_cli_nonfinite_rows(damped_npz, tmp_path, capsys):
    with np.load(damped_npz) as z:
        d = {k: z[k] for k in z.files}
    d["x_next"][:5, 0] = np.nan
    bad = tmp_path / "bad.npz"
    np.savez(bad, **d)
    assert main(["refine", "--system", "pendulum", "--data", str(bad)]) == 2
    assert "5 of 8000 rows contain NaN or inf" in capsys.readouterr().err
    out = tmp_path / "r.json"
    assert main(["refine", "--system", "pendulum", "--data", str(bad), "--drop-nonfinite", "--quiet",
                 "--out", str(out)]) == 0
    rep = json.loads(out.read_text())
    assert rep["dropped_nonfinite"] == 5 and rep["samples"] == 7995


def test_refine_cli_missing_arrays(tmp_path, capsys):
    p = tmp_path / "m.npz"
    np.savez(p, x=np.zeros((10, 2)), u=np.zeros((10, 1)))
    assert main(["refine", "--system", "pendulum", "--data", str(p)]) == 2
    assert "missing arrays" in capsys.readouterr().err

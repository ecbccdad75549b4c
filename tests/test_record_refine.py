"""The refinement recording: residual against velocity, before and after, read back from the .rrd."""

import numpy as np
import pytest

from simgap.cli import main
from simgap.errors import SimgapError
from simgap.refine.data import make_transitions
from simgap.refine.report import refine
from simgap.simulators.base import make_simulator
from simgap.systems import get_system
from simgap_viz.record import read_back, record_refinement


@pytest.fixture(scope="module")
def damped():
    """Pendulum transitions with an undeclared viscous damping of 0.5 on omega, refined."""
    s = get_system("pendulum")
    rng = np.random.default_rng(3)
    K = 6000
    x = s.x_lo + rng.random((K, 2)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, 21, K)]
    cfg = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 1e-5},
           "effects": {"linear": [[0, 0], [0, -0.5]]}}
    with make_simulator(cfg) as sim:
        xn = sim.step(x, u, rng)
    return refine("pendulum", make_transitions(x, u, xn, s.tau, system=s))


def _points(entity):
    rb = entity["chunks"][0]
    col = [c for c in rb.schema.names if c.endswith("positions")][0]
    return np.asarray(rb.column(col).to_pylist()[0], dtype=float)


def test_residual_vs_velocity_recording(damped, tmp_path):
    out = tmp_path / "refine.rrd"
    info = record_refinement(out, damped, max_points=3000)
    assert info["against"] == "omega" and info["points"] == 3000
    got = read_back(out)
    for nm in ("theta", "omega"):
        for w in ("before", "after", "before_mean", "after_mean"):
            assert f"/refine/{nm}/{w}" in got, (nm, w)
    assert "/refine/report" in got
    before = _points(got["/refine/omega/before"])
    after = _points(got["/refine/omega/after"])
    assert before.shape == (3000, 2) and after.shape == (3000, 2)
    # the structure is visible: before, the omega residual falls linearly with omega (damping);
    # after, it is flat and much smaller
    slope_before = np.polyfit(before[:, 0], before[:, 1], 1)[0]
    slope_after = np.polyfit(after[:, 0], after[:, 1], 1)[0]
    assert slope_before < 0 and abs(slope_after) < 0.05 * abs(slope_before)
    assert np.std(after[:, 1]) < 0.2 * np.std(before[:, 1])


def test_refine_cli_record_and_bad_variable(damped, tmp_path, capsys):
    with pytest.raises(SimgapError, match="unknown variable"):
        record_refinement(tmp_path / "x.rrd", damped, against="nope")
    assert not (tmp_path / "x.rrd").exists()
    npz = tmp_path / "d.npz"
    d = damped.data
    np.savez(npz, x=d.x, u=d.u, x_next=d.x_next, tau=d.tau)
    rrd = tmp_path / "r.rrd"
    assert main(["refine", "--system", "pendulum", "--data", str(npz), "--bootstrap", "10", "--record", str(rrd),
                 "--against", "omega"]) == 0
    assert "residual vs omega" in capsys.readouterr().out
    assert "/refine/omega/before" in read_back(rrd)
    assert main(["refine", "--system", "pendulum", "--data", str(npz), "--record", str(tmp_path / "x.txt")]) == 2

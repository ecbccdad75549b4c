"""The refinement loop on measured data: the EMPS benchmark record (real ball-screw axis).

The record is found through $SIMGAP_EMPS_DIR or in ../shared/data/emps/ next to the repository
(simgap.records). When it is absent the EMPS tests skip with a message saying where they looked.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from simgap.cli import main
from simgap.errors import SimgapError
from simgap.records import emps_missing_message, find_emps
from simgap.refine.report import refine
from simgap.refine.trajectory import from_trajectory_file, trajectory_to_transitions

EMPS = find_emps("estimation") or Path("DATA_EMPS.mat")
needs_record = pytest.mark.skipif(not EMPS.exists(), reason=emps_missing_message("estimation"))


@pytest.fixture(scope="module")
def emps_reports():
    out = {}
    for cutoff in (20.0, 50.0):
        data = from_trajectory_file(EMPS, preset="emps", cutoff_hz=cutoff)
        out[cutoff] = refine("emps", data).report
    return out


def _physical(rep, name):
    e = [e for e in rep["effects"] if e["name"] == name and e["state_name"] == "qd"]
    return e[0]["physical"]["value"] if e else None


@needs_record
def test_emps_effects_are_friction_and_stable_under_cutoff(emps_reports):
    for cutoff, rep in emps_reports.items():
        names = {(e["name"], e["state_name"]) for e in rep["effects"]}
        # a ball screw: viscous and Coulomb friction on the velocity update
        assert {("viscous_friction", "qd"), ("coulomb_friction", "qd")} <= names, (cutoff, names)
        assert rep["holdout_kind"] == "contiguous time segments"
        fv, fc = _physical(rep, "viscous_friction"), _physical(rep, "coulomb_friction")
        # friction opposes motion: negative forces per velocity / sign of velocity, physically sized
        assert -1000 < fv < -20, fv          # N s/m
        assert -100 < fc < -2, fc            # N
        # held-out velocity-update RMS error falls at least 5x
        assert rep["rms_before"][1] / rep["rms_after"][1] >= 5, (cutoff, rep["rms_before"], rep["rms_after"])
    # two cutoffs, same physics (within 5 %)
    a, b = emps_reports[20.0], emps_reports[50.0]
    for name in ("viscous_friction", "coulomb_friction"):
        assert _physical(a, name) == pytest.approx(_physical(b, name), rel=0.05), name


@needs_record
def test_emps_cli_from_trajectory_and_refine(tmp_path, capsys):
    npz, rep = tmp_path / "emps.npz", tmp_path / "rep.json"
    assert main(["data", "from-trajectory", str(EMPS), "--preset", "emps", "--cutoff", "20",
                 "--out", str(npz)]) == 0
    with np.load(npz) as z:
        assert {"x", "u", "x_next", "tau", "t"} <= set(z.files)
        assert float(z["tau"]) == pytest.approx(0.001, rel=1e-6)
        assert z["x"].shape[1] == 2
    rrd = tmp_path / "emps.rrd"
    assert main(["refine", "--system", "emps", "--data", str(npz), "--out", str(rep),
                 "--bootstrap", "20", "--record", str(rrd)]) == 0
    from simgap_viz.record import read_back
    got = read_back(rrd)  # the residual against the velocity qd, before and after
    assert {"/refine/qd/before", "/refine/qd/after", "/refine/qd/before_mean", "/refine/report"} <= set(got)
    r = json.loads(rep.read_text())
    units = {e["name"]: e["physical"]["unit"] for e in r["effects"] if e["physical"]}
    assert units["viscous_friction"] == "N s/m" and units["coulomb_friction"] == "N"
    assert "coulomb_friction" in capsys.readouterr().out


@needs_record
def test_emps_bad_records(tmp_path):
    import scipy.io
    raw = scipy.io.loadmat(str(EMPS))
    t, q, u = raw["t"].ravel(), raw["qm"].ravel(), raw["vir"].ravel()
    # wrong variable names
    wrong = tmp_path / "wrong.mat"
    scipy.io.savemat(str(wrong), {"time": t, "pos": q, "vir": u})
    with pytest.raises(SimgapError, match=r"missing variable\(s\) \['t', 'qm'\]"):
        from_trajectory_file(wrong, preset="emps")
    # too short
    with pytest.raises(SimgapError, match="record too short"):
        trajectory_to_transitions(t[:150], q[:150], u[:150], 20.0)
    # cutoff above Nyquist
    with pytest.raises(SimgapError, match="Nyquist = 500 Hz"):
        trajectory_to_transitions(t, q, u, 600.0)
    # non-uniform time stamps
    t2 = t.copy()
    t2[5000:] += 0.0004
    with pytest.raises(SimgapError, match="non-uniform time stamps"):
        trajectory_to_transitions(t2, q, u, 20.0)
    assert main(["data", "from-trajectory", str(wrong), "--preset", "emps", "--out",
                 str(tmp_path / "o.npz")]) == 2


def test_trajectory_conversion_on_a_synthetic_record():
    """Known motion q = A sin(w t): estimated velocity matches A w cos(w t) away from the edges."""
    fs, A, w = 1000.0, 0.1, 2 * np.pi * 0.5
    t = np.arange(0, 10, 1 / fs)
    q = A * np.sin(w * t)
    tr = trajectory_to_transitions(t, q, np.zeros_like(t), 20.0)
    np.testing.assert_allclose(tr.x[:, 1], A * w * np.cos(w * tr.t), atol=1e-4)
    np.testing.assert_allclose(tr.x_next[:-1], tr.x[1:])
    assert tr.meta["trim"] == 100 and tr.is_time_series


def test_from_trajectory_cli_csv_with_named_columns(tmp_path, capsys):
    """A user's own log: mass-spring-free cart with viscous friction, position-only CSV."""
    fs, M, b = 500.0, 2.0, 3.0
    t = np.arange(0, 20, 1 / fs)
    u = np.sign(np.sin(2 * np.pi * 0.4 * t)) * 4.0        # bang-bang force [N]
    v = np.zeros_like(t)
    q = np.zeros_like(t)
    for k in range(t.size - 1):                            # exact-enough simulation at 500 Hz
        v[k + 1] = v[k] + (u[k] - b * v[k]) / M / fs
        q[k + 1] = q[k] + v[k] / fs
    path = tmp_path / "log.csv"
    np.savetxt(path, np.column_stack([t, q, u]), delimiter=",", header="time,pos,force", comments="")
    out = tmp_path / "log.npz"
    assert main(["data", "from-trajectory", str(path), "--time", "time", "--position", "pos",
                 "--input", "force", "--cutoff", "40", "--out", str(out)]) == 0
    assert "low-pass 40 Hz" in capsys.readouterr().out
    with np.load(out) as z:
        assert z["x"].shape[1] == 2 and float(z["tau"]) == pytest.approx(1 / fs)
        # the estimated velocity follows the true one
        i = np.searchsorted(t, z["t"])
        assert np.max(np.abs(z["x"][:, 1] - v[i])) < 0.02 * np.max(np.abs(v))
    assert main(["data", "from-trajectory", str(path), "--time", "time", "--position", "pos",
                 "--input", "force", "--cutoff", "300", "--out", str(out)]) == 2
    assert "Nyquist = 250 Hz" in capsys.readouterr().err
    assert main(["data", "from-trajectory", str(path), "--time", "time", "--position", "pos",
                 "--cutoff", "40", "--out", str(out)]) == 2


def test_emps_found_through_environment_variable(tmp_path, monkeypatch, capsys):
    """$SIMGAP_EMPS_DIR is searched first; the missing-record message names every folder searched."""
    from simgap.records import EMPS_ENV, emps_search_dirs

    (tmp_path / "DATA_EMPS_PULSES.mat").write_bytes(b"")
    monkeypatch.setenv(EMPS_ENV, str(tmp_path))
    assert emps_search_dirs()[0] == tmp_path and find_emps("validation") == tmp_path / "DATA_EMPS_PULSES.mat"
    msg = emps_missing_message("validation")
    assert str(tmp_path) in msg and EMPS_ENV in msg and all(str(d) in msg for d in emps_search_dirs())
    with pytest.raises(SimgapError, match="unknown EMPS record"):
        find_emps("training")
    assert main(["data", "from-trajectory", "--out", str(tmp_path / "x.npz")]) != 0
    assert "trajectory file" in capsys.readouterr().err


@needs_record
def test_emps_cli_finds_record_by_itself(tmp_path, monkeypatch, capsys):
    from simgap.records import EMPS_ENV

    monkeypatch.setenv(EMPS_ENV, str(EMPS.parent))
    out = tmp_path / "val.npz"
    assert main(["data", "from-trajectory", "--preset", "emps", "--record", "validation", "--out", str(out)]) == 0
    assert f"EMPS validation record: {EMPS.parent / 'DATA_EMPS_PULSES.mat'}" in capsys.readouterr().out
    assert out.exists()

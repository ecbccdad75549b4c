"""The Silverbox (real measurements of an electronic Duffing oscillator): the cubic spring is named
from the library, and the refined model, saved and loaded, simulates the test record far better than
the linear nominal. The record is found through $SIMGAP_SILVERBOX_DIR or in ../shared/data/silverbox
beside the repository; when it is absent the tests skip saying where they looked."""

import importlib.util
import os
from pathlib import Path

import numpy as np
import pytest

from simgap.refine.refined import load_system, save_refined
from simgap.refine.report import refine
from simgap.refine.selection import SelectionOptions
from simgap.refine.trajectory import backward_transitions

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("refine_silverbox", ROOT / "bench" / "refine_silverbox.py")
sb = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sb)

DIRS = [os.environ.get("SIMGAP_SILVERBOX_DIR"), ROOT.parent / "shared" / "data" / "silverbox"]
RECORD = next((Path(d) / "SNLS80mV.mat" for d in DIRS if d and (Path(d) / "SNLS80mV.mat").exists()), None)
needs_record = pytest.mark.skipif(RECORD is None, reason=f"Silverbox record SNLS80mV.mat not found (looked in: "
                                  f"{', '.join(str(d) for d in DIRS if d)}); set SIMGAP_SILVERBOX_DIR")


@needs_record
def test_cubic_spring_named_and_refined_model_simulates_the_arrow_better(tmp_path):
    u, y, t = sb.load(RECORD)
    part = slice(40500, 40500 + 20000)
    est = backward_transitions(t[part], y[part], u[part])
    nominal = load_system(str(sb.NOMINAL))
    rep = refine(nominal, est, effects=["cubic_stiffness", "gravity", "viscous_friction", "input_gain"],
                 options=SelectionOptions(n_boot=5, max_lag=0)).report
    (c,) = [e for e in rep["effects"] if e["name"] == "cubic_stiffness"]
    assert c["state_name"] == "v" and c["variable"] == "y"
    # hardening, of the size a least-squares fit of y^3 gives on the whole record (-5.49e5 V/s^2/V^3)
    assert -8e5 < c["coefficient"] < -3e5, c
    res = refine(nominal, est, effects=["cubic_stiffness", "gravity"], options=SelectionOptions(n_boot=5, max_lag=0))
    loaded = load_system(str(save_refined(res.refined, tmp_path / "sb.json")))
    arrow = slice(100, 8100)                 # the first 8,000 samples of the test record
    ya, ua = y[arrow], u[arrow]
    p0, d0 = sb.free_run(nominal, ya, ua)
    p1, d1 = sb.free_run(loaded, ya, ua)
    assert d0 is None and d1 is None
    assert sb.rms_mv(p1, ya) < 0.6 * sb.rms_mv(p0, ya), (sb.rms_mv(p0, ya), sb.rms_mv(p1, ya))

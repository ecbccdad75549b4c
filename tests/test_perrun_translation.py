"""The translation-invariant interval MDP (simgap.perrun.translation) against the per-cell construction."""

import dataclasses

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.maps import load_map
from simgap.perrun.imdp import IMDPOptions
from simgap.perrun.sampling import build_imdp
from simgap.perrun.translation import build_imdp_translation
from simgap.simulators import make_simulator
from simgap.systems import get_system

L = np.array([[1.0, 0.0, 0.3], [0.0, 1.0, 0.3], [0.0, 0.0, 1.0]])


def _setup(noise=None):
    s = dataclasses.replace(get_system("turtlebot"), inputs=np.array([[v, w] for v in (0.0, 1.0) for w in (-1.0, 0.0, 1.0)]))
    cfg = {"kind": "numpy", "system": "turtlebot", "steps": 30}
    if noise:
        cfg["noise"] = noise
    return make_simulator(cfg, system=s), load_map("arena").spec(s)


def _rows(im, r):
    sl = slice(im.row_ptr[r], im.row_ptr[r + 1])
    return im.col[sl], im.hi[sl]


def test_noise_free_matches_the_per_cell_construction():
    """Without noise every run from a cell center is the same: the shifted runs of the reference
    cell must give each cell exactly the successors and sink status its own runs give (a wrong
    shift, sign, angle index or obstacle test changes some row)."""
    sim, spec = _setup()
    o = dict(eta=[0.25, 0.25, 2 * np.pi / 8], hold=1, n_runs=10, pilot_runs=1, lipschitz=L, seed=0)
    a = build_imdp(sim, spec, IMDPOptions(**o))
    b = build_imdp_translation(sim, spec, IMDPOptions(**o))
    assert b.meta["classes"] == 8 and b.meta["samples"] == 8 * 6 * 11
    assert np.array_equal(a.live, b.live) and np.array_equal(a.target, b.target)
    sinks = compared = 0
    for r in np.flatnonzero(np.repeat(a.live, a.M)):
        ca, ha = _rows(a, r)
        cb, hb = _rows(b, r)
        sa, sb = ha[ca == a.C][0] == 1.0, hb[cb == b.C][0] == 1.0   # count N (sink) or 0
        assert sa == sb, f"row {r}: sink {sa} per cell, {sb} shifted"
        sinks += sa
        if not sa:  # a safe run: the same successor cells
            assert set(ca.tolist()) == set(cb.tolist()), f"row {r}"
            compared += 1
    assert sinks > 100 and compared > 1000   # both kinds of rows are exercised


def test_noisy_support_and_bounds_are_consistent():
    sim, spec = _setup({"actuation_std": [0.05, 0.2]})
    im = build_imdp_translation(sim, spec, IMDPOptions(eta=[0.25, 0.25, 2 * np.pi / 8], hold=1, n_runs=200,
                                                       pilot_runs=20, lipschitz=L, seed=3))
    assert np.all(im.lo <= im.hi) and np.all(im.lo >= 0) and np.all(im.hi <= 1)
    rows = np.repeat(np.arange(im.C * im.M), np.diff(im.row_ptr))
    assert np.all(im.live[rows // im.M])                      # only live cells have rows
    assert np.all((im.col == im.C) | im.live[np.minimum(im.col, im.C - 1)] | im.target[np.minimum(im.col, im.C - 1)])
    lo_sum = np.bincount(rows, weights=im.lo, minlength=im.C * im.M)
    assert lo_sum.max() <= 1.0 + 1e-6                         # the intervals admit a distribution


def test_invariant_dimension_must_not_be_an_angle():
    sim, spec = _setup()
    with pytest.raises(SimgapError, match="invariant"):
        build_imdp_translation(sim, spec, IMDPOptions(eta=[0.5, 0.5, 1.0], n_runs=10, pilot_runs=1), invariant=(2,))


def test_cli_synthesize_level_run_with_invariant(tmp_path, capsys):
    """`[perrun] invariant` selects the shifted construction: its cost is classes x inputs x runs."""
    from pathlib import Path

    from simgap.cli import main
    from simgap.perrun.value_iteration import PerRunController

    toml = Path(__file__).parent / "data" / "perrun_turtle_tiny.toml"
    out = tmp_path / "c.npz"
    assert main(["synthesize", "--level", "run", "--spec", str(toml), "--out", str(out)]) == 0
    assert "p_cert(x0 = [3.5, 2.0, 1.5])" in capsys.readouterr().out
    ctl = PerRunController.load(out)
    assert ctl.meta["classes"] == 8 and ctl.meta["samples"] == 8 * 6 * 330 and ctl.meta["invariant"] == ["x", "y"]
    assert ctl.p_cert[ctl.target].min() == 1.0 and ctl.p_cert.max() <= 1.0
    bad = tmp_path / "bad.toml"
    bad.write_text(toml.read_text().replace('invariant = ["x", "y"]', 'invariant = ["theta"]'))
    assert main(["synthesize", "--level", "run", "--spec", str(bad), "--out", str(tmp_path / "b.npz")]) == 2
    assert "invariant must list non-angle state names" in capsys.readouterr().err
    assert not (tmp_path / "b.npz").exists()


def test_turtlebot_perrun_profile_is_valid():
    from simgap.config import load_experiment
    from simgap.perrun.stage import check_section

    e = load_experiment("turtlebot", "perrun")
    o = check_section(e.section("perrun"), e.system, e.plan().n_pairs, e.collect.n_runs,
                      e.section("rollout").get("horizon"))
    assert o["invariant"] == ["x", "y"] and o["hold"] == 1 and e.system.inputs.shape == (10, 2)
    assert e.simulator.to_dict()["noise"]["wheel_slip"] == [0.2, 1.0]
    assert load_experiment("turtlebot", "gazebo").section("perrun") == {}   # the other profiles are unchanged

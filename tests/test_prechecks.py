"""Refusals that the cover decides come before any collection and name the setting to change."""

from pathlib import Path

import numpy as np
import pytest

from simgap.cli import main
from simgap.errors import SimgapError

TINY = """
description = "tiny pendulum for the pre-collection checks"
[system]
name = "pendulum"
steps = 1
[simulator]
kind = "numpy"
noise = { actuation_std = 0.01 }
[collect]
epsilon = EPS
n_runs = 20
seed = 1
executor = "serial"
[certify]
degree = DEG
beta1 = 0.05
beta2 = 0.05
LHAT
[audit]
points = 10
runs = 50
[synthesis]
spec = "invariance"
eta = [0.005, 0.01]
[rollout]
n = 20
horizon = 20
x0 = [0.0, 0.0]
"""


def _toml(tmp_path, eps, deg, lhat=""):
    p = tmp_path / "exp.toml"
    p.write_text(TINY.replace("EPS", str(eps)).replace("DEG", str(deg)).replace("LHAT", lhat))
    return p


def test_degree_above_the_covers_values_is_refused_before_collection(tmp_path, capsys):
    # epsilon 0.21 on theta in [-0.2, 0.2]: 2 theta values, so theta^2 is dependent on 1 and theta
    out = tmp_path / "out"
    assert main(["run", str(_toml(tmp_path, 0.21, 2)), "--out", str(out), "--no-record"]) == 2
    err = capsys.readouterr().err
    assert "[certify] degree = 2 for theta" in err and "only 2 value(s) of theta" in err
    assert "[collect] epsilon" in err and "degree <= 1" in err and "Traceback" not in err
    assert not out.exists()  # nothing collected, no folder


def test_pair_distance_too_large_is_refused_before_collection(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(_toml(tmp_path, 0.21, 1, 'lhat = "simulator"')), "--out", str(out),
                 "--no-record"]) == 2
    err = capsys.readouterr().err
    assert "pair distance h = the cover's epsilon = 0.21" in err and "0.4 wide along theta" in err
    assert "[collect] epsilon" in err and "below 0.2" in err
    assert not out.exists()


def test_collect_warns_and_still_collects(tmp_path, capsys):
    assert main(["collect", str(_toml(tmp_path, 0.21, 2)), "--out", str(tmp_path / "st"), "--dry-run"]) == 0
    err = capsys.readouterr().err
    assert "warning: these data will not certify with the experiment's settings" in err


def test_gap_term_needs_two_values_per_covered_dimension():
    from simgap.certify.pipeline import CertifyOptions
    from simgap.cover import make_cover
    from simgap.pipeline import check_against_cover
    from simgap.systems import get_system

    s = get_system("pendulum")
    cover = make_cover(s, 0.3)  # theta: one value
    with pytest.raises(SimgapError, match="lipschitz_term = \"gap\".*1 value of theta"):
        check_against_cover(s, cover, CertifyOptions(degree=0, lipschitz_term="gap"))
    check_against_cover(s, cover, CertifyOptions(degree=0))  # the paper's term has no such need


@pytest.mark.parametrize("degree", [2, 3])
def test_the_degree_check_agrees_with_the_scenario_program(tmp_path, degree):
    """On data with 3 theta values the pre-check passes degree 2 (certify succeeds) and refuses
    degree 3 (certify's own rank check refuses it too): the condition d >= v is exact."""
    from simgap.certify import certify
    from simgap.certify.pipeline import CertifyOptions
    from simgap.collect import CollectionPlan, collect, load_store
    from simgap.cover import CoverSpec, make_cover
    from simgap.pipeline import check_against_cover
    from simgap.simulators.base import SimulatorConfig
    from simgap.systems import get_system

    s = get_system("pendulum")
    cover = make_cover(s, CoverSpec(epsilon=0.2, spacing=(0.14, 0.05)))
    assert int(cover.counts[0]) == 3
    o = CertifyOptions(degree=degree, beta1=0.05, beta2=0.05)
    plan = CollectionPlan(s, SimulatorConfig(kind="numpy", system="pendulum", steps=1,
                                             noise={"actuation_std": 0.01}), cover, n_runs=5, seed=1)
    collect(plan, tmp_path / "st", executor="serial")
    ds = load_store(tmp_path / "st")
    if degree < 3:
        check_against_cover(s, cover, o)
        assert certify(ds, o).dims
    else:
        with pytest.raises(SimgapError, match="only 3 value"):
            check_against_cover(s, cover, o)
        with pytest.raises(SimgapError, match="linearly dependent"):
            certify(ds, o)

"""The point of the loop: the refined model gives a tighter certified gap and a larger winning domain."""

import numpy as np
import pytest

from simgap.cli import main
from simgap.dataset import Dataset
from simgap.refine.compare import gap_comparison
from simgap.refine.data import from_dataset
from simgap.refine.report import refine
from simgap.simulators.base import make_simulator
from simgap.synthesis.spec import Box, Spec
from simgap.systems import get_system


def damped_dataset(eps=0.01, N=50, damping=2.0):
    s = get_system("pendulum")
    h = 2 * eps / np.sqrt(2)
    g1 = np.arange(s.x_lo[0], s.x_hi[0] + 1e-9, h)
    g2 = np.arange(s.x_lo[1], s.x_hi[1] + 1e-9, h)
    xr = np.array(np.meshgrid(g1, g2, indexing="ij")).reshape(2, -1).T
    R, M = len(xr), len(s.inputs)
    X, U = np.repeat(xr, M, axis=0), np.tile(s.inputs, (R, 1))
    rng = np.random.default_rng(0)
    with make_simulator({"kind": "numpy", "system": "pendulum", "noise": {"actuation_std": 0.005},
                         "effects": {"linear": [[0, 0], [0, -damping]]}}) as sim:
        runs = np.stack([sim.step(X, U, rng) for _ in range(N)])
    return Dataset(system=s, x=X, u=U, f_nom=s.f(X, U), mean=runs.mean(0), var=runs.var(0, ddof=1),
                   lo=runs.min(0), hi=runs.max(0), cover_index=np.repeat(np.arange(R), M),
                   input_index=np.tile(np.arange(M), R), n_runs=N, epsilon=eps, manifest={"hash": "t"})


def test_refined_model_tightens_gap_and_grows_winning_domain():
    ds = damped_dataset()
    res = refine("pendulum", from_dataset(ds))
    assert [e["name"] for e in res.report["effects"]] == ["viscous_friction"]
    c = gap_comparison(ds, res.refined, spec=Spec("invariance", safe=Box([0.0, -0.5], [0.2, 0.5])),
                       eta=[0.004, 0.01])
    # the damping gap tau * 2 * |omega| <= 5e-3 is gone from f': gamma on omega shrinks
    assert c["observed_gap_max_before"][1] > 4e-3 and c["observed_gap_max_after"][1] < 2e-4
    assert c["gamma_max_after"][1] < 0.5 * c["gamma_max_before"][1]
    assert c["gamma_mean_after"][1] < c["gamma_mean_before"][1]
    # theta has no gap either way (same certificate)
    assert c["gamma_max_after"][0] == pytest.approx(c["gamma_max_before"][0])
    # and the controller synthesized against f' + gamma' wins where f + gamma wins nothing
    assert c["winning_before"] < c["winning_after"]
    assert c["winning_after"] > 0.2 * c["domain_cells"]


def test_compare_gap_needs_a_collected_dataset(tmp_path, capsys):
    s = get_system("pendulum")
    rng = np.random.default_rng(1)
    x = s.x_lo + rng.random((2000, 2)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, 21, 2000)]
    np.savez(tmp_path / "t.npz", x=x, u=u, x_next=s.f(x, u) + 1e-4 * rng.standard_normal((2000, 2)), tau=s.tau)
    assert main(["refine", "--system", "pendulum", "--data", str(tmp_path / "t.npz"), "--compare-gap"]) == 2
    assert "need a collected data set" in capsys.readouterr().err


def test_held_comparison_composes_only_when_asked():
    """hold > 1 with a one-period gap is refused unless composing is asked for, and then labelled."""
    from simgap.errors import SimgapError

    ds = damped_dataset(eps=0.02, N=20)
    res = refine("pendulum", from_dataset(ds))
    spec = Spec("invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    with pytest.raises(SimgapError, match="compose"):
        gap_comparison(ds, res.refined, spec=spec, eta=[0.004, 0.01], hold=2)
    c = gap_comparison(ds, res.refined, spec=spec, eta=[0.004, 0.01], hold=2, compose_hold=True)
    assert c["hold"] == 2 and c["compose_hold"] is True and "winning_after" in c

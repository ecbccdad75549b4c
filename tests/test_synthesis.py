"""Symbolic controller synthesis: grid conventions, SAT box counts, soundness by sampling,
save/load, determinism, bad input and the CLI."""

from __future__ import annotations

import numpy as np
import pytest

from simgap.synthesis.examples import integrator_system
from simgap.cli import main
from simgap.errors import SimgapError
from simgap.synthesis.abstraction import ConstantGap
from simgap.synthesis.controller import Controller, synthesize
from simgap.synthesis.games import BoxCounter
from simgap.synthesis.grid import UniformGrid
from simgap.synthesis.spec import Box, Spec
from simgap.systems import get_system, input_grid


# ---------------------------------------------------------------------------------------
# small systems
# ---------------------------------------------------------------------------------------

def integrator(tau=0.07):
    """x+ = x + tau u on [0,1]^2, 5 x 5 inputs in [-1, 1]^2."""
    return integrator_system(tau)


class LinearGap:
    """gamma(x, u) = g0 + g1 |x_1| (both dims): a state-dependent gap with a sound box bound."""

    def __init__(self, g0=0.004, g1=0.01, n=2):
        self.g0, self.g1, self.n = g0, g1, n

    def gamma(self, x):
        return self.g0 + self.g1 * np.abs(x[:, :1]) * np.ones((1, self.n))

    def gamma_upper_box(self, lo, hi, u):
        m = np.maximum(np.abs(lo[:, :1]), np.abs(hi[:, :1]))
        return self.g0 + self.g1 * m * np.ones((1, self.n))


def _sample_in_cells(grid, ids, rng):
    """Uniform states inside the given cells (shrunk by a hair to stay off shared faces)."""
    c = grid.points(ids)
    return c + (rng.random(c.shape) - 0.5) * grid.eta * 0.999


def _disturb(gamma, rng):
    """A disturbance in [-gamma, gamma]: half extremal (+-gamma), half uniform."""
    w = (2 * rng.random(gamma.shape) - 1) * gamma
    ext = rng.random(gamma.shape[0]) < 0.5
    w[ext] = np.sign(w[ext]) * gamma[ext]
    return w


# ---------------------------------------------------------------------------------------
# grid and SAT
# ---------------------------------------------------------------------------------------

def test_grid_scots_alignment_and_roundtrip(rng):
    g = UniformGrid([0, 0, -3.5], [10, 10, 3.5], 0.2)
    assert g.shape == (51, 51, 35) and g.size == 91035
    assert np.allclose(g.first, [0, 0, -3.4]) and np.allclose(g.last, [10, 10, 3.4])
    ids = rng.integers(0, g.size, 500)
    assert np.array_equal(g.x_to_ids(g.points(ids)), ids)
    x = _sample_in_cells(g, ids, rng)
    assert np.array_equal(g.x_to_ids(x), ids)
    assert g.x_to_ids(np.array([[-0.2, 5, 0]]))[0] == -1  # beyond first - eta/2
    p = UniformGrid([0, -np.pi], [1, np.pi], [0.25, 0.3], periodic=(1,))
    assert p.shape == (5, 21) and np.isclose(p.eta[1], 2 * np.pi / 21)
    # wrapping: theta = pi is the same cell as -pi
    assert p.x_to_ids(np.array([[0.5, np.pi]]))[0] == p.x_to_ids(np.array([[0.5, -np.pi]]))[0]


@pytest.mark.parametrize("periodic", [(), (1,)])
def test_box_counter_matches_brute_force(rng, periodic):
    shape = (7, 9, 5)
    pm = np.zeros(3, bool)
    pm[list(periodic)] = True
    Z = rng.random(shape) < 0.6
    bc = BoxCounter(shape, pm).set(Z.ravel())
    lo = rng.integers(-1, 7, (400, 3))
    ext = rng.integers(1, 5, (400, 3))
    for d in periodic:  # wrapped and full-circle boxes
        lo[:, d] = rng.integers(-7, 12, 400)
        ext[:, d] = rng.integers(1, 9, 400)
    hi = lo + ext - 1
    nlo, nhi, ing = bc.normalize(lo, hi)
    got = bc.count(nlo, nhi)
    for i in np.flatnonzero(ing)[:150]:  # brute force over the box (small)
        axes = []
        for d in range(3):
            r = np.arange(lo[i, d], hi[i, d] + 1)
            axes.append(np.unique(r % shape[d]) if pm[d] else r)
        want = Z[np.ix_(*axes)].sum()
        assert got[i] == want
    assert ing.sum() > 20


# ---------------------------------------------------------------------------------------
# soundness by sampling
# ---------------------------------------------------------------------------------------

def _check_reach(sysm, spec, ctrl, gap_fn, hold, rng, n_samples=1500):
    win = np.flatnonzero(ctrl.winning_mask & ~ctrl.target)
    assert win.size > 50
    x = _sample_in_cells(ctrl.grid, rng.choice(win, n_samples), rng)
    budget = ctrl.steps_to_go(x)
    assert np.all(budget > 0)
    done = np.zeros(len(x), bool)
    for k in range(int(budget.max())):
        act = ~done
        if not act.any():
            break
        u = ctrl.input(x[act])  # strict: raises if a state left the winning domain
        xa = x[act]
        for _ in range(hold):
            xa = sysm.f(xa, u) + _disturb(gap_fn(xa), rng)
            xa = sysm.wrap(xa)
            assert not spec.violated(xa, sysm.x_lo, sysm.x_hi).any(), "left X or hit an obstacle"
        x[act] = xa
        reached = act.copy()
        reached[act] = ctrl.in_target(xa)
        assert np.all(spec.reached(x[reached]))
        done |= reached
        # worst-case steps-to-go bound: not yet in target after `budget` steps is a failure
        assert not np.any(~done & (budget <= k + 1))
    assert done.all()


def test_reach_avoid_sound_with_state_dependent_gap(rng):
    sysm = integrator()
    spec = Spec(kind="reach_avoid", target=Box([0.7, 0.7], [0.9, 0.9]),
                obstacles=(Box([0.4, 0.0], [0.6, 0.6]),))
    gap = LinearGap(0.006, 0.01)
    res = synthesize(sysm, spec, 0.03, gap=gap, hold=2, compose_hold=True)
    ctrl = res.controller
    assert not res.empty and res.stats["winning"] > 100
    # the gap enters the successor boxes; a much larger gap leaves nothing
    nominal = synthesize(sysm, spec, 0.03, hold=2)
    assert res.stats["transitions"] > nominal.stats["transitions"]
    assert synthesize(sysm, spec, 0.03, gap=LinearGap(0.02, 0.05), hold=2, compose_hold=True).empty
    _check_reach(sysm, spec, ctrl, gap.gamma, 2, rng)


def test_reach_avoid_sound_periodic_heading_with_hold(rng):
    base = get_system("turtlebot")
    import dataclasses
    sysm = dataclasses.replace(base, x_lo=np.array([0.0, 0.0, -np.pi]), x_hi=np.array([2.0, 2.0, np.pi]),
                               inputs=input_grid([-1, -1], [1, 1], [5, 5]))
    spec = Spec(kind="reach_avoid", target=Box([0.2, 0.2, -np.inf], [0.7, 0.7, np.inf]),
                obstacles=(Box([0.9, 0.0, -np.inf], [1.1, 1.2, np.inf]),))
    g = np.array([0.0005, 0.0005, 0.001])
    res = synthesize(sysm, spec, (0.05, 0.05, 2 * np.pi / 32), gap=g, hold=10, invariant_dims=(0, 1),
                     compose_hold=True)
    ctrl = res.controller
    assert ctrl.grid.periodic == (2,) and res.stats["winning"] > 1000
    _check_reach(sysm, spec, ctrl, lambda x: np.broadcast_to(g, x.shape), 10, rng, n_samples=800)


def test_invariance_sound_pendulum(rng):
    sysm = get_system("pendulum")
    spec = Spec(kind="invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    g = np.array([0.0001, 0.001])
    res = synthesize(sysm, spec, (0.004, 0.01), gap=g)
    ctrl = res.controller
    assert res.stats["winning"] > 300
    win = np.flatnonzero(ctrl.winning_mask)
    x = _sample_in_cells(ctrl.grid, rng.choice(win, 1000), rng)
    for _ in range(300):
        u = ctrl.input(x)
        x = sysm.f(x, u) + _disturb(np.broadcast_to(g, x.shape), rng)
        assert np.all(spec.safe.contains(x))
    assert ctrl.winning(x).all()


def test_invariant_dims_checked():
    sysm = get_system("pendulum")
    spec = Spec(kind="invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    with pytest.raises(SimgapError, match="invariant_dims"):
        synthesize(sysm, spec, (0.01, 0.05), invariant_dims=(0,))


# ---------------------------------------------------------------------------------------
# controller files, determinism, queries
# ---------------------------------------------------------------------------------------

def _small_reach():
    sysm = integrator()
    spec = Spec(kind="reach_avoid", target=Box([0.7, 0.7], [0.9, 0.9]),
                obstacles=(Box([0.4, 0.0], [0.6, 0.6]),))
    return sysm, spec


def test_save_load_roundtrip_and_determinism(tmp_path, rng):
    sysm, spec = _small_reach()
    a = synthesize(sysm, spec, 0.05, gap=ConstantGap([0.005, 0.005]), x0=[0.1, 0.1]).controller
    b = synthesize(sysm, spec, 0.05, gap=ConstantGap([0.005, 0.005]), x0=[0.1, 0.1]).controller
    for f in ("steps", "valid_packed", "chosen", "target"):
        assert np.array_equal(getattr(a, f), getattr(b, f))
    path = a.save(tmp_path / "c.npz")
    c = Controller.load(path, system=sysm)
    x = rng.random((300, 2))
    assert np.array_equal(a.input_index(x), c.input_index(x))
    assert np.array_equal(a.valid_inputs(x), c.valid_inputs(x))
    assert np.array_equal(a.steps_to_go(x), c.steps_to_go(x))
    assert c.size == a.size and c.hold == a.hold and c.kind == "reach_avoid"
    assert c.spec.to_dict() == spec.to_dict() and np.allclose(c.x0, [0.1, 0.1])
    assert c.meta["gap"]["info"]["gamma"] == [0.005, 0.005]
    # built-in systems are rebuilt from the file
    ps = Spec(kind="invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    p = synthesize(get_system("pendulum"), ps, (0.004, 0.01)).controller
    q = Controller.load(p.save(tmp_path / "p.npz"))
    assert q.system.name == "pendulum" and q.size == p.size


def test_controller_queries_and_determinization(rng):
    sysm, spec = _small_reach()
    ctrl = synthesize(sysm, spec, 0.05).controller
    x = rng.random((500, 2))
    idx = ctrl.input_index(x)
    valid = ctrl.valid_inputs(x)
    win = ctrl.winning(x)
    tgt = ctrl.in_target(x)
    # the chosen input is the lowest-index valid input; -1 outside the domain and on the target
    has = valid.any(axis=1)
    assert np.array_equal(idx[has & ~tgt], valid[has & ~tgt].argmax(axis=1))
    assert np.all(idx[~win | tgt] == -1)
    assert np.all(ctrl.steps_to_go(x)[tgt] == 0)
    assert ctrl.size_with_target == ctrl.size + int(ctrl.target.sum())


# ---------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("eta,msg", [(0.0, "eta must be > 0"), (-0.1, "eta must be > 0"),
                                     (2.0, "larger than the extent")])
def test_bad_eta(eta, msg):
    sysm, spec = _small_reach()
    with pytest.raises(SimgapError, match=msg):
        synthesize(sysm, spec, eta)


def test_bad_specs():
    sysm = integrator()
    obs = (Box([0.4, 0.0], [0.6, 0.6]),)
    with pytest.raises(SimgapError, match="inside obstacle"):
        synthesize(sysm, Spec(kind="reach_avoid", target=Box([0.45, 0.1], [0.55, 0.2]), obstacles=obs), 0.05)
    with pytest.raises(SimgapError, match="outside X"):
        synthesize(sysm, Spec(kind="reach_avoid", target=Box([2, 2], [3, 3])), 0.05)
    with pytest.raises(SimgapError, match="empty target"):
        synthesize(sysm, Spec(kind="reach_avoid", target=Box([0.71, 0.71], [0.72, 0.72])), 0.05)
    with pytest.raises(SimgapError, match="empty safe set"):
        synthesize(sysm, Spec(kind="invariance", safe=Box([0.2, 0.2], [0.22, 0.22])), 0.05)
    with pytest.raises(SimgapError, match="empty target"):  # every target cell is an obstacle cell
        synthesize(sysm, Spec(kind="reach_avoid", target=Box([0.3, 0.3], [0.5, 0.5]),
                              obstacles=(Box([0.2, 0.2], [0.45, 0.6]), Box([0.44, 0.2], [0.6, 0.6]))), 0.05)


def test_bad_gap_dimension_and_system():
    sysm, spec = _small_reach()
    with pytest.raises(SimgapError, match="3 components"):
        synthesize(sysm, spec, 0.05, gap=[0.1, 0.1, 0.1])

    class Wrong:
        system_name = "pendulum"

        def gamma_upper_box(self, lo, hi, u):
            return np.zeros_like(lo)

    with pytest.raises(SimgapError, match="pendulum"):
        synthesize(sysm, spec, 0.05, gap=Wrong())


def test_real_certificate_for_other_system_rejected():
    from simgap.certify.pipeline import certify
    from simgap.certify.synthetic import synthetic_dataset
    ds = synthetic_dataset({"kind": "numpy", "system": "pendulum", "noise": {"actuation_std": 0.05}},
                           epsilon=0.08, n_runs=20, seed=1)
    cert = certify(ds)
    tb = get_system("turtlebot")
    spec = Spec(kind="reach_avoid", target=Box([0.2, 0.2, -np.inf], [0.9, 0.9, np.inf]))
    with pytest.raises(SimgapError, match="pendulum"):
        synthesize(tb, spec, 0.2, gap=cert)
    # and on its own system the certificate's gamma enters the abstraction (bigger boxes)
    ps = Spec(kind="invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    with_gap = synthesize(get_system("pendulum"), ps, (0.004, 0.01), gap=cert)
    without = synthesize(get_system("pendulum"), ps, (0.004, 0.01))
    assert with_gap.stats["transitions"] > without.stats["transitions"]


def test_empty_winning_domain_is_a_result_with_a_reason():
    tb = get_system("turtlebot")
    spec = Spec(kind="reach_avoid", target=Box([0.2, 0.2, -np.inf], [0.9, 0.9, np.inf]))
    res = synthesize(tb.with_steps(1), spec, (0.16, 0.16, 0.4), hold=1)
    assert res.empty and res.controller.size == 0
    assert "control authority" in res.stats["diagnosis"]
    with pytest.raises(SimgapError, match="outside the controller's winning domain"):
        res.controller.input(np.array([[2.0, 2.0, 0.0]]))


def test_initial_state_outside_winning_domain_raises():
    sysm, spec = _small_reach()
    ctrl = synthesize(sysm, spec, 0.05).controller
    ctrl.check_winning(np.array([[0.8, 0.8]]))  # target: fine
    with pytest.raises(SimgapError, match="outside the controller's winning domain"):
        ctrl.check_winning(np.array([[0.5, 0.3]]))  # inside the obstacle
    with pytest.raises(SimgapError, match="outside the grid"):
        ctrl.input(np.array([[1.5, 0.3]]))
    assert np.isnan(ctrl.input(np.array([[1.5, 0.3]]), strict=False)).all()


# ---------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------

def test_cli_synthesize(tmp_path, capsys):
    out = tmp_path / "p.npz"
    rc = main(["synthesize", "--system", "pendulum", "--no-gap", "--safe", "0,0.2,-0.5,0.5",
               "--eta", "0.004,0.01", "--out", str(out), "--json", str(tmp_path / "s.json")])
    text = capsys.readouterr().out
    assert rc == 0 and out.exists() and "winning" in text and "transitions" in text
    assert Controller.load(out).size > 0
    # empty winning domain: exit 1, nothing written, a reason printed
    out2 = tmp_path / "t.npz"
    rc = main(["synthesize", "--system", "turtlebot", "--no-gap", "--spec", "arena", "--eta", "0.16,0.16,0.4",
               "--out", str(out2)])
    text = capsys.readouterr().out
    assert rc == 1 and not out2.exists() and "EMPTY" in text and "--hold" in text
    # bad input: exit 2 with a message
    rc = main(["synthesize", "--system", "pendulum", "--no-gap", "--safe", "0,0.2", "--eta", "0.01",
               "--out", str(tmp_path / "x.npz")])
    assert rc == 2 and "--safe" in capsys.readouterr().err


def test_cli_synthesize_from_experiment(tmp_path, capsys):
    out = tmp_path / "tb.npz"
    rc = main(["synthesize", "--spec", "turtlebot", "--no-gap", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0 and "reach_avoid" in text and "x0            [3.5, 2.0, 1.5]: winning" in text
    ctrl = Controller.load(out)
    assert ctrl.system.name == "turtlebot" and ctrl.system.steps == 30 and ctrl.n_inputs == 25
    rc = main(["synthesize", "--spec", "turtlebot", "--system", "pendulum", "--no-gap", "--out", str(out)])
    assert rc == 2 and "does not match" in capsys.readouterr().err


@pytest.mark.slow
def test_turtlebot_case_study_resolution():
    """Paper-scale: 51 x 51 x 79 cells, 441 inputs, input held 10 x 0.01 s (about 30 s CPU)."""
    from simgap.maps import load_map
    tb = get_system("turtlebot")
    arena = load_map("arena")
    res = synthesize(tb, arena.spec(tb), 0.08, hold=10, x0=arena.x0(tb))
    assert res.stats["cells"] == 205_479 and res.stats["inputs"] == 441
    assert res.controller.winning(arena.x0(tb)[None])[0]
    assert res.stats["winning"] > 100_000

"""Invariant-set synthesis: the proved ellipsoid against fresh points and worst-case disturbances,
mutations of the proof (no nonlinear remainder, no gap) that the same check catches, and bad input."""

import itertools

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.synthesis import invariant_set as iv
from simgap.synthesis.controller import Controller
from simgap.synthesis.ellipsoid_controller import EllipsoidController
from simgap.synthesis.interval_map import IntervalMap
from simgap.synthesis.spec import Box, Spec
from simgap.system_file import load_system_file

# an inverted pendulum whose destabilizing term hardens (th + 10 th^3): over |th| <= 1 the
# linearization misses most of it, so a proof without the nonlinear remainder claims too much
CUBIC = """
format = "simgap-system"
name = "cubicpend"
states = ["th", "w"]
inputs = ["u"]
x_lo = [-1.0, -2.0]
x_hi = [1.0, 2.0]
tau = 0.1
input_grid = {lo = [-4.0], hi = [4.0], counts = [9]}
[params]
a = 1.0
k = 10.0
[dynamics]
kind = "continuous"
substeps = 2
th = "w"
w = "a*th + k*th^3 - 0.2*w + u"
"""

# x+ = A x + B u with known A, B (states of very different widths: finite differences must
# divide each column by its own step)
LINEAR = """
format = "simgap-system"
name = "lin3"
states = ["a", "b", "c"]
inputs = ["u"]
x_lo = [-1.0, -10.0, -0.1]
x_hi = [1.0, 10.0, 0.1]
tau = 0.1
input_grid = {lo = [-1.0], hi = [1.0], counts = [5]}
[dynamics]
kind = "discrete"
a = "1.1*a + 0.02*b + 3*c"
b = "0.5*a + 0.9*b + u"
c = "-0.01*a + 0.001*b + 0.8*c + 0.05*u"
"""

# an unstable mode (x1+ = 1.2 x1) that the input cannot reach
UNCONTROLLABLE = LINEAR.replace('a = "1.1*a + 0.02*b + 3*c"', 'a = "1.2*a"').replace('name = "lin3"', 'name = "unc"')


@pytest.fixture
def cubic(tmp_path):
    (tmp_path / "cubic.toml").write_text(CUBIC)
    return load_system_file(tmp_path / "cubic.toml")


def _spec(s):
    return Spec(kind="invariance", safe=Box(s.x_lo, s.x_hi))


def worst_level(ctrl, system, w, n_points=400, seed=0) -> float:
    """max over fresh points of E (half on its boundary) and every vertex of the box [-w, w] of
    the level (x+ - x*)^T P (x+ - x*), x+ = f(x, u(x)) + w; > 1 means a point left E.
    Also asserts E inside X and u(E) inside the system's input range."""
    rng = np.random.default_rng(seed)
    n = system.n
    L = np.linalg.cholesky(ctrl.P)
    z = rng.normal(size=(n_points, n))
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    z[n_points // 2:] *= rng.random((n_points - n_points // 2, 1)) ** (1 / n)
    x = ctrl.x_star + np.linalg.solve(L.T, z.T).T          # e^T P e = |z|^2
    assert ctrl.winning(x * (1 - 1e-12) + ctrl.x_star * 1e-12).all()
    assert np.all(x >= system.x_lo) and np.all(x <= system.x_hi)
    u = ctrl.input(x * (1 - 1e-12) + ctrl.x_star * 1e-12)
    U = system.inputs
    assert np.all(u >= U.min(axis=0) - 1e-12) and np.all(u <= U.max(axis=0) + 1e-12)
    xp = system.f(x, u)
    worst = 0.0
    for signs in itertools.product((-1.0, 1.0), repeat=n):
        worst = max(worst, float(ctrl.level(xp + np.asarray(signs) * w).max()))
    return worst


def test_linearization_divides_each_column_by_its_own_step(tmp_path):
    (tmp_path / "lin.toml").write_text(LINEAR)
    s = load_system_file(tmp_path / "lin.toml")
    A, B = iv.linearize(s, np.zeros(3), np.zeros(1))
    assert np.allclose(A, [[1.1, 0.02, 3], [0.5, 0.9, 0], [-0.01, 0.001, 0.8]], atol=1e-7)
    assert np.allclose(B, [[0], [1], [0.05]], atol=1e-7)


def test_interval_jacobian_encloses_the_closed_loop(cubic):
    K = np.array([[-4.0, -3.0]])
    lo, hi = np.array([-0.6, -1.0]), np.array([0.4, 1.5])
    ulo, uhi = np.array([-8.0]), np.array([7.0])
    flo, fhi, Jc, Jr = IntervalMap(cubic).closed_loop(lo[None], hi[None], ulo[None], uhi[None], K)
    rng = np.random.default_rng(3)
    x = lo + rng.random((300, 2)) * (hi - lo)
    g = lambda x: cubic.f(x, x @ K.T)
    for j in range(2):
        e = np.zeros(2)
        e[j] = 1e-6
        d = (g(x + e) - g(x - e)) / 2e-6
        assert np.all(np.abs(d - Jc[0][:, j]) <= Jr[0][:, j] + 1e-6)
    y = g(x)
    assert np.all((y >= flo[0]) & (y <= fhi[0]))
    assert np.all(Jr[0] < 1.0)   # and not vacuous


def test_proved_set_holds_fresh_points_and_worst_case_gap(cubic, tmp_path):
    gap = np.array([0.002, 0.008])
    res = iv.synthesize_invariant_set(cubic, _spec(cubic), gap=gap)
    assert not res.empty, res.stats.get("diagnosis")
    ctrl = res.controller
    v = res.verification
    assert v.ok and v.total <= 1 and v.gap_scale >= 1
    assert np.allclose(v.w_max, gap)
    assert worst_level(ctrl, cubic, gap) <= 1.0
    # the margin is a margin: gap_scale x the gap still holds on fresh points
    assert worst_level(ctrl, cubic, gap * v.gap_scale * 0.999, seed=1) <= 1.0
    # the file round trip keeps the set and the query interface
    path = ctrl.save(tmp_path / "c.npz")
    back = Controller.load(path)
    assert isinstance(back, EllipsoidController)
    assert np.array_equal(back.P, ctrl.P) and np.array_equal(back.K, ctrl.K)
    assert back.meta["margins"]["gap_scale"] == pytest.approx(v.gap_scale)
    assert res.stats["gap_scale"] == pytest.approx(v.gap_scale)
    assert back.system is not None and back.system.name == "cubicpend"


def test_nominal_set_without_gap(cubic):
    res = iv.synthesize_invariant_set(cubic, _spec(cubic))
    assert not res.empty
    assert np.isinf(res.verification.gap_scale)
    assert worst_level(res.controller, cubic, np.zeros(2)) <= 1.0


def _linear_only(monkeypatch):
    """Mutation: the closed loop's Jacobian is its value at x* (no nonlinear remainder, R = 0)."""
    def closed_loop(self, x_lo, x_hi, u_lo, u_hi, K):
        xs = 0.5 * (x_lo + x_hi)[0]
        us = 0.5 * (u_lo + u_hi)[0]
        A, B = iv.linearize(self.system, xs, us)
        J = np.broadcast_to(A + B @ K, (x_lo.shape[0],) + A.shape)
        return x_lo, x_hi, J.copy(), np.zeros_like(J)
    monkeypatch.setattr(IntervalMap, "closed_loop", closed_loop)


def test_mutation_without_nonlinear_remainder_is_caught(cubic, monkeypatch):
    real = iv.synthesize_invariant_set(cubic, _spec(cubic))
    _linear_only(monkeypatch)
    bad = iv.synthesize_invariant_set(cubic, _spec(cubic))
    assert not bad.empty
    # the mutated proof claims a larger set than the real one, and points leave it
    assert bad.stats["volume"] > real.stats["volume"]
    assert worst_level(bad.controller, cubic, np.zeros(2)) > 1.0


def test_mutation_without_gap_is_caught(cubic, monkeypatch):
    gap = np.array([0.01, 0.04])
    real = iv.synthesize_invariant_set(cubic, _spec(cubic), gap=gap)
    assert real.empty                                  # honest: no set for this gap
    d = real.stats["diagnosis"]
    assert "gamma would have to be at most" in d and "gamma_w <=" in d
    assert "levers: the input range" in d and "X and the safe set" in d and "plan_input_weight" not in d
    s = real.verification.gap_scale
    assert 0 < s < 1
    monkeypatch.setattr(iv, "gap_bound", lambda gap, n, *a: (np.zeros(n), "mutated: no gap"))
    bad = iv.synthesize_invariant_set(cubic, _spec(cubic), gap=gap)
    assert not bad.empty
    assert worst_level(bad.controller, cubic, gap) > 1.0


def test_verification_refuses_a_set_outside_the_safe_box_or_input_range(cubic):
    res = iv.synthesize_invariant_set(cubic, _spec(cubic))
    c = res.controller
    lo, hi = cubic.x_lo, cubic.x_hi
    big = iv.verify_invariant(cubic, c.x_star, c.u_star, c.K, c.P / 100, lo, hi, [-4.0], [4.0])
    failed = {f["name"] for f in big.failed()}
    assert not big.ok and "E inside the safe set" in failed
    narrow = iv.verify_invariant(cubic, c.x_star, c.u_star, c.K, c.P, lo, hi, [-0.01], [0.01])
    assert not narrow.ok and "u(E) inside the input range" in {f["name"] for f in narrow.failed()}


# ----- bad input ------------------------------------------------------------------------

def test_equilibrium_outside_the_safe_set(cubic):
    with pytest.raises(SimgapError, match="outside the safe set"):
        iv.synthesize_invariant_set(cubic, _spec(cubic), x_star=[1.5, 0.0], u_star=[0.0])


def test_not_an_equilibrium_prints_the_residual(cubic):
    with pytest.raises(SimgapError, match=r"not an equilibrium.*residual"):
        iv.synthesize_invariant_set(cubic, _spec(cubic), x_star=[0.0, 0.0], u_star=[1.0])


def test_given_equilibrium_off_centre(cubic):
    # th = 0.2 is an equilibrium with u* = -(0.2 + 10 * 0.008)
    res = iv.synthesize_invariant_set(cubic, _spec(cubic), x_star=[0.2, 0.0], u_star=[-0.28])
    assert not res.empty
    assert worst_level(res.controller, cubic, np.zeros(2)) <= 1.0


def test_K_of_the_wrong_shape(cubic):
    with pytest.raises(SimgapError, match=r"K must have shape 1 x 2"):
        iv.synthesize_invariant_set(cubic, _spec(cubic), K=[[1.0, 2.0, 3.0]])
    with pytest.raises(SimgapError, match="does not stabilize"):
        iv.synthesize_invariant_set(cubic, _spec(cubic), K=[[1.0, 1.0]])


def test_not_stabilizable(tmp_path):
    (tmp_path / "u.toml").write_text(UNCONTROLLABLE)
    s = load_system_file(tmp_path / "u.toml")
    with pytest.raises(SimgapError, match="not stabilizable.*1.2"):
        iv.synthesize_invariant_set(s, _spec(s))


def test_solver_missing_or_failing(cubic, monkeypatch):
    with pytest.raises(SimgapError, match="solver must be one of"):
        iv.synthesize_invariant_set(cubic, _spec(cubic), solver="MOSEK")
    import cvxpy as cp
    monkeypatch.setattr(cp, "installed_solvers", lambda: ["OSQP"])
    with pytest.raises(SimgapError, match="CLARABEL is not installed"):
        iv.synthesize_invariant_set(cubic, _spec(cubic))
    monkeypatch.undo()
    monkeypatch.setattr(iv, "design_ellipsoid", lambda *a, **k: (None, "infeasible_inaccurate"))
    with pytest.raises(SimgapError, match="found no ellipsoid.*infeasible_inaccurate"):
        iv.synthesize_invariant_set(cubic, _spec(cubic))


def test_spec_other_than_invariance(cubic):
    spec = Spec(kind="reach_avoid", target=Box([0.5, -1], [0.9, 1]))
    with pytest.raises(SimgapError, match="invariance specifications only"):
        iv.synthesize_invariant_set(cubic, spec)


def test_builtin_system_without_formulas_is_refused():
    from simgap.system_ref import resolve_system
    s = resolve_system("pendulum")
    with pytest.raises(SimgapError, match="not a system file"):
        iv.synthesize_invariant_set(s, Spec(kind="invariance", safe=Box(s.x_lo, s.x_hi)))


# ----- the controller in the rest of simgap ----------------------------------------------

def test_cli_synthesize_then_rollout(tmp_path, capsys):
    import json

    from simgap.cli import main
    (tmp_path / "cubic.toml").write_text(CUBIC)
    sysf, ctrl = str(tmp_path / "cubic.toml"), str(tmp_path / "c.npz")
    rc = main(["synthesize", "--method", "invariant_set", "--system", sysf, "--no-gap",
               "--safe", "-1,1,-2,2", "--x0", "0.05,0", "--out", ctrl])
    out = capsys.readouterr().out
    assert rc == 0 and "contraction" in out and "wrote" in out
    sim = json.dumps({"kind": "numpy", "system": sysf, "noise": {"actuation_std": 0.05}})
    rc = main(["rollout", "--controller", ctrl, "--simulator", sim, "--n", "50", "--horizon", "60",
               "--out", str(tmp_path / "r.json"), "--mean-map-runs", "20"])
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rc == 0 and rep["n_rollouts"] == 50
    assert rep["left_domain"] == 0 and rep["failures"] == 0 and rep["mean_map"]["satisfied"]
    # a gap too large: exit 1, the reason printed, nothing written
    rc = main(["synthesize", "--method", "invariant_set", "--system", sysf, "--gamma", "0.05,0.2",
               "--safe", "-1,1,-2,2", "--out", str(tmp_path / "none.npz")])
    out = capsys.readouterr().out
    assert rc == 1 and "gamma would have to be at most" in out and not (tmp_path / "none.npz").exists()
    # reach-avoid: refused with a message
    spec = tmp_path / "ra.json"
    spec.write_text(json.dumps(Spec(kind="reach_avoid", target=Box([0.5, -1], [0.9, 1])).to_dict()))
    rc = main(["synthesize", "--method", "invariant_set", "--system", sysf, "--no-gap", "--spec", str(spec),
               "--out", str(tmp_path / "ra.npz")])
    assert rc == 2 and "invariance" in capsys.readouterr().err and not (tmp_path / "ra.npz").exists()


def test_edited_controller_file_is_refused(cubic, tmp_path):
    res = iv.synthesize_invariant_set(cubic, _spec(cubic))
    path = res.controller.save(tmp_path / "c.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["K"] = arrays["K"] * 1.5   # a stronger gain than the proof was made for
    np.savez(tmp_path / "edited.npz", **arrays)
    with pytest.raises(SimgapError, match="modified after it was written"):
        Controller.load(tmp_path / "edited.npz")


def test_gap_from_gamma_sup_or_labelled_fallback():
    calls = []

    class Continuous:                       # a certificate made for continuous inputs
        continuous = True
        inputs = np.array([[-1.0], [0.0], [1.0]])

        def gamma_upper_box(self, lo, hi, u):
            raise AssertionError("a continuous-input certificate is read with gamma_sup")

        def gamma_sup(self, x_lo, x_hi, u_lo, u_hi):
            calls.append((x_lo, x_hi, u_lo, u_hi))
            return np.abs(x_hi) + u_hi

    w, how = iv.gap_bound(Continuous(), 2, [-0.1, -0.2], [0.1, 0.2], [-0.3], [0.4])
    assert np.allclose(w, [0.5, 0.6]) and "gamma_sup" in how
    assert np.allclose(calls[0][0], [-0.1, -0.2]) and np.allclose(calls[0][3], [0.4])

    class GridOnly:                          # certified at its grid inputs only
        continuous = False
        inputs = np.array([[-1.0], [0.0], [1.0], [2.0]])

        def gamma_upper_box(self, lo, hi, u):
            return np.repeat(np.abs(u), 2, axis=1) + 0.0 * lo

    w, how = iv.gap_bound(GridOnly(), 2, [-0.1, -0.2], [0.1, 0.2], [-0.3], [0.4])
    # the grid values bracketing [-0.3, 0.4] are -1 .. 1: max |u| = 1 (2 is not used)
    assert np.allclose(w, [1.0, 1.0]) and "NOT covered" in how


# ----- simgap run with method = "invariant_set" ------------------------------------------

EXPERIMENT = """
system = "cubic.toml"
[simulator]
kind = "numpy"
noise = { actuation_std = 0.01 }
[collect]
epsilon = 0.2
n_runs = 8
seed = 1
executor = "serial"
[certify]
degree = 1
[audit]
points = 20
runs = 20
[synthesis]
spec = "invariance"
method = "invariant_set"
set_states = 2
[rollout]
n = 20
horizon = 30
x0 = [0.01, 0.0]
[profiles.small.collect]
n_runs = 8
"""


def test_run_experiment_with_invariant_sets(tmp_path):
    from simgap.config import load_experiment
    from simgap.pipeline import comparison_table, run_experiment
    from simgap_viz.results import load_run
    (tmp_path / "cubic.toml").write_text(CUBIC)
    (tmp_path / "exp.toml").write_text(EXPERIMENT)
    exp = load_experiment(tmp_path / "exp.toml", "small")
    out = tmp_path / "run"
    summary = run_experiment(exp, out, log=lambda m: None)
    nominal = summary["methods"]["nominal"]
    assert nominal["winning_cells"] == 1 and (out / "controller_nominal.npz").is_file()
    assert nominal["failures"] == 0 and nominal["n_rollouts"] == 20
    assert nominal["rollouts_in_set"]["states"] == 2 and nominal["rollouts_in_set"]["n_rollouts"] == 40
    for m in ("deterministic", "stochastic"):
        e = summary["methods"][m]
        # a controller file exactly when a set was proved; otherwise the reason
        assert (out / f"controller_{m}.npz").is_file() == bool(e["winning_cells"])
        if not e["winning_cells"]:
            assert "gamma would have to be at most" in e["rollouts"]["skipped"]
    table = comparison_table(summary)
    assert "yes: E invariant" in table and "nominal" in table and "single runs failing from states in E" in table
    run = load_run(out)                      # no grid controller; the proved sets and the nominal model's
    assert set(run.methods) == {"deterministic", "stochastic"}
    assert all(mr.synthesis is None for mr in run.methods.values())
    for m, mr in run.methods.items():
        assert (mr.invariant_set is not None) == bool(summary["methods"][m]["winning_cells"])
    assert run.nominal is not None and run.nominal.rollouts.n_rollouts == 20
    assert np.allclose(run.nominal.invariant_set.P, Controller.load(out / "controller_nominal.npz").P)
    from simgap_viz.figures import plot_run
    written = {p.name for p in plot_run(out, tmp_path / "fig")}
    assert {"invariant_sets.png", "invariant_sets.pdf"} <= written   # E drawn by `simgap plot`
    # the GUI: the nominal model's set with its rollouts; the layer draws E's projection on the map's
    # two states (the engine's outline: half-widths sqrt((P^-1)_ii), not a slice's 1 / sqrt(P_ii))
    from simgap_viz.app import SimgapApp
    app = SimgapApp(port=0, executor="serial")
    try:
        app.load_run(run, "nominal")
        assert app.results["rollout"] is run.nominal.rollouts and app.rollout_drawn["total"] == 20
        assert not app.settings.use_gap
        drawn = {(m, role): hw for m, role, _label, _c, hw in app.invariant_drawn}
        E = run.nominal.invariant_set
        want = np.sqrt(np.diag(np.linalg.inv(E.P)))[:2]
        assert drawn["nominal", "ellipsoid"] == pytest.approx(want, rel=1e-3)
        legend = app.panels["view"].legend.content
        assert "invariant ellipsoid E" in legend and "tube" not in legend  # the method's own words
        app.set_layer_visible("invariant", False)
        assert app.invariant_drawn == []
        app.panels["system"].run_method.value = "stochastic"   # back to a method's own results
        assert app.run_method == "stochastic"
    finally:
        app.stop()


def test_run_checks_before_any_work(tmp_path):
    from simgap.config import load_experiment
    from simgap.pipeline import run_experiment
    (tmp_path / "cubic.toml").write_text(CUBIC)
    (tmp_path / "exp.toml").write_text(EXPERIMENT.replace('set_states = 2', 'set_states = 2\nK = [[1.0, 2.0, 3.0]]'))
    exp = load_experiment(tmp_path / "exp.toml", "small")
    with pytest.raises(SimgapError, match="K must have shape 1 x 2"):
        run_experiment(exp, tmp_path / "run", log=lambda m: None)
    assert not (tmp_path / "run").exists()   # nothing written
    (tmp_path / "exp2.toml").write_text(EXPERIMENT.replace('set_states = 2', 'set_states = 2\nhold = 2'))
    with pytest.raises(SimgapError, match="hold must be 1"):
        run_experiment(load_experiment(tmp_path / "exp2.toml", "small"), tmp_path / "run2", log=lambda m: None)
    assert not (tmp_path / "run2").exists()

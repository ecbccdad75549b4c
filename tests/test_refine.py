"""Refinement loop: residuals, effect library, sparse selection, refined systems, bad input."""

import json

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.refine.data import load_transitions, make_transitions
from simgap.refine.effects import (candidate_effects, integrator_pairs, library_candidates, user_effect,
                                   velocity_dims)
from simgap.refine.refined import load_system, refined_system, save_refined
from simgap.refine.report import refine
from simgap.refine.residual import residuals
from simgap.refine.selection import SelectionOptions
from simgap.simulators.base import make_simulator
from simgap.systems import get_system


def sample(sysname, K, seed, sim_config=None, extra=None, process_std=1e-4):
    """K independent transitions from uniform states in X and random inputs from U."""
    s = get_system(sysname)
    rng = np.random.default_rng(seed)
    x = s.x_lo + rng.random((K, s.n)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, len(s.inputs), K)]
    cfg = sim_config or {"kind": "numpy", "system": sysname, "noise": {"process_std": process_std}}
    with make_simulator(cfg) as sim:
        xn = sim.step(x, u, rng)
    if extra is not None:
        xn = xn + s.tau * extra(x, u)
    return make_transitions(x, u, xn, s.tau, system=s)


def effect_keys(rep):
    return sorted((e["name"], e["state_name"]) for e in rep["effects"])


# ----- undeclared effects are found ---------------------------------------------------------

def test_pendulum_numpy_damping_found_and_noise_floor_reached():
    d = 0.5
    data = sample("pendulum", 20000, 1, {"kind": "numpy", "system": "pendulum",
                                         "noise": {"process_std": 1e-4},
                                         "effects": {"linear": [[0, 0], [0, -d]]}})
    res = refine("pendulum", data)
    rep = res.report
    assert effect_keys(rep) == [("viscous_friction", "omega")]
    e = rep["effects"][0]
    assert e["variable"] == "omega" and e["state"] == 1
    # x2+ = x2 + tau (... - d x2): coefficient -d, within 2 % (and within 4 bootstrap stderr)
    assert abs(e["coefficient"] + d) < 0.02 * d
    assert abs(e["coefficient"] + d) < 4 * e["stderr"] + 1e-3
    assert e["explained_fraction"] > 0.9
    # held-out RMS falls to the noise floor (process_std = 1e-4)
    assert rep["rms_before"][1] > 5e-4
    assert rep["rms_after"][1] < 1.05e-4
    assert rep["unexplained"] is False


def test_pendulum_pybullet_joint_damping_found():
    c = 0.05  # N m s / rad, not declared by the nominal model
    cfg = {"kind": "pybullet_pendulum", "system": "pendulum", "noise": {"sensor_std": [1e-5, 1e-4]},
           "effects": {"joint_damping": c}}
    data = sample("pendulum", 20000, 3, cfg)
    rep = refine("pendulum", data).report
    keys = effect_keys(rep)
    assert ("viscous_friction", "omega") in keys
    # Bullet's semi-implicit Euler puts tau^2 theta'' into theta+: the library's integration term
    assert set(keys) <= {("viscous_friction", "omega"), ("integration", "theta")}
    visc = next(e for e in rep["effects"] if e["name"] == "viscous_friction")
    # physical units: torque per angular velocity, within 3 % of the planted damping
    assert visc["physical"]["value"] == pytest.approx(-c, rel=0.03)
    integ = [e for e in rep["effects"] if e["name"] == "integration"]
    if integ:
        assert integ[0]["coefficient"] == pytest.approx(0.005, rel=0.02)  # = tau for semi-implicit Euler
    # the sensor noise on omega (1e-4) is the floor
    assert rep["rms_before"][1] > 2e-4
    assert rep["rms_after"][1] < 1.1e-4
    assert rep["unexplained"] is False


def test_turtlebot_actuator_gain_found():
    g = 0.8
    data = sample("turtlebot", 20000, 2, {"kind": "numpy", "system": "turtlebot",
                                          "noise": {"process_std": 1e-4}, "effects": {"input_gain": g}})
    rep = refine("turtlebot", data).report
    assert effect_keys(rep) == [("input_gain", "theta"), ("input_gain", "x"), ("input_gain", "y")]
    for e in rep["effects"]:
        assert e["coefficient"] == pytest.approx(g - 1, abs=0.005)
        assert e["input"] == ("omega" if e["state_name"] == "theta" else "v")
        assert e["physical"]["value"] == pytest.approx(g, abs=0.005)
    assert max(rep["rms_after"]) < 1.05e-4
    assert min(rb / ra for rb, ra in zip(rep["rms_before"], rep["rms_after"])) > 5


def test_turtlebot_pybullet_actuator_gain_found():
    k = 0.85  # the robot drives 15 % slower than commanded; the unicycle model does not know
    cfg = {"kind": "pybullet_turtlebot", "system": "turtlebot", "noise": {"sensor_std": 1e-4},
           "effects": {"actuator_gain": [k, 1.0]}}
    rep = refine("turtlebot", sample("turtlebot", 3000, 3, cfg)).report
    gains = {e["state_name"]: e for e in rep["effects"] if e["name"] == "input_gain"}
    for st in ("x", "y"):
        assert gains[st]["input"] == "v"
        assert gains[st]["physical"]["value"] == pytest.approx(k, abs=0.01)
        i = ("x", "y").index(st)
        assert rep["rms_before"][i] / rep["rms_after"][i] > 5
        assert rep["rms_after"][i] < 1.2e-4          # sensor noise 1e-4 is the floor
    # nothing planted on the heading: whatever is found there is small (Bullet's own turn-rate response)
    for e in rep["effects"]:
        if e["state_name"] == "theta":
            assert abs(e["coefficient"]) < 0.05


def test_user_term_outside_library_is_found_when_named():
    extra = lambda x, u: np.stack([0.3 * np.sin(3 * x[:, 1]), 0 * x[:, 1], 0 * x[:, 1]], axis=1)
    data = sample("turtlebot", 15000, 5, extra=extra)
    s = get_system("turtlebot")
    rep = refine(s, data, user_terms=[user_effect(s, "terrain", "x", "sin(3*y)")]).report
    assert effect_keys(rep) == [("terrain", "x")]
    assert rep["effects"][0]["coefficient"] == pytest.approx(0.3, abs=0.01)
    assert rep["unexplained"] is False


# ----- no false discoveries, unexplained residuals are flagged --------------------------------

@pytest.mark.parametrize("sysname", ["pendulum", "turtlebot"])
def test_pure_noise_reports_no_effect(sysname):
    for seed in range(8):
        data = sample(sysname, 4000, 100 + seed, process_std=1e-3)
        rep = refine(sysname, data, options=SelectionOptions(seed=seed, n_boot=20)).report
        assert rep["effects"] == [], (seed, rep["effects"])
        assert rep["unexplained"] is False
        assert rep["rms_after"] == rep["rms_before"]


def test_effect_outside_library_is_flagged_unexplained():
    # a position-dependent push on x (terrain), not in the library
    extra = lambda x, u: np.stack([0.3 * np.sin(3 * x[:, 1]), 0 * x[:, 1], 0 * x[:, 1]], axis=1)
    data = sample("turtlebot", 15000, 6, extra=extra)
    rep = refine("turtlebot", data).report
    assert rep["unexplained"] is True
    st = {s["state_name"]: s for s in rep["states"]}
    assert st["x"]["unexplained"] and not st["y"]["unexplained"] and not st["theta"]["unexplained"]
    assert st["x"]["remaining_fraction"] > 0.5          # most of it is left ...
    assert st["x"]["structure_r2"] > 0.5                # ... and it is structure, not noise


# ----- effect library ---------------------------------------------------------------------------

def test_library_terms_as_they_enter_the_model():
    s = get_system("turtlebot")
    keys = {e.key(s): e for e in candidate_effects(s)}
    assert velocity_dims(s) == () and velocity_dims(get_system("pendulum")) == (1,)
    assert integrator_pairs(get_system("emps")) == [(0, 1)]
    x = np.array([[1.0, 2.0, 0.3]])
    u = np.array([[0.5, -0.7]])
    assert keys["input_gain:x:v"](x, u)[0] == pytest.approx(0.5 * np.cos(0.3), rel=1e-6)
    assert keys["input_gain:y:v"](x, u)[0] == pytest.approx(0.5 * np.sin(0.3), rel=1e-6)
    assert keys["input_gain:theta:omega"](x, u)[0] == pytest.approx(-0.7, rel=1e-6)
    assert "input_gain:x:omega" not in keys          # omega does not enter x's update
    p = get_system("pendulum")
    pk = {e.key(p): e for e in candidate_effects(p)}
    xp = np.array([[0.1, -0.3]])
    assert pk["gravity:omega"](xp, np.zeros((1, 1)))[0] == pytest.approx(-14.715 * np.sin(0.1), rel=1e-6)
    assert pk["coulomb_friction:omega:omega"](xp, np.zeros((1, 1)))[0] == -1.0
    assert pk["drag:omega:omega"](xp, np.zeros((1, 1)))[0] == pytest.approx(-0.09)
    assert pk["deadband:omega:torque"](xp, np.array([[0.4]]))[0] == pytest.approx(3.0, rel=1e-6)
    # the EMPS double integrator has no gravity term
    assert not any(e.name == "gravity" for e in library_candidates(get_system("emps")))


def test_unknown_effect_and_bad_user_terms():
    s = get_system("pendulum")
    with pytest.raises(SimgapError, match="unknown effect name"):
        candidate_effects(s, ["bias", "stiction"])
    with pytest.raises(SimgapError, match="not allowed"):
        user_effect(s, "t1", "omega", "__import__('os')")
    with pytest.raises(SimgapError, match="unknown state"):
        user_effect(s, "t1", "phi", "sin(theta)")
    with pytest.raises(SimgapError, match="clashes"):
        user_effect(s, "bias", "omega", "theta")


# ----- refined system ---------------------------------------------------------------------------

def test_refined_system_save_load_and_use(tmp_path):
    data = sample("pendulum", 8000, 7, {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 1e-4},
                                        "effects": {"linear": [[0, 0], [0, -0.5]], "bias": [0, 0.2]}})
    res = refine("pendulum", data)
    assert effect_keys(res.report) == [("bias", "omega"), ("viscous_friction", "omega")]
    ref = res.refined
    path = save_refined(ref, tmp_path / "ref.json")
    loaded = load_system(str(path))
    x, u = data.x[:100], data.u[:100]
    np.testing.assert_allclose(loaded.f(x, u), ref.f(x, u), rtol=0, atol=1e-15)
    # f' = f + tau * sum c g exactly
    c = {e["name"]: e["coefficient"] for e in res.report["effects"]}
    expect = get_system("pendulum").f(x, u)
    expect[:, 1] += 0.005 * (c["bias"] + c["viscous_friction"] * x[:, 1])
    np.testing.assert_allclose(ref.f(x, u), expect, atol=1e-14)
    # the residual of f' on held-out data is what the report says
    r_after = residuals(loaded, data).r[res.heldout]
    np.testing.assert_allclose(np.sqrt(np.mean(r_after ** 2, axis=0)), res.report["rms_after"], rtol=1e-9)
    # a first-class system: Lipschitz bound, steps, a simulator built on it
    L = loaded.lipschitz_f()
    assert L is not None and np.all(np.isfinite(L))
    assert loaded.with_steps(3).f(x, u).shape == (100, 2)
    with make_simulator({"kind": "numpy", "system": "pendulum"}, system=loaded) as sim:
        np.testing.assert_allclose(sim.mean_next(x, u), ref.f(x, u), atol=1e-15)
    assert loaded.params["base_system"] == "pendulum"
    assert json.loads(path.read_text())["base"] == "pendulum"
    # refining the refined model finds nothing more
    again = refine(str(path), data).report
    assert again["effects"] == []
    assert load_system("turtlebot").name == "turtlebot"
    with pytest.raises(SimgapError, match="unknown system"):
        load_system("no_such_system.json")


def test_refined_with_coulomb_has_no_lipschitz_bound():
    s = get_system("pendulum")
    e = [x for x in candidate_effects(s, ["coulomb_friction"])]
    ref = refined_system(s, e, [-0.1])
    assert ref.jacobian_bound is None
    x = np.array([[0.0, 0.2], [0.0, -0.2]])
    np.testing.assert_allclose(ref.f(x, np.zeros((2, 1)))[:, 1] - s.f(x, np.zeros((2, 1)))[:, 1],
                               [-0.0005, 0.0005], atol=1e-15)


def test_residuals_views():
    data = sample("pendulum", 2000, 8)
    r = residuals(get_system("pendulum"), data)
    v, rr = r.against("omega")
    np.testing.assert_array_equal(v, data.x[:, 1])
    assert rr.shape == (2000, 2)
    np.testing.assert_array_equal(r.against("u1")[0], data.u[:, 0])
    b = r.binned("theta", bins=10)
    assert b["mean"].shape == (10, 2) and b["count"].sum() == 2000
    st = r.stats()
    assert set(st) == {"theta", "omega"} and st["omega"]["rms"] > 0
    with pytest.raises(SimgapError, match="unknown variable"):
        r.against("speed")


def test_angle_residuals_are_wrapped():
    s = get_system("turtlebot")
    x = np.array([[1.0, 1.0, np.pi - 0.001]] * 3)
    u = np.array([[0.0, 1.0]] * 3)
    f = s.f(x, u)                        # heading crosses +pi and wraps to about -pi
    data = make_transitions(x, u, f + np.array([0, 0, 0.002]), s.tau, system=s)
    np.testing.assert_allclose(residuals(s, data).r[:, 2], 0.002, atol=1e-12)


# ----- data sources and bad input ---------------------------------------------------------------

def test_collected_dataset_is_accepted(tmp_path):
    from simgap.dataset import Dataset
    s = get_system("pendulum")
    rng = np.random.default_rng(9)
    xr = s.x_lo + rng.random((300, 2)) * (s.x_hi - s.x_lo)
    X = np.repeat(xr, len(s.inputs), axis=0)
    U = np.tile(s.inputs, (300, 1))
    N = 50
    with make_simulator({"kind": "numpy", "system": "pendulum", "noise": {"process_std": 1e-3},
                         "effects": {"linear": [[0, 0], [0, -0.5]]}}) as sim:
        runs = np.stack([sim.step(X, U, rng) for _ in range(N)])
    ds = Dataset(system=s, x=X, u=U, f_nom=s.f(X, U), mean=runs.mean(0), var=runs.var(0, ddof=1),
                 lo=runs.min(0), hi=runs.max(0), cover_index=np.repeat(np.arange(300), 21),
                 input_index=np.tile(np.arange(21), 300), n_runs=N, epsilon=0.01, manifest={"hash": "x"})
    path = ds.save_npz(tmp_path / "ds.npz")
    tr = load_transitions(path)
    np.testing.assert_array_equal(tr.x_next, ds.mean)
    rep = refine("pendulum", tr).report
    assert effect_keys(rep) == [("viscous_friction", "omega")]
    assert rep["effects"][0]["coefficient"] == pytest.approx(-0.5, abs=0.02)
    # a data set collected at steps = 2 keeps its own tau even when the plain system is named
    import dataclasses
    s2 = s.with_steps(2)
    ds2 = dataclasses.replace(ds, system=s2, f_nom=s2.f(X, U))
    tr2 = load_transitions(ds2.save_npz(tmp_path / "ds2.npz"), system=s)
    assert tr2.tau == pytest.approx(0.01)


def test_csv_and_npz_loading_and_bad_files(tmp_path):
    data = sample("pendulum", 500, 10)
    s = get_system("pendulum")
    header = "theta,omega,torque,theta_next,omega_next,tau"
    arr = np.column_stack([data.x, data.u, data.x_next, np.full(500, s.tau)])
    np.savetxt(tmp_path / "d.csv", arr, delimiter=",", header=header, comments="")
    tr = load_transitions(tmp_path / "d.csv", system=s)
    np.testing.assert_allclose(tr.x_next, data.x_next)
    np.savez(tmp_path / "missing.npz", x=data.x, u=data.u, tau=s.tau)
    with pytest.raises(SimgapError, match=r"missing arrays \['x_next'\]"):
        load_transitions(tmp_path / "missing.npz")
    np.savez(tmp_path / "shape.npz", x=data.x, u=data.u, x_next=data.x_next[:-1], tau=s.tau)
    with pytest.raises(SimgapError, match="x_next has shape"):
        load_transitions(tmp_path / "shape.npz")
    np.savez(tmp_path / "dims.npz", x=data.x[:, :1], u=data.u, x_next=data.x_next[:, :1], tau=s.tau)
    with pytest.raises(SimgapError, match="1 state columns"):
        load_transitions(tmp_path / "dims.npz", system=s)
    xn = data.x_next.copy()
    xn[[3, 7, 11], 1] = np.nan
    xn[20, 0] = np.inf
    np.savez(tmp_path / "nan.npz", x=data.x, u=data.u, x_next=xn, tau=s.tau)
    with pytest.raises(SimgapError, match="4 of 500 rows contain NaN or inf"):
        load_transitions(tmp_path / "nan.npz")
    tr = load_transitions(tmp_path / "nan.npz", drop_nonfinite=True)
    assert tr.K == 496 and tr.n_dropped == 4
    with pytest.raises(SimgapError, match="does not exist"):
        load_transitions(tmp_path / "nope.npz")
    with pytest.raises(SimgapError, match="tau must be a finite positive"):
        make_transitions(data.x, data.u, data.x_next, -1.0)


def test_too_few_samples_and_rank_deficient_design():
    data = sample("pendulum", 40, 11)
    with pytest.raises(SimgapError, match="too few samples"):
        refine("pendulum", data)
    # the input never varies: input_gain on omega is collinear with bias
    s = get_system("pendulum")
    rng = np.random.default_rng(12)
    x = s.x_lo + rng.random((3000, 2)) * (s.x_hi - s.x_lo)
    u = np.full((3000, 1), 0.5)
    data = make_transitions(x, u, s.f(x, u) + 1e-4 * rng.standard_normal((3000, 2)), s.tau, system=s)
    rep = refine("pendulum", data).report
    notes = {st["state_name"]: " ".join(st["notes"]) for st in rep["states"]}
    assert "dropped input_gain:omega:torque: collinear with bias:omega" in notes["omega"]
    assert "dropped deadband:omega:torque: collinear with bias:omega" in notes["omega"]
    assert rep["effects"] == []
    assert refine("pendulum", data, effects=["bias", "viscous_friction"]).report["effects"] == []
    with pytest.raises(SimgapError, match="not a whole multiple"):
        refine("pendulum", make_transitions(x, u, x, 0.0033, system=s))


def test_parquet_loading(tmp_path):
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq
    data = sample("pendulum", 300, 13)
    cols = {"x1": data.x[:, 0], "x2": data.x[:, 1], "u1": data.u[:, 0], "x1_next": data.x_next[:, 0],
            "x2_next": data.x_next[:, 1], "tau": np.full(300, 0.005), "t": np.arange(300) * 0.005}
    pq.write_table(pa.table(cols), tmp_path / "d.parquet")
    tr = load_transitions(tmp_path / "d.parquet", system=get_system("pendulum"))
    np.testing.assert_allclose(tr.x_next, data.x_next)
    assert tr.is_time_series


def test_time_series_holdout_is_contiguous_segments():
    from simgap.refine.selection import split_heldout
    t = np.arange(1000) * 0.001
    held = split_heldout(1000, t, SelectionOptions(holdout=0.3, n_segments=5))
    assert held.sum() == 300
    edges = np.flatnonzero(np.diff(held.astype(int)) != 0)
    assert len(edges) == 9           # 5 held-out blocks: 5 starts + 4 ends (the last block runs to the end)
    assert held[140:200].all() and not held[:140].any()


def test_refined_with_integration_and_coulomb_round_trips(tmp_path):
    s = get_system("emps")
    effs = candidate_effects(s, ["coulomb_friction", "viscous_friction", "integration"])
    keys = [e.key(s) for e in effs]
    assert keys == ["coulomb_friction:qd:qd", "viscous_friction:qd:qd", "integration:q:qd"]
    from simgap.refine.refined import build_refined
    ref = build_refined(s, "emps", effs, [-0.2, -2.2, 0.0005], [0.01, 0.1, 1e-6])
    x = np.array([[0.1, 0.05], [0.1, -0.05]])
    u = np.array([[1.0], [1.0]])
    # integration uses the refined acceleration: q+ = q + tau v + tau * 0.0005 * a'
    a = 35.15 / 95.1 * 1.0 - 0.2 * np.sign(x[:, 1]) - 2.2 * x[:, 1]
    np.testing.assert_allclose(ref.f(x, u)[:, 0], x[:, 0] + 0.001 * x[:, 1] + 0.001 * 0.0005 * a, rtol=1e-9)
    np.testing.assert_allclose(ref.f(x, u)[:, 1], x[:, 1] + 0.001 * a, rtol=1e-12)
    loaded = load_system(str(save_refined(ref, tmp_path / "e.json")))
    np.testing.assert_allclose(loaded.f(x, u), ref.f(x, u), rtol=0, atol=1e-15)
    assert loaded.jacobian_bound is None      # Coulomb friction is discontinuous


@pytest.mark.parametrize("name,extra,coef", [
    ("drag", lambda x, u: np.stack([0 * x[:, 0], -3 * x[:, 1] * np.abs(x[:, 1])], 1), -3.0),
    ("coulomb_friction", lambda x, u: np.stack([0 * x[:, 0], -0.5 * np.sign(x[:, 1])], 1), -0.5),
    ("gravity", lambda x, u: np.stack([0 * x[:, 0], -0.05 * 14.715 * np.sin(x[:, 0])], 1), 0.05),
    ("bias", lambda x, u: np.stack([0 * x[:, 0], 0.2 + 0 * x[:, 0]], 1), 0.2),
])
def test_each_velocity_effect_is_named(name, extra, coef):
    rep = refine("pendulum", sample("pendulum", 8000, 40, extra=extra)).report
    assert [(e["name"], e["state_name"]) for e in rep["effects"]] == [(name, "omega")]
    assert rep["effects"][0]["coefficient"] == pytest.approx(coef, rel=0.03)
    assert rep["rms_after"][1] < 1.05e-4

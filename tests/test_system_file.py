"""System files: a nominal model the repository does not contain (a damped Duffing oscillator),
written as TOML, taken from `simgap collect` to `simgap gui` with the command line only, and
rebuilt by every later command from what the data, certificate and controller embed (the file is
deleted after the collection)."""

import json

import numpy as np
import pytest

from simgap.certify.certificate import load as load_cert
from simgap.cli import main
from simgap.collect import load_store
from simgap.errors import SimgapError
from simgap.synthesis.controller import Controller
from simgap.runge_kutta import rk4_integrate
from simgap.system_file import load_system_file, system_from_spec
from simgap.system_ref import resolve_system, system_digest, system_ref

DUFFING = """
# a damped Duffing oscillator, unit mass:  x'' = -k x - k3 x^3 - d x' + F
format = "simgap-system"
name = "duffing"
states = ["x", "v"]
inputs = ["F"]
units = {x = "m", v = "m/s", F = "N"}
x_lo = [-1.0, -1.5]
x_hi = [1.0, 1.5]
tau = 0.1
velocities = ["v"]
input_grid = {lo = [-1.0], hi = [1.0], counts = [5]}

[params]
d = 0.3
k = 1.0
k3 = 0.5

[dynamics]
kind = "continuous"
substeps = 4
x = "v"
v = "-k*x - k3*x^3 - d*v + F"
"""

# the simulator: the same oscillator with an extra viscous damping 0.1 v the model lacks, and
# actuation noise
EXP = """
system = "duffing.toml"
[simulator]
kind = "numpy"
noise = { actuation_std = 0.01 }
effects = { linear = [[0.0, 0.0], [0.0, -0.1]] }
[collect]
epsilon = 0.04
n_runs = 30
seed = 1
executor = "serial"
"""

SIM = json.dumps({"kind": "numpy", "system": "duffing", "noise": {"actuation_std": 0.01},
                  "effects": {"linear": [[0.0, 0.0], [0.0, -0.1]]}})


def duffing_rhs(x, u, d=0.3, k=1.0, k3=0.5):
    return np.stack([x[:, 1], -k * x[:, 0] - k3 * x[:, 0] ** 3 - d * x[:, 1] + u[:, 0]], axis=1)


def test_continuous_model_is_rk4_of_its_right_hand_side(tmp_path):
    (tmp_path / "d.toml").write_text(DUFFING)
    s = load_system_file(tmp_path / "d.toml")
    assert (s.name, s.state_names, s.input_names, s.n, s.m, s.tau) == ("duffing", ("x", "v"), ("F",), 2, 1, 0.1)
    assert s.inputs[:, 0].tolist() == [-1.0, -0.5, 0.0, 0.5, 1.0]
    rng = np.random.default_rng(0)
    x = s.x_lo + rng.random((50, 2)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, 5, 50)]
    # parameters folded in, 4 substeps per base period, held over k = 3 periods
    want = rk4_integrate(duffing_rhs, rk4_integrate(duffing_rhs, rk4_integrate(duffing_rhs, x, u, 0.1, 4), u, 0.1, 4),
                         u, 0.1, 4)
    np.testing.assert_array_equal(s.with_steps(3).f(x, u), want)
    assert np.abs(s.f(x, u) - rk4_integrate(duffing_rhs, x, u, 0.1, 1)).max() > 1e-7  # substeps matter
    # the estimated Jacobian bound holds on states it was not estimated on
    J = s.jacobian_bound_f(s.inputs)
    assert s.params["_jacobian"] == "estimated" and J.shape == (5, 2, 2)
    h = 1e-6
    xs = s.x_lo + rng.random((2000, 2)) * (s.x_hi - s.x_lo)
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        for ui in range(5):
            uu = np.repeat(s.inputs[ui:ui + 1], len(xs), axis=0)
            d = np.abs(s.f(xs + e, uu) - s.f(xs - e, uu)) / (2 * h)
            assert np.all(d <= J[ui, :, j] + 1e-7), (j, ui, d.max(axis=0), J[ui, :, j])


def test_discrete_map_given_bound_and_growth_matrix(tmp_path):
    di = """
name = "double_integrator"
states = ["p", "q"]
inputs = ["a"]
x_lo = [-1, -1]
x_hi = [1, 1]
tau = 0.2
input_set = [[-1], [0], [1]]
translation_invariant = ["p"]
[params]
b = 2.0
[dynamics]
kind = "discrete"
p = "p + dt*q + 0.5*dt^2*b*a"
q = "q + dt*b*a"
[bounds]
jacobian = [[1, "dt"], [0, 1]]
"""
    (tmp_path / "di.toml").write_text(di)
    s = load_system_file(tmp_path / "di.toml")
    x, u = np.array([[0.5, -0.25]]), np.array([[1.0]])
    np.testing.assert_allclose(s.f(x, u), [[0.5 - 0.05 + 0.04, -0.25 + 0.4]])
    np.testing.assert_array_equal(s.jacobian_bound_f(u)[0], [[1, 0.2], [0, 1]])
    assert s.params["_jacobian"] == "given"
    from simgap.system_file import translation_invariant_dims
    assert translation_invariant_dims(s) == (0,)
    # a continuous model with a growth matrix L: the one-step bound is exp(L tau)
    g = DUFFING.replace("[dynamics]", "[bounds]\ngrowth = [[0, 1], [2.5, -0.3]]\n[dynamics]")
    (tmp_path / "g.toml").write_text(g)
    sg = load_system_file(tmp_path / "g.toml")
    from scipy.linalg import expm
    np.testing.assert_allclose(sg.jacobian_bound_f(sg.inputs[:1])[0], expm(np.array([[0, 1], [2.5, -0.3]]) * 0.1))


def test_embedded_round_trip_and_digest(tmp_path):
    (tmp_path / "d.toml").write_text(DUFFING)
    s = resolve_system(str(tmp_path / "d.toml"), steps=2)
    ref = json.loads(json.dumps(system_ref(s)))  # what manifests, certificates and controllers hold
    assert ref["format"] == "simgap-system" and ref["steps"] == 2
    back = resolve_system(ref, paths=False)
    x, u = np.array([[0.3, -1.0]]), np.array([[0.5]])
    assert back.steps == 2 and np.array_equal(back.f(x, u), s.f(x, u))
    assert system_digest(back) == system_digest(s)
    # the digest is the model: another coefficient changes it, a comment or the name does not
    (tmp_path / "e.toml").write_text(DUFFING.replace("k3 = 0.5", "k3 = 0.6"))
    (tmp_path / "f.toml").write_text(("# another comment\n" + DUFFING).replace('name = "duffing"', 'name = "duff2"'))
    assert system_digest(load_system_file(tmp_path / "e.toml")) != system_digest(s)
    assert system_digest(load_system_file(tmp_path / "f.toml")) == system_digest(s)
    # a reference read from data never opens a file
    with pytest.raises(SimgapError, match="unknown system"):
        resolve_system(str(tmp_path / "d.toml"), paths=False)
    # the embedded object is checked like the file
    with pytest.raises(SimgapError, match="unknown variable 'G'"):
        system_from_spec(dict(ref, dynamics={"kind": "continuous", "x": "v", "v": "G*x"}))


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    """`simgap collect` on the Duffing experiment; then the system file is deleted."""
    d = tmp_path_factory.mktemp("duffing")
    (d / "duffing.toml").write_text(DUFFING)
    (d / "exp.toml").write_text(EXP)
    assert main(["collect", str(d / "exp.toml"), "--profile", "base", "--out", str(d / "store"), "--no-progress"]) == 0
    digest = system_digest(load_system_file(d / "duffing.toml"))
    (d / "duffing.toml").unlink()
    return d, digest


def test_collect_to_gui_with_the_command_line_only(collected, tmp_path, capsys):
    d, digest = collected
    store = d / "store"
    ds = load_store(store)
    assert ds.system.name == "duffing" and system_digest(ds.system) == digest
    # the simulator ran the file's dynamics plus the planted damping: the gap is tau * 0.1 |v| + noise
    assert 0.01 < np.abs(ds.mean - ds.f_nom)[:, 1].max() < 0.02
    cert = tmp_path / "cert.json"
    assert main(["certify", str(store), "--degree", "1", "--out", str(cert)]) == 0
    c = load_cert(cert)
    assert c.system_name == "duffing" and c.system_digest == digest and c.system_ref["format"] == "simgap-system"
    # with L_f from the Jacobian bound (state mode), a file without [bounds] says it is estimated
    from simgap.certify import CertifyOptions, certify
    c_state = certify(ds, CertifyOptions(degree=1, lipschitz_mode="state"))
    assert c_state.dims[0].lipschitz_how["L_f"].startswith("estimated: ")
    # synthesize with the certificate alone: the model comes from what the certificate embeds
    ctrl = tmp_path / "ctrl.npz"
    capsys.readouterr()
    assert main(["synthesize", "--cert", str(cert), "--safe=-0.8,0.8,-1.2,1.2", "--eta", "0.05,0.05",
                 "--x0", "0.1,0.1", "--out", str(ctrl)]) == 0
    out = capsys.readouterr().out
    assert "system        duffing" in out and "x0            [0.1, 0.1]: winning" in out
    loaded = Controller.load(ctrl)
    assert loaded.system.name == "duffing" and loaded.size > 0 and system_digest(loaded.system) == digest
    rep = tmp_path / "ro.json"
    assert main(["rollout", "--controller", str(ctrl), "--simulator", SIM, "--n", "50", "--horizon", "40",
                 "--mean-map-runs", "50", "--out", str(rep)]) == 0
    r = json.loads(rep.read_text())
    assert r["system"] == "duffing" and r["n_rollouts"] == 50 and r["failures"] == 0
    # the app starts on the data set (engine-side loading, then the command itself)
    from simgap_viz import engine
    from simgap_viz.experiment import app_inputs
    settings, data, _, _, _ = app_inputs(dataset=str(store))
    assert data.system.name == "duffing" and "duffing" in engine.SYSTEMS
    assert engine.system_by_name("duffing", 3).tau == pytest.approx(0.3)
    assert engine.default_spec(data.system).safe.lo.tolist() == [-1.0, -1.5]
    assert main(["gui", "--dataset", str(store), "--port", "0", "--exit-after", "0.3"]) == 0
    # a second certificate with a changed model is refused for the recorded one
    bad = dict(c.system_ref, params={"d": 0.3, "k": 1.0, "k3": 0.7})
    with pytest.raises(SimgapError, match="different model"):
        c.check_system(resolve_system(bad, paths=False))


def test_refining_a_file_system_gives_a_refined_system_on_top(collected, tmp_path, capsys):
    d, digest = collected
    store = d / "store"
    (tmp_path / "duffing.toml").write_text(DUFFING)
    refd = tmp_path / "refd.json"
    assert main(["refine", "--system", str(tmp_path / "duffing.toml"), "--data", str(store), "--quiet",
                 "--save-system", str(refd), "--out", str(tmp_path / "rep.json")]) == 0
    j = json.loads(refd.read_text())
    assert j["base"]["format"] == "simgap-system" and j["base"]["name"] == "duffing"
    eff = {e["name"]: e["coefficient"] for e in j["effects"]}
    assert eff.get("viscous_friction") == pytest.approx(-0.1, abs=0.01)  # the planted damping, on v
    (tmp_path / "duffing.toml").unlink()
    r = resolve_system(str(refd))  # needs no system file: the base is embedded
    x, u = np.array([[0.2, 1.0]]), np.array([[0.0]])
    assert r.f(x, u)[0, 1] < load_store(store).system.f(x, u)[0, 1]  # damped more
    cert = tmp_path / "c.json"
    assert main(["certify", str(store), "--system", str(refd), "--degree", "1", "--out", str(cert)]) == 0
    c = load_cert(cert)
    assert c.system_name == r.name and c.system_digest != digest
    assert c.nominal_system().name == r.name
    # f' holds the damping: its certified gap in v is smaller than the file model's
    base = tmp_path / "b.json"
    assert main(["certify", str(store), "--degree", "1", "--out", str(base)]) == 0
    assert c.dims[1].gap_max < load_cert(base).dims[1].gap_max


def test_experiment_steps_and_the_app_given_a_file(tmp_path):
    """The file's own steps hold unless the experiment sets [system] steps; `simgap gui --system
    FILE` selects the model by name (engine-side loading of simgap_viz)."""
    from simgap.config import load_experiment
    (tmp_path / "duffing.toml").write_text(DUFFING.replace("tau = 0.1", "tau = 0.1\nsteps = 3"))
    (tmp_path / "exp.toml").write_text(EXP)
    assert load_experiment(tmp_path / "exp.toml", None).system.steps == 3
    (tmp_path / "exp2.toml").write_text(EXP.replace('system = "duffing.toml"', '[system]\nname = "duffing.toml"\nsteps = 2'))
    assert load_experiment(tmp_path / "exp2.toml", None).system.steps == 2
    from simgap_viz import engine
    from simgap_viz.experiment import app_inputs
    settings, *_ = app_inputs(system=str(tmp_path / "duffing.toml"))
    assert settings.system == "duffing" and settings.simulator == "numpy"
    s = engine.make_system(settings)
    assert s.name == "duffing" and s.n == 2 and len(settings.eta) == 2
    x, u = np.array([[0.3, 0.2]]), np.array([[1.0]])
    assert np.array_equal(s.with_steps(1).f(x, u), load_system_file(tmp_path / "duffing.toml").with_steps(1).f(x, u))


def test_run_folder_reopens_without_its_system_file(tmp_path):
    """`simgap run` on a system file; `simgap gui RESULTS` after the file is gone uses the model
    the run's data embed (and a changed file is refused, not used)."""
    (tmp_path / "duffing.toml").write_text(DUFFING)
    (tmp_path / "exp.toml").write_text(EXP.replace("epsilon = 0.04", "epsilon = 0.15").replace("n_runs = 30", "n_runs = 8")
                                       + "[synthesis]\neta = [0.1, 0.1]\n[rollout]\nn = 10\nhorizon = 5\n"
                                         "x0 = [0.0, 0.0]\n[audit]\npoints = 5\nruns = 20\n")
    res = tmp_path / "res"
    assert main(["run", str(tmp_path / "exp.toml"), "--profile", "base", "--out", str(res), "--no-record"]) == 0
    (tmp_path / "duffing.toml").unlink()
    from simgap_viz.results import load_run
    run = load_run(res)
    assert run.experiment.system.name == "duffing" and set(run.methods) == {"stochastic", "deterministic"}
    assert main(["gui", str(res), "--port", "0", "--exit-after", "0.3"]) == 0
    (tmp_path / "duffing.toml").write_text(DUFFING.replace("k3 = 0.5", "k3 = 0.9"))
    with pytest.raises(SimgapError, match="different system"):
        load_run(res)


CARTPOLE = """
name = "cartpole_textbook"
states = ["x", "theta", "xd", "thetad"]
inputs = ["F"]
x_lo = [-1.0, -0.5, -2.0, -2.0]
x_hi = [1.0, 0.5, 2.0, 2.0]
tau = 0.02
angles = ["theta"]
translation_invariant = ["x"]
velocities = ["xd", "thetad"]
input_set = [[-10.0], [0.0], [10.0]]
[params]
g = 9.8
mc = 1.0
mp = 0.1
l = 0.5
[definitions]   # in an order where each uses a later one: evaluated by dependency, not by position
xacc = "temp - mp*l*thetaacc*cos(theta)/(mc + mp)"
thetaacc = "(g*sin(theta) - cos(theta)*temp) / (l*(4/3 - mp*cos(theta)^2/(mc + mp)))"
temp = "(F + mp*l*thetad^2*sin(theta))/(mc + mp)"
[dynamics]
kind = "continuous"
substeps = 2
x = "xd"
theta = "thetad"
xd = "xacc"
thetad = "thetaacc"
"""


def cartpole_rhs(z, u, g=9.8, mc=1.0, mp=0.1, l=0.5):
    th, xd, thd, F = z[:, 1], z[:, 2], z[:, 3], u[:, 0]
    temp = (F + mp * l * thd ** 2 * np.sin(th)) / (mc + mp)
    thacc = (g * np.sin(th) - np.cos(th) * temp) / (l * (4.0 / 3.0 - mp * np.cos(th) ** 2 / (mc + mp)))
    xacc = temp - mp * l * thacc * np.cos(th) / (mc + mp)
    return np.stack([xd, thd, xacc, thacc], axis=1)


def test_definitions_give_the_textbook_cartpole(tmp_path):
    (tmp_path / "cp.toml").write_text(CARTPOLE)
    s = load_system_file(tmp_path / "cp.toml")
    rng = np.random.default_rng(3)
    x = s.x_lo + rng.random((40, 4)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, 3, 40)]
    want = rk4_integrate(cartpole_rhs, x, u, 0.02, 2)
    want[:, 1] = (want[:, 1] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(s.f(x, u), want, rtol=0, atol=1e-14)
    from simgap.system_file import translation_invariant_dims
    assert translation_invariant_dims(s) == (0,) and s.params["velocity_dims"] == [2, 3]
    # embedded in JSON with sorted keys (as manifests are): the same model
    ref = json.loads(json.dumps(system_ref(s), sort_keys=True))
    assert list(ref["definitions"]) == ["temp", "thetaacc", "xacc"]
    np.testing.assert_array_equal(resolve_system(ref, paths=False).f(x, u), s.f(x, u))
    # cycles and self-reference are refused by name
    cyc = CARTPOLE.replace('temp = "(F + mp*l*thetad^2*sin(theta))/(mc + mp)"', 'temp = "xacc + F"')
    with pytest.raises(SimgapError, match=r"definitions \['temp', 'thetaacc', 'xacc'\] use each other in a cycle"):
        system_from_spec(dict(__import__("tomllib").loads(cyc), format="simgap-system"))
    selfref = CARTPOLE.replace('temp = "(F + mp*l*thetad^2*sin(theta))/(mc + mp)"', 'temp = "2*temp"')
    with pytest.raises(SimgapError, match="definition 'temp' uses itself"):
        system_from_spec(dict(__import__("tomllib").loads(selfref), format="simgap-system"))


def test_synthesize_records_the_experiments_x0_so_rollout_needs_none(collected, tmp_path, capsys):
    """An invariance experiment has no map to give x0; `simgap synthesize --spec EXP` records its
    [rollout] x0 in the controller, and `simgap rollout` starts there without --x0 (before, rollout
    refused with "give --x0"). An x0 outside X is refused, naming [rollout] x0."""
    d, _ = collected
    store = d / "store"
    (tmp_path / "duffing.toml").write_text(DUFFING)
    spec = ("[synthesis]\nspec = \"invariance\"\nsafe_lo = [-0.8, -1.2]\nsafe_hi = [0.8, 1.2]\neta = [0.05, 0.05]\n"
            "[rollout]\nx0 = [0.1, -0.1]\n")
    (tmp_path / "exp.toml").write_text(EXP + spec)
    cert = tmp_path / "cert.json"
    assert main(["certify", str(store), "--degree", "1", "--out", str(cert)]) == 0
    ctrl = tmp_path / "ctrl.npz"
    assert main(["synthesize", "--cert", str(cert), "--spec", str(tmp_path / "exp.toml"), "--profile", "base",
                 "--out", str(ctrl)]) == 0
    assert Controller.load(ctrl).x0.tolist() == [0.1, -0.1]
    rep = tmp_path / "ro.json"
    capsys.readouterr()
    assert main(["rollout", "--controller", str(ctrl), "--simulator", SIM, "--n", "20", "--horizon", "20",
                 "--out", str(rep)]) == 0
    assert json.loads(rep.read_text())["x0"] == [0.1, -0.1]
    (tmp_path / "exp.toml").write_text(EXP + spec.replace("[0.1, -0.1]", "[0.1, -3.0]"))
    capsys.readouterr()
    assert main(["synthesize", "--cert", str(cert), "--spec", str(tmp_path / "exp.toml"), "--profile", "base",
                 "--out", str(tmp_path / "c2.npz")]) != 0
    assert "[rollout] x0" in capsys.readouterr().err
    assert not (tmp_path / "c2.npz").exists()

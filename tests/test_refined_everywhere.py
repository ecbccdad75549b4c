"""A refined-system JSON is accepted wherever a system is: experiment TOML (collect, run), certify,
audit, synthesize, rollout, data sets and controllers (embedded, not tied to the file)."""

import json

import numpy as np
import pytest

from simgap.certify.certificate import load as load_cert
from simgap.cli import main
from simgap.collect import load_store
from simgap.dataset import load_dataset
from simgap.errors import SimgapError
from simgap.refine.effects import effect_from_spec
from simgap.refine.refined import build_refined, save_refined
from simgap.synthesis.controller import Controller
from simgap.systems import get_system
from simgap.system_ref import resolve_system, system_digest, system_ref

C = -2.0  # strong viscous friction: f' differs from f by tau * 2 * omega per step


def refined_pendulum(c=C, name="pendulum_damped"):
    base = get_system("pendulum")
    eff = effect_from_spec(base, {"name": "viscous_friction", "state": 1, "variable": "omega"})
    return build_refined(base, "pendulum", [eff], [c], name=name)


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    """refined.json + an experiment on it (numpy simulator), collected with `simgap collect`."""
    d = tmp_path_factory.mktemp("refd")
    save_refined(refined_pendulum(), d / "refined.json")
    (d / "exp.toml").write_text("""
[system]
name = "refined.json"
[simulator]
kind = "numpy"
system = "pendulum"
noise = { process_std = 1e-4 }
[collect]
epsilon = 0.05
n_runs = 10
seed = 3
chunk_size = 1024
""")
    assert main(["collect", str(d / "exp.toml"), "--out", str(d / "store"), "--no-progress", "--profile", "base"]) == 0
    return d


def test_resolve_and_ref_round_trip(tmp_path):
    r = refined_pendulum()
    ref = system_ref(r.with_steps(3))
    assert isinstance(ref, dict) and ref["steps"] == 3 and ref["name"] == "pendulum_damped"
    back = resolve_system(json.loads(json.dumps(ref)))
    x = np.array([[0.3, -1.0], [0.1, 2.0]])
    u = np.array([[0.5], [-1.0]])
    assert back.steps == 3 and np.allclose(back.f(x, u), r.with_steps(3).f(x, u))
    assert not np.allclose(back.f(x, u), get_system("pendulum", 3).f(x, u))
    assert system_ref(get_system("emps")) == "emps" and resolve_system("emps").name == "emps"
    # other coefficients, same name: another digest
    assert system_digest(refined_pendulum(c=-1.0)) != system_digest(r) != system_digest(get_system("pendulum"))
    # a reference read from a data file never opens a file
    p = save_refined(r, tmp_path / "r.json")
    assert resolve_system(str(p)).name == "pendulum_damped"
    with pytest.raises(SimgapError, match="unknown system"):
        resolve_system(str(p), paths=False)


def test_collect_on_refined_system_embeds_it(collected, tmp_path):
    ds = load_store(collected / "store")
    assert ds.system.name == "pendulum_damped"
    # the simulator ran the refined dynamics: the gap to f' is noise, to the base model it is not
    assert ds.gap().max() < 3e-4
    assert np.abs(ds.mean - get_system("pendulum").f(ds.x, ds.u)).max() > 3e-3  # tau * 2 * |omega|max
    # self-contained: no longer tied to the file
    (collected / "refined.json").rename(collected / "moved.json")
    try:
        again = load_store(collected / "store")
        assert np.array_equal(again.f_nom, ds.f_nom)
        npz = ds.save_npz(tmp_path / "d.npz")
        one = load_dataset(npz)
        assert one.system.name == "pendulum_damped" and np.allclose(one.system.f(ds.x, ds.u), ds.f_nom)
    finally:
        (collected / "moved.json").rename(collected / "refined.json")


def test_certify_synthesize_rollout_with_refined_json(collected, tmp_path, capsys):
    sysf, store = collected / "refined.json", collected / "store"
    cert = tmp_path / "cert.json"
    assert main(["certify", str(store), "--degree", "1", "--out", str(cert)]) == 0
    c = load_cert(cert)
    assert c.system_name == "pendulum_damped" and c.system_digest == system_digest(resolve_system(str(sysf)))
    # the certified gap is accepted for f' (at tau = 5 ms gamma, mostly L * eps, outgrows what one
    # step of control can undo: exit 1 = empty winning domain, not 2 = refused)
    capsys.readouterr()
    assert main(["synthesize", "--system", str(sysf), "--cert", str(cert), "--safe", "-0.2,0.2,-0.5,0.5",
                 "--eta", "0.01,0.05", "--out", str(tmp_path / "c.npz")]) == 1
    assert "system        pendulum_damped" in capsys.readouterr().out
    ctrl = tmp_path / "ctrl.npz"
    assert main(["synthesize", "--system", str(sysf), "--steps", "20", "--no-gap", "--safe", "-0.2,0.2,-0.5,0.5",
                 "--eta", "0.02,0.05", "--out", str(ctrl)]) == 0
    loaded = Controller.load(ctrl)
    assert loaded.system.name == "pendulum_damped" and loaded.size > 0
    x = np.array([[0.1, 0.5]])
    assert np.allclose(loaded.system.f(x, [[0.2]]), resolve_system(str(sysf), 20).f(x, [[0.2]]))
    # the certificate refuses the base model and a same-named model with other coefficients
    other = tmp_path / "other.json"
    save_refined(refined_pendulum(c=-1.0), other)
    capsys.readouterr()
    assert main(["synthesize", "--system", str(other), "--cert", str(cert), "--safe", "-0.3,0.3,-1,1",
                 "--eta", "0.05,0.2", "--out", str(tmp_path / "bad.npz")]) == 2
    assert "different model" in capsys.readouterr().err
    assert main(["synthesize", "--system", "pendulum", "--cert", str(cert), "--safe", "-0.3,0.3,-1,1",
                 "--eta", "0.05,0.2", "--out", str(tmp_path / "bad.npz")]) == 2
    assert not (tmp_path / "bad.npz").exists()
    # rollout: the controller's embedded model drives the numpy simulator, no file needed
    rep = tmp_path / "ro.json"
    sim = json.dumps({"kind": "numpy", "system": "pendulum_damped", "steps": 20,
                      "noise": {"process_std": 1e-4}})
    assert main(["rollout", "--controller", str(ctrl), "--simulator", sim, "--x0", "0.05", "0.1",
                 "--n", "20", "--horizon", "30", "--mean-map-runs", "0", "--out", str(rep)]) == 0
    r = json.loads(rep.read_text())
    assert r["system"] == "pendulum_damped"
    # audit of the refined certificate against fresh runs of the data's simulator
    assert main(["audit", str(cert), "--data", str(store), "--points", "20", "--runs", "50"]) in (0, 1)


def test_certify_and_audit_a_refined_model_on_base_data(tmp_path, capsys):
    """`certify --system refined.json` on data collected for the base model: f_nom becomes f'."""
    (tmp_path / "exp.toml").write_text("""
[system]
name = "pendulum"
[simulator]
kind = "numpy"
noise = { process_std = 1e-4 }
effects = { linear = [[0.0, 0.0], [0.0, -2.0]] }
[collect]
epsilon = 0.25
n_runs = 10
seed = 4
""")
    store = tmp_path / "store"
    assert main(["collect", str(tmp_path / "exp.toml"), "--out", str(store), "--no-progress", "--profile", "base"]) == 0
    sysf = save_refined(refined_pendulum(), tmp_path / "refined.json")
    c_base, c_ref = tmp_path / "base.json", tmp_path / "ref.json"
    assert main(["certify", str(store), "--degree", "1", "--out", str(c_base)]) == 0
    assert main(["certify", str(store), "--degree", "1", "--system", str(sysf), "--out", str(c_ref)]) == 0
    cb, cr = load_cert(c_base), load_cert(c_ref)
    assert cb.system_name == "pendulum" and cr.system_name == "pendulum_damped"
    # f' holds the planted damping: its certified gap is far smaller
    assert max(d.gap_max for d in cr.dims) < 0.2 * max(d.gap_max for d in cb.dims)
    capsys.readouterr()
    assert main(["audit", str(c_ref), "--data", str(store), "--system", str(sysf), "--points", "30",
                 "--runs", "100"]) == 0
    assert "pendulum_damped" in capsys.readouterr().out
    # without --system the data set does not match the refined certificate
    assert main(["audit", str(c_ref), "--data", str(store), "--points", "5", "--runs", "10"]) == 2
    assert main(["certify", str(store), "--level", "run", "--alpha", "0.1", "--system", str(sysf)]) == 2


@pytest.mark.parametrize("doc,msg", [
    ({"format": "simgap-refined-system", "base": "pendulum", "effects": [
        {"name": "evil", "state": 1, "params": {"expr": "__import__('os').system('true')"},
         "coefficient": 1.0}]}, "__import__"),
    ({"format": "simgap-refined-system", "base": "pendulum", "effects": [
        {"name": "bias", "state": 1, "coefficient": "a lot"}]}, "not a number"),
    ({"format": "simgap-refined-system", "base": "pendulum", "name": "pendulum", "effects": []}, "built-in"),
    (__import__("functools").reduce(lambda d, _: {"format": "simgap-refined-system", "base": d, "effects": []},
                                    range(100), "pendulum"), "nested"),
    ({"format": "simgap-refined-system", "base": "/etc/passwd", "effects": []}, "base"),
    ({"format": "other", "base": "pendulum", "effects": []}, "format"),
])
def test_hostile_refined_json_refused_everywhere(tmp_path, capsys, doc, msg):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(SimgapError, match=msg):
        resolve_system(str(bad))
    (tmp_path / "exp.toml").write_text('[system]\nname = "bad.json"\n[simulator]\nkind = "numpy"\n'
                                       '[collect]\nepsilon = 0.25\nn_runs = 4\n')
    assert main(["collect", str(tmp_path / "exp.toml"), "--out", str(tmp_path / "s"), "--no-progress", "--profile", "base"]) == 2
    assert not (tmp_path / "s").exists()
    assert main(["synthesize", "--system", str(bad), "--no-gap", "--safe", "-0.3,0.3,-1,1", "--eta", "0.05,0.2",
                 "--out", str(tmp_path / "c.npz")]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_deeply_nested_file_is_refused(tmp_path):
    bad = tmp_path / "deep.json"
    bad.write_text('{"format": "simgap-refined-system", "effects": [], "base": ' * 100000 + '"pendulum"'
                   + "}" * 100000)
    with pytest.raises(SimgapError, match="deep.json"):
        resolve_system(str(bad))


def test_experiment_system_path_is_confined(tmp_path, capsys):
    inner = tmp_path / "exp"
    inner.mkdir()
    save_refined(refined_pendulum(), tmp_path / "outside.json")
    (inner / "exp.toml").write_text('[system]\nname = "../outside.json"\n[simulator]\nkind = "numpy"\n'
                                    '[collect]\nepsilon = 0.25\nn_runs = 4\n')
    assert main(["collect", str(inner / "exp.toml"), "--out", str(tmp_path / "s"), "--no-progress", "--profile", "base"]) == 2
    assert "outside" in capsys.readouterr().err


def test_gui_inputs_take_a_refined_json(collected):
    from simgap_viz import engine
    from simgap_viz.experiment import app_inputs

    settings, data, *_ = app_inputs(system=str(collected / "refined.json"), dataset=str(collected / "store"))
    assert settings.system == "pendulum_damped" and data.system.name == "pendulum_damped"
    s = engine.make_system(settings)
    x = np.array([[0.1, 0.4]])
    assert np.allclose(s.f(x, [[0.3]]), data.system.f(x, [[0.3]]))
    assert engine.base_system(s).name == "pendulum"  # the app's own collections simulate the base system

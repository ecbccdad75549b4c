"""The example plugin package (examples/plugin, installed by .ci/run) through every stage: its
system ``double_integrator`` and simulator kind ``example_drag`` are found by name only, and go
through collect, certify, synthesize, rollout and the app."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from simgap import plugins
from simgap.certify.certificate import load as load_cert
from simgap.cli import main
from simgap.collect import load_store
from simgap.synthesis.controller import Controller
from simgap.systems import get_system
from simgap.system_ref import system_ref

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "plugin"


@pytest.fixture(scope="module")
def installed():
    plugins.refresh()
    if "double_integrator" not in plugins.system_plugins() or "example_drag" not in plugins.simulator_plugins():
        pytest.fail("the example plugin is not installed: pip install -e examples/plugin (.ci/run does)")


def test_listed_with_keys(installed, capsys):
    assert main(["plugins", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    systems = {e["name"]: e for e in d["systems"]}
    sims = {e["kind"]: e for e in d["simulators"]}
    assert systems["double_integrator"]["states"] == ["p", "v"]
    assert systems["double_integrator"]["source"].startswith("simgap-example-plugin 0.1.0")
    assert systems["pendulum"]["source"] == "built-in"
    assert sims["example_drag"]["randomize"] == ["mass"] and sims["example_drag"]["effects"] == ["drag"]
    assert sims["example_drag"]["options"] == ["substeps"]
    assert main(["plugins"]) == 0
    assert "example_drag" in capsys.readouterr().out


def test_simulator_is_seeded_batched_and_has_its_drag(installed):
    from simgap.simulators.base import make_simulator
    s = get_system("double_integrator")
    assert system_ref(s) == "double_integrator"  # recorded by name, like a built-in
    cfg = {"kind": "example_drag", "system": "double_integrator", "noise": {"actuation_std": 0.02},
           "randomize": {"mass": 0.02}, "effects": {"drag": 0.5}}
    sim = make_simulator(cfg)
    rng = np.random.default_rng(0)
    x = s.x_lo + rng.random((64, 2)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, 5, 64)]
    noise = sim.draw_noise(64, np.random.default_rng(1))
    batch = sim.step_with_noise(x, u, noise)
    one = np.concatenate([sim.step_with_noise(x[i:i + 1], u[i:i + 1], {k: v[i:i + 1] for k, v in noise.items()})
                          for i in range(64)])
    assert np.array_equal(batch, one)
    assert np.array_equal(sim.step(x, u, np.random.default_rng(5)), sim.step(x, u, np.random.default_rng(5)))
    # noise-free: drag -0.5 v|v| slows the cart by about tau * 0.5 v|v| against the nominal model
    quiet = make_simulator(dict(cfg, noise={}, randomize={}))
    xv = np.array([[0.0, 0.8]])
    dv = quiet.step(xv, [[0.0]], rng)[0, 1] - s.f(xv, [[0.0]])[0, 1]
    assert dv == pytest.approx(-0.1 * 0.5 * 0.64, rel=0.05)


def test_collect_certify_synthesize_rollout_and_app(installed, tmp_path, capsys):
    exp = tmp_path / "experiment.toml"
    shutil.copy(EXAMPLE / "experiment.toml", exp)
    store = tmp_path / "data"
    assert main(["collect", str(exp), "--profile", "base", "--out", str(store), "--epsilon", "0.04",
                 "--n-runs", "20", "--no-progress"]) == 0
    ds = load_store(store)
    assert ds.system.name == "double_integrator" and ds.manifest["simulator"]["kind"] == "example_drag"
    cert = tmp_path / "cert.json"
    assert main(["certify", str(store), "--degree", "1", "--out", str(cert)]) == 0
    c = load_cert(cert)
    assert c.system_name == "double_integrator" and c.system_ref is None  # a name, not an embedded model
    assert c.nominal_system().name == "double_integrator"
    ctrl = tmp_path / "ctrl.npz"
    capsys.readouterr()
    assert main(["synthesize", "--cert", str(cert), "--safe=-0.8,0.8,-0.8,0.8", "--eta", "0.04,0.04",
                 "--x0", "0,0", "--out", str(ctrl)]) == 0
    assert "x0            [0.0, 0.0]: winning" in capsys.readouterr().out
    assert Controller.load(ctrl).system.name == "double_integrator"
    rep = tmp_path / "ro.json"
    assert main(["rollout", "--controller", str(ctrl), "--simulator", str(exp), "--profile", "base", "--n", "100",
                 "--horizon", "50", "--mean-map-runs", "0", "--out", str(rep)]) == 0
    r = json.loads(rep.read_text())
    assert r["system"] == "double_integrator" and r["failures"] == 0 and r["n_rollouts"] == 100

    # the app: the names are offered, the experiment loads, synthesis and rollouts run through the engine
    from simgap_viz import engine
    from simgap_viz.app import SimgapApp
    from simgap_viz.experiment import app_inputs
    assert "double_integrator" in engine.SYSTEMS and "example_drag" in engine.SIMULATORS
    settings, _, spec, _, e = app_inputs(experiment=str(exp), profile="base")
    assert settings.system == "double_integrator" and settings.simulator == "example_drag"
    app = SimgapApp(port=0, settings=settings, dataset=ds, spec=spec, experiment=e, executor="serial")
    try:
        app.update_settings(use_gap=True, eta=(0.04, 0.04), hold=1, n_rollouts=50, horizon=40, x0=(0.0, 0.0))
        app.synthesize()
        out = app.wait(120)
        assert out.ok, out.error
        assert app.results["synthesize"].stats["winning"] > 0
        app.rollout()
        out = app.wait(120)
        assert out.ok, out.error
        ro = app.results["rollout"]
        assert ro.trajectories.shape == (50, 41, 2) and ro.success.all()
    finally:
        app.stop()
    assert main(["gui", "--experiment", str(exp), "--profile", "base", "--port", "0", "--exit-after", "0.3"]) == 0


def test_broken_and_shadowing_plugins_are_named(monkeypatch):
    """A plugin that does not import, builds no System, or takes a built-in's name: a message
    naming the plugin and its package (never a traceback), and the built-in keeps its name."""
    from importlib import metadata

    from simgap.errors import SimgapError
    from simgap.system_ref import resolve_system

    eps = [metadata.EntryPoint("broken", "no_such_module_xyz:factory", plugins.SYSTEM_GROUP),
           metadata.EntryPoint("not_a_system", "json:dumps", plugins.SYSTEM_GROUP),
           metadata.EntryPoint("pendulum", "json:loads", plugins.SYSTEM_GROUP),
           metadata.EntryPoint("bad_sim", "json:JSONDecoder", plugins.SIMULATOR_GROUP)]
    monkeypatch.setattr(metadata, "entry_points", lambda group: [e for e in eps if e.group == group])
    plugins.refresh()
    try:
        assert sorted(plugins.system_plugins()) == ["broken", "not_a_system"]
        assert [p.name for _, p in plugins.shadowed()] == ["pendulum"]
        assert resolve_system("pendulum").params["g"] == 9.81  # the built-in, not the plugin
        with pytest.raises(SimgapError, match="plugin 'broken' .*does not load: ModuleNotFoundError"):
            get_system("broken")
        with pytest.raises(SimgapError, match="plugin system 'not_a_system' .*failed to build"):
            get_system("not_a_system")
        with pytest.raises(SimgapError, match="installed plugins: broken, not_a_system"):
            get_system("nothing_like_it")
        from simgap.simulators.base import simulator_class
        with pytest.raises(SimgapError, match="plugin simulator 'bad_sim' .*not a subclass"):
            simulator_class("bad_sim")
    finally:
        monkeypatch.undo()
        plugins.refresh()

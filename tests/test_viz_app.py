"""Engine-to-GUI wiring of the viser app, without a browser.

Setting a handle's value from Python fires its on_update callbacks (viser 1.1), so these tests
drive the app through its real controls; button clicks are one-line calls into the methods
called here (collect, certify, ...).
"""

import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap_viz.jobs import JobRunner
from simgap_viz.settings import Settings, parse_vector

PENDULUM_NUMPY = {"kind": "numpy", "system": "pendulum", "noise": {"actuation_std": 0.05},
                  "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]]}}


@pytest.fixture(scope="module")
def tiny_dataset():
    from simgap.certify.synthetic import synthetic_dataset
    return synthetic_dataset(PENDULUM_NUMPY, 0.05, 20, seed=1)


@pytest.fixture
def app(tiny_dataset):
    from simgap_viz.app import SimgapApp
    a = SimgapApp(port=0, executor="serial")
    a.set_dataset(tiny_dataset)
    yield a
    a.stop()


# ----- settings ---------------------------------------------------------------------------
def test_stage_keys_follow_dependencies():
    s = Settings()
    t = s.replace(delta1=(0.01, 0.02), delta2=(0.01, 0.02))
    assert s.stage_key("collect") == t.stage_key("collect")
    assert s.stage_key("certify") != t.stage_key("certify")
    assert s.stage_key("synthesize") != t.stage_key("synthesize")
    u = s.replace(eta=(0.02, 0.04))
    assert u.stage_key("certify") == s.stage_key("certify")
    assert u.stage_key("synthesize") != s.stage_key("synthesize")
    assert s.replace(epsilon=0.1).stage_key("collect") != s.stage_key("collect")


@pytest.mark.parametrize("change, word", [
    ({"epsilon": 0.0}, "epsilon"), ({"epsilon": float("nan")}, "epsilon"), ({"n_runs": 1}, "N1hat"),
    ({"confidence": 1.5}, "confidence"), ({"delta1": (0.1,), "delta2": (0.1, 0.1)}, "delta1"),
    ({"degree": 9}, "degree"), ({"eta": (0.1, -1.0)}, "eta"), ({"concentration": "hoeffding"}, "concentration"),
])
def test_settings_validation_names_the_value(change, word):
    with pytest.raises(SimgapError, match=word):
        Settings().replace(**change).validate(2)


def test_parse_vector():
    assert parse_vector("0.1", "d", 3) == (0.1, 0.1, 0.1)
    assert parse_vector("0.1, 0.2", "d", 2) == (0.1, 0.2)
    assert parse_vector("", "d", 2, allow_empty=True) is None
    with pytest.raises(SimgapError, match="delta_1"):
        parse_vector("0.1, abc", "delta_1", 2)
    with pytest.raises(SimgapError, match="need 1 or 2"):
        parse_vector("1,2,3", "d", 2)


# ----- job runner -------------------------------------------------------------------------
def test_job_runner_progress_cancel_and_errors():
    seen = []
    finished = []
    jr = JobRunner(on_progress=lambda name, f: seen.append(f), on_finish=finished.append)
    jr.submit("ok", lambda ctx: [ctx.progress(i, 4) for i in range(5)] and 42)
    out = jr.wait(10)
    assert out.ok and out.result == 42 and seen[-1] == 1.0

    started = threading.Event()

    def long(ctx):
        started.set()
        for i in range(10_000):
            time.sleep(0.001)
            ctx.progress(i, 10_000)
        return "never"

    jr.submit("long", long)
    started.wait(5)
    with pytest.raises(SimgapError, match="still running"):
        jr.submit("second", lambda ctx: 1)
    assert jr.cancel()
    out = jr.wait(10)
    assert out.cancelled and not out.ok and out.name == "long"

    def bad(ctx):
        raise SimgapError("epsilon must be > 0")

    jr.submit("bad", bad)
    out = jr.wait(10)
    assert not out.ok and "epsilon" in out.error
    assert [o.name for o in finished] == ["ok", "long", "bad"]


# ----- the app ----------------------------------------------------------------------------
def test_bad_values_notify_and_keep_settings(app):
    panel = app.panels["system"]
    before = app.settings
    panel.epsilon.value = -0.5
    assert app.notifications and "epsilon" in app.notifications[-1][1]
    assert app.settings.epsilon == before.epsilon
    cert = app.panels["certificate"]
    cert.terms.value = "sin(x1"  # unparseable basis term
    assert "basis term" in app.notifications[-1][1]
    assert app.settings.terms == ""
    cert.terms.value = "bogus(x1)"
    assert "bogus" in app.notifications[-1][1]
    cert.value_range.value = -1.0
    assert "range b" in app.notifications[-1][1] and app.settings.value_range is None
    # the GUI is still alive: a good value goes through
    n = len(app.notifications)
    cert.terms.value = "sin(x1)"
    assert app.settings.terms == "sin(x1)" and len(app.notifications) == n
    app.wait(60)


def test_certify_summary_and_cheap_recertify(app):
    app.certify()
    out = app.wait(60)
    assert out.ok, out.error
    cert = app.results["certify"]
    summary = app.panels["certificate"].summary.content
    assert "joint confidence" in summary and "omega" in summary
    jc = cert.joint_confidence
    # target confidence 0.9 split over 2 dims x 2 betas; a dimension without noise spends none
    assert 0.9 - 1e-9 <= jc < 1.0
    from simgap_viz.layers import scene
    drawn = app.set_view(dim=1)
    # the data gaps are drawn with the surface only; a gamma that hardly varies is not a surface by default
    assert (drawn["points"].shape[0] > 0) == drawn["shown"]
    assert drawn["shown"] == ((drawn["range"][1] - drawn["range"][0]) / drawn["range"][1] >= scene.GAMMA_VISIBLE)
    app.set_flat_gamma(True)
    drawn = app.set_view(dim=1)
    assert drawn["shown"]
    assert drawn["vertices"].shape == (41 * 41, 3) and drawn["faces"].shape == (2 * 40 * 40, 3)
    assert drawn["points"].shape[0] > 0
    assert app.last_data_covered is not None and app.last_data_covered.all()  # gap <= gamma on the data

    # a basis change re-certifies from the cached data (auto), the summary changes
    key2 = app.result_keys["certify"]
    app.panels["certificate"].degree.value = 1
    app.wait(60)
    assert app.result_keys["certify"] != key2
    assert app.results["certify"].dims[1].terms == ["1", "x1", "x2", "u1"]
    assert app.panels["certificate"].summary.content != summary
    # switching to per-dimension deltas pre-fills the certificate's own deltas: gamma stays
    cp = app.panels["certificate"]
    before = app.results["certify"]
    cp.mode.value = "per dimension"
    app.wait(60)
    after = app.results["certify"]
    assert after is not before and [d.delta1 for d in after.dims] == [d.delta1 for d in before.dims]
    x, u = app.results["collect"].x[:50], app.results["collect"].u[:50]
    np.testing.assert_allclose(after.gamma(x, u), before.gamma(x, u), rtol=1e-9)
    # per-dimension deltas through the GUI
    cp.delta1.value = "0.01, 0.01"
    cp.delta2.value = "0.01, 0.01"  # re-certifies after the job the first change started
    deadline = time.time() + 60
    while time.time() < deadline and [d.delta2 for d in app.results["certify"].dims] != [0.01, 0.01]:
        time.sleep(0.1)
    app.wait(60)
    c = app.results["certify"]
    assert [d.delta1 for d in c.dims] == [0.01, 0.01] and [d.delta2 for d in c.dims] == [0.01, 0.01]
    # switching back to confidence mode pre-fills this certificate's joint confidence
    cp.mode.value = "target confidence"
    app.wait(60)
    assert cp.confidence.value == pytest.approx(c.joint_confidence, rel=1e-5)
    # confidence 0.9 and degree 2 again is a cache hit: the same object, no job
    cp.confidence.value = 0.9
    app.wait(60)
    cp.degree.value = 2
    app.wait(60)
    assert app.result_keys["certify"] == key2
    assert app.results["certify"] is cert  # from the cache
    assert app.status.content.startswith("certify: from cache")


def test_view_controls(app):
    app.certify()
    app.wait(60)
    v = app.panels["view"]
    v.b.value = v.a.value  # same variable twice: notification, no crash
    assert "two different variables" in app.notifications[-1][1]
    v.b.value = "torque"
    assert app.view["b"] == 2 and v.sliders[2].disabled and not v.sliders[1].disabled
    before = app.server.scene  # the app still draws after slider moves
    v.sliders[1].value = 0.3
    assert app.view["fixed"][1] == pytest.approx(0.3)
    assert before is app.server.scene


def test_collect_through_engine_and_cancel(tiny_dataset):
    from simgap_viz.app import SimgapApp
    a = SimgapApp(port=0, executor="serial", settings=Settings(epsilon=0.1, n_runs=5, noise_std=0.05))
    try:
        a.collect()
        out = a.wait(120)
        assert out.ok, out.error
        d = a.results["collect"]
        assert d.n_runs == 5 and d.epsilon == 0.1 and d.system.name == "pendulum"
        # same settings again: cache hit, no job
        a.collect()
        assert a.status.content.startswith("collect: from cache")
        # a long collection is cancelled from the cancel button's method
        a.update_settings(epsilon=0.004, n_runs=400)
        a.collect()
        time.sleep(0.3)
        a.cancel()
        out = a.wait(120)
        assert out.cancelled, out
        assert a.notifications[-1][0] == "Cancelled"
        assert a.results["collect"] is d or a.results["collect"] is None
    finally:
        a.stop()


def test_gui_stays_responsive_while_a_job_runs(app):
    """Another control reacts while a long job runs on the worker thread."""
    release = threading.Event()

    def slow(ctx):
        release.wait(10)
        return None

    app.start_job("slow", slow)
    t0 = time.perf_counter()
    app.panels["synthesis"].eta.value = "0.02, 0.05"
    assert time.perf_counter() - t0 < 0.5
    assert app.settings.eta == (0.02, 0.05)
    assert not app.cancel_button.disabled
    release.set()
    app.wait(10)
    assert app.cancel_button.disabled


def test_refine_report(app):
    app.refine()
    out = app.wait(60)
    assert out.ok, out.error
    rep = app.panels["refine"].report.content
    assert "viscous_friction" in rep  # the damping effect of the numpy simulator is found
    gap_f = app.results["collect"].gap().max(axis=0)
    rp = app.panels["refine"]
    rp.res_var.value = "torque"  # residual of omega against the input: one point per data row
    assert app.view["res_var"] == "torque" and rp.show_residuals() == app.results["collect"].K
    app.compare_refined()
    out = app.wait(120)
    assert out.ok, out.error
    assert "max observed gap" in app.panels["refine"].comparison.content
    # switch the nominal model to f': same empirical means, smaller observed gap, same simulator
    app.use_refined()
    assert app.system.name == "pendulum_refined" and app.settings.system == "pendulum_refined"
    assert "pendulum_refined" in app.panels["system"].system.options
    gap_r = app.results["collect"].gap().max(axis=0)
    assert gap_r[1] < 0.5 * gap_f[1]
    app.certify()
    out = app.wait(120)
    assert out.ok, out.error
    assert app.results["certify"].system_name == "pendulum_refined"
    app.update_settings(use_gap=False, eta=(0.005, 0.01), n_rollouts=20, horizon=30)
    app.rollout()  # synthesizes first, then rolls out in the base system's simulator
    out = app.wait(120)
    assert out.ok, out.error
    assert app.results["rollout"].trajectories.shape == (20, 31, 2)


def test_unavailable_stage_button_disabled(app, monkeypatch):
    from simgap_viz import engine
    avail = engine.availability()
    for stage in ("synthesize", "rollout"):
        b = [p.buttons[stage] for p in app.panels.values() if stage in p.buttons][0]
        if not avail[stage][0]:
            assert b.disabled
            with pytest.raises(SimgapError, match="disabled"):
                engine.require(stage)


def test_cli_gui_prints_url():
    p = subprocess.run([sys.executable, "-m", "simgap", "gui", "--port", "0", "--exit-after", "0.5"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "open http://127.0.0.1:" in p.stdout


def test_synthesize_and_rollout_layers(app):
    """Synthesis and rollouts through the engine; the layers hold all rollouts in one node."""
    from simgap_viz import engine
    from simgap_viz.layers import geometry as G
    from simgap_viz.layers import scene
    if not (engine.availability()["synthesize"][0] and engine.availability()["rollout"][0]):
        pytest.skip("synthesis engine not available")
    # the nominal model alone (no gap) has a winning domain at this grid
    app.update_settings(use_gap=False, eta=(0.005, 0.01), hold=1, n_rollouts=200, horizon=150)
    app.synthesize()
    out = app.wait(120)
    assert out.ok, out.error
    syn = app.results["synthesize"]
    assert syn.stats["winning"] > 0 and "winning" in app.panels["synthesis"].stats.content
    centers, widths, frac = engine.winning_cells(syn)
    assert centers.shape[0] == syn.stats["winning"] and np.all(frac == 1.0)  # 2-D: one cell per column
    assert scene.draw_winning(app) == syn.stats["winning"]  # one image: a pixel block per (x1, x2) column
    # the map's categories are the engine's: winning = steps >= 0, unsafe = blocked or outside the safe set
    blocked, allowed = engine.cell_labels(syn)
    wm = G.winning_map(syn.controller, blocked, allowed)
    win = syn.controller.winning_mask
    assert wm["counts"]["winning"] == win.sum() and wm["counts"]["unsafe"] == (~win & (blocked | ~allowed)).sum()
    assert wm["counts"]["losing"] == (~win & ~blocked & allowed).sum()
    img = wm["image"]
    assert img.shape[0] % syn.controller.grid.shape[1] == 0 and img.shape[1] % syn.controller.grid.shape[0] == 0
    k = img.shape[1] // syn.controller.grid.shape[0]
    cell = img[::k, ::k][::-1].transpose(1, 0, 2)  # back to (i, j) cell order
    is_win = np.all(cell == G.WIN_ALL, axis=2).ravel()  # invariance in 2-D: every winning cell fully winning
    assert np.array_equal(is_win, win)
    app.rollout()
    out = app.wait(120)
    assert out.ok, out.error
    ro = app.results["rollout"]
    assert ro.trajectories.shape == (200, 151, 2)
    seg = G.rollout_segments(G.Frame(app.system), ro.trajectories, ~ro.success)
    assert seg["points"].shape == (200 * 150, 2, 3)  # one batched node, every step
    red = np.all(seg["colors"][:, 0] == G.RED, axis=1).reshape(200, 150)
    assert np.array_equal(red.all(axis=1), ~ro.success)
    # a subset is drawn (failures first), all are counted
    app.set_time(n_draw=50)
    assert app.rollout_drawn == {"drawn": 50, "total": 200, "failed": int((~ro.success).sum()),
                                 "failed_drawn": min(50, int((~ro.success).sum())), "segments": 50 * 150}
    # the drawn rollouts are one image of the square: blue where a drawn trajectory passes
    img = G.rollout_image(G.Frame(app.system), ro.trajectories[:1], np.zeros(1, bool), px=64, width=1)
    P = (G.Frame(app.system).xy(ro.trajectories[0])[:, :2] + 1) * 32
    rows, cols = np.clip(63 - P[:, 1].astype(int), 0, 63), np.clip(P[:, 0].astype(int), 0, 63)
    one = round(255 * G.RUN_ALPHA)
    assert np.all(img[rows, cols, :3] == G.RUN_BLUE) and np.all(img[rows, cols, 3] >= one)
    assert (img[..., 3] > 0).sum() < 0.5 * 64 * 64 and np.median(img[rows, cols, 3]) < 2 * one  # one run: faint
    # translucent runs add up: ten runs along the same path are much denser than one (100 vs 1000 differ)
    img10 = G.rollout_image(G.Frame(app.system), np.repeat(ro.trajectories[:1], 10, axis=0), np.zeros(10, bool),
                            px=64, width=1)
    want = 255 * (1 - (1 - G.RUN_ALPHA) ** 10)
    assert np.all(img10[rows, cols, 3] >= want - 1) and np.all(img10[..., 3][img[..., 3] == 0] == 0)
    sent = []
    add_image = app.server.scene.add_image
    app.server.scene.add_image = lambda name, *a, **k: (sent.append(name), add_image(name, *a, **k))[1]
    app.refresh_result_layers()  # nothing changed: the rollouts and the map are not sent again
    assert sent == []
    assert scene.draw_rollouts(app) == 50 * 150
    app.set_time(n_draw=60)
    assert sent == ["/rollouts/all"] and app.rollout_drawn["drawn"] == 60
    app.server.scene.add_image = add_image
    assert "60 of 200 drawn" in app.panels["view"].legend.content
    sub = G.rollout_subset(np.arange(200) % 7 == 0, 20)
    assert sub.size == 20 and np.all(sub % 7 == 0)  # 29 failures: the subset is all failures
    app.set_time(t=75, rollout_index=3)  # moves the pendulum body to that rollout's angle
    th = ro.trajectories[3, 75, 0]
    np.testing.assert_allclose(app.body_frame.wxyz, [np.cos(th / 2), 0, np.sin(th / 2), 0], atol=1e-6)
    assert "rollouts of pendulum" in app.panels["rollouts"].stats.content

    # with the certified gap at this coarse data the domain is empty: a visible notification
    app.update_settings(use_gap=True)
    app.synthesize()
    app.wait(120)
    if app.results["synthesize"].empty:
        assert app.notifications[-1][0] == "Empty winning domain"
        app.rollout()
        app.wait(60)
        assert "empty winning domain" in app.notifications[-1][1]


def test_rollout_cancel(app):
    """A long rollout job stops at the next simulator step after cancel."""
    from simgap_viz import engine
    if not engine.availability()["rollout"][0]:
        pytest.skip("rollout engine not available")
    app.update_settings(use_gap=False, eta=(0.005, 0.01), n_rollouts=1000, horizon=5000)
    app.synthesize()
    assert app.wait(120).ok
    app.rollout()
    time.sleep(1.0)
    app.cancel()
    out = app.wait(60)
    assert out.cancelled and out.seconds < 15
    assert app.results["rollout"] is None


def test_simulator_bodies_from_urdf():
    """The PyBullet bodies come from the URDF visual geometry, in metres."""
    from simgap.systems import get_system
    from simgap_viz.layers.bodies import simulator_bodies
    pend = simulator_bodies("pybullet_pendulum", get_system("pendulum"))
    assert len(pend) == 1
    from simgap.simulators._bullet import URDF_DIR
    from simgap_viz.layers.bodies import urdf_meshes
    (_, rod), = urdf_meshes(URDF_DIR / "pendulum.urdf", joint_positions=[0.0])
    ext = rod.bounds[1] - rod.bounds[0]  # hanging straight down from the pivot at the origin
    assert ext[2] == pytest.approx(1.0, abs=1e-9) and ext[0] == pytest.approx(0.02, abs=1e-3)  # l = 1, r = 0.01
    assert rod.bounds[1][2] == pytest.approx(0.0, abs=1e-9)
    tb = simulator_bodies("pybullet_turtlebot", get_system("turtlebot"))
    names = [n for n, _, _ in tb]
    assert any(n.startswith("robot_") for n in names) and sum(n.startswith("obstacle_") for n in names) >= 1


def test_change_during_a_job_recertifies_afterwards(app):
    """A basis change while a job runs is applied after it, without an error notification."""
    release = threading.Event()
    app.certify()
    app.wait(60)
    n = len(app.notifications)
    app.start_job("slow", lambda ctx: release.wait(10))
    app.panels["certificate"].degree.value = 1
    # the re-certification waits for the job (the status line may already show the job's progress)
    assert app._pending == app.certify
    release.set()
    deadline = time.time() + 60
    while time.time() < deadline and (app.results["certify"] is None
                                      or app.results["certify"].dims[0].terms != ["1", "x1", "x2", "u1"]):
        time.sleep(0.1)
    app.wait(60)
    assert app.results["certify"].dims[0].terms == ["1", "x1", "x2", "u1"]
    assert len(app.notifications) == n


def test_glb_lines_and_unlit_surface():
    """The GLB writer: one LINES primitive (segment pairs) or an indexed, unlit, translucent
    triangle mesh, with the given sRGB colors stored as linear vertex colors; read back by trimesh."""
    import io
    import json
    import struct

    import trimesh

    from simgap_viz.layers import geometry as G

    def chunk(b):
        n = struct.unpack("<I", b[12:16])[0]
        return json.loads(b[20:20 + n])
    P = np.random.default_rng(0).random((7, 2, 3))
    C = np.zeros((7, 2, 3), np.uint8)
    C[:] = G.BLUE
    C[3] = G.RED
    b = G.glb(P, C)
    doc = chunk(b)
    assert doc["meshes"][0]["primitives"][0]["mode"] == 1 and doc["accessors"][0]["count"] == 14
    path = trimesh.load(io.BytesIO(b), file_type="glb").geometry["GLTF"]
    np.testing.assert_allclose(np.sort(path.vertices, axis=0), np.sort(P.reshape(-1, 3), axis=0), atol=1e-6)
    lin = G.srgb_to_linear(np.array([G.BLUE, G.RED]))
    body = b[20 + struct.unpack("<I", b[12:16])[0] + 8:]
    col = np.frombuffer(body[14 * 12: 14 * 12 + 14 * 8], np.uint16).reshape(14, 4)[:, :3] / 65535
    np.testing.assert_allclose(col[6:8], [lin[1]] * 2, atol=1e-4)  # segment 3 red, the others blue
    np.testing.assert_allclose(col[:6], [lin[0]] * 6, atol=1e-4)
    V = np.random.default_rng(1).random((9, 3))
    F = G.grid_faces(3, 3)
    b = G.glb(V, np.zeros((9, 3), np.uint8), F, unlit=True, opacity=0.85)
    mat = chunk(b)["materials"][0]
    assert "KHR_materials_unlit" in mat["extensions"] and mat["alphaMode"] == "BLEND"
    mesh = trimesh.load(io.BytesIO(b), file_type="glb", force="mesh")
    assert mesh.faces.shape == (8, 3) and np.allclose(mesh.vertices, V, atol=1e-6)
    lit = chunk(G.glb(V, np.zeros((9, 3), np.uint8), F))
    assert "NORMAL" in lit["meshes"][0]["primitives"][0]["attributes"] and "alphaMode" not in lit["materials"][0]


def test_gamma_layer_height_scale_and_colors(app):
    """The height scale follows each certificate; the data gaps are colored by their margin."""
    from simgap_viz.layers import geometry as G
    app.certify()
    assert app.wait(60).ok
    app.set_flat_gamma(True)  # drawn even where it hardly varies (by default only the legend gives its value)
    d1 = app.set_view(dim=1)
    top1 = d1["top"]
    assert d1["vertices"][:, 2].max() <= 1.0 + 1e-6 and d1["vertices"][:, 2].max() > 0.5  # visible, in [0, 1]
    assert top1 == pytest.approx(max(d1["range"][1], 0.0), rel=1e-6) or top1 >= d1["range"][1]
    assert "gamma_omega" in app.panels["view"].legend.content
    m = d1["margin"]
    col = G.margin_colors(m, 1.0)
    assert np.array_equal(np.all(col == G.RED, axis=1), m < 0)
    # a looser certificate: the scale widens, the surface stays inside [0, 1]
    conf = app.settings.confidence
    app.update_settings(confidence=0.999)
    assert app.wait(60).ok
    d2 = app.set_view(dim=1)
    assert d2["top"] > top1 and d2["vertices"][:, 2].max() <= 1.0 + 1e-6
    # back to the tighter one: the session's scale stays, so its surface stands visibly lower than the
    # looser one's (a per-certificate scale would stretch both to height 1 and the same colors)
    app.update_settings(confidence=conf)
    assert app.wait(60).ok
    d3 = app.set_view(dim=1)
    assert d3["top"] == d2["top"]
    np.testing.assert_allclose(d3["vertices"][:, 2], d1["vertices"][:, 2] * top1 / d2["top"], rtol=1e-5)
    assert d3["vertices"][:, 2].max() < 0.99 * d2["vertices"][:, 2].max()
    legend = app.panels["view"].legend.content
    assert f"{d2['top']:.4g} rad/s/step" in legend and "on this slice" in legend and "constant" not in legend
    assert np.all(G.nice_ticks(0.0, 0.0058, 4) <= 0.0058) and G.nice_ticks(-0.2, 0.2, 5).tolist() == \
        pytest.approx([-0.2, -0.1, 0.0, 0.1, 0.2])


def test_typed_number_applies_at_once_when_valid_and_waits_otherwise(app):
    """A browser's valid confidence applies without the typing wait; "0." (0) waits, so a
    half-typed number never notifies while the user is still typing."""
    from types import SimpleNamespace
    cp = app.panels["certificate"]
    browser = SimpleNamespace(client=object())
    cbs = cp.confidence._impl.update_cb

    def type_value(v):
        cp.set_quiet(cp.confidence, v)
        for cb in cbs:
            cb(browser)

    n = len(app.notifications)
    type_value(0.0)  # what "0." parses to: not applied now, no notification yet
    assert app.settings.confidence != 0.0 and len(app.notifications) == n
    type_value(0.85)  # valid: applied at once (the pending "0." is dropped)
    assert app.settings.confidence == 0.85
    time.sleep(0.8)
    assert len(app.notifications) == n
    type_value(1.5)  # invalid and left: notified after the wait, settings kept
    assert app.settings.confidence == 0.85 and len(app.notifications) == n
    time.sleep(0.8)
    assert app.settings.confidence == 0.85 and app.notifications[-1][0] == "Invalid value"
    app.wait(60)


def test_newer_settings_supersede_a_running_certify_quietly(app):
    """A certification knob changed while a certify runs cancels it (no "Cancelled" notice) and
    the certificate that lands is the newer settings' one."""
    app.certify()
    app.wait(60)
    before = app.results["certify"]
    started = threading.Event()

    def slow(ctx):  # stands for a long certify: reports progress, so a cancel stops it
        started.set()
        for _ in range(600):
            ctx.progress(0, 1)
            time.sleep(0.05)

    n = len(app.notifications)
    app.start_job("certify", slow)
    assert started.wait(10)
    t0 = time.time()
    app.update_settings(confidence=0.8)
    deadline = time.time() + 60
    while time.time() < deadline and (app.results["certify"] is before or app.jobs.busy):
        time.sleep(0.05)
    app.wait(60)
    assert app.results["certify"] is not before and app.settings.confidence == 0.8
    assert app.result_keys["certify"] == app.settings.stage_key("certify")
    assert time.time() - t0 < 20  # not the 30 s the superseded job would have taken
    assert all(t != "Cancelled" for t, _, _ in app.notifications[n:])
    # a cancel by the user is still announced
    started.clear()
    app.start_job("certify", slow)
    assert started.wait(10)
    app.cancel()
    app.wait(60)
    assert app.notifications[-1][0] == "Cancelled"


def test_status_names_stale_layers_next_button_and_the_running_stage():
    """Without a browser: after a settings change the status names the stale layers and the button
    to press with the engine's collection estimate; a Certify that must collect reports progress as
    "collect" (then "certify"), with the time elapsed; a new collection keeps the winning domain and
    the rollouts, marked stale; the estimate's numbers are the engine's cost model."""
    from simgap.cover import estimate_cost
    from simgap_viz import engine
    from simgap_viz.app import SimgapApp
    a = SimgapApp(port=0, executor="serial", settings=Settings(epsilon=0.1, n_runs=5, noise_std=0.05))
    names = []
    report = a.jobs._on_progress
    a.jobs._on_progress = lambda name, f: (names.append((name, a.jobs.context.name)), report(name, f))
    try:
        assert "next: press **Collect**" in a.settings_status()
        a.certify()
        out = a.wait(120)
        assert out.ok, out.error
        stages = [n for n, _ in names]
        assert stages[0] == "collect" and stages[-1] == "certify" and {j for _, j in names} == {"certify"}, names
        # the nominal model alone has a winning domain at this grid (as in test_synthesize_and_rollout_layers)
        a.update_settings(use_gap=False, eta=(0.005, 0.01), hold=1, n_rollouts=50, horizon=100)
        a.synthesize()
        assert a.wait(120).ok
        a.rollout()
        assert a.wait(300).ok
        syn, ro = a.results["synthesize"], a.results["rollout"]
        assert a.stale_stages() == [] and a.next_action() is None
        a.update_settings(n_runs=6)
        st = a.status.content
        assert st.startswith("changed: **N1hat**") and "next: press **Collect**" in st, st
        for layer in ("data (data gaps)", "certificate (gamma)", "winning domain", "rollouts"):
            assert layer in st, (layer, st)
        est = engine.collect_estimate(a.settings, a.system)
        cover, _ = engine._collect_setup(a.settings, a.system)
        ref = estimate_cost(cover, 6)
        assert (est.n_pairs, est.sim_steps) == (ref.n_pairs, ref.sim_steps)
        assert f"{ref.n_pairs:,} (x_r, u) pairs x N1hat 6 = {ref.sim_steps:,} simulator steps" in st, st
        a.collect()
        assert a.wait(120).ok
        # the new data set keeps the winning domain and the rollouts on screen, marked stale
        assert a.results["synthesize"] is syn and a.results["rollout"] is ro
        assert a.stale == {"synthesize", "rollout"} and a.results["certify"] is None
        assert a.next_action() == "certify" and "next: press **Certify**" in a.status.content, a.status.content
        assert a.timings["collect"] > 0 and "collect" in a._estimates
    finally:
        a.stop()


def test_a_change_made_while_the_rate_is_timed_still_gets_its_time(monkeypatch):
    """Two quick N1hat edits: the second finds the background calibration busy. When the first one's
    calibration ends, the status (still "time not estimated yet") is redrawn from the settings now
    current, with a time. (It used to be redrawn only if the settings had not changed meanwhile, so
    the status could wait for a time forever; a browser test saw it under load.)"""
    from simgap_viz import engine
    from simgap_viz.app import SimgapApp
    monkeypatch.setattr(engine, "_RATES", {})
    gate, real = threading.Event(), engine.collect_estimate

    def slow_calibration(*args, calibrate=False, **kw):
        if calibrate:
            assert gate.wait(30)
        return real(*args, calibrate=calibrate, **kw)

    monkeypatch.setattr(engine, "collect_estimate", slow_calibration)
    a = SimgapApp(port=0, executor="serial", settings=Settings(epsilon=0.1, n_runs=5, noise_std=0.05))
    try:
        assert a.update_settings(n_runs=7)
        assert "time not estimated yet" in a.status.content and a._calibrating
        assert a.update_settings(n_runs=9)  # while the first calibration runs
        assert "N1hat 9" in a.status.content and "time not estimated yet" in a.status.content
        gate.set()
        deadline = time.time() + 60
        while "time not estimated yet" in a.status.content and time.time() < deadline:
            time.sleep(0.05)
        st = a.status.content
        assert "N1hat 9" in st and "simulator steps, about" in st, st
    finally:
        a.stop()


class _FakeCamera:
    """A client's camera as viser's handle shows it at connect time (viser calls the connect handler
    after the client's first camera message: the window's size is known)."""

    def __init__(self, size):
        self.image_width, self.image_height = size
        self.callbacks, self.sent = [], []

    def on_update(self, fn):
        self.callbacks.append(fn)

    def __setattr__(self, name, value):
        if name == "look_at":
            self.sent.append(tuple(value))
        object.__setattr__(self, name, value)


class _FakeClient:
    """A client that connects while another thread (a job's redraw: scene.fit_camera for every
    client) is sending the camera: the connect handler runs on viser's thread pool meanwhile."""

    client_id = 987

    def __init__(self, app, size):
        import types
        self.app, self.camera, self.connect = app, _FakeCamera(size), None
        self.gui = types.SimpleNamespace(main_panel=types.SimpleNamespace(set_width=lambda w: None))

    def atomic(self):
        import contextlib
        if self.connect is None:  # the first camera sent: the client's connect handler runs now
            self.connect = threading.Thread(target=self.app._on_connect, args=(self,))
            self.connect.start()
            self.connect.join(1.0)  # done meanwhile (or waiting for the fit lock)
        return contextlib.nullcontext()


def test_a_window_fitted_while_another_thread_sends_the_camera_is_not_fitted_over():
    """A redraw's camera (computed before the window's size was recorded) and the connect handler's
    fit ran on two threads: the redraw's default camera could be sent after the fit, the size was
    recorded and never fitted again, and the scene stayed unfitted (seen at 1280 x 800 now and
    then). The last camera sent is the window's fit, at both sizes."""
    from simgap_viz.app import SimgapApp, panel_width
    from simgap_viz.layers import scene
    a = SimgapApp(port=0, executor="serial", settings=Settings(epsilon=0.1, n_runs=5, noise_std=0.05))
    try:
        for size in ((1280, 800), (1920, 1080)):
            client = _FakeClient(a, size)
            a.windows.pop(client.client_id, None)
            scene.fit_camera(a, [client])  # a redraw of every client's camera, as the client connects
            client.connect.join(10)
            assert a.windows[client.client_id] == {"size": size, "panel": panel_width(size[0])}
            look, _ = scene.window_camera(a, a.windows[client.client_id])
            assert np.allclose(client.camera.sent[-1], look), (size, client.camera.sent)
    finally:
        a.stop()


def test_status_line_has_no_doubled_parentheses(monkeypatch):
    """The estimate after 'next: press ...' ends with its own '(calibrated here, ...)': it follows a
    dash, not a parenthesis of its own (the status line showed '...worker(s)))')."""
    from simgap_viz import engine
    from simgap_viz.app import SimgapApp
    monkeypatch.setattr(engine, "_RATES", {})  # not a rate an earlier test's collection measured
    a = SimgapApp(port=0, executor="serial", settings=Settings(epsilon=0.1, n_runs=5, noise_std=0.05))
    try:
        # the simulator's rate timed here first (the app does it on a background thread)
        assert engine.collect_estimate(a.settings, a.system, None, a.executor, calibrate=True).seconds is not None
        a.update_settings(n_runs=7)
        st = a.status.content
        assert "next: press **Collect** \u2014 collect:" in st and "(calibrated here" in st, st
        assert "))" not in st, st
        a.timings["certify"] = 1.5  # a certify that must collect first: both estimates, one after the other
        assert "))" not in a.settings_status() and "collect:" in a.estimate_text("certify")
        assert ", then certify: about 1.5 s (its last run here)" in a.estimate_text("certify")
    finally:
        a.stop()

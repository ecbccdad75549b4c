"""What each synthesis method proved, in its own words (simgap.synthesis.statement), and everything
that reads it: the box tube's statement against its controller (every box drawn is the box the
proof holds, the band per period, p_cert the noise tube's), a small box-tube run end to end (the
summary, the CLI table, the app's header, legend, proved-sets layer, Synthesis and Per run tabs, and
the page in a real browser at 1280 x 800 and 1920 x 1080) never in another method's words."""

import io
import re

import numpy as np
import pytest

from simgap.synthesis import box_tube as bt
from simgap.synthesis.noise_tube import NoiseTube
from simgap.synthesis.spec import Box, Spec
from simgap.synthesis.statement import DrawnSet, Statement, not_proved, statement_of
from test_invariant_set import CUBIC  # noqa: E402

#: the words of the other methods, never said of a box tube
NOT_TUBE = re.compile(r"invariant set|invariant ellipsoid|\bE\b|winning (cells|domain)|x0 in E")

#: a cubic pendulum with actuation noise and a uniform sub-Gaussian certificate: the stochastic
#: box tube is proved with a per-run statement (p_cert 0.96) in about 10 s
TUBE_RUN = """
system = "cubic.toml"
[simulator]
kind = "numpy"
noise = { actuation_std = 0.01 }
[collect]
epsilon = 0.1
n_runs = 30
seed = 1
executor = "serial"
[certify]
degree = 1
concentration = "subgaussian"
safety = 1.0
lipschitz_term = "gap"
uniform = true
continuous_inputs = true
[audit]
points = 20
runs = 20
[synthesis]
spec = "invariance"
method = "box_tube"
x_star = [0.0, 0.0]
u_star = [0.0]
margin_search = false
nominal = false
[rollout]
n = 50
x0 = [0.3, 0.0]
"""


@pytest.fixture(scope="module")
def tube_run(tmp_path_factory):
    """A finished `simgap run` folder of a box tube with a per-run statement (module-scoped)."""
    from simgap.config import load_experiment
    from simgap.pipeline import run_experiment
    d = tmp_path_factory.mktemp("tuberun")
    (d / "cubic.toml").write_text(CUBIC)
    (d / "exp.toml").write_text(TUBE_RUN)
    summary = run_experiment(load_experiment(d / "exp.toml", None), d / "out", log=lambda m: None)
    assert summary["methods"]["stochastic"]["winning_cells"] == 1, summary["methods"]["stochastic"]["synthesis"]
    return d / "out"


@pytest.fixture(scope="module")
def tube(tmp_path_factory):
    """A proved box tube of the cubic pendulum (constant gap) with a hand-made noise tube."""
    from simgap.system_file import load_system_file
    p = tmp_path_factory.mktemp("st") / "cubic.toml"
    p.write_text(CUBIC)
    s = load_system_file(p)
    res = bt.synthesize_box_tube(s, Spec(kind="invariance", safe=Box(s.x_lo, s.x_hi)), np.array([2e-3, 2e-2]),
                                 x0=[0.5, 0.0], x_star=[0, 0], u_star=[0], margin_search=False,
                                 target_lo=[-0.2, -0.5], target_hi=[0.2, 0.5])
    assert not res.empty
    c = res.controller
    c.noise_tube = NoiseTube(lam=5.0, sigma=np.array([0.001, 0.01]), radii=2 * c.radii + 1e-3, H=1.5 * c.H,
                             beta_cert=0.04, horizon=2 * c.T0 + 1)
    return c


def test_tube_statement_draws_the_proved_boxes_and_states_p_cert(tube):
    """Every box the statement draws is the box the proof holds at that period (tube, then terminal),
    the band per period is box_at(t) along each state, the noise tube's boxes are the per-run
    statement's, and p_cert is the noise tube's bound at the horizon. A statement that drew only the
    terminal box, shifted the periods by one or took the mean's tube for the noise tube fails here."""
    st = tube.statement()
    assert st.proved and st.method == "box_tube" and "box tube" in st.name and st.set_name == "the tube"
    assert not NOT_TUBE.search(st.headline + " ".join(r.label + r.value for r in st.rows))
    # margin_search off: said as such, not as a factor ("gamma x not searched")
    assert "margin not searched" in st.headline and "gamma x not" not in st.headline + tube.summary()
    T = 2 * tube.T0 + 1
    for role, noise in (("tube", False), ("noise_tube", True)):
        ds = st.set_of(role)
        assert ds.kind == "boxes" and len(ds.centers) == tube.T0 + 2
        for dim in range(2):
            t, lo, hi = ds.band(dim, T)
            for k in (0, 1, tube.T0 // 2, tube.T0, tube.T0 + 1, T):
                b = tube.box_at(int(t[k]), noise=noise)
                assert lo[k] == pytest.approx(b.c[dim] - b.r[dim]) and hi[k] == pytest.approx(b.c[dim] + b.r[dim])
        rects = ds.outlines((0, 1))
        assert len(rects) == tube.T0 + 2
        for t in (0, tube.T0, tube.T0 + 1):
            b = tube.box_at(t, noise=noise)
            assert rects[t].min(axis=0) == pytest.approx(b.c - b.r) and rects[t].max(axis=0) == pytest.approx(b.c + b.r)
    assert np.allclose(st.set_of("terminal").half_widths[0], tube.H)
    tgt = st.set_of("target")
    assert tgt.centers[0] - tgt.half_widths[0] == pytest.approx([-0.2, -0.5])
    assert st.per_run is not None and st.per_run.p_cert == pytest.approx(tube.noise_tube.p_run(T))
    assert st.per_run.horizon == T and "noise tube" in st.per_run.event
    # with the run's record: p_cert at the rollouts' horizon and the runs counted as single runs
    e = {"per_run_empirical": {"p_cert": 0.5, "horizon": 7, "in_noise_tube": 49, "n_rollouts": 50},
         "reach_and_stay": {"T0": tube.T0, "held": 50, "of": 50, "runs_in_tube": 3, "mean_map_in_tube": False},
         "confidence_proof": 0.96}
    st = tube.statement(e)
    assert st.per_run.p_cert == 0.5 and st.per_run.horizon == 7
    about = {r.label: r.about for r in st.rows}
    assert about["single runs inside the noise tube (p_cert's event)"] == "single_runs"
    assert about["mean map inside the tube"] == "mean_map" and all(
        r.confidence == "all rows" for r in st.rows if r.about == "proof")
    # a mean map outside a proved tube of a noisy certificate is a violation, and says so
    assert any("OUTSIDE the proved tube" in n for n in st.notes)


def test_statement_round_trips_and_not_proved_speaks_for_its_method(tube):
    st = tube.statement()
    for ds in st.sets:
        back = DrawnSet.from_dict(ds.to_dict())
        assert back.role == ds.role and np.array_equal(back.centers, ds.centers) and np.array_equal(back.periods, ds.periods)
    j = st.to_json()
    assert all(set(s) == {"role", "label", "kind"} for s in j["sets"]) and j["per_run"]["p_cert"] == st.per_run.p_cert
    assert isinstance(statement_of("box_tube", tube), Statement)
    no = statement_of("box_tube", None, {"diagnosis": "no tube proved: the gap is too large"})
    assert not no.proved and "box tube" in no.name and no.notes == ["no tube proved: the gap is too large"]
    assert not_proved("invariant_set").name == "invariant ellipsoid E"


def test_tube_run_in_its_own_words(tube_run):
    """The run's summary, CLI table and app speak of the tube: the header names it, the legend its
    tube, noise tube and terminal box, the Per run tab shows p_cert beside p_emp, and no panel
    speaks of an invariant set E; the proved-sets layer draws the loaded method's tube along the plan."""
    import json

    from simgap.pipeline import comparison_table
    from simgap_viz.app import SimgapApp
    from simgap_viz.results import load_run
    summary = json.loads((tube_run / "summary.json").read_text())
    sto = summary["methods"]["stochastic"]
    assert sto["statement"]["method"] == "box_tube" and sto["statement"]["per_run"]["p_cert"] > 0.5
    table = comparison_table(summary)
    assert "box tube from x0" in table and "invariant set" not in table and "x0 in E" not in table
    assert f"{sto['per_run_empirical']['p_cert']:.4f}" in table
    run = load_run(tube_run)
    app = SimgapApp(port=0, executor="serial")
    try:
        app.load_run(run)
        assert "box tube from x0" in app.status.content and "p_cert" in app.status.content
        roles = [d[1] for d in app.invariant_drawn if d[0] == "stochastic"]
        assert roles[:3] == ["tube", "noise_tube", "terminal"]
        legend = app.panels["view"].legend.content
        assert "box tube" in legend and "noise tube" in legend and "terminal box" in legend
        note = app.panels["perrun"].note.content
        p = sto["statement"]["per_run"]["p_cert"]
        assert f"**{p:.4f}**" in note and f"{sto['per_run_empirical']['p_emp']:.4f}" in note
        texts = [h.content for p_ in app.panels.values() for h in vars(p_).values() if hasattr(h, "content")
                 and isinstance(getattr(h, "content", None), str)]
        assert not any(re.search(r"invariant set|Invariant sets E|\bE proved", t) for t in texts + [app.status.content])
        # the Synthesis tab: the run's own method, its keys and what it proved; no grid inputs
        syn = app.panels["synthesis"]
        assert not syn.eta.visible and not syn.hold.visible and "box tube" in syn.method.content
        for want in ("plan T0", "terminal box half-widths H", "margin", "noise tube", "p_cert = "):
            assert want in syn.stats.content, want
        # Synthesize makes a tube again (not a grid over the states), replacing the method's set
        before = run.methods["stochastic"].invariant_set
        app.synthesize(background=False)
        after = run.methods["stochastic"]
        assert after.invariant_set is not before and after.invariant_set.kind == "box_tube"
        assert app.results.get("synthesize") is None  # no grid controller was made
        assert np.allclose(after.invariant_set.radii, before.radii) and after.statement.per_run is not None
    finally:
        app.stop()


def _orange(png: bytes) -> np.ndarray:
    """Pixels of the tube's color (scene.ROLE_STYLE["tube"], shaded by the lights) in a canvas PNG."""
    from PIL import Image
    im = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=int)
    r, g, b = im[..., 0], im[..., 1], im[..., 2]
    return (r > 170) & (g > 60) & (g < 160) & (b < 80) & (r - g > 70)


@pytest.mark.browser
def test_tube_run_in_the_browser(tube_run, tmp_path):
    """The box-tube run in a real headless browser (Playwright + chromium, software WebGL; one page,
    about 12 CPU-seconds), by what the page shows: the header and the Per run tab name the tube and
    p_cert in its own words (never an invariant set E), and the proved-sets layer draws the tube's
    boxes whole, left of the panel, at 1280 x 800 and 1920 x 1080 (screenshots in tmp_path)."""
    from test_browser_app import _assert_window_fit, _need_browser
    _need_browser()
    from playwright.sync_api import sync_playwright

    from simgap_viz import screenshot as S
    from simgap_viz.app import SimgapApp
    from simgap_viz.results import load_run

    app = SimgapApp(port=0, executor="serial")
    try:
        app.load_run(load_run(tube_run))
        p_cert = app.run.methods["stochastic"].statement.per_run.p_cert
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path=S.CHROMIUM, args=S.ARGS)
            try:
                page = S.open_page(b, app.url + "/?fixedDpr=1", 1280, 800)
                text = page.inner_text("body")
                assert "box tube from x0" in text and f"p_cert {p_cert:.3g}" in text, text[:400]
                S.show_tab(page, "Per run", settle=1.0)
                per = page.inner_text("body")
                assert "Per-run statements of the methods" in per and f"{p_cert:.4f}" in per
                S.show_tab(page, "View", settle=1.0)
                view = page.inner_text("body")
                assert "noise tube" in view and "terminal box" in view
                for t in (text, per, view):
                    assert not re.search(r"invariant set|Invariant sets E|\bE proved", t)
                shots = {}
                for w, h in ((1280, 800), (1920, 1080)):
                    page.set_viewport_size({"width": w, "height": h})
                    deadline = 30
                    while app.windows.get(max(app.server.get_clients()), {}).get("size") != (w, h) and deadline:
                        page.wait_for_timeout(500)
                        deadline -= 1
                    _assert_window_fit(app, w, h)
                    page.screenshot(path=str(tmp_path / f"tube-{w}.png"))
                    shots[w] = S.settled_canvas(page, tmp_path / f"canvas-{w}.png")
            finally:
                b.close()
    finally:
        app.stop()
    from simgap_viz.app import panel_width
    for w, png in shots.items():
        tube = _orange(png)
        assert tube.sum() > 150, f"{w}: the tube's boxes are hardly drawn ({tube.sum()} px)"
        ys, xs = np.nonzero(tube)
        # whole and left of the panel: no tube pixel on the canvas' edges or under the panel
        assert xs.min() > 2 and ys.min() > 2 and ys.max() < tube.shape[0] - 3, (w, xs.min(), ys.min(), ys.max())
        assert xs.max() < tube.shape[1] - panel_width(w), (w, xs.max(), tube.shape[1] - panel_width(w))

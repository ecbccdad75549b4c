"""`simgap plot RUN`: the paper's figures from a finished run (matplotlib), with units and every rollout,
ready for a two-column paper: one legend per figure, one color per method, no overlapping labels, an
inset where no data run, dense rollouts rasterized inside vector PDFs (each <= 1 MB)."""

import subprocess
import sys
import types

import numpy as np
import pytest

from simgap.errors import SimgapError

from test_viz_results import run_dir  # noqa: F401  (the tiny real run folder, module-scoped fixture)


@pytest.fixture
def drawn(monkeypatch):
    """Each figure handed to figures.save (its axes, read before it is saved and closed), without
    the label-overlap and inset measurements of ``captured`` (a full draw each)."""
    from simgap_viz import figures
    figs = {}
    real = figures.save

    def keep(fig, out_dir, name):
        figs[name] = {"axes": [{"title": a.get_title(), "ylabel": a.get_ylabel(), "axes": a, "insets": a.child_axes}
                               for a in fig.axes],
                      "legends": [t.get_text() for lg in fig.legends for t in lg.get_texts()]}
        return real(fig, out_dir, name)

    monkeypatch.setattr(figures, "save", keep)
    return figs


@pytest.fixture
def captured(monkeypatch):
    """What each figure handed to figures.save shows (read before it is saved and closed)."""
    from matplotlib.colors import to_hex

    from simgap_viz import figures
    figs = {}
    real = figures.save

    def keep(fig, out_dir, name):
        axes = []
        for a in fig.axes:
            lines = a.get_lines()
            runs = getattr(a, "_simgap_runs", [])  # the runs: drawn as one image per axes at save time
            axes.append({"xlabel": a.get_xlabel(), "ylabel": a.get_ylabel(), "title": a.get_title(),
                         "lines": len(lines), "legend": a.get_legend() is not None, "axes": a,
                         "colors": [to_hex(r[1]) for r in runs],
                         "rasterized": sum(len(r[0]) for r in runs), "insets": a.child_axes})
        figs[name] = {"axes": axes, "legends": [[t.get_text() for t in lg.get_texts()] for lg in fig.legends],
                      "overlaps": figures.text_overlaps(fig), "inches": tuple(fig.get_size_inches()), "fig": fig,
                      "inset_cover": _inset_cover(fig)}
        return real(fig, out_dir, name)

    monkeypatch.setattr(figures, "save", keep)
    return figs


def _inset_cover(fig) -> list:
    """Per inset: the share of its parent axes' plotted points (data lines) that fall under the inset
    or its title, in display coordinates."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    out = []
    for a in fig.axes:
        for ins in a.child_axes:
            bb = ins.get_tightbbox(r)
            paths = [np.column_stack(ln.get_data()).astype(float) for ln in a.get_lines() if len(ln.get_xdata()) > 1]
            paths += [p for r in getattr(a, "_simgap_runs", []) for p in r[0]]
            pts = np.concatenate([a.transData.transform(p) for p in paths])
            inside = (pts[:, 0] >= bb.x0) & (pts[:, 0] <= bb.x1) & (pts[:, 1] >= bb.y0) & (pts[:, 1] <= bb.y1)
            out.append(float(inside.mean()))
    return out


def test_plot_run_figures(run_dir, tmp_path, captured):  # noqa: F811
    from matplotlib.colors import to_hex
    from PIL import Image

    from simgap_viz.figures import METHOD_STYLE, plot_run
    from simgap_viz.results import load_run
    run = load_run(run_dir)
    written = plot_run(run_dir, tmp_path / "fig")
    names = {p.name for p in written}
    assert names == {f"{n}.{e}" for n in ("trajectories", "states_time", "gamma_slices") for e in ("png", "pdf")}
    for p in written:
        if p.suffix == ".png":
            im = np.asarray(Image.open(p).convert("RGB"), float)
            assert im.shape[0] > 300 and im.std() > 10, p  # a drawn picture, not a blank canvas
        else:
            assert p.read_bytes()[:5] == b"%PDF-"
    assert not list((tmp_path / "fig").glob(".*tmp*"))
    # a figure file simgap plot did not write (or that changed since) is never overwritten: refused
    # before anything is drawn; its own earlier figures are replaced on a re-plot
    mine = tmp_path / "fig" / "states_time.pdf"
    mine.write_bytes(b"a user's own file")
    before = {q.name: q.stat().st_mtime_ns for q in (tmp_path / "fig").iterdir()}
    with pytest.raises(SimgapError, match="states_time.pdf"):
        plot_run(run_dir, tmp_path / "fig")
    assert mine.read_bytes() == b"a user's own file"
    assert {q.name: q.stat().st_mtime_ns for q in (tmp_path / "fig").iterdir()} == before
    mine.unlink()
    assert {q.name for q in plot_run(run_dir, tmp_path / "fig")} == names

    for name, f in captured.items():
        assert f["overlaps"] == [], (name, f["overlaps"])  # no two labels drawn over each other
        assert len(f["legends"]) == 1 and not any(a["legend"] for a in f["axes"]), name  # one legend per figure
        assert f["inches"][0] == pytest.approx(7.0), name  # a two-column paper's text width
    # units on the axes; every rollout drawn (one line each, rasterized, in its method's color) plus the
    # mean map, the rollout average and x0
    traj = captured["trajectories"]
    main = [a for a in traj["axes"] if "runs fail" in a["title"]]
    assert [a["title"].split(" gap")[0] for a in main] == ["deterministic", "stochastic"]
    for a, m in zip(main, ("deterministic", "stochastic")):
        ro = run.methods[m].rollouts
        R = ro.trajectories.shape[0]
        assert a["xlabel"] == "theta [rad]"
        assert a["lines"] == 3 and a["rasterized"] == R  # every run, in one rasterized artist
        fails = int((~np.asarray(ro.success)).sum())
        assert a["title"] == f"{m} gap: {fails} of {R} runs fail"
        assert set(a["colors"]) <= {to_hex(METHOD_STYLE[m]), "#ff0000"}  # the method's color, failures red
    assert main[0]["ylabel"] == "omega [rad/s]"
    assert f"stochastic gap: {R} rollouts" in traj["legends"][0] and "mean map (the guarantee)" in traj["legends"][0]
    assert all(c <= 0.02 for c in traj["inset_cover"]), traj["inset_cover"]  # insets where no data run
    st = captured["states_time"]
    assert {a["ylabel"] for a in st["axes"] if a["ylabel"]} == {"theta [rad]", "omega [rad/s]"}
    assert "time [s]" in {a["xlabel"] for a in st["axes"]}
    for a in st["axes"]:  # the same method colors as the trajectories
        m = a["title"].split(" gap")[0] if a["title"] else None
        if m:
            assert set(a["colors"]) == {to_hex(METHOD_STYLE[m])}
    gs = captured["gamma_slices"]
    assert {a["ylabel"] for a in gs["axes"] if a["ylabel"]} == {"gamma_theta [rad/step]", "gamma_omega [rad/s/step]"}


def test_dense_rollouts_keep_pdfs_small(run_dir, tmp_path, captured):  # noqa: F811
    """1000 rollouts x 401 steps per method (the small profile's size) give PDFs <= 1 MB: the rollouts
    are rasterized inside the vector PDF (as vector paths they made 9.8 MB and 5.6 MB), and the inset
    still avoids the runs."""
    from simgap_viz import figures
    from simgap_viz.results import load_run
    from simgap.pipeline import experiment_spec
    run = load_run(run_dir)
    rng = np.random.default_rng(0)
    for m, res in run.methods.items():
        ro = res.rollouts
        base = np.asarray(ro.mean_trajectory)
        T = np.interp(np.linspace(0, base.shape[0] - 1, 401), np.arange(base.shape[0]), np.arange(base.shape[0]))
        path = np.stack([np.interp(T, np.arange(base.shape[0]), base[:, k]) for k in range(base.shape[1])], axis=1)
        X = path[None] + np.cumsum(rng.normal(0, 2e-4, (1000, 401, path.shape[1])), axis=1)
        res.rollouts = types.SimpleNamespace(trajectories=X, success=np.ones(1000, bool), mean_trajectory=X.mean(0),
                                             mean_map_trajectory=path, x0=path[0], tau=float(ro.tau))
    spec, _, _ = experiment_spec(run.experiment)
    paths = figures.trajectories(run, spec, tmp_path) + figures.states_time(run, tmp_path)
    for p in paths:
        if p.suffix == ".pdf":
            assert p.stat().st_size <= 1_000_000, (p.name, p.stat().st_size)
    assert captured["trajectories"]["overlaps"] == [] and captured["states_time"]["overlaps"] == []
    assert all(c <= 0.02 for c in captured["trajectories"]["inset_cover"])


def test_plot_cli_and_bad_input(run_dir, tmp_path):  # noqa: F811
    r = subprocess.run([sys.executable, "-m", "simgap", "plot", str(run_dir), "--out", str(tmp_path / "f"),
                        "--style", "slide"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "trajectories.pdf" in r.stdout and (tmp_path / "f" / "gamma_slices.png").is_file()
    from PIL import Image
    assert Image.open(tmp_path / "f" / "trajectories.png").size[0] > 1500  # 11 in at 150 dpi
    for args, msg in (([str(tmp_path)], "no summary.json"), ([str(run_dir), "--out", str(tmp_path / "no" / "f")],
                                                               "does not exist"),
                      ([str(run_dir), "--max-drawn", "0"], "--max-drawn"),
                      ([str(run_dir), "--style", "poster"], "invalid choice")):
        r = subprocess.run([sys.executable, "-m", "simgap", "plot", *args], capture_output=True, text=True,
                           timeout=300)
        assert r.returncode == 2 and msg in r.stderr and "Traceback" not in r.stderr, (args, r.stderr)
    assert not (tmp_path / "no").exists()


def _ellipsoid_run(P, x_star, with_rollouts=True):
    """A synthetic invariant-set run: a 3-state system, E = {(x - x*)^T P (x - x*) <= 1}, 50 rollouts
    that stay near x* (what the figure reads: experiment.system, methods, nominal, summary)."""
    from simgap.synthesis.ellipsoid_controller import EllipsoidController
    from simgap.systems import System
    s = System(name="e3", state_names=("a", "b", "c"), input_names=("u",), x_lo=np.array([-2.0, -2.0, -2.0]),
               x_hi=np.array([2.0, 2.0, 2.0]), inputs=np.zeros((1, 1)), base_tau=0.1, step=lambda x, u: x)
    ctrl = EllipsoidController(x_star, [0.0], np.zeros((1, 3)), P, system=s)
    rng = np.random.default_rng(3)
    ro = None
    if with_rollouts:
        X = np.asarray(x_star) + 0.05 * np.cumsum(rng.normal(size=(50, 20, 3)), axis=1) / 20
        ro = types.SimpleNamespace(trajectories=X, success=np.ones(50, bool), mean_trajectory=X.mean(0),
                                   mean_map_trajectory=X.mean(0), x0=X[0, 0], tau=0.1)
    res = types.SimpleNamespace(invariant_set=ctrl, rollouts=ro)
    summary = {"methods": {"stochastic": {"winning_cells": 0, "synthesis": {"gap_scale": 0.0047}},
                           "nominal": {"winning_cells": 1}}}
    return types.SimpleNamespace(experiment=types.SimpleNamespace(system=s), system=s, methods={}, nominal=res,
                                 summary=summary, path=None), ctrl


def test_invariant_set_figure_draws_projections(tmp_path, captured):
    """The figure of an invariant-set run draws E's PROJECTION on each pair of states: its extent is
    x* +- sqrt((P^-1)_ii) exactly, which a slice through x* (extent 1 / sqrt(P_ii), smaller for this
    correlated P) or the wrong block of P^-1 would not give; a failed method is named with its margin;
    the labels do not overlap."""
    from simgap_viz import figures
    A = np.array([[1.0, 0.9, 0.3], [0.0, 0.5, -0.4], [0.0, 0.0, 0.3]])
    Q = A @ A.T  # P^-1: strongly correlated states
    P = np.linalg.inv(Q)
    xs = np.array([0.3, -0.2, 0.1])
    run, ctrl = _ellipsoid_run(P, xs)
    paths = figures.invariant_sets(run, None, tmp_path)
    assert {p.name for p in paths} == {"invariant_sets.png", "invariant_sets.pdf"}
    f = captured["invariant_sets"]
    assert f["overlaps"] == [], f["overlaps"]
    assert len(f["legends"]) == 1 and "invariant ellipsoid E, nominal model (no gap)" in f["legends"][0]
    assert "nominal model (no gap): 50 runs" in f["legends"][0]
    assert "stochastic gap: nothing proved (margin s = 0.0047" in f["fig"]._suptitle.get_text()
    assert "tube" not in f["fig"]._suptitle.get_text() + " ".join(f["legends"][0])  # the ellipsoid's own words
    h = np.sqrt(np.diag(Q))
    assert np.all(1 / np.sqrt(np.diag(P)) < 0.9 * h)  # the slice would be visibly smaller
    seen = set()
    for a in f["axes"]:
        for ln in a["axes"].collections:
            gid = ln.get_gid() or ""
            if not gid.startswith("ellipsoid:"):
                continue
            i, j = (int(v) for v in gid.split(":")[2].split(","))
            seen.add((i, j))
            x, y = ln.get_segments()[0].T
            assert x.min() == pytest.approx(xs[i] - h[i], rel=1e-3) and x.max() == pytest.approx(xs[i] + h[i], rel=1e-3)
            assert y.min() == pytest.approx(xs[j] - h[j], rel=1e-3) and y.max() == pytest.approx(xs[j] + h[j], rel=1e-3)
            # every outline point is on the projection's boundary: (y - c)^T P2 (y - c) = 1
            c, P2 = ctrl.projection((i, j))
            e = np.column_stack([x, y]) - c
            assert np.allclose(np.einsum("bi,ij,bj->b", e, P2, e), 1.0)
    assert seen == {(0, 1), (0, 2), (1, 2)}
    # the projection contains every point of E (sampled), which a slice does not
    from simgap.synthesis.set_synthesis import states_in_set
    pts = states_in_set(ctrl, 4000, 0)
    for d in ((0, 1), (0, 2), (1, 2)):
        c, P2 = ctrl.projection(d)
        e = pts[:, d] - c
        lv = np.einsum("bi,ij,bj->b", e, P2, e)
        assert lv.max() <= 1 + 1e-9 and lv.max() > 0.9
    with pytest.raises(Exception, match="two different state indices"):
        ctrl.projection((1, 1))
    # a run without any proved set: no figure
    run.nominal = None
    assert figures.invariant_sets(run, None, tmp_path / "none") == []


def test_states_time_names_the_mean_maps_input_switch():
    """The states_time note names the step where the mean map's input switches (its jump), with the
    two inputs of the controller at the mean; a method whose mean-map input never switches in the
    horizon's second half is not named."""
    from simgap_viz.figures import mean_map_switch_note

    T, tau = 40, 0.01
    mean = np.zeros((T + 1, 2))
    mm = mean.copy()
    mm[31:, 1] = 0.02  # the jump: m_31 - m_30 = 0.02 in the second state
    inputs = np.array([[-1.0], [0.0], [0.6]])

    class Ctrl:
        def __init__(self, idx):
            self.idx, self.inputs = idx, inputs

        def input_index(self, x):
            assert x.shape == (T, 2)  # the input at every mean-map state that takes a step
            return self.idx

    switch = np.zeros(T, int)
    switch[30:] = 2  # the input applied at m_30 (the step to m_31) is 0.6, before it -1
    system = types.SimpleNamespace(x_lo=np.array([-1.0, -1.0]), x_hi=np.array([1.0, 1.0]), state_names=["theta", "omega"])

    def method(idx):
        ro = types.SimpleNamespace(mean_map_trajectory=mm, mean_trajectory=mean, tau=tau)
        return types.SimpleNamespace(rollouts=ro, synthesis=types.SimpleNamespace(controller=Ctrl(idx)))

    run = types.SimpleNamespace(system=system, methods={"deterministic": method(switch),
                                                        "stochastic": method(np.zeros(T, int))})
    note = mean_map_switch_note(run, ["deterministic", "stochastic"])
    assert "deterministic gap, t = 0.3 s: omega steps by +0.02 as the input at the mean switches from -1 to 0.6" in note
    assert "stochastic gap" not in note and "no angle wrap" in note
    assert mean_map_switch_note(run, ["stochastic"]) == ""


def _synthetic_run(n: int, kind: str, spread: float, tmp_path):
    """A run of an n-state system as `simgap plot` reads it (RunResults built in memory): for
    ``kind`` "grid" both methods with a certificate, a data set and rollouts; for "invariant_set"
    the stochastic certificate's and the nominal model's proved ellipsoids with their rollouts and
    the deterministic certificate's failed proof. The rollouts settle at x* with a final spread of
    ``spread`` times the box (0.01: under the 5 % that draws the zoom on the final states)."""
    from simgap.synthesis.ellipsoid_controller import EllipsoidController
    from simgap.synthesis.spec import Box, Spec
    from simgap.systems import System
    from simgap_viz.results import MethodResults, RunResults
    rng = np.random.default_rng(n)
    names = tuple(f"s{i}" for i in range(n))
    x_lo, x_hi = -np.ones(n), np.ones(n)
    system = System(name=f"sys{n}", state_names=names, input_names=("u",), x_lo=x_lo, x_hi=x_hi,
                    inputs=np.linspace(-1, 1, 3)[:, None], base_tau=0.1, step=lambda x, u: x)
    x_star = np.linspace(-0.2, 0.2, n)
    R, T = 30, 40
    decay = np.exp(-np.arange(T) / 8.0)[None, :, None]
    x0 = x_star + 0.5 * (x_hi - x_star)
    noise = spread * (x_hi - x_lo) * rng.uniform(-0.5, 0.5, (R, 1, n))
    X = x_star + (x0 - x_star) * decay + noise * (1 - decay)  # every run leaves x0 and settles near x*

    def rollouts(shift):
        Y = X + shift
        return types.SimpleNamespace(trajectories=Y, success=np.ones(R, bool), mean_trajectory=Y.mean(0),
                                     mean_map_trajectory=(x_star + (x0 - x_star) * decay[0]) + shift, x0=Y[0, 0],
                                     tau=0.1)

    def certificate(scale):  # gamma_i(x, u) = scale (1 + x_i^2): positive, shaped along its own state
        return types.SimpleNamespace(gamma=lambda x, u: scale * (1 + np.asarray(x) ** 2))

    xs = rng.uniform(x_lo, x_hi, (200, n))
    xs[:, 1:] = 0.0  # on the line gamma_slices draws along s0: the data gaps near it are shown
    us = np.zeros((200, 1))
    dataset = types.SimpleNamespace(x=xs, u=us, epsilon=0.05, gap=lambda: 0.01 * (1 + xs ** 2) * 0.8)
    methods, nominal = {}, None
    if kind == "grid":
        spec = Spec(kind="reach_avoid", target=Box(x_star - 0.1, x_star + 0.1),
                    obstacles=(Box(np.full(n, 0.5), np.full(n, 0.7)),))
        for i, m in enumerate(("deterministic", "stochastic")):
            methods[m] = MethodResults(dataset=dataset, certificate=certificate(0.01 * (2 - i)), audit=None,
                                       synthesis=None, rollouts=rollouts(0.01 * i))
        summary = {"methods": {m: {"winning_cells": 10} for m in methods}}
    else:
        spec = Spec(kind="invariance", safe=Box(x_lo * 0.9, x_hi * 0.9))
        P = np.diag(1.0 / (0.6 * (x_hi - x_lo)) ** 2)
        ctrl = EllipsoidController(x_star, [0.0], np.zeros((1, n)), P, system=system)
        methods["deterministic"] = MethodResults(dataset=dataset, certificate=certificate(0.02), audit=None,
                                                 synthesis=None)
        methods["stochastic"] = MethodResults(dataset=dataset, certificate=certificate(0.01), audit=None,
                                              synthesis=None, rollouts=rollouts(0.0), invariant_set=ctrl)
        nominal = MethodResults(dataset=None, certificate=None, audit=None, synthesis=None,
                                rollouts=rollouts(0.005), invariant_set=ctrl)
        summary = {"sections": {"synthesis": {"method": "invariant_set"}},
                   "methods": {"deterministic": {"winning_cells": 0, "synthesis": {"gap_scale": 0.004}},
                               "stochastic": {"winning_cells": 1}, "nominal": {"winning_cells": 1}}}
    run = RunResults(path=tmp_path, summary=summary, methods=methods, stage_system=system, spec=spec)
    run.nominal = nominal
    return run, X


@pytest.mark.parametrize("kind", ["grid", "invariant_set"])
@pytest.mark.parametrize("n", [2, 3, 4, 6])
def test_every_figure_for_every_method_and_dimension(n, kind, tmp_path, drawn):
    """Every figure of `simgap plot` is drawn for 2, 3, 4 and 6 states, for a grid run and an
    invariant-set run, with the runs' final spread under 5 % of the box (which draws the zoom on the
    final states: with 4 states it joined the rollouts' two plotted columns with the 4-state mean
    trajectory and raised) and over it. Each trajectory panel draws the mean map and the rollout
    average over the first two states, the same columns as the rollouts."""
    from PIL import Image

    from simgap_viz.figures import plot_run, trajectories
    for spread in ((0.01, 0.2) if n == 4 else (0.01,)):  # with and without the zoom (4 states: the crash)
        run, X = _synthetic_run(n, kind, spread, tmp_path)
        out = tmp_path / f"fig-{spread}"
        if spread > 0.05:  # without the zoom only the trajectories change: that figure alone
            out.mkdir()
            written = trajectories(run, run.spec, out)
            figs = {"trajectories"}
        else:
            written = plot_run(run, out)
            figs = {"trajectories", "states_time", "gamma_slices"} | ({"invariant_sets"} if kind != "grid" else set())
        assert {p.name for p in written} == {f"{f}.{e}" for f in figs for e in ("png", "pdf")}
        for p in written:
            if p.suffix == ".png":
                im = np.asarray(Image.open(p).convert("RGB"), float)
                assert im.shape[0] > 300 and im.std() > 10, p  # a drawn picture, not a blank canvas
        traj = drawn["trajectories"]
        main = [a for a in traj["axes"] if "runs fail" in a["title"]]
        assert len(main) == 2
        assert all(len(a["insets"]) == (1 if spread < 0.05 else 0) for a in main), spread
        for a in main:
            m = a["title"].split(" gap")[0].split(" model")[0]
            ro = (run.nominal if m == "nominal" else run.methods[m]).rollouts
            paths = [np.column_stack(ln.get_data()) for ln in a["axes"].get_lines() if not ln.get_rasterized()]
            mm, avg = np.asarray(ro.mean_map_trajectory)[:, :2], np.asarray(ro.mean_trajectory)[:, :2]
            assert any(p.shape == mm.shape and np.allclose(p, mm) for p in paths), m
            assert any(p.shape == avg.shape and np.allclose(p, avg) for p in paths), m
        # the nominal model's mean map is no guarantee about the simulator: the legend says so
        assert ("mean map (the guarantee; nominal: none)" if kind != "grid" else "mean map (the guarantee)") \
            in traj["legends"]
        if spread > 0.05:
            continue
        st = drawn["states_time"]
        assert {a["ylabel"].split(" ")[0] for a in st["axes"] if a["ylabel"]} == {f"s{i}" for i in range(n)}
        gs = drawn["gamma_slices"]
        assert len([a for a in gs["axes"] if a["axes"].get_lines()]) == n * n
        if kind != "grid":
            pairs = {tuple(int(v) for v in (ln.get_gid() or "E:x:").split(":")[2].split(","))
                     for a in drawn["invariant_sets"]["axes"] for ln in a["axes"].collections
                     if (ln.get_gid() or "").startswith("ellipsoid:stochastic")}
            from simgap_viz.figures import state_pairs
            assert pairs == set(state_pairs(n))

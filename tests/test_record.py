"""Rerun recordings, read back with rerun.chunk.RrdReader (rerun-sdk 0.41); `simgap view`."""

import os
import subprocess
import sys

import numpy as np
import pytest

from simgap.errors import SimgapError

PENDULUM_NUMPY = {"kind": "numpy", "system": "pendulum", "noise": {"actuation_std": 0.05},
                  "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]]}}


@pytest.fixture(scope="module")
def run_results():
    """A tiny but real run: data, certificate, a controller for the nominal model, 60 rollouts
    (and 30 more from another seed, recorded as a second method)."""
    from simgap.certify.synthetic import synthetic_dataset
    from simgap_viz import engine
    from simgap_viz.jobs import JobContext
    from simgap_viz.settings import Settings

    ds = synthetic_dataset(PENDULUM_NUMPY, 0.05, 20, seed=1)
    s = Settings(epsilon=0.05, n_runs=20, use_gap=False, eta=(0.005, 0.01), n_rollouts=60, horizon=80)
    ctx = JobContext(name="test")
    cert = engine.certify(ds, s, ctx)
    spec = engine.default_spec(ds.system)
    syn = engine.synthesize(ds.system, spec, None, s, ctx)
    ro = engine.rollout(ds.system, spec, syn, s, ctx)
    ro2 = engine.rollout(ds.system, spec, syn, s.replace(n_rollouts=30, rollout_seed=5), ctx)
    return ds, cert, spec, syn, ro, ro2


def _positions_per_row(rb, col):
    return [len(v) for v in rb.column(col).to_pylist()]


def _strip(rb, path):
    return np.asarray(rb[path]["chunks"][0].column("LineStrips3D:strips").to_pylist()[0][0])


def test_record_read_back(tmp_path, run_results):
    """Two methods in one recording: every entity entity_paths() names (and docs/app.md lists) is
    in the file and nothing else; each method's entities hold that method's results."""
    from simgap_viz.record import entity_paths, read_back, record_run

    ds, cert, spec, syn, ro, ro2 = run_results
    out = tmp_path / "run.rrd"
    methods = {"deterministic": dict(dataset=ds, certificate=cert, synthesis=syn, rollouts=ro2),
               "stochastic": dict(dataset=ds, certificate=cert, synthesis=syn, rollouts=ro)}
    info = record_run(out, ds.system, spec=spec, methods=methods, res=31)
    assert out.exists() and info["bytes"] == out.stat().st_size
    assert not list(tmp_path.glob(".*tmp*")), "temporary file left behind"
    rb = read_back(out)
    got = {k.lstrip("/") for k in rb} - {"__properties", "world"}  # the recording's own, the view coordinates
    assert got == set(entity_paths(ds.system.state_names, ("deterministic", "stochastic"))) == set(info["entities"])

    # rollouts: R strips; the animated state has T+1 time rows of R points each, on two timelines
    for m, r in (("stochastic", ro), ("deterministic", ro2)):
        R, T1 = r.trajectories.shape[:2]
        paths = rb[f"/world/{m}/rollouts/paths"]["chunks"][0]
        assert len(paths.column("LineStrips3D:strips").to_pylist()[0]) == R
        assert len(paths.column("LineStrips3D:strips").to_pylist()[0][0]) == T1
        st = rb[f"/world/{m}/rollouts/state"]
        assert st["rows"] == T1 and {"step", "time"} <= st["columns"] and not st["static"]
        counts = sum((_positions_per_row(c, "Points3D:positions") for c in st["chunks"]), [])
        assert counts == [R] * T1
        steps = np.concatenate([np.asarray(c.column("step").to_pylist()) for c in st["chunks"]])
        assert np.array_equal(np.sort(steps), np.arange(T1))
        # the mean map (what the guarantee is about) and the rollout average, each its own entity
        assert np.allclose(_strip(rb, f"/world/{m}/rollouts/mean_map")[:, :2], r.mean_map_trajectory[:, :2], atol=1e-6)
        assert np.allclose(_strip(rb, f"/world/{m}/rollouts/mean")[:, :2], r.mean_trajectory[:, :2], atol=1e-6)
        # the time-series views: T+1 scalars on the step timeline
        for key, want in (("mean", r.mean_trajectory), ("mean_map", r.mean_map_trajectory)):
            ts = rb[f"/timeseries/omega/{m}/{key}"]
            assert "step" in ts["columns"]
            vals = np.concatenate([np.asarray(c.column("Scalars:scalars").to_pylist(), float).ravel()
                                   for c in ts["chunks"] if "Scalars:scalars" in c.schema.names])
            assert vals.shape == (T1,) and np.allclose(vals, np.asarray(want)[:, 1])
        first = np.asarray(st["chunks"][0].column("Points3D:positions").to_pylist()[0])
        assert np.allclose(first[:, :2], r.x0[None, :2], atol=1e-6) and np.allclose(first[:, 2], 0)
    assert not np.allclose(ro.mean_map_trajectory, ro2.mean_map_trajectory)  # the methods' data differ
    assert (info["n_rollouts"], info["n_steps"]) == (60, 81)

    # gamma meshes: res^2 vertices and 2 (res-1)^2 triangles per dimension
    for name in ("theta", "omega"):
        mesh = rb[f"/gamma/stochastic/{name}/surface"]["chunks"][0]
        assert len(mesh.column("Mesh3D:vertex_positions").to_pylist()[0]) == 31 * 31
        assert len(mesh.column("Mesh3D:triangle_indices").to_pylist()[0]) == 2 * 30 * 30
    assert info["gamma_vertices"] == 31 * 31 and info["gamma_triangles"] == 2 * 30 * 30

    # winning domain: one box per winning cell of the 2-D grid
    boxes = rb["/world/stochastic/winning"]["chunks"][0]
    assert len(boxes.column("Boxes3D:centers").to_pylist()[0]) == syn.stats["winning"] == info["winning_cells"]["stochastic"]
    text = rb["/summary"]["chunks"][0].column("TextDocument:text").to_pylist()[0]
    text = "".join(text) if isinstance(text, list) else text
    assert "joint confidence" in text and "rollouts of pendulum" in text
    assert "## deterministic" in text and "## stochastic" in text

    # a default blueprint is in the file
    from rerun.chunk import RrdReader
    assert len(RrdReader(str(out)).blueprints()) == 1


def test_gamma_heights_share_one_scale_across_methods(tmp_path, run_results):
    """The methods' surfaces are drawn at one height scale per state (not each stretched to 1):
    a certificate with twice the gamma stands twice as high."""
    from simgap_viz.record import read_back, record_run

    ds, cert, spec, syn, ro, ro2 = run_results

    class Doubled:  # the same certificate with gamma doubled (engine.gamma_function reads .gamma)
        def __init__(self, c):
            self._c = c

        def __getattr__(self, k):
            return getattr(self._c, k)

        def gamma(self, x, u):
            return 2 * self._c.gamma(x, u)

    out = tmp_path / "two.rrd"
    record_run(out, ds.system, methods={"a": dict(certificate=cert), "b": dict(certificate=Doubled(cert))})
    rb = read_back(out)
    z = {m: np.asarray(rb[f"/gamma/{m}/omega/surface"]["chunks"][0].column("Mesh3D:vertex_positions")
                       .to_pylist()[0])[:, 2] for m in ("a", "b")}
    assert np.isclose(z["b"].max(), 1.0) and np.allclose(z["b"], 2 * z["a"], rtol=1e-5)



def test_record_draws_the_invariant_sets_projection(tmp_path):
    """An invariant-set method's E is drawn on the map as its projection onto (x1, x2): the outline's
    extent is x* +- sqrt((P^-1)_ii) (a slice through x* would be narrower for this correlated P)."""
    from simgap.synthesis.ellipsoid_controller import EllipsoidController
    from simgap.systems import System
    from simgap_viz.record import read_back, record_run

    s = System(name="e3", state_names=("a", "b", "c"), input_names=("u",), x_lo=np.array([-2.0, -2.0, -2.0]),
               x_hi=np.array([2.0, 2.0, 2.0]), inputs=np.zeros((1, 1)), base_tau=0.1, step=lambda x, u: x)
    P = np.array([[4.0, 3.0, 0.5], [3.0, 4.0, 0.0], [0.5, 0.0, 2.0]])
    x_star = np.array([0.3, -0.2, 0.0])
    ctrl = EllipsoidController(x_star, [0.0], np.zeros((1, 3)), P, system=s)
    out = tmp_path / "inv.rrd"
    info = record_run(out, s, methods={"nominal": {"invariant_set": ctrl}})
    assert "world/nominal/invariant_set" in info["entities"]
    rb = read_back(out)
    pts = np.asarray(rb["/world/nominal/invariant_set"]["chunks"][0].column("LineStrips3D:strips").to_pylist()[0][0])
    half = np.sqrt(np.diag(np.linalg.inv(P)))[:2]
    np.testing.assert_allclose(pts[:, :2].max(axis=0), x_star[:2] + half, rtol=1e-3)
    np.testing.assert_allclose(pts[:, :2].min(axis=0), x_star[:2] - half, rtol=1e-3)
    assert np.all(half > 1 / np.sqrt(np.diag(P))[:2] * 1.2)  # the slice would be visibly narrower

def test_record_partial_and_bad_paths(tmp_path, run_results):
    from simgap_viz.record import read_back, record_run

    ds, cert, spec, syn, ro, _ = run_results
    out = tmp_path / "cert_only.rrd"
    info = record_run(out, ds.system, certificate=cert)
    rb = read_back(out)
    m = cert.method
    assert f"/gamma/{m}/omega/surface" in rb and f"/world/{m}/rollouts/state" not in rb and info["n_rollouts"] == 0
    with pytest.raises(SimgapError, match=".rrd"):
        record_run(tmp_path / "x.txt", ds.system)
    with pytest.raises(SimgapError, match="does not exist"):
        record_run(tmp_path / "missing" / "x.rrd", ds.system)


def test_cli_record(tmp_path):
    out = tmp_path / "cli.rrd"
    p = subprocess.run([sys.executable, "-m", "simgap", "record", "--out", str(out), "--experiment", "pendulum",
                        "--profile", "small", "--epsilon", "0.1", "--n-runs", "5", "--no-gap", "--eta", "0.005,0.01",
                        "--n-rollouts", "20", "--horizon", "30", "--executor", "serial"],
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "rerun " + str(out) in p.stdout
    from simgap_viz.record import read_back
    rb = read_back(out)
    assert sum(v["rows"] for k, v in rb.items() if k.endswith("/rollouts/state")) == 31
    bad = subprocess.run([sys.executable, "-m", "simgap", "record", "--out", str(tmp_path / "b.rrd"),
                          "--experiment", "pendulum", "--profile", "small", "--epsilon", "-1"],
                         capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert bad.returncode == 2 and "epsilon" in bad.stderr


def _port_free(port: int) -> bool:
    import socket
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


def _start_view(args, cwd):
    """`simgap view ARGS` in the background; (process, URL) once it printed the address."""
    import re
    import time
    p = subprocess.Popen([sys.executable, "-m", "simgap", "view", *map(str, args)], stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True, cwd=cwd)
    lines, deadline = [], time.time() + 90
    while time.time() < deadline:
        line = p.stdout.readline()
        if not line:
            break
        lines.append(line)
        m = re.search(r"open (http://\S+) in a browser", line)
        if m:
            return p, m.group(1)
    p.kill()
    raise AssertionError("simgap view printed no address: " + "".join(lines))


def test_view_refuses_bad_input(tmp_path):
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "fake.rrd").write_text("not a recording")
    (tmp_path / "empty").mkdir()
    for arg, msg in (("missing", "does not exist"), ("notes.txt", "not a Rerun recording"),
                     ("fake.rrd", "not a readable Rerun recording"), ("empty", "holds no run.rrd")):
        r = subprocess.run([sys.executable, "-m", "simgap", "view", arg], capture_output=True, text=True,
                           cwd=tmp_path, timeout=120)
        assert r.returncode == 2 and msg in r.stderr and "Traceback" not in r.stderr, (arg, r.stderr)


@pytest.mark.browser
def test_view_serves_the_recording_and_stops_everything(tmp_path, run_results):
    """`simgap view RUN` prints an address whose page shows the recording (not rerun's welcome page):
    the gamma surfaces' colors fill the canvas; on SIGTERM both ports are free again (the native
    viewer process is stopped with its launcher)."""
    import io
    import re
    import signal
    import time

    from PIL import Image
    from test_browser_app import ARGS, CHROMIUM, _need_browser

    from simgap_viz.record import METHOD_COLORS, record_run
    _need_browser()
    from playwright.sync_api import sync_playwright

    ds, cert, spec, syn, ro, _ = run_results
    run = tmp_path / "run"
    run.mkdir()
    record_run(run / "run.rrd", ds.system, dataset=ds, certificate=cert, spec=spec, synthesis=syn, rollouts=ro,
               method="stochastic")
    proc, url = _start_view([run, "--web-port", 0, "--grpc-port", 0], tmp_path)
    from urllib.parse import parse_qs, unquote, urlparse
    grpc = parse_qs(urlparse(url).query)["url"][0]
    assert re.fullmatch(r"rerun\+http://127\.0\.0\.1:\d+/proxy", grpc) and "%2B" in url, url
    ports = [urlparse(url).port, urlparse(grpc.replace("rerun+", "")).port]
    assert not any(_port_free(p) for p in ports), url
    if os.environ.get("SIMGAP_MUTATE_VIEW"):  # check of the check: the bare address shows the welcome page
        url = unquote(url).split("?")[0]
    try:
        with sync_playwright() as pw:
            b = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = b.new_page(viewport={"width": 1280, "height": 800})
            page.goto(url)
            orange, deadline = 0, time.time() + 150
            while orange < 2000 and time.time() < deadline:  # the wasm viewer loads slowly under SwiftShader
                time.sleep(3)
                png = page.screenshot(path=str(tmp_path / "view.png"))
                img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
                orange = int(np.count_nonzero(np.all(np.abs(img - np.array(METHOD_COLORS["stochastic"])) <= 40, axis=-1)))
            b.close()
        assert orange >= 2000, f"the page does not show the recording's gamma_omega surface ({orange} px)"
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    time.sleep(0.5)
    assert all(_port_free(p) for p in ports), "a port is still held after simgap view ended"


def test_view_killed_leaves_no_viewer(tmp_path, run_results):
    """SIGKILL of `simgap view` (no cleanup code runs) still stops the native viewer: both ports free."""
    import signal
    import time
    from urllib.parse import parse_qs, urlparse

    from simgap_viz.record import record_run
    ds, cert, spec, syn, ro, _ = run_results
    record_run(tmp_path / "c.rrd", ds.system, certificate=cert)
    proc, url = _start_view([tmp_path / "c.rrd", "--web-port", 0, "--grpc-port", 0], tmp_path)
    grpc = parse_qs(urlparse(url).query)["url"][0]
    ports = [urlparse(url).port, urlparse(grpc.replace("rerun+", "")).port]
    assert not any(_port_free(p) for p in ports)
    proc.send_signal(signal.SIGKILL)
    proc.wait(30)
    deadline = time.time() + 20
    while time.time() < deadline and not all(_port_free(p) for p in ports):
        time.sleep(0.5)
    assert all(_port_free(p) for p in ports), "the viewer outlived a killed `simgap view`"


def _descendants(pid: int) -> list:
    """(pid, state, name) of every live descendant of ``pid`` (Linux /proc)."""
    procs = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = open(f"/proc/{d}/stat").read()
            except OSError:
                continue
            name = stat[stat.index("(") + 1:stat.rindex(")")]
            state, ppid = stat[stat.rindex(")") + 2:].split()[:2]
            procs[int(d)] = (int(ppid), state, name)
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        kids = [(c, s, n) for c, (pp, s, n) in procs.items() if pp == p]
        out += kids
        todo += [c for c, _, _ in kids]
    return out


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads the process tree from /proc")
def test_view_starts_no_browser_and_leaves_no_process(tmp_path, run_results):
    """`simgap view` runs the viewer alone: no browser child (the viewer's --web-viewer mode opened
    one, a chromium it never reaped: a defunct process while it ran), no zombie, and after SIGTERM no
    descendant of it is left. (Its idle CPU is measured by bench/bench_view_cpu.py, not timed here.)"""
    import signal
    import time

    from simgap_viz.record import record_run
    ds, cert, spec, syn, ro, _ = run_results
    run = tmp_path / "run"
    run.mkdir()
    record_run(run / "run.rrd", ds.system, dataset=ds, certificate=cert, spec=spec, synthesis=syn, rollouts=ro,
               method="stochastic")
    proc, url = _start_view([run, "--web-port", 0, "--grpc-port", 0], tmp_path)
    try:
        time.sleep(6)  # the browser the old command line opened appeared within a few seconds
        tree = _descendants(proc.pid)
        assert tree, "no viewer process under simgap view"
        assert all(n == "rerun" for _, _, n in tree), tree  # the viewer, no browser
        assert not [t for t in tree if t[1] == "Z"], tree
        pids = [p for p, _, _ in tree]
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    time.sleep(0.5)
    left = [p for p in pids if os.path.exists(f"/proc/{p}")]
    assert not left, f"processes left after simgap view ended: {left}"

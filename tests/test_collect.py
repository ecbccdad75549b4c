"""Collection: statistics, seeded determinism, serial == local pool, cancellation/resume, the store, bad input."""

import json
import re
import threading
import time

import numpy as np
import pytest

from simgap.collect import CollectionPlan, chunk_rng, collect, load_samples, load_store, store_status
from simgap.cover import CoverSpec, make_cover
from simgap.dataset import load_dataset
from simgap.errors import SimgapError
from simgap.simulators import base as sim_base
from simgap.simulators.base import SimulatorConfig, make_simulator
from simgap.simulators.numpy_sim import NumpySimulator
from simgap.systems import System, get_system, input_grid

FIELDS = ("x", "u", "f_nom", "mean", "var", "lo", "hi", "cover_index", "input_index")

PEND_SIM = SimulatorConfig("numpy", "pendulum", noise={"actuation_std": 0.05, "sensor_std": 1e-4},
                           effects={"linear": [[0.0, 0.0], [0.0, -0.5]]})


def pend_plan(eps=0.05, n_runs=40, seed=7, sim=PEND_SIM, **kw):
    s = get_system("pendulum")
    return CollectionPlan(system=s, simulator=sim, cover=make_cover(s, eps), n_runs=n_runs, seed=seed, **kw)


def assert_same(a, b):
    for k in FIELDS:
        x, y = getattr(a, k), getattr(b, k)
        assert x.dtype == y.dtype and np.array_equal(x, y), k


def test_statistics_match_the_raw_samples(tmp_path):
    plan = pend_plan(n_runs=30, keep_samples=True, chunk_size=50, batch_runs=300)  # 10 pairs per step call
    res = collect(plan, tmp_path / "s", executor="serial")
    assert res.complete and res.computed == plan.n_chunks
    ds = load_store(tmp_path / "s")
    Y = load_samples(tmp_path / "s")
    assert Y.shape == (ds.K, 30, 2)
    np.testing.assert_array_equal(ds.mean, Y.mean(axis=1))
    np.testing.assert_array_equal(ds.var, Y.var(axis=1, ddof=1))
    np.testing.assert_array_equal(ds.lo, Y.min(axis=1))
    np.testing.assert_array_equal(ds.hi, Y.max(axis=1))
    # the rows are the cover x inputs, cover-major, with f computed by the nominal model
    cover, U = plan.cover, plan.system.inputs
    assert ds.K == cover.N * len(U)
    np.testing.assert_array_equal(ds.x, cover.points[ds.cover_index])
    np.testing.assert_array_equal(ds.u, U[ds.input_index])
    assert ds.cover_index[0] == 0 and ds.input_index[:3].tolist() == [0, 1, 2]
    np.testing.assert_array_equal(ds.f_nom, plan.system.f(ds.x, ds.u))
    # chunk 1 reproduced by hand from its own generator: 50 pairs, two step calls of 10 pairs
    sim = make_simulator(PEND_SIM)
    rng = chunk_rng(7, 1)
    rows = slice(50, 100)
    want = [sim.step(np.repeat(ds.x[rows][i:i + 10], 30, 0), np.repeat(ds.u[rows][i:i + 10], 30, 0), rng)
            for i in range(0, 50, 10)]
    np.testing.assert_array_equal(Y[rows], np.concatenate(want).reshape(50, 30, 2))
    # the manifest carries what later stages need
    m = ds.manifest
    assert m["hash"] == res.hash == plan.hash() and len(m["hash"]) == 64
    assert m["simulator"] == PEND_SIM.to_dict() and m["seed"] == 7 and m["n_runs"] == 30
    assert m["system"]["name"] == "pendulum" and m["cover"]["n_points"] == plan.cover.N
    assert ds.epsilon == 0.05 and ds.n_runs == 30


def test_gap_estimates_the_true_mean():
    """With additive noise the empirical mean converges to the numpy simulator's exact E fhat."""
    import tempfile
    sim = SimulatorConfig("numpy", "pendulum", noise={"process_std": 1e-3},
                          effects={"linear": [[0.0, 0.0], [0.0, -0.5]]})
    plan = pend_plan(eps=0.1, n_runs=400, sim=sim)
    with tempfile.TemporaryDirectory() as d:
        collect(plan, d + "/s", executor="serial")
        ds = load_dataset(d + "/s")
    true_mean = make_simulator(sim).mean_next(ds.x, ds.u)
    z = (ds.mean - true_mean) / np.sqrt(1e-6 / 400)
    assert np.abs(z).max() < 6
    assert np.allclose(ds.var, 1e-6, rtol=0.3)
    # the damping gap in omega is visible above the noise: tau * 0.5 * |omega|
    big = np.abs(ds.x[:, 1]) > 0.3
    assert np.all(ds.gap()[big, 1] > 0.005 * 0.5 * 0.3 - 6 * 1e-3 / 20)


def test_angle_statistics_across_the_seam(tmp_path):
    s = get_system("turtlebot").with_steps(1)
    s = s.__class__(**{**s.__dict__, "inputs": input_grid([0, 0], [0, 0], [1, 1])})  # u = 0: stay put
    sim = SimulatorConfig("numpy", "turtlebot", noise={"sensor_std": [0.0, 0.0, 0.3]})
    cover = make_cover(s, CoverSpec(0.2, invariant_dims=("x", "y")))
    plan = CollectionPlan(system=s, simulator=sim, cover=cover, n_runs=2000, seed=1)
    collect(plan, tmp_path / "s", executor="serial")
    ds = load_store(tmp_path / "s", system=s)
    # headings next to +-pi: the wrapped mean stays next to f_nom, the variance is the true 0.09
    assert np.abs(s.diff(ds.mean, ds.f_nom)[:, 2]).max() < 0.05
    np.testing.assert_allclose(ds.var[:, 2], 0.09, rtol=0.15)
    assert np.all(ds.lo[:, 2] < ds.f_nom[:, 2]) and np.all(ds.hi[:, 2] > ds.f_nom[:, 2])
    assert np.all(np.abs(ds.mean[:, 2]) <= np.pi)


def test_seeded_determinism_and_executor_independence(tmp_path):
    plan = pend_plan(eps=0.04, n_runs=25, chunk_size=37)
    collect(plan, tmp_path / "serial", executor="serial")
    collect(plan, tmp_path / "pool2", executor="local", workers=2)
    collect(plan, tmp_path / "pool1", executor="local", workers=1)
    a, b, c = (load_store(tmp_path / n) for n in ("serial", "pool2", "pool1"))
    assert_same(a, b)
    assert_same(a, c)
    assert a.hash == b.hash
    other = pend_plan(eps=0.04, n_runs=25, chunk_size=37, seed=8)
    collect(other, tmp_path / "seed8", executor="serial")
    d = load_store(tmp_path / "seed8")
    assert d.hash != a.hash and not np.array_equal(d.mean, a.mean)
    np.testing.assert_array_equal(d.f_nom, a.f_nom)


def test_cancel_and_resume_equals_uninterrupted(tmp_path):
    plan = pend_plan(eps=0.04, n_runs=25, chunk_size=37)
    stop = threading.Event()
    seen = []

    def on_progress(done, total):
        seen.append((done, total))
        if done >= 3 * 37:
            stop.set()

    r1 = collect(plan, tmp_path / "s", executor="serial", on_progress=on_progress, should_stop=stop)
    assert r1.cancelled and not r1.complete and r1.done == 3
    assert seen[0] == (0, plan.n_pairs)
    with pytest.raises(SimgapError, match=r"incomplete: \d+ of \d+ chunks missing.*resume"):
        load_store(tmp_path / "s")
    assert store_status(tmp_path / "s")["done"] == 3
    stale = tmp_path / "s" / "chunks" / ".c000007.npz.999999999.tmp"  # a killed writer's half-written file
    stale.write_bytes(b"half")
    seen.clear()
    r2 = collect(plan, tmp_path / "s", executor="local", workers=2, on_progress=lambda d, t: seen.append(d))
    assert r2.complete and r2.resumed_from == 3 and r2.computed == plan.n_chunks - 3
    assert seen[0] == 3 * 37 and seen[-1] == plan.n_pairs
    assert not stale.exists()
    collect(plan, tmp_path / "ref", executor="serial")
    assert_same(load_store(tmp_path / "s"), load_store(tmp_path / "ref"))


def test_chunk_subset(tmp_path):
    plan = pend_plan(eps=0.04, n_runs=10, chunk_size=100)
    r = collect(plan, tmp_path / "s", executor="serial", chunk_ids=[0, 2])
    assert r.done == 2 and not r.cancelled
    with pytest.raises(SimgapError, match="out of range"):
        collect(plan, tmp_path / "s", executor="serial", chunk_ids=[plan.n_chunks])


def test_resume_with_different_config_is_refused(tmp_path):
    plan = pend_plan(eps=0.05, n_runs=20)
    collect(plan, tmp_path / "s", executor="serial", chunk_ids=[0])
    before = {p.name: p.read_bytes() for p in (tmp_path / "s").rglob("*") if p.is_file()}
    for other, key in [(pend_plan(eps=0.05, n_runs=21), "n_runs"), (pend_plan(eps=0.05, n_runs=20, seed=8), "seed"),
                       (pend_plan(eps=0.04, n_runs=20), "cover.epsilon"),
                       (pend_plan(eps=0.05, n_runs=20, sim=SimulatorConfig("numpy", "pendulum")),
                        "simulator.effects")]:
        with pytest.raises(SimgapError, match=f"different configuration.*{key}"):
            collect(other, tmp_path / "s", executor="serial")
    after = {p.name: p.read_bytes() for p in (tmp_path / "s").rglob("*") if p.is_file()}
    assert before == after


def test_nan_in_configuration_is_refused(tmp_path):
    bad = SimulatorConfig("numpy", "pendulum", effects={"linear": [[0.0, 0.0], [0.0, float("nan")]]})
    with pytest.raises(SimgapError, match="NaN"):
        collect(pend_plan(sim=bad), tmp_path / "s", executor="serial")
    assert not (tmp_path / "s").exists()


class NanSim(NumpySimulator):
    """A numpy simulator that returns NaN for fast-spinning states (a stand-in for a physics blow-up)."""

    def step_with_noise(self, x, u, noise):
        out = super().step_with_noise(x, u, noise)
        out[x[:, 1] > 0.3, 1] = np.nan
        return out


def test_nan_from_simulator_leaves_no_data(tmp_path, monkeypatch):
    monkeypatch.setitem(sim_base._BACKENDS, "nan_test", f"{__name__}:NanSim")
    bad = SimulatorConfig("nan_test", "pendulum")
    from simgap.executors import LocalExecutor
    for ex in ("serial", "local"):
        store = tmp_path / ex
        # the monkeypatched backend reaches pool workers only by fork; a thread another test left alive in
        # this process (a progress bar's monitor) would make the default start method forkserver
        executor = ex if ex == "serial" else LocalExecutor(2, start_method="fork")
        with pytest.raises(SimgapError, match=r"chunk (\d+).*NaN") as err:
            collect(pend_plan(sim=bad, chunk_size=20), store, executor=executor)
        failed = int(re.search(r"chunk (\d+)", str(err.value)).group(1))
        files = sorted(p.name for p in (store / "chunks").iterdir())
        assert f"c{failed:06d}.npz" not in files
        assert all(re.fullmatch(r"c\d{6}\.npz", f) for f in files)  # no temp file left behind
        with pytest.raises(SimgapError, match="incomplete"):
            load_store(store)


@pytest.mark.parametrize("kw,match", [
    ({"n_runs": 1}, "N1hat must be >= 2"), ({"n_runs": 0}, "N1hat"), ({"n_runs": 2.5}, "integer"),
    ({"seed": -1}, "seed"), ({"chunk_size": 0}, "chunk_size"), ({"batch_runs": 0}, "batch_runs")])
def test_bad_plan(kw, match):
    with pytest.raises(SimgapError, match=match):
        pend_plan(**kw)


def test_plan_consistency_checks():
    s = get_system("pendulum")
    with pytest.raises(SimgapError, match="simulates 'turtlebot'"):
        CollectionPlan(s, SimulatorConfig("numpy", "turtlebot"), make_cover(s, 0.1), n_runs=5)
    with pytest.raises(SimgapError, match="steps"):
        CollectionPlan(s, SimulatorConfig("numpy", "pendulum", steps=2), make_cover(s, 0.1), n_runs=5)
    with pytest.raises(SimgapError, match="unknown simulator kind"):
        make_simulator(SimulatorConfig("bogus", "pendulum"))


def test_cover_points_outside_x_or_tampered():
    import dataclasses
    s = get_system("pendulum")
    cover = make_cover(s, 0.1)
    with pytest.raises(SimgapError, match="outside X"):
        CollectionPlan(s, PEND_SIM, dataclasses.replace(cover, points=cover.points + 0.3), n_runs=5)
    with pytest.raises(SimgapError, match="differ from what its spec produces"):
        CollectionPlan(s, PEND_SIM, dataclasses.replace(cover, points=cover.points * 0.5), n_runs=5)


def test_unreadable_or_mismatched_store(tmp_path):
    with pytest.raises(SimgapError, match="does not exist"):
        load_store(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SimgapError, match="not a simgap store"):
        load_store(tmp_path / "empty")
    with pytest.raises(SimgapError, match="does not exist"):
        load_dataset(tmp_path / "nope.npz")

    plan = pend_plan(eps=0.1, n_runs=5, chunk_size=30)
    collect(plan, tmp_path / "s", executor="serial")
    load_store(tmp_path / "s")
    # wrong system
    with pytest.raises(SimgapError, match="different system"):
        load_store(tmp_path / "s", system=get_system("pendulum").with_steps(2))
    # a corrupted chunk is named
    chunk = tmp_path / "s" / "chunks" / "c000001.npz"
    good = chunk.read_bytes()
    chunk.write_bytes(good[:100])
    with pytest.raises(SimgapError, match="c000001.npz is unreadable"):
        load_store(tmp_path / "s")
    chunk.write_bytes(good)
    # a chunk from another collection
    collect(pend_plan(eps=0.1, n_runs=5, chunk_size=30, seed=99), tmp_path / "t", executor="serial")
    (tmp_path / "s" / "chunks" / "c000002.npz").write_bytes((tmp_path / "t" / "chunks" / "c000002.npz").read_bytes())
    with pytest.raises(SimgapError, match="another collection"):
        load_store(tmp_path / "s")
    # a hand-edited manifest
    m = json.loads((tmp_path / "t" / "manifest.json").read_text())
    m["config"]["n_runs"] = 6
    (tmp_path / "t" / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(SimgapError, match="modified"):
        load_store(tmp_path / "t")
    (tmp_path / "t" / "manifest.json").write_text("{not json")
    with pytest.raises(SimgapError, match="unreadable"):
        load_store(tmp_path / "t")
    # refuse to write into a foreign non-empty directory
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "notes.txt").write_text("mine")
    with pytest.raises(SimgapError, match="non-empty directory"):
        collect(plan, tmp_path / "foreign", executor="serial")


# a user-defined system at module level, so that worker processes can unpickle it
def _cart_step(x, u, dt):
    return np.stack([x[:, 0] + dt * x[:, 1], x[:, 1] + dt * (u[:, 0] - 0.1 * x[:, 1])], axis=1)


CART = System(name="cart", state_names=("p", "v"), input_names=("F",), x_lo=(-1, -1), x_hi=(1, 1),
              inputs=input_grid([-1], [1], [5]), base_tau=0.01, step=_cart_step)


def test_user_defined_system_through_the_pool(tmp_path):
    sim = SimulatorConfig("numpy", "cart", noise={"process_std": 1e-3})
    plan = CollectionPlan(CART, sim, make_cover(CART, 0.2), n_runs=10, seed=3)
    collect(plan, tmp_path / "a", executor="serial")
    collect(plan, tmp_path / "b", executor="local", workers=2)
    with pytest.raises(SimgapError, match="cannot rebuild"):
        load_store(tmp_path / "a")
    a, b = load_store(tmp_path / "a", system=CART), load_store(tmp_path / "b", system=CART)
    assert_same(a, b)
    assert isinstance(make_simulator(sim, CART), NumpySimulator)


PYB_SIM = SimulatorConfig("pybullet_pendulum", "pendulum", noise={"actuation_std": 0.05, "sensor_std": 1e-4},
                          effects={"joint_damping": 0.1}, options={"branches": 25})


def test_pybullet_pendulum_collection(tmp_path):
    """A small real PyBullet collection: serial == local pool; batched rows == one-row-at-a-time rows."""
    pytest.importorskip("pybullet")
    plan = pend_plan(eps=0.1, n_runs=30, seed=5, sim=PYB_SIM, chunk_size=40, keep_samples=True)
    collect(plan, tmp_path / "serial", executor="serial")
    collect(plan, tmp_path / "pool", executor="local", workers=2)
    a, b = load_store(tmp_path / "serial"), load_store(tmp_path / "pool")
    assert_same(a, b)
    Y = load_samples(tmp_path / "pool")
    # chunk 2 again, one row at a time with the chunk's own noise draws
    sim = make_simulator(PYB_SIM)
    rows = slice(80, 120)
    xs, us = np.repeat(a.x[rows], 30, 0), np.repeat(a.u[rows], 30, 0)
    noise = sim.draw_noise(len(xs), chunk_rng(5, 2))
    for i in (0, 17, 599, len(xs) - 1):
        one = sim.step_with_noise(xs[i:i + 1], us[i:i + 1], {k: v[i:i + 1] for k, v in noise.items()})
        np.testing.assert_array_equal(one[0], Y[rows].reshape(-1, 2)[i])
    sim.close()
    # joint damping makes a gap in omega that grows with |omega| (the nominal model has none)
    g = a.system.diff(a.mean, a.f_nom)[:, 1]
    fast = np.abs(a.x[:, 1]) > 0.35
    assert np.all(np.sign(g[fast]) == -np.sign(a.x[fast, 1]))


def test_ray_missing_is_a_clear_error(monkeypatch):
    import sys

    from simgap.executors import make_executor
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(SimgapError, match="pip install"):
        make_executor("ray")
    with pytest.raises(SimgapError, match="unknown executor"):
        make_executor("dask")
    with pytest.raises(SimgapError, match="workers"):
        make_executor("local", workers=-2)


def test_progress_bar_and_stop_checks():
    import io

    from simgap.progress import ProgressBar, as_stop_check
    buf = io.StringIO()
    bar = ProgressBar(unit="pairs", stream=buf, scale=100.0, scale_unit="sim steps", desc="collect")
    for done in range(200, 1001, 50):  # a resumed run: 200 pairs were done before
        time.sleep(0.002)
        bar(done, 1000)
    out = buf.getvalue()
    final = out.replace("\r", "\n").strip().splitlines()[-1]
    assert final.startswith("collect: 100%") and "1000/1000" in final, final
    rate = float(final.split(", ")[-1].split(" sim steps/s")[0].replace(",", ""))
    assert 0 < rate < 800 * 100 / 0.032, final  # 800 new pairs x 100 steps in at least 16 sleeps
    assert "\r" not in out and out.count("\n") <= 2  # off a terminal: lines, no redraw storm (first, final)
    ev = threading.Event()
    check = as_stop_check(ev)
    assert not check()
    ev.set()
    assert check()
    assert as_stop_check(lambda: 1)() is True and as_stop_check(None)() is False
    with pytest.raises(TypeError):
        as_stop_check(3)


class NanEverywhereSim(NumpySimulator):
    """A numpy simulator whose every run blows up: the first chunk fails."""

    def step_with_noise(self, x, u, noise):
        return np.full_like(super().step_with_noise(x, u, noise), np.nan)


@pytest.mark.parametrize("sim,match", [
    (SimulatorConfig("nosuch", "pendulum"), "unknown simulator kind 'nosuch'"),
    (SimulatorConfig("numpy", "pendulum", noise={"actuaton_std": 0.1}), "unknown noise keys"),
    (SimulatorConfig("nan_all", "pendulum"), r"chunk 0 .*NaN")])
def test_failed_collection_leaves_no_store(tmp_path, monkeypatch, sim, match):
    """A collection that fails before its first chunk is stored leaves no folder behind (it is checked
    before anything is created, or removed with its manifest); an existing folder is never removed."""
    monkeypatch.setitem(sim_base._BACKENDS, "nan_all", f"{__name__}:NanEverywhereSim")
    store = tmp_path / "deep" / "store"
    with pytest.raises(SimgapError, match=match):
        collect(pend_plan(sim=sim, chunk_size=20), store, executor="serial")
    assert list(tmp_path.iterdir()) == []  # neither the store nor the parent it would have created
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(SimgapError, match=match):
        collect(pend_plan(sim=sim, chunk_size=20), empty, executor="serial")
    assert empty.is_dir() and list(empty.iterdir()) == []  # the user's folder stays, as empty as it was


def test_progress_off_a_terminal_is_one_line_per_update():
    """Written to a file or a pipe, progress is whole lines (a log keeps each), the first at once, then
    at most one per interval, the last at the end; a bar closed early says where it stopped. On a
    terminal it stays tqdm's redraw in place."""
    import io

    from simgap.progress import ProgressBar

    buf = io.StringIO()
    bar = ProgressBar(unit="pairs", stream=buf, desc="collect", interval_off_tty=0.05)
    t0 = time.monotonic()
    for done in range(0, 101):
        time.sleep(0.003)
        bar(done, 100)
    took = time.monotonic() - t0
    lines = buf.getvalue().split("\n")
    assert lines[-1] == "" and "\r" not in buf.getvalue()
    lines = lines[:-1]
    assert lines[0].startswith("collect:   0% 0/100 pairs [")
    assert lines[-1].startswith("collect: 100% 100/100 pairs [") and "left" not in lines[-1]
    assert 3 <= len(lines) <= took / 0.05 + 2, (len(lines), took)  # throttled, yet more than first and last
    pct = [int(ln.split("%")[0].split()[-1]) for ln in lines]
    assert pct == sorted(pct) and len(set(pct)) == len(pct)
    assert all(", " in ln and "pairs/s]" in ln for ln in lines[1:])  # a rate once work was done
    # stopped early: close() writes where it stopped (once), then nothing more
    buf = io.StringIO()
    bar = ProgressBar(unit="runs", stream=buf, desc="audit", interval_off_tty=60.0)
    bar(0, 50)
    bar(20, 50)
    bar.close()
    bar.close()
    assert buf.getvalue().splitlines() == [buf.getvalue().splitlines()[0], buf.getvalue().splitlines()[1]]
    assert buf.getvalue().splitlines()[1].startswith("audit:  40% 20/50 runs [")

    class Tty(io.StringIO):
        def isatty(self):
            return True

    buf = Tty()
    bar = ProgressBar(unit="pairs", stream=buf, desc="collect")
    for done in range(0, 101, 10):
        bar(done, 100)
    assert "\r" in buf.getvalue()  # a terminal: tqdm redraws in place

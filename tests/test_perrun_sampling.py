"""Interval-MDP sampling through the executors: the same bits on any executor and worker count, on a
local Ray instance, and after kill -9 and resume; a store of another configuration is refused."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.perrun import cost
from simgap.perrun.imdp import IMDPOptions
from simgap.perrun.sampling import RUNS_ARRAYS, build_imdp
from simgap.simulators import make_simulator
from simgap.simulators.base import SimulatorConfig
from simgap.synthesis.spec import Box, Spec
from simgap.systems import get_system

REPO = Path(__file__).resolve().parents[1]
SPEC = Spec("invariance", safe=Box([-0.15, -0.5], [0.15, 0.5]))
FIELDS = ("row_ptr", "col", "lo", "hi", "k_lo", "k_hi", "live", "target")
# a small noisy pendulum: 35 live cells x 21 inputs; about a second per build in one process
CASE = """
from simgap.perrun.imdp import IMDPOptions
from simgap.simulators import make_simulator
from simgap.simulators.base import SimulatorConfig
from simgap.synthesis.spec import Box, Spec
from simgap.systems import get_system
system = get_system("pendulum", steps=1)
sim = make_simulator(SimulatorConfig("numpy", "pendulum", noise={"actuation_std": 0.2}, steps=1), system)
spec = Spec("invariance", safe=Box([-0.15, -0.5], [0.15, 0.5]))
"""


@pytest.fixture(scope="module")
def sim():
    s = get_system("pendulum", steps=1)
    with make_simulator(SimulatorConfig("numpy", "pendulum", noise={"actuation_std": 0.2}, steps=1), s) as sm:
        yield sm


def _opts(**kw):
    return IMDPOptions(**{"eta": [0.05, 0.125], "hold": 10, "n_runs": 300, "pilot_runs": 50, "seed": 1, **kw})


def _same(a, b):
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and np.array_equal(x, y), f
    assert a.meta["lipschitz"] == b.meta["lipschitz"] and a.meta["samples"] == b.meta["samples"]


@pytest.fixture(scope="module")
def serial(sim):
    """Per cell and shared runs, in this process (the reference of every comparison below)."""
    return {"cell": build_imdp(sim, SPEC, _opts()), "shared": build_imdp(sim, SPEC, _opts(share=3))}


@pytest.mark.parametrize("kind", ["cell", "shared"])
def test_local_pool_with_one_or_two_workers_equals_this_process(sim, serial, kind):
    """Chunks drawn from per-chunk generators: a pool of 1 or 2 workers (chunks finishing in any order,
    simulators rebuilt from their config) gives the interval MDP of the serial build bit for bit.
    Fails if a chunk's randomness came from a stream shared across chunks or from the worker."""
    o = _opts(share=3 if kind == "shared" else None)
    for w in (1, 2):
        _same(build_imdp(sim, SPEC, o, executor="local", workers=w), serial[kind])
    assert serial[kind].meta["sampling"]["chunks"] > 10
    assert serial[kind].nnz > serial[kind].live.sum() * 21          # rows with real successors


def test_chunking_is_part_of_the_configuration(sim, serial):
    """Another chunk size cuts the random streams differently: other counts (so chunk_size is hashed
    into the store's configuration), the same support structure in expectation."""
    other = build_imdp(sim, SPEC, _opts(chunk_size=5))
    assert other.meta["sampling"]["config_hash"] != serial["cell"].meta["sampling"]["config_hash"]
    assert not np.array_equal(other.k_hi, serial["cell"].k_hi)


@pytest.mark.ray
def test_ray_equals_local_pool(sim, serial):
    """A real local Ray instance (started once here, both phases reuse it) gives the pool's bits."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        for kind, o in (("cell", _opts()), ("shared", _opts(share=3))):
            _same(build_imdp(sim, SPEC, o, executor="ray", workers=2), serial[kind])
    finally:
        ray.shutdown()


def _chunk_digests(folder: Path) -> dict:
    out = {}
    for p in sorted((folder / "chunks").glob("c*.npz")):
        with np.load(p, allow_pickle=False) as z:
            out[p.name] = str(z["digest"])
    return out


def test_kill_9_mid_sampling_and_resume_is_bit_identical(sim, serial, tmp_path):
    """A local pool sampling into a store is killed with SIGKILL once some chunks are written; the same
    call on the store (here in this process) keeps those chunks, computes the rest and gives the
    uninterrupted build bit for bit, with the same content digest per chunk as a store written in one go.
    Fails if resumed chunks were drawn from a stream that depends on what ran before."""
    store = tmp_path / "killed"
    script = CASE + f"""
from simgap.perrun.sampling import build_imdp
build_imdp(sim, spec, IMDPOptions(eta=[0.05, 0.125], hold=10, n_runs=300, pilot_runs=50, seed=1, chunk_size=2),
           executor="local", workers=2, store={str(store)!r})
print("finished")
"""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    chunks = store / "runs" / "chunks"
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120 and p.poll() is None and len(list(chunks.glob("c*.npz"))) < 20:
        time.sleep(0.01)
    os.kill(p.pid, signal.SIGKILL)
    out, err = p.communicate()
    assert "finished" not in out, "the sampling ended before it could be killed"
    n_runs_chunks = json.loads((store / "runs" / "manifest.json").read_text())["config"]["n_chunks"]
    before = _chunk_digests(store / "runs")
    assert 20 <= len(before) < n_runs_chunks
    stamps = {q.name: q.stat().st_mtime_ns for q in chunks.glob("c*.npz")}
    resumed = build_imdp(sim, SPEC, _opts(chunk_size=2), store=store)
    one_go = build_imdp(sim, SPEC, _opts(chunk_size=2), store=tmp_path / "one_go")
    _same(resumed, one_go)
    after = _chunk_digests(store / "runs")
    assert len(after) == n_runs_chunks and after == _chunk_digests(tmp_path / "one_go" / "runs")
    assert all(after[k] == v for k, v in before.items())          # the killed run's chunks were kept,
    assert all((chunks / k).stat().st_mtime_ns == t for k, t in stamps.items())   # not recomputed
    _same(build_imdp(sim, SPEC, _opts(chunk_size=2)), resumed)    # and equal the build without a store
    assert not list(store.rglob("*.tmp"))


def test_store_refuses_other_configuration_and_modified_chunks(sim, tmp_path):
    store = tmp_path / "st"
    a = build_imdp(sim, SPEC, _opts(n_runs=100, pilot_runs=20), store=store)
    with pytest.raises(SimgapError, match="different configuration.*n_runs"):
        build_imdp(sim, SPEC, _opts(n_runs=120, pilot_runs=20), store=store)
    # a chunk re-saved with other counts is found by its digests and recomputed: the same result
    p = store / "runs" / "chunks" / "c000003.npz"
    with np.load(p, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["n_hit"] = arrays["n_hit"] + 1
    np.savez(p, **arrays)
    again = build_imdp(sim, SPEC, _opts(n_runs=100, pilot_runs=20), store=store)
    _same(again, a)
    assert set(RUNS_ARRAYS) <= set(np.load(p).files)
    # simgap run's own store (replace_other): the changed options replace the old samples, said in the log
    said = []
    other = build_imdp(sim, SPEC, _opts(n_runs=120, pilot_runs=20), store=store, replace_other=True, log=said.append)
    assert any("removed the per-run samples of another configuration" in m and "runs" in m for m in said)
    assert other.meta["n_runs"] == 120
    _same(other, build_imdp(sim, SPEC, _opts(n_runs=120, pilot_runs=20)))
    said.clear()
    build_imdp(sim, SPEC, _opts(n_runs=120, pilot_runs=20), store=store, replace_other=True, log=said.append)
    assert not any("removed" in m for m in said)                  # the same options resume, nothing removed


def test_refusal_names_the_numbers(tmp_path):
    """A per-run stage the machine cannot hold (4e9 cells: tens of TB of interval entries) is refused
    before any sampling, with exit 2, the numbers (simulator steps, interval entries, memory needed and
    available) and nothing written, through the command users run."""
    from cli_helpers import files, refused, simgap
    toml = REPO / "tests" / "data" / "perrun_tiny.toml"
    before = files(tmp_path)
    t0 = time.monotonic()
    r = simgap("synthesize", "--level", "run", "--spec", toml, "--eta", "0.00001,0.00001", "--out",
               tmp_path / "c.npz", "--store", tmp_path / "st", "--workers", "2", cwd=tmp_path)
    refused(r, "4,000,000,000 cells x 21 inputs", "5.04e+14 simulator steps", "2.69e+12 interval entries",
            "needs about 54 TB of memory", "is available", "coarser [perrun] eta")
    assert r.returncode == 2 and time.monotonic() - t0 < 60 and files(tmp_path) == before


def test_time_refusal_counts_cpu_hours_at_the_sampling_rate():
    """Over 6 hours at the calibrated rates: refused naming the steps and CPU-hours, with the way out
    (more workers through Ray, or the override); the sampling's own rate, not the simulator's, prices
    the interval MDP."""
    s = get_system("pendulum")
    o = {"eta": [0.04, 0.1], "hold": 20, "horizon": 400, "n_runs": 4000, "pilot_runs": 400, "n_rollouts": 10000,
         "n_states": 20}
    fast = cost.perrun_size(o, s, rate_per_worker=1e7, sampling_rate=1e7)
    slow = cost.perrun_size(o, s, rate_per_worker=1e7, sampling_rate=1e5)
    assert slow["cpu_hours"] == pytest.approx(slow["sampling_steps"] / 1e5 / 3600 + slow["rollout_steps"] / 1e7 / 3600)
    assert slow["cpu_hours"] > 30 * fast["cpu_hours"]
    with pytest.raises(SimgapError, match=r"simulator steps.*CPU-hours.*would take about .* on 4 worker\(s\).*"
                                          r"--executor ray --address.*SIMGAP_NO_SIZE_CHECK"):
        cost.check_perrun(o, s, rate_per_worker=1e7, workers=4, sampling_rate=1e3)       # 15.5 h
    cost.check_perrun(o, s, rate_per_worker=1e7, workers=4, sampling_rate=1e7)      # 8 min: accepted


def test_calibration_measures_rate_and_support(sim, serial):
    """The projection's sampling rate and support per row are measured on a few pairs: the support is
    that of the real build within a factor 2 (here the one-cell widening of the calibration against the
    secants' own), and the memory estimate uses it rather than the a-priori guess of 32 per row."""
    from simgap.perrun.sampling import calibrate_sampling
    cal = calibrate_sampling(sim, SPEC, _opts())
    real = serial["cell"].nnz / (serial["cell"].live.sum() * serial["cell"].M)
    assert cal["rate"] > 0 and 0.5 * real <= cal["entries_per_row"] <= 2 * real, (cal, real)
    o = {"eta": [0.05, 0.125], "hold": 10, "horizon": 40, "n_runs": 300, "pilot_runs": 50, "n_rollouts": 10,
         "n_states": 1}
    s = sim.system
    guess, measured = cost.perrun_size(o, s), cost.perrun_size(o, s, entries_per_row=150.0)
    C = np.prod(np.ceil((s.x_hi - s.x_lo) / np.array([0.05, 0.125])))
    assert measured["entries"] == C * 21 * 150 and guess["entries"] == C * 21 * 32
    assert measured["memory"] - guess["memory"] == pytest.approx(C * 21 * (150 - 32) * 20)

"""No silent hours: every command whose work can take long prints its estimate within seconds,
before the work, and refuses work over the machine's memory with the numbers, writing nothing.

The long commands are started as a user would (a subprocess), their first lines read with a
timeout, and then they are killed: these are not timing tests of the work itself.
"""

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cli_helpers import REPO, refused, simgap

DUFFING = REPO / "examples" / "duffing"


def _start(*args, cwd):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, "-m", "simgap", *map(str, args)], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)


def lines_until(proc, word: str, timeout: float = 30.0) -> list:
    """stdout lines up to the first one starting with ``word``, read within ``timeout`` seconds of
    the process's start (the work an estimate announces takes minutes; 30 s leaves room for a loaded
    machine's imports); the process is killed afterwards either way."""
    import selectors
    out, t0 = [], time.monotonic()
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    try:
        while time.monotonic() - t0 < timeout:
            if not sel.select(timeout=max(0.0, timeout - (time.monotonic() - t0))):
                break
            line = proc.stdout.readline()
            if not line:
                break
            out.append(line.rstrip("\n"))
            if line.startswith(word):
                return out
        raise AssertionError(f"no line starting with {word!r} within {timeout} s; got {out}")
    finally:
        proc.kill()
        proc.wait()


@pytest.fixture(scope="module")
def duffing(tmp_path_factory):
    """The Duffing example (no profiles) with a large [audit], collected and certified."""
    d = tmp_path_factory.mktemp("duffing")
    for f in ("duffing.toml", "experiment.toml"):
        shutil.copy(DUFFING / f, d / f)
    text = (d / "experiment.toml").read_text().replace("points = 20\nruns = 200", "points = 5000\nruns = 20000")
    assert "runs = 20000" in text
    (d / "experiment.toml").write_text(text)
    r = simgap("collect", "experiment.toml", "--out", "data", "--n-runs", "4", "--no-progress", cwd=d)
    assert r.returncode == 0, r.stderr
    sys.path.insert(0, str(REPO))
    from simgap.certify import certify
    from simgap.dataset import load_dataset
    certify(load_dataset(d / "data"), degree=1, beta1=0.05, beta2=0.05).save(d / "cert.json")
    return d


def test_audit_reads_the_experiment_and_prints_its_estimate_first(duffing):
    # the experiment's [audit] asks 5000 points x 20000 runs: minutes, not the default 200 x 2000
    lines = lines_until(_start("audit", "cert.json", "--data", "data", "--experiment", "experiment.toml",
                               cwd=duffing), "estimate:")
    assert "5,000 points x 20,000 runs" in lines[0] and "experiment.toml [audit]" in lines[0], lines
    assert "100,000,000 simulator runs" in lines[-1] and "peak memory" in lines[-1], lines
    # flags override the section
    lines = lines_until(_start("audit", "cert.json", "--data", "data", "--experiment", "experiment.toml",
                               "--points", "3000", cwd=duffing), "estimate:")
    assert "3,000 points x 20,000 runs" in lines[0] and "--points" in lines[0], lines


def test_audit_over_memory_is_refused_before_any_run(duffing):
    from simgap.checks import available_memory
    from simgap.certify.audit import audit_cost
    from simgap.system_ref import resolve_system
    runs = 10 ** 9  # one point's runs go at once: a chunk of 10^9 rows
    need = audit_cost(1, runs, resolve_system(str(duffing / "duffing.toml")))["memory"]
    if need <= available_memory():
        pytest.skip(f"this machine has more than {need / 2 ** 30:.0f} GB available")
    r = simgap("audit", "cert.json", "--data", "data", "--points", "1", "--runs", runs, "--out", "rep.json",
               cwd=duffing, timeout=60)
    refused(r, "auditing 1 points x 1,000,000,000 runs", "of memory", "--runs")
    assert "estimate:" in r.stdout
    assert not (duffing / "rep.json").exists()


def test_certify_lhat_simulator_prints_its_estimate_then_progress(duffing):
    lines = lines_until(_start("certify", "data", "--degree", "1", "--beta", "0.05", "--lhat", "simulator",
                               cwd=duffing), "estimate:")
    assert "2,000 pairs x 100 runs x 2 ends = 400,000 simulator runs" in lines[-1], lines
    r = simgap("certify", "data", "--degree", "1", "--beta", "0.05", "--lhat", "simulator", cwd=duffing)
    assert r.returncode == 0, r.stderr
    assert "Lhat_fhat (simulator)" in r.stderr and "400000/400000" in r.stderr, r.stderr


def test_synthesis_prints_cells_boxes_and_memory_before_building(duffing):
    # 4,001 x 3,001 cells x 9 inputs: minutes of abstraction; the estimate comes first
    lines = lines_until(_start("synthesize", "--no-gap", "--spec", "experiment.toml", "--eta", "0.0005,0.001",
                               "--out", "big.npz", cwd=duffing), "estimate:")
    est = lines[-1]
    assert "4001 x 3001 = 12,007,001 cells x 9 inputs" in est, est
    assert "valid boxes" in est and "transitions" in est and "peak memory" in est, est
    assert not (duffing / "big.npz").exists()


def test_synthesis_estimate_matches_the_built_abstraction():
    """The sampled boxes stand for all cells: the estimate is within 25 % of what is built."""
    import numpy as np
    sys.path.insert(0, str(REPO))
    from simgap.synthesis.abstraction import build_abstraction
    from simgap.synthesis.boxes import pair_volumes
    from simgap.synthesis.cost import synthesis_cost
    from simgap.synthesis.grid import UniformGrid
    from simgap.system_ref import resolve_system
    s = resolve_system(str(DUFFING / "duffing.toml"))
    for eta, gap in (([0.02, 0.02], np.array([0.002, 0.01])), ([0.01, 0.05], None)):
        grid = UniformGrid(s.x_lo, s.x_hi, eta)
        est = synthesis_cost(s, grid, gap)
        ab = build_abstraction(s, grid, gap=gap)
        boxes, trans = int(ab.ok.sum()), float(pair_volumes(ab)[ab.ok].sum())
        assert est["cells"] == grid.size and est["pairs"] == grid.size * len(s.inputs)
        assert abs(est["boxes"] / boxes - 1) < 0.25, (eta, est["boxes"], boxes)
        assert abs(est["transitions"] / trans - 1) < 0.25, (eta, est["transitions"], trans)


def test_synthesis_over_memory_is_refused_with_the_numbers(duffing):
    from simgap.checks import available_memory
    # 40,001 x 50,001 = 2.0e9 cells (under the grid's 2^31 limit), 9 inputs
    r = simgap("synthesize", "--no-gap", "--spec", "experiment.toml", "--eta", "0.00005,0.00006",
               "--out", "huge.npz", cwd=duffing, timeout=120)
    if r.returncode == 0 or "of memory" not in r.stderr:
        assert available_memory() > 100 * 2 ** 30, r.stderr  # only a very large machine builds it
        pytest.skip("this machine has over 100 GB available")
    refused(r, "synthesis on 2,000,090,001 cells x 9 inputs", "of memory", "coarser --eta")
    assert "estimate:" in r.stdout
    assert not (duffing / "huge.npz").exists()


@pytest.mark.parametrize("kind", ["invariance", "reach_avoid"])
def test_the_game_reports_its_iterations(kind):
    """The games say how far they are while they run (throttled; here every iteration)."""
    import numpy as np
    sys.path.insert(0, str(REPO))
    import simgap.synthesis.controller as controller
    from simgap.synthesis.fixed_point import game_progress
    from simgap.synthesis.spec import Box, Spec
    from simgap.system_ref import resolve_system
    s = resolve_system(str(DUFFING / "duffing.toml"))
    spec = (Spec(kind="invariance", safe=Box(np.array([-0.8, -1.2]), np.array([0.8, 1.2]))) if kind == "invariance"
            else Spec(kind="reach_avoid", target=Box(np.array([-0.1, -0.1]), np.array([0.1, 0.1]))))
    lines = []
    orig = controller.game_progress
    try:
        controller.game_progress = lambda log: game_progress(log, every=0.0)
        res = controller.synthesize(s, spec, [0.02, 0.02], gap=np.array([0.002, 0.01]), log=lines.append)
    finally:
        controller.game_progress = orig
    its = [int(ln.split("iteration ")[1].split(",")[0].replace(",", "")) for ln in lines if ln.startswith("game: iter")]
    assert lines[0].startswith("estimate:") and its, lines
    assert its == sorted(its) and its[-1] <= res.stats["iterations"] and its[-1] >= res.stats["iterations"] - 1


def test_shared_boxes_with_a_wide_gap_are_not_refused():
    """The TurtleBot's boxes are shared along x and y: its game keeps no list per transition. A wide
    gap (boxes of ~1,600 cells) on the separation scan's grid (413,343 cells x 25 inputs) was refused
    at "84.7 GB" when every transition was charged 8 bytes; the estimate now follows the game that
    runs, and a smaller grid with the same gap is synthesized."""
    import numpy as np
    sys.path.insert(0, str(REPO))
    from simgap.synthesis.controller import synthesize
    from simgap.synthesis.cost import synthesis_cost
    from simgap.synthesis.grid import UniformGrid
    from simgap.config import load_experiment
    from simgap.synthesis.spec import Box, Spec
    s = load_experiment(REPO / "assets" / "experiments" / "turtlebot.toml", "gazebo").system  # 25 inputs, 0.3 s
    assert len(s.inputs) == 25
    gap = np.array([0.3, 0.3, 0.3])
    big = synthesis_cost(s, UniformGrid(s.x_lo, s.x_hi, [0.05, 0.05, 0.0997331]), gap, 1, (0, 1))
    assert big["mean_box_cells"] > 1000 and big["transitions"] > 1e9, big
    assert big["memory"] < 2 ** 30, big["memory_parts"]
    spec = Spec(kind="reach_avoid", target=Box(np.array([2.5, 2.5, -np.pi]), np.array([4.0, 4.0, np.pi])))
    res = synthesize(s, spec, [0.1, 0.1, 0.2], gap=gap / 3)
    assert res.stats["invariant_dims"] == [0, 1] and res.stats["game_method"] == "sat"
    assert res.controller.size > 0

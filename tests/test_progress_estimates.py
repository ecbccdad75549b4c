"""No silent minute: every long path prints its estimate first, then progress, and its totals
match the work done (a small numpy pendulum drives each path in seconds)."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from simgap.cli import main

TINY = """
description = "tiny pendulum for the estimate and progress tests"
[system]
name = "pendulum"
steps = 1
[simulator]
kind = "numpy"
noise = { actuation_std = 0.01 }
effects = { linear = [[0.0, 0.0], [0.0, -0.1]] }
[collect]
epsilon = 0.01
n_runs = 20
seed = 1
executor = "serial"
[certify]
degree = 2
beta1 = 0.05
beta2 = 0.05
lhat = "simulator"
lipschitz_term = "gap"
lhat_pairs = 300
lhat_runs = 20
[audit]
points = 10
runs = 50
seed = 7
[synthesis]
spec = "invariance"
eta = [0.005, 0.01]
hold = 1
[rollout]
n = 50
horizon = 60
x0 = [0.05, 0.1]
seed = 11
"""

BAR = re.compile(r"(\d+)/(\d+)(?: [a-z]+)? \[")  # a progress line: done/total [unit] [


def _lines(text: str):
    # on a terminal tqdm redraws with carriage returns (each redraw a line of its own); off one, a line each
    return [ln for part in text.splitlines() for ln in part.split("\r") if ln.strip()]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("tiny")
    (d / "tiny.toml").write_text(TINY)
    return d


def test_run_prints_each_stages_estimate_before_its_progress(tiny_run, capsys):
    out = tiny_run / "out"
    assert main(["run", str(tiny_run / "tiny.toml"), "--out", str(out), "--no-record"]) == 0
    cap = capsys.readouterr()
    err = _lines(cap.err)
    for stage in ("collect/stochastic", "certify/stochastic", "audit/stochastic", "rollout/stochastic"):
        est = next(i for i, ln in enumerate(err) if ln.startswith(f"[{stage}] ") and
                   ("estimate" in ln or "estimated time" in ln))
        start = err.index(f"[{stage}] ...")
        done = next(i for i, ln in enumerate(err) if ln.startswith(f"[{stage}] done in"))
        if stage.startswith("collect"):
            assert est < start  # the collection's estimate comes before the stage starts
        else:
            assert est < done
        bars = [ln for ln in err[est:done] if ln.startswith(stage) and BAR.search(ln)]
        assert bars, f"no progress lines for {stage}"
        last = BAR.search(bars[-1])
        assert last.group(1) == last.group(2)  # the count reaches its total
    # the simulator Lipschitz runs: their estimate counts the gap's runs too, and the bar's total is that count
    line = next(ln for ln in err if ln.startswith("[certify/stochastic] estimate: Lhat_fhat"))
    rows = int(re.search(r"= ([\d,]+) simulator runs", line).group(1).replace(",", ""))
    assert rows == 2 * 300 * 20 + 2 * 2 * max(100, 300 // 2) * 20
    bar = next(ln for ln in err if ln.startswith("certify/stochastic: Lipschitz (simulator)") and BAR.search(ln))
    assert int(BAR.search(bar).group(2)) == rows
    # the rollout estimate counts the mean map; printed times include the whole run
    assert any("+ mean map 100 runs x 2 x 60 steps" in ln for ln in err)
    assert "wall time of the whole run:" in cap.out
    s = json.loads((out / "summary.json").read_text())
    assert s["wall_seconds"] >= sum(s["seconds"].values())


def test_certify_progress_total_is_the_work_done():
    """The count certify reports (and its estimate prints) is exactly the simulator rows it runs."""
    from simgap.certify.pipeline import CertifyOptions, certify, simulator_rows, _LIP_CACHE
    from simgap.collect import CollectionPlan, collect, load_store
    from simgap.cover import make_cover
    from simgap.simulators import make_simulator
    from simgap.simulators.base import SimulatorConfig
    from simgap.systems import get_system
    import tempfile

    s = get_system("pendulum")
    cfg = SimulatorConfig(kind="numpy", system="pendulum", steps=1, noise={"actuation_std": 0.01})
    with tempfile.TemporaryDirectory() as d:
        plan = CollectionPlan(s, cfg, make_cover(s, 0.02), n_runs=10, seed=1)
        collect(plan, Path(d) / "st", executor="serial")
        ds = load_store(Path(d) / "st")
    o = CertifyOptions(degree=1, lhat="simulator", lipschitz_term="gap", lhat_pairs=200, lhat_runs=10, seed=3)
    _LIP_CACHE.clear()
    want = simulator_rows(ds, o)

    class Counting:
        def __init__(self, inner):
            self.inner, self.system, self.rows = inner, inner.system, 0

        def draw_noise(self, B, rng):
            return self.inner.draw_noise(B, rng)

        def step_with_noise(self, x, u, noise):
            self.rows += len(x)
            return self.inner.step_with_noise(x, u, noise)

        def step_with_noise_in_parts(self, x, u, noise, on_rows):
            self.rows += len(x)
            return self.inner.step_with_noise_in_parts(x, u, noise, on_rows)

    seen = []
    with make_simulator(cfg.to_dict(), system=s) as sim:
        counting = Counting(sim)
        certify(ds, o, simulator=counting, on_progress=lambda d, t: seen.append((d, t)))
    assert counting.rows == want["rows"] > 0
    assert seen[-1] == (want["rows"], want["rows"])
    assert all(b[0] >= a[0] for a, b in zip(seen, seen[1:]))  # one count, never going back


def test_rollout_prints_estimate_first_and_counts_the_mean_map(tiny_run, capsys):
    out = tiny_run / "out"
    if not (out / "controller_stochastic.npz").exists():
        assert main(["run", str(tiny_run / "tiny.toml"), "--out", str(out), "--no-record"]) == 0
    capsys.readouterr()
    rep = tiny_run / "r.json"
    assert main(["rollout", "--controller", str(out / "controller_stochastic.npz"), "--simulator",
                 str(tiny_run / "tiny.toml"), "--out", str(rep)]) == 0
    cap = capsys.readouterr()
    lines = cap.out.splitlines()
    assert lines[0].startswith("rollout settings:") and lines[1].startswith("estimate: 50 rollouts x 60 steps")
    bars = [ln for ln in _lines(cap.err) if ln.startswith("rollouts, then mean map") and BAR.search(ln)]
    assert bars and BAR.search(bars[-1]).groups() == ("120", "120")  # rollouts' 60 steps, then the mean map's 60
    tm = json.loads(rep.read_text())["timing"]
    assert tm["total_wall_s"] >= tm["wall_s"] + tm["mean_map_s"]
    assert any(f"{tm['total_wall_s']:.2f} s wall in all" in ln for ln in lines)


def test_rollout_cost_counts_the_runs_made():
    """rollout_cost's rows = the robot steps of rollouts that all run to the horizon + the mean map's."""
    from simgap.rollout.closed_loop import rollout, rollout_cost
    from simgap.simulators import make_simulator
    from simgap.synthesis.controller import synthesize
    from simgap.synthesis.spec import Box, Spec
    from simgap.systems import get_system

    s = get_system("pendulum")
    spec = Spec(kind="invariance", safe=Box(s.x_lo * 0.9, s.x_hi * 0.9))
    res = synthesize(s, spec, [0.01, 0.02], gap=None, x0=np.zeros(2))
    with make_simulator({"kind": "numpy", "system": "pendulum", "steps": 1, "noise": {"actuation_std": 0.001}},
                        system=s) as sim:
        seen = []
        rr = rollout(res.controller, sim, np.zeros(2), n_rollouts=30, horizon=20, mean_map_runs=40,
                     on_estimate=seen.append)
    c = rollout_cost(30, 20, 40)
    assert rr.n_failures == 0
    assert c["rows"] == rr.timing["robot_steps"] + rr.mean_map["robot_steps"]
    assert len(seen) == 1 and seen[0].startswith("estimate: 30 rollouts x 20 steps")


def test_rollout_estimate_of_a_reach_avoid_controller_prices_its_steps_to_go():
    """Runs end at the target: the estimate prices the controller's worst-case steps to go from x0
    (not the whole horizon, which stays the stated upper bound)."""
    from simgap.rollout.closed_loop import rollout_cost, rollout_cost_text
    c = rollout_cost(10, 100, 0, rate=10.0, expected_steps=20)
    assert c["seconds"] == pytest.approx(10 * 20 / 10.0) and c["max_seconds"] == pytest.approx(10 * 100 / 10.0)
    assert "if the runs end at the target within the expected 20 steps" in rollout_cost_text(c)
    full = rollout_cost(10, 100, 0, rate=10.0)
    assert full["seconds"] == full["max_seconds"] and "at most about" in rollout_cost_text(full)

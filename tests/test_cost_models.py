"""The cost models behind the printed estimates, checked by hand computations with fake rates.

No test here times anything: a fake clock (advanced by fake simulators) stands in for
``time.perf_counter``, and the models' arithmetic is compared with the numbers worked out in
each test. Each fix to an estimate has a test the earlier formula fails (named in its docstring).
"""

import numpy as np
import pytest

import simgap.cover as cover_mod
from simgap.systems import get_system


class FakeClock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


class FakeSim:
    """``step`` of B runs costs ``per_run`` s each, plus ``build`` s per row never seen before
    (per-row resources built on first use: MuJoCo's model copies, a world's bodies)."""

    def __init__(self, clock, per_run, build=0.0, system="pendulum"):
        self.clock, self.per_run, self.build = clock, per_run, build
        self.system = get_system(system)
        self.capacity = 0
        self.calls = []

    def step(self, x, u, rng, **kw):
        B = len(x)
        self.clock.t += B * self.per_run + max(0, B - self.capacity) * self.build
        self.capacity = max(self.capacity, B)
        self.calls.append(B)
        return x


@pytest.fixture
def clock(monkeypatch):
    c = FakeClock()
    monkeypatch.setattr(cover_mod.time, "perf_counter", c)
    return c


def test_calibrate_rate_leaves_out_first_use_builds(clock):
    """10 us per run and 1 ms to build each new row: the rate is 100,000 runs/s. The earlier
    calibration timed the first batch of each new size, builds included: 4096 runs in 4096 x 10 us
    + 3072 x 1 ms = 3.113 s, i.e. 1,316 runs/s (76x too slow; the cart-pole's MuJoCo rate was 5x)."""
    sim = FakeSim(clock, per_run=1e-5, build=1e-3)
    rate = cover_mod.calibrate_rate(sim, n_runs=4096, budget=0.3)
    assert rate == pytest.approx(1e5, rel=1e-9)
    assert sim.calls[:2] == [64, 256]  # grows x4 from 64 (each size called once before it is timed)
    old = 4096 / (4096 * 1e-5 + (4096 - 1024) * 1e-3)
    assert rate / old > 50


def test_calibrate_rate_times_repeats_until_budget(clock):
    """2 us per run, n_runs 1024: sizes 64, 256, 1024 untimed (about 2.7 ms), then batches of 1024
    (2.048 ms each) until 0.1 s have passed since the start: the rate is runs / their time."""
    sim = FakeSim(clock, per_run=2e-6)
    rate = cover_mod.calibrate_rate(sim, n_runs=1024, budget=0.1)
    assert rate == pytest.approx(5e5, rel=1e-9)
    timed = sim.calls[3:]
    assert set(timed) == {1024}
    assert clock.t >= 0.1 and len(timed) == int(np.ceil((0.1 - 64 * 2e-6 - 256 * 2e-6 - 1024 * 2e-6 - 64 * 2e-6)
                                                       / (1024 * 2e-6)))


def test_calibrate_rate_slow_simulator_stops_growing(clock):
    """1 ms per run: 64 runs take 64 ms, 256 runs 0.256 s >= budget / 4: growth stops at 256
    (not 4096, which would take 4 s) and two timed batches of 256 give 1,000 runs/s."""
    sim = FakeSim(clock, per_run=1e-3)
    rate = cover_mod.calibrate_rate(sim, n_runs=4096, budget=0.5)
    assert rate == pytest.approx(1000.0)
    assert max(sim.calls) == 256 and sim.calls == [64, 256, 256, 256]


def test_a_small_stage_is_timed_for_a_share_of_its_work(clock):
    """10 us per run and a stage of 20,000 runs (0.2 s): the batches grow to 4,096 runs (the whole
    budget bounds the growth: the rate is timed at the stage's batch size) and the timing stops after
    two of them, 0.082 s, past the 0.05 s floor (5 % of the work would be 0.01 s): 13,632 runs,
    0.136 s, with the same rate. Without ``work`` (and before it existed)
    the timing ran for the whole 0.5 s budget, 2.5x the stage it priced (a tiny ``simgap run``
    spent 1.9 of its 6.3 s timing simulators). A large stage keeps the whole budget."""
    sim = FakeSim(clock, per_run=1e-5)
    rate = cover_mod.calibrate_rate(sim, n_runs=4096, budget=0.5, work=20_000)
    assert rate == pytest.approx(1e5, rel=1e-9)
    spent_small = clock.t
    assert spent_small == pytest.approx((64 + 256 + 1024 + 4096 + 2 * 4096) * 1e-5)
    clock.t = 0.0
    cover_mod.calibrate_rate(FakeSim(clock, per_run=1e-5), n_runs=4096, budget=0.5)
    assert clock.t >= 0.5
    clock.t = 0.0
    cover_mod.calibrate_rate(FakeSim(clock, per_run=1e-5), n_runs=4096, budget=0.5, work=1e9)  # 10,000 s of work
    assert clock.t >= 0.5


def test_timed_rate_budget_follows_the_work(clock):
    """timed_rate on 1 ms units with work of 2,000 units (2 s): 5 % is 0.1 s, so after the growing
    batches (1 + 4 + 16 units, untimed) it times two batches of 64 (the second ends past 0.1 s):
    128 units / 0.128 s = 1,000 units/s."""
    calls = []

    def batch(k, timed):
        clock.t += k * 1e-3
        calls.append((k, timed))

    rate = cover_mod.timed_rate(batch, 1, 64, budget=1.0, grow=0.25, work=2000)
    assert rate == pytest.approx(1000.0)
    assert calls == [(1, False), (4, False), (16, False), (64, False), (64, True), (64, True)]


class MemoSim(FakeSim):
    """Answers a batch it has seen (same rows) from a memo, at no cost: ParallelSimulator's memo of
    large batches, or any simulator whose noise-free draws repeat."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.seen = set()

    def step(self, x, u, rng, **kw):
        key = np.asarray(x).tobytes()
        if key in self.seen:
            self.calls.append(len(x))
            return x
        self.seen.add(key)
        return super().step(x, u, rng, **kw)


def test_calibrate_rate_is_not_timed_on_a_memo(clock):
    """Each timed batch takes other rows: a memoizing simulator costs 10 us per run in every batch.
    Repeating the same rows (the repeated batches of the fixed calibration, without the row
    subsets) the memo would answer in no time and the rate would be unbounded; here it is 100,000
    runs/s. (A guard of the fix above, not a fix of the earlier formula, which timed no repeat.)"""
    sim = MemoSim(clock, per_run=1e-5)
    rate = cover_mod.calibrate_rate(sim, n_runs=4096, budget=0.3)
    assert rate == pytest.approx(1e5, rel=1e-9)


def test_collection_seconds_by_hand():
    """43,239 pairs in chunks of 655 (67 chunks) on 2 workers at 250 pairs/s per worker: 34 rounds
    of 655 / 250 = 2.62 s = 89.08 s, + start 0.2 s + set-up 0.3 s + 34 x 0.02 s writing = 90.26 s.
    The earlier formula, runs / (rate x workers) = 43,239 / 500 = 86.478 s, leaves out the start,
    the set-up, the writing and the last round's idle worker."""
    from simgap.collect import collection_seconds
    s = collection_seconds(43239, 655, 2, 250.0, setup_s=0.3, start_s=0.2, write_s=0.02)
    assert s == pytest.approx(0.2 + 0.3 + 34 * 655 / 250 + 34 * 0.02)
    assert s - 43239 / 500 > 3.5


def test_collection_seconds_small_and_uneven():
    """3 chunks on 4 workers: one round (3 workers busy, one idle); 0 pairs cost nothing; a
    collection smaller than a chunk costs its own pairs, not a whole chunk's."""
    from simgap.collect import collection_seconds
    assert collection_seconds(30, 10, 4, 5.0) == pytest.approx(10 / 5.0)
    assert collection_seconds(0, 10, 4, 5.0, start_s=1.0) == 0.0
    assert collection_seconds(4, 10, 2, 2.0, start_s=0.5, write_s=0.1) == pytest.approx(0.5 + 2.0 + 0.1)


def test_deterministic_collection_priced_with_its_own_rate(monkeypatch):
    """The noise-free collection (N1hat = 2) is priced from its own workers' pairs per second, not
    from runs / (the stochastic simulator's rate x workers): with statistics and chunk overhead a
    noise-free pair at 2 runs costs far more than 2 runs of the stochastic rate. The workers'
    measurements are faked: 1,000 pairs/s, set-up 0.5 s, pool start 0.25 s."""
    import simgap.collect as C
    from simgap.config import load_experiment
    from simgap.pipeline import baseline_experiment

    plan = baseline_experiment(load_experiment("pendulum")).plan()

    class FakeEx(C.Executor):
        name, workers = "local", 2

        def map_chunks(self, fn, job, ids, on_result, should_stop=lambda: False):
            for c in ids:
                on_result(c, {"setup_s": 0.5, "pairs_per_s": 1000.0, "pid": c, "seconds": 0.0})
            return True

    monkeypatch.setattr(C, "_write_seconds", lambda plan: 0.01)
    t = {"now": 0.0}
    monkeypatch.setattr(C.time, "perf_counter", lambda: t.__setitem__("now", t["now"] + 0.125) or t["now"])
    est = C.estimate_collection(plan, FakeEx())
    K, S = plan.n_pairs, plan.chunk_size
    rounds = -(-plan.n_chunks // 2)
    # the calibration's wall time is two clock reads apart = 0.125 s (its tasks' own 0 s): the pool's start
    assert est["start_s"] == pytest.approx(0.125)
    assert est["seconds"] == pytest.approx(0.125 + 0.5 + rounds * S / 1000.0 + rounds * 0.01)
    assert est["runs_per_s"] == pytest.approx(1000.0 * plan.n_runs)


class _Nominal:
    def __init__(self, outcome, reach_time):
        self.outcome, self.reach_time = np.array([outcome]), np.array([reach_time])


class _Spec:
    def __init__(self, kind):
        self.kind = kind


class _Ctrl:
    def steps_to_go(self, x):
        return np.array([30.0])


def test_rollouts_priced_on_the_nominal_path():
    """A reach-avoid rollout is priced at the nominal path's steps to the target (42 steps), not the
    controller's worst-case steps to go x hold (+1): (30 + 1) x 5 = 155; the horizon (400) stays the
    upper bound. Without a reaching nominal path the worst case is used; invariance runs the horizon."""
    from simgap.rollout.closed_loop import expected_rollout_steps, rollout_cost
    from simgap.rollout.judge import SUCCESS, TIMEOUT
    x0 = np.zeros(2)
    assert expected_rollout_steps(_Spec("reach_avoid"), _Nominal(SUCCESS, 42), _Ctrl(), x0, 5) == 42
    assert expected_rollout_steps(_Spec("reach_avoid"), _Nominal(TIMEOUT, -1), _Ctrl(), x0, 5) == 155
    assert expected_rollout_steps(_Spec("invariance"), _Nominal(SUCCESS, 42), _Ctrl(), x0, 5) is None
    # 1000 rollouts + mean map 1000 runs (10 groups of 100 more): 3000 runs per step, 42 steps, 1e5 runs/s
    c = rollout_cost(1000, 400, 1000, rate=1e5, expected_steps=42)
    assert c["seconds"] == pytest.approx(3000 * 42 / 1e5)
    assert c["max_seconds"] == pytest.approx(3000 * 400 / 1e5)


def test_audit_rate_times_the_audit_batch(clock, monkeypatch):
    """audit_rate calibrates at the audit's batch: min(points, 1e6 // runs) x runs rows, capped at
    65,536 (200 points x 2,000 runs: one chunk of 400,000 rows, calibrated at 65,536; 10 points x
    100 runs: 1,000 rows). audit_cost then prices rows / rate with workers = 1 (the simulator's
    processes are in the rate): 400,000 rows at 2e5 runs/s = 2 s."""
    import importlib
    A = importlib.import_module("simgap.certify.audit")
    seen = []
    monkeypatch.setattr(cover_mod, "calibrate_rate",
                        lambda sim, n_runs, budget, work: seen.append((n_runs, work)) or 2e5)
    assert A.audit_rate(object(), 200, 2000) == 2e5 and seen[-1] == (65536, 400_000)
    A.audit_rate(object(), 10, 100)
    assert seen[-1] == (1000, 1000)  # the audit's runs: the timing's share of them
    c = A.audit_cost(200, 2000, get_system("pendulum"), 2e5, workers=1)
    assert c["seconds"] == pytest.approx(2.0)


class DedupSim(FakeSim):
    """Simulates each distinct row once (the TurtleBot's noise-free step): cost per distinct row."""

    def step(self, x, u, rng, **kw):
        B = len(x)
        d = len(np.unique(np.asarray(x), axis=0))
        self.clock.t += d * self.per_run
        self.calls.append(B)
        return x


def test_calibrate_rate_with_repeated_rows(clock):
    """Lipschitz runs of a noise-free simulator: 100 identical rows per pair. A simulator that runs
    each distinct row once at 1 ms costs 1 ms per 100 rows: 100,000 rows/s. Timed on distinct rows
    (the earlier calibration, repeat = 1) it is 1,000 rows/s: the TurtleBot's deterministic certify
    was priced 5.8x too long (9.8 s for 1.7 s)."""
    rate = cover_mod.calibrate_rate(DedupSim(clock, per_run=1e-3), n_runs=4096, budget=0.5, repeat=100)
    c2 = FakeClock()
    cover_mod.time.perf_counter = c2
    old = cover_mod.calibrate_rate(DedupSim(c2, per_run=1e-3), n_runs=4096, budget=0.5)
    assert old == pytest.approx(1000.0)
    # the blocks of 100 cut at the batch's end leave a partial block: at least 50x the distinct-row rate
    assert rate > 50 * old


def test_the_fitting_modules_are_loaded_before_an_audit_estimate_is_printed():
    """No cost model prices a module's first import (scipy.stats: 1-2 s under load, measured in the
    arm's first audit: 2.3 s for an estimate of 0.4 s). audit_rate, which the estimate line waits
    for, loads it, so the estimate covers what follows the line. A fresh process: nothing else
    has imported scipy.stats there."""
    import subprocess
    import sys
    code = ("import sys, simgap.cover as c; c.calibrate_rate = lambda *a, **k: 1e5\n"
            "import simgap.certify.audit as A\n"
            "assert 'scipy.stats' not in sys.modules\n"
            "A.audit_rate(object(), 10, 100)\n"
            "print('scipy.stats' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "True"

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
    (not 4096, which would take 4 s) and one timed batch of 256 gives 1,000 runs/s."""
    sim = FakeSim(clock, per_run=1e-3)
    rate = cover_mod.calibrate_rate(sim, n_runs=4096, budget=0.5)
    assert rate == pytest.approx(1000.0)
    assert max(sim.calls) == 256

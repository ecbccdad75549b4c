"""The Ray executor on a real local Ray instance gives bit-identical PyBullet data to the local process pool."""

import numpy as np
import pytest

from simgap.collect import CollectionPlan, collect, load_store
from simgap.cover import make_cover
from simgap.simulators.base import SimulatorConfig
from simgap.systems import get_system

pytest.importorskip("ray")


@pytest.mark.ray
def test_ray_equals_local_pool(tmp_path):
    s = get_system("pendulum")
    sim = SimulatorConfig("pybullet_pendulum", "pendulum", noise={"actuation_std": 0.05, "sensor_std": 1e-4},
                          effects={"joint_damping": 0.1}, options={"branches": 25})
    plan = CollectionPlan(s, sim, make_cover(s, 0.05), n_runs=20, seed=123, chunk_size=97)
    r_ray = collect(plan, tmp_path / "ray", executor="ray", workers=2)
    # Ray's native threads outlive its shutdown: the pool after it must not fork beside them (a forked
    # worker hung for good in a lock one of them held, now and then)
    from simgap.executors import LocalExecutor, native_threads
    assert native_threads() and LocalExecutor(2)._context().get_start_method() == "forkserver"
    r_pool = collect(plan, tmp_path / "pool", executor="local", workers=2)
    assert r_ray.complete and r_ray.computed == plan.n_chunks > 2
    a, b = load_store(tmp_path / "ray"), load_store(tmp_path / "pool")
    for k in ("x", "u", "f_nom", "mean", "var", "lo", "hi", "cover_index", "input_index"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert a.hash == b.hash
    import ray
    assert not ray.is_initialized()  # the instance started for the collection was shut down

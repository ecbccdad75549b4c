import numpy as np
import pytest

from simgap import SimgapError, System, get_system, input_grid
from simgap.simulators import make_simulator


def test_pendulum_matches_paper_equations():
    s = get_system("pendulum")
    assert s.inputs.shape == (21, 1) and s.tau == 0.005
    x = np.array([[0.1, -0.2]])
    u = np.array([[0.5]])
    tau, g, l, m = 0.005, 9.81, 1.0, 1.0
    want = [0.1 + tau * -0.2, -(3 * g * tau / (2 * l)) * np.sin(0.1) - 0.2 + 3 * tau * 0.5 / (m * l * l)]
    np.testing.assert_allclose(s.f(x, u)[0], want, rtol=0, atol=1e-15)


def test_turtlebot_and_steps():
    s = get_system("turtlebot")
    assert s.inputs.shape == (441, 2) and s.angle_dims == (2,)
    s10 = s.with_steps(10)
    assert s10.tau == pytest.approx(0.1)
    x = np.array([[1.0, 1.0, np.pi - 0.001]])
    u = np.array([[1.0, 1.0]])
    y = s10.f(x, u)
    assert -np.pi <= y[0, 2] < np.pi  # wrapped across the seam
    # ten held steps = ten single steps
    z = x
    for _ in range(10):
        z = s.f(z, u)
    np.testing.assert_allclose(y, z, atol=1e-12)


def test_user_system_in_a_few_lines():
    def step(x, u, tau):
        return np.stack([x[:, 0] + tau * x[:, 1], x[:, 1] + tau * u[:, 0]], axis=1)

    s = System(name="cart", state_names=("p", "v"), input_names=("F",), x_lo=(-1, -1), x_hi=(1, 1),
               inputs=input_grid([-1], [1], [5]), base_tau=0.1, step=step)
    assert s.f(np.zeros((1, 2)), np.ones((1, 1)))[0, 1] == pytest.approx(0.1)
    assert s.lipschitz_f() is None


@pytest.mark.parametrize("kwargs,msg", [
    (dict(x_lo=(1, 0), x_hi=(0, 1)), "x_lo < x_hi"),
    (dict(inputs=np.zeros((0, 1))), "input set is empty"),
    (dict(inputs=np.array([[np.nan]])), "NaN"),
    (dict(steps=0), "steps"),
])
def test_bad_system_descriptions(kwargs, msg):
    base = dict(name="b", state_names=("a", "b"), input_names=("u",), x_lo=(0, 0), x_hi=(1, 1),
                inputs=np.array([[0.0]]), base_tau=0.1, step=lambda x, u, t: x)
    base.update(kwargs)
    with pytest.raises(SimgapError, match=msg):
        System(**base)


def test_unknown_system_and_states_outside_X():
    with pytest.raises(SimgapError, match="unknown system"):
        get_system("segway")
    with pytest.raises(SimgapError, match="outside X"):
        get_system("pendulum").check_states(np.array([[0.5, 0.0]]))


def test_numpy_simulator_batched_equals_unbatched():
    sim = make_simulator({"kind": "numpy", "system": "pendulum", "steps": 3,
                          "noise": {"actuation_std": 0.1, "process_std": 1e-3, "sensor_std": 1e-3}})
    rng = np.random.default_rng(0)
    x = rng.uniform(sim.system.x_lo, sim.system.x_hi, (50, 2))
    u = sim.system.inputs[rng.integers(0, 21, 50)]
    noise = sim.draw_noise(50, np.random.default_rng(1))
    batched = sim.step_with_noise(x, u, noise)
    single = np.vstack([sim.step_with_noise(x[i:i + 1], u[i:i + 1], {k: v[i:i + 1] for k, v in noise.items()})
                        for i in range(50)])
    np.testing.assert_array_equal(batched, single)


def test_units_of_builtins_params_and_system_files():
    """Axis labels take units from the system: the built-ins' table, params['units'], a system file's."""
    from pathlib import Path

    from simgap.systems import get_system, labelled, units
    from simgap.system_ref import resolve_system
    assert units(get_system("pendulum")) == (("rad", "rad/s"), ("N m",))
    assert units(get_system("turtlebot"))[0] == ("m", "m", "rad")
    cart = System(name="cart", state_names=("p", "v"), input_names=("F",), x_lo=(-1, -1), x_hi=(1, 1),
                  inputs=input_grid([-1], [1], [3]), base_tau=0.01, step=lambda x, u, t: x,
                  params={"units": {"p": "m", "F": "N"}})
    assert units(cart) == (("m", ""), ("N",))
    assert labelled("p", "m") == "p [m]" and labelled("v", "") == "v"
    bare = System(name="bare", state_names=("a",), input_names=("b",), x_lo=(0,), x_hi=(1,),
                  inputs=input_grid([0], [1], [2]), base_tau=0.1, step=lambda x, u, t: x)
    assert units(bare) == (("",), ("",))
    duffing = Path(__file__).resolve().parents[1] / "examples" / "duffing" / "duffing.toml"
    if duffing.is_file():
        assert units(resolve_system(str(duffing))) == (("m", "m/s"), ("N",))

"""An example simgap plugin: one system and one simulator backend, registered by name.

* system ``double_integrator``: a cart on a rail, p [m], v [m/s], force a [N] on a 1 kg cart,
  exact zero-order-hold discretisation over tau = 0.1 s:
  p+ = p + tau v + tau^2 a / 2,  v+ = v + tau a.  X = [-1, 1] x [-1, 1], U = {-2, -1, 0, 1, 2}.
* simulator kind ``example_drag``: the same cart with what the model lacks, integrated with
  ``substeps`` explicit-Euler substeps per period: quadratic air drag -c v |v| / mass
  (``effects.drag`` = c [kg/m]), a per-run mass 1 + N(0, randomize.mass^2) (relative), actuation
  noise N(0, noise.actuation_std^2) held per run. Every random number comes from the generator
  simgap passes to ``draw_noise``; ``step_with_noise`` is deterministic and row-independent, so
  batched and one-at-a-time runs are bit-identical.

Registered in pyproject.toml under the entry-point groups ``simgap.systems`` and
``simgap.simulators``; install with ``pip install -e examples/plugin`` and check with
``simgap plugins``.
"""

from __future__ import annotations

import numpy as np

from simgap.errors import SimgapError
from simgap.simulators.base import Simulator, as_vector
from simgap.systems import System, input_grid

TAU = 0.1


def double_integrator() -> System:
    """The cart on a rail (module docstring), with its exact Jacobian |d step/dx| = [[1, tau], [0, 1]]."""

    def step(x, u, dt):
        p, v, a = x[:, 0], x[:, 1], u[:, 0]
        return np.stack([p + dt * v + 0.5 * dt * dt * a, v + dt * a], axis=1)

    def jac(u):
        return np.broadcast_to(np.array([[1.0, TAU], [0.0, 1.0]]), (np.atleast_2d(u).shape[0], 2, 2))

    return System(name="double_integrator", state_names=("p", "v"), input_names=("a",),
                  x_lo=(-1.0, -1.0), x_hi=(1.0, 1.0), inputs=input_grid([-2.0], [2.0], [5]),
                  base_tau=TAU, step=step, jacobian_bound=jac, params={"mass": 1.0})


class DragSimulator(Simulator):
    """Cart with quadratic drag, per-run mass and actuation noise (numpy, Euler substeps)."""

    NOISE_KEYS = ("actuation_std",)
    RANDOMIZE_KEYS = ("mass",)
    EFFECT_KEYS = ("drag",)
    OPTION_KEYS = ("substeps",)

    def __init__(self, config, system=None):
        super().__init__(config, system)
        s = self.system
        if s.n != 2 or s.m != 1:
            raise SimgapError(f"simulator 'example_drag' simulates a cart (2 states, 1 input); "
                              f"system {s.name!r} has {s.n} states and {s.m} inputs")
        self.act_std = as_vector(config.noise.get("actuation_std", 0.0), 1, "noise.actuation_std")
        self.mass_std = float(as_vector(config.randomize.get("mass", 0.0), 1, "randomize.mass")[0])
        self.drag = float(as_vector(config.effects.get("drag", 0.0), 1, "effects.drag")[0])
        sub = config.options.get("substeps", 20)
        if isinstance(sub, bool) or not isinstance(sub, int) or sub < 1:
            raise SimgapError(f"simulator 'example_drag': options.substeps must be an integer >= 1, got {sub!r}")
        self.substeps = sub

    def draw_noise(self, B, rng):
        return {"act": rng.standard_normal((B, 1)) * self.act_std,
                "mass": 1.0 + self.mass_std * rng.standard_normal(B)}

    def step_with_noise(self, x, u, noise):
        s = self.system
        p, v = x[:, 0].astype(float), x[:, 1].astype(float)
        a_in = u[:, 0] + noise["act"][:, 0]
        mass = np.maximum(noise["mass"], 0.1)  # a mass near zero is not a cart
        h = s.base_tau / self.substeps
        for _ in range(s.steps * self.substeps):
            acc = (a_in - self.drag * v * np.abs(v)) / mass
            p, v = p + h * v, v + h * acc
        return s.wrap(np.stack([p, v], axis=1))

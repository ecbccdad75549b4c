"""A pure-numpy stochastic simulator for any system: fast, exact ground truth for tests.

x+ = f_true(x, u + a) + sum_k process noise + s, run over ``steps`` base periods, where

* a ~ N(0, actuation_std^2) per input, drawn once per run and held (``noise.actuation_std``);
* process noise ~ N(0, process_std^2) per state, added after every base step (``noise.process_std``);
* s ~ N(0, sensor_std^2) on the read-back state (``noise.sensor_std``);
* f_true is the nominal step plus undeclared effects, per base step of length dt:
  ``effects.bias`` (per-state constant rate c: x_i += dt c_i),
  ``effects.input_gain`` (the input is scaled by g: u -> g u),
  ``effects.linear`` (an n x n matrix A: x += dt A x, e.g. viscous damping on a velocity).

With zero noise, E fhat = f_true, so the true gap E fhat - f is known in closed form.
"""

from __future__ import annotations

from typing import Dict

import numpy as np

from ..errors import SimgapError
from .base import Simulator, as_vector


class NumpySimulator(Simulator):
    NOISE_KEYS = ("actuation_std", "process_std", "sensor_std")
    EFFECT_KEYS = ("bias", "input_gain", "linear")
    TYPES = {"noise": dict.fromkeys(NOISE_KEYS, "numbers"),
             "effects": {"bias": "numbers", "input_gain": "number", "linear": "matrix"}}

    def __init__(self, config, system=None):
        super().__init__(config, system)
        s = self.system
        nz, ef = config.noise, config.effects
        self.act_std = as_vector(nz.get("actuation_std", 0.0), s.m, "noise.actuation_std")
        self.proc_std = as_vector(nz.get("process_std", 0.0), s.n, "noise.process_std")
        self.sens_std = as_vector(nz.get("sensor_std", 0.0), s.n, "noise.sensor_std")
        self.bias = np.asarray(ef.get("bias", np.zeros(s.n)), dtype=float).reshape(-1)
        self.gain = float(ef.get("input_gain", 1.0))
        self.A = np.asarray(ef.get("linear", np.zeros((s.n, s.n))), dtype=float)
        if self.bias.shape != (s.n,) or self.A.shape != (s.n, s.n):
            raise SimgapError(f"numpy simulator: effects.bias needs {s.n} values and effects.linear {s.n}x{s.n}")

    def draw_noise(self, B: int, rng: np.random.Generator) -> Dict[str, np.ndarray]:
        s = self.system
        return {
            "act": rng.standard_normal((B, s.m)) * self.act_std,
            "proc": rng.standard_normal((s.steps, B, s.n)).transpose(1, 0, 2) * self.proc_std,
            "sens": rng.standard_normal((B, s.n)) * self.sens_std,
        }

    def true_step(self, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """One base step of the true (noise-free) dynamics including the undeclared effects."""
        return self.system.step(x, self.gain * u, dt) + dt * (self.bias + x @ self.A.T)

    def step_with_noise(self, x, u, noise):
        s = self.system
        u = u + noise["act"]
        for k in range(s.steps):
            x = self.true_step(x, u, s.base_tau) + noise["proc"][:, k]
        return s.wrap(x + noise["sens"])

    def mean_next(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """E fhat(x, u) when the only noise is additive (process/sensor) and zero-mean.

        Exact when actuation_std = 0 or the dynamics are affine in u; else an approximation.
        """
        s = self.system
        x = np.atleast_2d(np.asarray(x, dtype=float))
        for _ in range(s.steps):
            x = self.true_step(x, np.atleast_2d(u), s.base_tau)
        return s.wrap(x)

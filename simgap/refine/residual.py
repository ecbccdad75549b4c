"""Residuals r = x_next - f(x, u) of a model on transition data, with statistics and views.

For every sample k and state dimension i, r_ki = x_next_ki - f_i(x_k, u_k), with angle
dimensions wrapped to [-pi, pi) (:meth:`System.diff`). Units are the state's units (per
sampling period tau, not per second).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import SimgapError
from ..systems import System
from .data import Transitions


@dataclass
class Residuals:
    """Residuals of ``system`` on ``data``; r is (K, n)."""

    system: System
    data: Transitions
    r: np.ndarray

    @property
    def mean(self) -> np.ndarray:
        """Per-dimension mean of r, (n,)."""
        return self.r.mean(axis=0)

    @property
    def rms(self) -> np.ndarray:
        """Per-dimension root mean square sqrt(mean_k r_ki^2), (n,)."""
        return np.sqrt(np.mean(self.r ** 2, axis=0))

    @property
    def max_abs(self) -> np.ndarray:
        """Per-dimension max_k |r_ki|, (n,)."""
        return np.abs(self.r).max(axis=0)

    def stats(self) -> dict:
        """JSON-ready statistics per state dimension (name -> mean, rms, max_abs)."""
        return {name: {"mean": float(a), "rms": float(b), "max_abs": float(c)}
                for name, a, b, c in zip(self.system.state_names, self.mean, self.rms, self.max_abs)}

    def variables(self) -> list:
        """Names accepted by :meth:`against`: state names, input names, x1.., u1.., and t."""
        s = self.system
        out = list(s.state_names) + list(s.input_names)
        out += [f"x{i + 1}" for i in range(s.n)] + [f"u{j + 1}" for j in range(s.m)]
        if self.data.t is not None:
            out.append("t")
        return out

    def values(self, var: str) -> np.ndarray:
        """Values (K,) of a state, an input or time, by name (``omega``, ``x2``, ``u1``, ``t``)."""
        s = self.system
        if var in s.state_names:
            return self.data.x[:, s.state_names.index(var)]
        if var in s.input_names:
            return self.data.u[:, s.input_names.index(var)]
        if var[:1] == "x" and var[1:].isdigit() and 1 <= int(var[1:]) <= s.n:
            return self.data.x[:, int(var[1:]) - 1]
        if var[:1] == "u" and var[1:].isdigit() and 1 <= int(var[1:]) <= s.m:
            return self.data.u[:, int(var[1:]) - 1]
        if var == "t" and self.data.t is not None:
            return self.data.t
        raise SimgapError(f"unknown variable {var!r}; known: {', '.join(self.variables())}")

    def against(self, var: str) -> tuple:
        """(values (K,), residuals (K, n)) for plotting the residual against one variable."""
        return self.values(var), self.r

    def binned(self, var: str, bins: int = 30) -> dict:
        """Residual mean and standard deviation in ``bins`` equal-width bins of ``var``.

        Returns ``{"centers": (b,), "count": (b,), "mean": (b, n), "std": (b, n)}``; empty bins
        give NaN. Makes structure visible when K is large (e.g. friction against velocity).
        """
        v = self.values(var)
        lo, hi = float(v.min()), float(v.max())
        if hi <= lo:
            hi = lo + 1.0
        edges = np.linspace(lo, hi, bins + 1)
        idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, bins - 1)
        cnt = np.bincount(idx, minlength=bins).astype(float)
        n = self.r.shape[1]
        s1 = np.stack([np.bincount(idx, self.r[:, i], minlength=bins) for i in range(n)], axis=1)
        s2 = np.stack([np.bincount(idx, self.r[:, i] ** 2, minlength=bins) for i in range(n)], axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = s1 / cnt[:, None]
            var = s2 / cnt[:, None] - mean ** 2
        return {"centers": 0.5 * (edges[:-1] + edges[1:]), "count": cnt, "mean": mean,
                "std": np.sqrt(np.maximum(var, 0.0))}


def residuals(system: System, data: Transitions) -> Residuals:
    """r = x_next - f(x, u) (angles wrapped) of ``system`` on ``data``.

    ``system.tau`` must equal ``data.tau`` (use :func:`match_tau` first).
    """
    if abs(system.tau - data.tau) > 1e-4 * data.tau:
        raise SimgapError(f"system {system.name!r} has tau = {system.tau:g} s but the data have "
                          f"tau = {data.tau:g} s")
    f = system.f(data.x, data.u)
    return Residuals(system=system, data=data, r=system.diff(data.x_next, f))


def match_tau(system: System, tau: float) -> System:
    """The system sampled at the data's tau: steps k = tau / base_tau must be an integer.

    A relative mismatch up to 1e-4 (clock jitter of measured records) is accepted.
    """
    k = tau / system.base_tau
    kr = int(round(k))
    if kr < 1 or abs(k - kr) > 1e-4 * max(1.0, k):
        raise SimgapError(f"data tau = {tau:g} s is not a whole multiple of system {system.name!r}'s "
                          f"base_tau = {system.base_tau:g} s")
    return system if kr == system.steps else system.with_steps(kr)
